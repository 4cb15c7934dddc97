//! PIV output files: `piv_mean.csv`, per-frame vector CSV and `.npy`
//! stacks of the fields at every step. Everything goes through
//! [`AtomicFile`].
//!
//! The `.npy` stack is written while streaming: the number of steps is only
//! known at the end, so the data goes to a hidden spill file first and is
//! copied behind a correct header on [`NpyStack::finish`]. (A minimal NPY
//! v1.0 writer of its own; `crate::io::npy` holds the general writers.)

use std::fs::File;
use std::io::{BufWriter, Read, Write};
use std::path::{Path, PathBuf};

use super::{MeanRow, VectorField};
use crate::error::{Error, Result};
use crate::io::atomic::AtomicFile;

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
pub fn write_mean_csv_calibrated(
    path: &Path,
    rows: &[MeanRow],
    calib: Option<&crate::calib::Calibration>,
) -> Result<()> {
    AtomicFile::write_all_to(path, mean_csv(rows, calib).as_bytes())
}

/// The text of `piv_mean.csv` ([`write_mean_csv_calibrated`]).
pub fn mean_csv(rows: &[MeanRow], calib: Option<&crate::calib::Calibration>) -> String {
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
pub fn write_vectors_csv(path: &Path, f: &VectorField) -> Result<()> {
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

/// NPY v1.0 header for a C-order array (see [`crate::io::npy`]).
pub(crate) fn npy_header(descr: &str, shape: &[usize]) -> Vec<u8> {
    crate::io::npy::array_header(descr, shape)
}

/// A stack of 2-D frames (`ny × nx`) of one dtype (`<f4` or `|u1`) written
/// as a 3-D `.npy` `(steps, ny, nx)`.
pub struct NpyStack {
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
    pub fn create(target: &Path, descr: &'static str, ny: usize, nx: usize) -> Result<Self> {
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
    pub fn push_f32(&mut self, vals: impl Iterator<Item = f32>) -> Result<()> {
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
    pub fn push_u8(&mut self, vals: &[u8]) -> Result<()> {
        let w = self.spill.as_mut().expect("open");
        w.write_all(vals)
            .map_err(|e| Error::io(&self.spill_path, e))?;
        self.steps += 1;
        Ok(())
    }

    /// Write the `.npy` file (header and all frames) atomically to the
    /// target and remove the spill file; an error names the file that
    /// could not be read or written.
    pub fn finish(mut self) -> Result<()> {
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn npy_header_is_aligned_and_parsable() {
        let h = npy_header("<f4", &[3, 4, 5]);
        assert_eq!(h.len() % 64, 0);
        let s = String::from_utf8_lossy(&h[10..]);
        assert!(s.contains("'shape': (3, 4, 5)"), "{s}");
        assert!(h.ends_with(b"\n"));
    }

    #[test]
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
