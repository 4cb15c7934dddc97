//! PIV output files: the `piv_mean` and `piv_steps` tables, per-frame
//! vector tables (Parquet, CSV or `.npy`) and `.npy` stacks of the fields at every step. Everything goes through
//! [`AtomicFile`].
//!
//! The `.npy` stack is written while streaming: the number of steps is only
//! known at the end, so the data goes to a hidden spill file first and is
//! copied behind a correct header on `NpyStack::finish`. (A minimal NPY
//! v1.0 writer of its own; `crate::io::npy` holds the general writers.)

use std::fs::File;
use std::io::{BufWriter, Read, Write};
use std::path::{Path, PathBuf};

use super::{MeanRow, VectorField};
use crate::error::{Error, Result};
use crate::io::atomic::AtomicFile;
use crate::table::{write_table, Col, TableFormat};

fn fmt(v: f64) -> String {
    if v.is_finite() {
        format!("{v}")
    } else {
        "nan".to_string()
    }
}

/// `write_mean_csv`, with the physical columns of `calib` after the
/// pixel ones when given (`X_mm,Y_mm,U_m_s,V_m_s,uu_m2_s2,vv_m2_s2,
/// uv_m2_s2`, `crate::calib::Calibration::field_columns`).
pub(crate) fn write_mean_csv_calibrated(
    path: &Path,
    rows: &[MeanRow],
    calib: Option<&crate::calib::Calibration>,
) -> Result<()> {
    AtomicFile::write_all_to(path, mean_csv(rows, calib).as_bytes())
}

/// The text of `piv_mean.csv` (`write_mean_csv_calibrated`).
pub(crate) fn mean_csv(rows: &[MeanRow], calib: Option<&crate::calib::Calibration>) -> String {
    use std::fmt::Write as _;
    let extra = match calib {
        Some(_) => crate::calib::header_suffix(crate::calib::Calibration::field_columns()),
        None => String::new(),
    };
    let mut f = format!("x,y,u,v,uu,vv,uv,valid{extra}\n");
    for r in rows {
        // Writing to a String cannot fail.
        let _ = write!(
            f,
            "{},{},{},{},{},{},{},{}",
            r.x,
            r.y,
            fmt(r.u),
            fmt(r.v),
            fmt(r.uu),
            fmt(r.vv),
            fmt(r.uv),
            r.valid
        );
        if let Some(c) = calib {
            for v in c.field_values(r.x, r.y, r.u, r.v, r.uu, r.vv, r.uv) {
                let _ = write!(f, ",{}", fmt(v));
            }
        }
        f.push('\n');
    }
    f
}

/// Per-frame vectors: `x,y,u,v,flag` (px, px per frame step, flag bits of
/// `super::validate::flag`; 0 = valid).
pub(crate) fn write_vectors_csv(path: &Path, f: &VectorField) -> Result<()> {
    let mut out = AtomicFile::create(path)?;
    let io = |e| Error::io(path, e);
    writeln!(out, "x,y,u,v,flag").map_err(io)?;
    for k in 0..f.grid.len() {
        let (i, j) = (k % f.grid.nx, k / f.grid.nx);
        writeln!(
            out,
            "{},{},{},{},{}",
            f.grid.x(i),
            f.grid.y(j),
            fmt(f.u[k]),
            fmt(f.v[k]),
            f.flags[k]
        )
        .map_err(io)?;
    }
    out.commit()
}

/// One row of the `piv_mean` table: a node's statistics and, with a
/// calibration, their physical values.
struct MeanTableRow {
    r: MeanRow,
    phys: [f64; 7],
}

macro_rules! mean_cols {
    ($($extra:expr),*) => {
        [
            Col::f64("x", |m: &MeanTableRow| m.r.x),
            Col::f64("y", |m: &MeanTableRow| m.r.y),
            Col::f64("u", |m: &MeanTableRow| m.r.u),
            Col::f64("v", |m: &MeanTableRow| m.r.v),
            Col::f64("uu", |m: &MeanTableRow| m.r.uu),
            Col::f64("vv", |m: &MeanTableRow| m.r.vv),
            Col::f64("uv", |m: &MeanTableRow| m.r.uv),
            Col::f64("valid", |m: &MeanTableRow| m.r.valid),
            $($extra),*
        ]
    };
}

/// Columns of the `piv_mean` table (px, px/s, (px/s)², fraction).
static MEAN_COLUMNS: [Col<MeanTableRow>; 8] = mean_cols!();
/// [`MEAN_COLUMNS`] and the physical columns of a calibration.
static MEAN_COLUMNS_CALIBRATED: [Col<MeanTableRow>; 15] = mean_cols!(
    Col::f64("X_mm", |m: &MeanTableRow| m.phys[0]),
    Col::f64("Y_mm", |m: &MeanTableRow| m.phys[1]),
    Col::f64("U_m_s", |m: &MeanTableRow| m.phys[2]),
    Col::f64("V_m_s", |m: &MeanTableRow| m.phys[3]),
    Col::f64("uu_m2_s2", |m: &MeanTableRow| m.phys[4]),
    Col::f64("vv_m2_s2", |m: &MeanTableRow| m.phys[5]),
    Col::f64("uv_m2_s2", |m: &MeanTableRow| m.phys[6])
);

/// The `piv_mean` table (`piv_mean.parquet`, `.csv` or `.npy`) in `dir`:
/// the columns of [`mean_csv`], physical ones with `calib`. The path
/// written.
pub(crate) fn write_mean_table(
    dir: &Path,
    format: TableFormat,
    rows: &[MeanRow],
    calib: Option<&crate::calib::Calibration>,
) -> Result<PathBuf> {
    let cols: &'static [Col<MeanTableRow>] = match calib {
        Some(_) => &MEAN_COLUMNS_CALIBRATED,
        None => &MEAN_COLUMNS,
    };
    let table = rows.iter().map(|&r| MeanTableRow {
        r,
        phys: calib.map_or([f64::NAN; 7], |c| {
            c.field_values(r.x, r.y, r.u, r.v, r.uu, r.vv, r.uv)
        }),
    });
    write_table(dir, "piv_mean", format, cols, table, |p| {
        write_mean_csv_calibrated(p, rows, calib)
    })
}

/// One row of the `piv_steps` table: step index, its first pulse, its
/// time (µs).
struct StepRow(i64, i64, f64);

static STEP_COLUMNS: [Col<StepRow>; 3] = [
    Col::i64("step", |r| r.0),
    Col::i64("first_pulse", |r| r.1),
    Col::f64("t_us", |r| r.2),
];

/// The text of `piv_steps.csv`: `step,first_pulse,t_us` per field.
pub(crate) fn steps_csv(steps: &[(i64, f64)]) -> String {
    let mut t = String::from("step,first_pulse,t_us\n");
    for (k, (p, tu)) in steps.iter().enumerate() {
        t.push_str(&format!("{k},{p},{tu}\n"));
    }
    t
}

/// The `piv_steps` table in `dir` (`step,first_pulse,t_us` of every
/// field). The path written.
pub(crate) fn write_steps_table(
    dir: &Path,
    format: TableFormat,
    steps: &[(i64, f64)],
) -> Result<PathBuf> {
    let rows = steps
        .iter()
        .enumerate()
        .map(|(k, &(p, t))| StepRow(k as i64, p, t));
    write_table(dir, "piv_steps", format, &STEP_COLUMNS, rows, |p| {
        AtomicFile::write_all_to(p, steps_csv(steps).as_bytes())
    })
}

/// One row of a per-frame vectors table.
struct VectorRow {
    x: f64,
    y: f64,
    u: f64,
    v: f64,
    flag: i64,
}

static VECTOR_COLUMNS: [Col<VectorRow>; 5] = [
    Col::f64("x", |r| r.x),
    Col::f64("y", |r| r.y),
    Col::f64("u", |r| r.u),
    Col::f64("v", |r| r.v),
    Col::i64("flag", |r| r.flag),
];

/// A per-frame vectors table `stem.parquet` (`.csv`, `.npy`) in `dir`:
/// the columns of `write_vectors_csv`. The path written.
pub(crate) fn write_vectors_table(
    dir: &Path,
    stem: &str,
    format: TableFormat,
    f: &VectorField,
) -> Result<PathBuf> {
    let rows = (0..f.grid.len()).map(|k| {
        let (i, j) = (k % f.grid.nx, k / f.grid.nx);
        VectorRow {
            x: f.grid.x(i),
            y: f.grid.y(j),
            u: f.u[k],
            v: f.v[k],
            flag: f.flags[k] as i64,
        }
    });
    write_table(dir, stem, format, &VECTOR_COLUMNS, rows, |p| {
        write_vectors_csv(p, f)
    })
}

/// NPY v1.0 header for a C-order array (see [`crate::io::npy`]).
pub(crate) fn npy_header(descr: &str, shape: &[usize]) -> Vec<u8> {
    crate::io::npy::array_header(descr, shape)
}

/// A stack of 2-D frames (`ny × nx`) of one dtype (`<f4` or `|u1`) written
/// as a 3-D `.npy` `(steps, ny, nx)`.
pub(crate) struct NpyStack {
    target: PathBuf,
    spill_path: PathBuf,
    spill: Option<BufWriter<File>>,
    descr: &'static str,
    frame_len: usize,
    ny: usize,
    nx: usize,
    steps: usize,
}

impl NpyStack {
    /// Start a stack to be written to `target` with dtype `descr`
    /// (`"<f4"` or `"|u1"`) and frames of `ny × nx`; frames are spilled to
    /// a hidden file next to `target` until [`finish`](Self::finish). An
    /// error when that file cannot be created.
    pub(crate) fn create(target: &Path, descr: &'static str, ny: usize, nx: usize) -> Result<Self> {
        let dir = target
            .parent()
            .filter(|d| !d.as_os_str().is_empty())
            .unwrap_or(Path::new("."));
        let name = target
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        let spill_path = dir.join(format!(".{}.{}.spill", name, std::process::id()));
        let f = File::create(&spill_path).map_err(|e| Error::io(&spill_path, e))?;
        let elem = if descr == "|u1" { 1 } else { 4 };
        Ok(NpyStack {
            target: target.to_path_buf(),
            spill_path,
            spill: Some(BufWriter::new(f)),
            descr,
            frame_len: ny * nx * elem,
            ny,
            nx,
            steps: 0,
        })
    }

    /// Append one `<f4` frame of `ny · nx` values, row-major.
    pub(crate) fn push_f32(&mut self, vals: impl Iterator<Item = f32>) -> Result<()> {
        let w = self.spill.as_mut().expect("open");
        let mut n = 0;
        for v in vals {
            w.write_all(&v.to_le_bytes())
                .map_err(|e| Error::io(&self.spill_path, e))?;
            n += 4;
        }
        debug_assert_eq!(n, self.frame_len);
        self.steps += 1;
        Ok(())
    }

    /// Append one `|u1` frame of `ny · nx` values, row-major.
    pub(crate) fn push_u8(&mut self, vals: &[u8]) -> Result<()> {
        let w = self.spill.as_mut().expect("open");
        w.write_all(vals)
            .map_err(|e| Error::io(&self.spill_path, e))?;
        self.steps += 1;
        Ok(())
    }

    /// Write the `.npy` file (header and all frames) atomically to the
    /// target and remove the spill file; an error names the file that
    /// could not be read or written.
    pub(crate) fn finish(mut self) -> Result<()> {
        let w = self.spill.take().expect("open");
        w.into_inner()
            .map_err(|e| Error::io(&self.spill_path, e.into_error()))?;
        let mut out = AtomicFile::create(&self.target)?;
        out.write_all(&npy_header(self.descr, &[self.steps, self.ny, self.nx]))
            .map_err(|e| Error::io(&self.target, e))?;
        let mut f = File::open(&self.spill_path).map_err(|e| Error::io(&self.spill_path, e))?;
        let mut buf = vec![0u8; 1 << 20];
        loop {
            let n = f
                .read(&mut buf)
                .map_err(|e| Error::io(&self.spill_path, e))?;
            if n == 0 {
                break;
            }
            out.write_all(&buf[..n])
                .map_err(|e| Error::io(&self.target, e))?;
        }
        out.commit()?;
        let _ = std::fs::remove_file(&self.spill_path);
        Ok(())
    }
}

impl Drop for NpyStack {
    fn drop(&mut self) {
        // Unfinished (error path) or finished: the spill file never stays.
        self.spill.take();
        let _ = std::fs::remove_file(&self.spill_path);
    }
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;

    /// Same columns; values equal bit for bit (NaN equal to NaN).
    fn assert_same(a: &crate::compare::Table, b: &crate::compare::Table) {
        assert_eq!(a.names, b.names);
        for (x, y) in a.cols.iter().zip(&b.cols) {
            assert_eq!(x.len(), y.len());
            for (p, q) in x.iter().zip(y) {
                assert!(
                    p.to_bits() == q.to_bits() || (p.is_nan() && q.is_nan()),
                    "{p} {q}"
                );
            }
        }
    }

    #[ebptv_macros::unit_test]
    fn mean_and_steps_tables_hold_the_csv_values_in_every_format() {
        let dir = tempfile::tempdir().unwrap();
        let rows: Vec<MeanRow> = (0..40)
            .map(|i| {
                let f = i as f64;
                MeanRow {
                    x: 16.0 * (i % 8) as f64,
                    y: 16.0 * (i / 8) as f64,
                    u: if i % 7 == 3 {
                        f64::NAN
                    } else {
                        1.0 / (f + 0.3)
                    },
                    v: -f * 1e5 / 3.0,
                    uu: f.sqrt(),
                    vv: 1e-300 * f,
                    uv: -0.1 * f,
                    valid: f / 40.0,
                }
            })
            .collect();
        let steps: Vec<(i64, f64)> = (0..9).map(|k| (5 * k, 200.0 * k as f64 + 0.125)).collect();
        let calib = crate::calib::Calibration {
            px_per_mm: 12.5,
            origin_px: [10.0, 5.0],
            y_axis: crate::calib::YAxis::Up,
            mask: None,
        };
        for cal in [None, Some(&calib)] {
            let mut tables = Vec::new();
            for fmt in [TableFormat::Csv, TableFormat::Parquet, TableFormat::Npy] {
                let d = dir.path().join(format!("{fmt:?}{}", cal.is_some()));
                std::fs::create_dir_all(&d).unwrap();
                let m = write_mean_table(&d, fmt, &rows, cal).unwrap();
                let s = write_steps_table(&d, fmt, &steps).unwrap();
                assert_eq!(m, d.join(fmt.file_name("piv_mean")));
                assert_eq!(crate::table::TableFormat::sniff(&m).unwrap(), fmt);
                if fmt == TableFormat::Csv {
                    assert_eq!(std::fs::read_to_string(&m).unwrap(), mean_csv(&rows, cal));
                }
                tables.push((
                    crate::compare::read_table(&m, &[]).unwrap(),
                    crate::compare::read_table(&s, &[]).unwrap(),
                ));
            }
            assert_eq!(tables[0].0.names.len(), if cal.is_some() { 15 } else { 8 });
            assert_eq!(tables[0].1.names, ["step", "first_pulse", "t_us"]);
            for t in &tables[1..] {
                assert_same(&tables[0].0, &t.0);
                assert_same(&tables[0].1, &t.1);
            }
        }
    }

    #[ebptv_macros::unit_test]
    fn npy_header_is_aligned_and_parsable() {
        let h = npy_header("<f4", &[3, 4, 5]);
        assert_eq!(h.len() % 64, 0);
        let s = String::from_utf8_lossy(&h[10..]);
        assert!(s.contains("'shape': (3, 4, 5)"), "{s}");
        assert!(h.ends_with(b"\n"));
    }

    #[ebptv_macros::unit_test]
    fn npy_stack_writes_header_and_data() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("u.npy");
        let mut s = NpyStack::create(&p, "<f4", 2, 3).unwrap();
        s.push_f32((0..6).map(|i| i as f32)).unwrap();
        s.push_f32((6..12).map(|i| i as f32)).unwrap();
        s.finish().unwrap();
        let b = std::fs::read(&p).unwrap();
        let hl = 10 + u16::from_le_bytes([b[8], b[9]]) as usize;
        assert!(String::from_utf8_lossy(&b[..hl]).contains("(2, 2, 3)"));
        let vals: Vec<f32> = b[hl..]
            .chunks(4)
            .map(|c| f32::from_le_bytes(c.try_into().unwrap()))
            .collect();
        assert_eq!(vals, (0..12).map(|i| i as f32).collect::<Vec<_>>());
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
    }
}
