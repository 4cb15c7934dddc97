//! Grid files: the mergeable state (`grid_state.json`), the `grid` and
//! `grid_extra` tables (Parquet, CSV or `.npy`), `profile.csv` and PNG maps.
//!
//! The state is JSON with only the non-empty bins; f64 values are written
//! in shortest round-trip form so reading a state back reproduces the sums.

use std::io::Write;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::accumulate::{BinAcc, GridAccumulator};
use super::estimate::GridStats;
use super::spec::GridSpec;
use crate::calib::Calibration;
use crate::error::{Error, Result};
use crate::io::atomic::AtomicFile;
use crate::table::{write_table, Col, TableFormat};

const STATE_FORMAT: &str = "ebptv-grid-state";
const STATE_VERSION: u32 = 1;

#[derive(Serialize, Deserialize)]
struct StateFile {
    format: String,
    version: u32,
    spec: GridSpec,
    rejected: u64,
    outside: u64,
    /// (flat index, sums) of the non-empty bins.
    bins: Vec<(usize, BinAcc)>,
}

/// Write the accumulator so that `ebptv grid --merge` can combine it with others.
pub(crate) fn save_state(path: &Path, acc: &GridAccumulator) -> Result<()> {
    let text = state_json(acc).map_err(|e| Error::io(path, e.into()))?;
    let mut f = AtomicFile::create(path)?;
    f.write_all(text.as_bytes())
        .map_err(|e| Error::io(path, e))?;
    f.commit()
}

/// The text of `grid_state.json` (`save_state`).
pub(crate) fn state_json(acc: &GridAccumulator) -> serde_json::Result<String> {
    let st = StateFile {
        format: STATE_FORMAT.into(),
        version: STATE_VERSION,
        spec: acc.spec,
        rejected: acc.rejected,
        outside: acc.outside,
        bins: acc
            .bins
            .iter()
            .enumerate()
            .filter(|(_, b)| b.n > 0)
            .map(|(k, b)| (k, b.clone()))
            .collect(),
    };
    serde_json::to_string(&st)
}

/// Read a state written by [`save_state`].
pub(crate) fn load_state(path: &Path) -> Result<GridAccumulator> {
    let text = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    state_from_json(&text, path)
}

/// A state from the text of a `grid_state.json` (`path` names it in
/// errors).
pub(crate) fn state_from_json(text: &[u8], path: &Path) -> Result<GridAccumulator> {
    let st: StateFile = serde_json::from_slice(text).map_err(|e| {
        Error::corrupt(
            path,
            0,
            format!("not an ebptv grid state (grid_state.json): {e}"),
        )
    })?;
    if st.format != STATE_FORMAT || st.version != STATE_VERSION {
        return Err(Error::corrupt(
            path,
            0,
            format!(
                "unsupported grid state format {} v{}",
                st.format, st.version
            ),
        ));
    }
    let spec = GridSpec::from_window(
        st.spec.lattice,
        st.spec.weighting,
        st.spec.i0,
        st.spec.j0,
        st.spec.nx,
        st.spec.ny,
    )
    .map_err(|e| Error::corrupt(path, 0, e.to_string()))?;
    // Re-validate the lattice (a hand-edited file must not smuggle in bin 0).
    crate::grid::spec::Lattice::with_origin(
        spec.lattice.bin_w,
        spec.lattice.bin_h,
        spec.lattice.overlap,
        spec.lattice.origin_x,
        spec.lattice.origin_y,
    )
    .map_err(|e| Error::corrupt(path, 0, e.to_string()))?;
    let mut acc = GridAccumulator::new(spec);
    acc.rejected = st.rejected;
    acc.outside = st.outside;
    for (k, b) in st.bins {
        if k >= acc.bins.len() {
            return Err(Error::corrupt(
                path,
                0,
                format!("bin index {k} outside the {}x{} grid", spec.nx, spec.ny),
            ));
        }
        acc.bins[k] = b;
    }
    Ok(acc)
}

fn num(x: f64) -> String {
    if x.is_finite() {
        format!("{x}")
    } else {
        "nan".into()
    }
}

/// [`write_grid_csv`], with the physical columns of `calib` after the
/// pixel ones when given ([`Calibration::field_columns`]:
/// `X_mm,Y_mm,U_m_s,V_m_s,uu_m2_s2,vv_m2_s2,uv_m2_s2`).
pub(crate) fn write_grid_csv_calibrated(
    path: &Path,
    g: &GridStats,
    calib: Option<&Calibration>,
) -> Result<()> {
    let mut f = AtomicFile::create(path)?;
    let mut s = String::from("x,y,count,u,v,uu,vv,uv");
    if calib.is_some() {
        s.push_str(&crate::calib::header_suffix(Calibration::field_columns()));
    }
    s.push('\n');
    for (iy, &y) in g.ys.iter().enumerate() {
        for (ix, &x) in g.xs.iter().enumerate() {
            let b = g.at(ix, iy);
            s.push_str(&format!(
                "{},{},{},{},{},{},{},{}",
                x,
                y,
                b.count,
                num(b.u),
                num(b.v),
                num(b.uu),
                num(b.vv),
                num(b.uv)
            ));
            if let Some(c) = calib {
                let vals = c.field_values(x, y, b.u, b.v, b.uu, b.vv, b.uv);
                for v in vals {
                    s.push(',');
                    s.push_str(&num(v));
                }
            }
            s.push('\n');
        }
    }
    f.write_all(s.as_bytes()).map_err(|e| Error::io(path, e))?;
    f.commit()
}

/// Columns of `grid_extra.csv`.
#[ebptv_macros::testkit]
pub(crate) const EXTRA_HEADER: &str =
    "x,y,n_tracks,se_u,se_v,se_uu,se_vv,se_uv,dudx,dudy,dvdx,dvdy,fit_params";

/// `grid_extra.csv`: per bin `x,y,n_tracks,se_u,se_v,se_uu,se_vv,se_uv,
/// dudx,dudy,dvdx,dvdy,fit_params` (same row order as `grid.csv`).
pub(crate) fn write_extra_csv(path: &Path, g: &GridStats) -> Result<()> {
    let mut f = AtomicFile::create(path)?;
    let mut s = String::from(EXTRA_HEADER);
    s.push('\n');
    for (iy, &y) in g.ys.iter().enumerate() {
        for (ix, &x) in g.xs.iter().enumerate() {
            let b = g.at(ix, iy);
            s.push_str(&format!(
                "{},{},{},{},{},{},{},{},{},{},{},{},{}\n",
                x,
                y,
                b.n_tracks,
                num(b.se_u),
                num(b.se_v),
                num(b.se_uu),
                num(b.se_vv),
                num(b.se_uv),
                num(b.dudx),
                num(b.dudy),
                num(b.dvdx),
                num(b.dvdy),
                b.fit_params
            ));
        }
    }
    f.write_all(s.as_bytes()).map_err(|e| Error::io(path, e))?;
    f.commit()
}

/// One row of the `grid` table: a bin's centre, its statistics and, with
/// a calibration, their physical values.
pub(crate) struct GridRow {
    x: f64,
    y: f64,
    count: i64,
    stats: [f64; 5],
    phys: [f64; 7],
}

macro_rules! grid_cols {
    ($($extra:expr),*) => {
        [
            Col::f64("x", |r: &GridRow| r.x),
            Col::f64("y", |r: &GridRow| r.y),
            Col::i64("count", |r: &GridRow| r.count),
            Col::f64("u", |r: &GridRow| r.stats[0]),
            Col::f64("v", |r: &GridRow| r.stats[1]),
            Col::f64("uu", |r: &GridRow| r.stats[2]),
            Col::f64("vv", |r: &GridRow| r.stats[3]),
            Col::f64("uv", |r: &GridRow| r.stats[4]),
            $($extra),*
        ]
    };
}

/// Columns of the `grid` table (px, px/s, (px/s)²).
static GRID_COLUMNS: [Col<GridRow>; 8] = grid_cols!();
/// [`GRID_COLUMNS`] and the physical columns of a calibration
/// (`X_mm,Y_mm,U_m_s,V_m_s,uu_m2_s2,vv_m2_s2,uv_m2_s2`).
static GRID_COLUMNS_CALIBRATED: [Col<GridRow>; 15] = grid_cols!(
    Col::f64("X_mm", |r: &GridRow| r.phys[0]),
    Col::f64("Y_mm", |r: &GridRow| r.phys[1]),
    Col::f64("U_m_s", |r: &GridRow| r.phys[2]),
    Col::f64("V_m_s", |r: &GridRow| r.phys[3]),
    Col::f64("uu_m2_s2", |r: &GridRow| r.phys[4]),
    Col::f64("vv_m2_s2", |r: &GridRow| r.phys[5]),
    Col::f64("uv_m2_s2", |r: &GridRow| r.phys[6])
);

/// The rows of the `grid` table, by y then x.
fn grid_rows<'a>(
    g: &'a GridStats,
    calib: Option<&'a Calibration>,
) -> impl Iterator<Item = GridRow> + 'a {
    g.ys.iter().enumerate().flat_map(move |(iy, &y)| {
        g.xs.iter().enumerate().map(move |(ix, &x)| {
            let b = g.at(ix, iy);
            GridRow {
                x,
                y,
                count: b.count as i64,
                stats: [b.u, b.v, b.uu, b.vv, b.uv],
                phys: calib.map_or([f64::NAN; 7], |c| {
                    c.field_values(x, y, b.u, b.v, b.uu, b.vv, b.uv)
                }),
            }
        })
    })
}

/// The `grid` table (`grid.parquet`, `grid.csv` or `grid.npy`) in `dir`;
/// with `calib` its physical columns after the pixel ones. The path
/// written.
pub(crate) fn write_grid_table(
    dir: &Path,
    format: TableFormat,
    g: &GridStats,
    calib: Option<&Calibration>,
) -> Result<PathBuf> {
    let cols: &'static [Col<GridRow>] = match calib {
        Some(_) => &GRID_COLUMNS_CALIBRATED,
        None => &GRID_COLUMNS,
    };
    write_table(dir, "grid", format, cols, grid_rows(g, calib), |p| {
        write_grid_csv_calibrated(p, g, calib)
    })
}

/// One row of the `grid_extra` table.
pub(crate) struct ExtraRow {
    x: f64,
    y: f64,
    n_tracks: i64,
    vals: [f64; 9],
    fit_params: i64,
}

/// Columns of the `grid_extra` table ([`EXTRA_HEADER`]).
static EXTRA_COLUMNS: [Col<ExtraRow>; 13] = [
    Col::f64("x", |r| r.x),
    Col::f64("y", |r| r.y),
    Col::i64("n_tracks", |r| r.n_tracks),
    Col::f64("se_u", |r| r.vals[0]),
    Col::f64("se_v", |r| r.vals[1]),
    Col::f64("se_uu", |r| r.vals[2]),
    Col::f64("se_vv", |r| r.vals[3]),
    Col::f64("se_uv", |r| r.vals[4]),
    Col::f64("dudx", |r| r.vals[5]),
    Col::f64("dudy", |r| r.vals[6]),
    Col::f64("dvdx", |r| r.vals[7]),
    Col::f64("dvdy", |r| r.vals[8]),
    Col::i64("fit_params", |r| r.fit_params),
];

/// The `grid_extra` table in `dir`, rows as in the `grid` table. The path
/// written.
pub(crate) fn write_extra_table(dir: &Path, format: TableFormat, g: &GridStats) -> Result<PathBuf> {
    let rows = g.ys.iter().enumerate().flat_map(|(iy, &y)| {
        g.xs.iter().enumerate().map(move |(ix, &x)| {
            let b = g.at(ix, iy);
            ExtraRow {
                x,
                y,
                n_tracks: b.n_tracks as i64,
                vals: [
                    b.se_u, b.se_v, b.se_uu, b.se_vv, b.se_uv, b.dudx, b.dudy, b.dvdx, b.dvdy,
                ],
                fit_params: b.fit_params as i64,
            }
        })
    });
    write_table(dir, "grid_extra", format, &EXTRA_COLUMNS, rows, |p| {
        write_extra_csv(p, g)
    })
}

/// `.npy` arrays in `dir`: `grid_x.npy` (nx), `grid_y.npy` (ny) bin centres
/// and `grid_<q>.npy` of shape (ny, nx) for q in count, n_tracks, u, v, uu,
/// vv, uv, se_u, se_v (f64, NaN for empty bins).
pub(crate) fn write_grid_npy(dir: &Path, g: &GridStats) -> Result<()> {
    use crate::io::npy::write_npy_f64;
    let shape = [g.spec.ny, g.spec.nx];
    write_npy_f64(dir.join("grid_x.npy"), &[g.spec.nx], &g.xs)?;
    write_npy_f64(dir.join("grid_y.npy"), &[g.spec.ny], &g.ys)?;
    let qs: [(&str, Vec<f64>); 9] = [
        ("count", g.map(|b| b.count as f64)),
        ("n_tracks", g.map(|b| b.n_tracks as f64)),
        ("u", g.map(|b| b.u)),
        ("v", g.map(|b| b.v)),
        ("uu", g.map(|b| b.uu)),
        ("vv", g.map(|b| b.vv)),
        ("uv", g.map(|b| b.uv)),
        ("se_u", g.map(|b| b.se_u)),
        ("se_v", g.map(|b| b.se_v)),
    ];
    for (name, v) in qs.iter() {
        write_npy_f64(dir.join(format!("grid_{name}.npy")), &shape, v)?;
    }
    Ok(())
}

/// Time-resolved fields as `.npy`: `fields_u.npy`, `fields_v.npy` (f64,
/// NaN where a bin had no sample in a frame) and `fields_count.npy` of
/// shape (frames, ny, nx), `fields_t_us.npy` (frames) the frame centres.
pub(crate) fn write_fields_npy(
    dir: &Path,
    spec: &GridSpec,
    f: &crate::grid::fields::FieldSeries,
) -> Result<()> {
    use crate::io::npy::write_npy_f64;
    let (nt, nb) = (f.frames.n, spec.n_bins());
    if f.bins.len() != nb || f.bins.iter().enumerate().any(|(k, &b)| k != b) {
        return Err(Error::param(
            "fields",
            "writing fields needs the series of every bin in order",
        ));
    }
    // Series are stored bin-major; numpy wants (t, y, x).
    let transpose = |src: &dyn Fn(usize) -> f64| {
        let mut out = vec![0.0; nt * nb];
        for b in 0..nb {
            for k in 0..nt {
                out[k * nb + b] = src(b * nt + k);
            }
        }
        out
    };
    let shape = [nt, spec.ny, spec.nx];
    write_npy_f64(dir.join("fields_u.npy"), &shape, &transpose(&|e| f.u[e]))?;
    write_npy_f64(dir.join("fields_v.npy"), &shape, &transpose(&|e| f.v[e]))?;
    write_npy_f64(
        dir.join("fields_count.npy"),
        &shape,
        &transpose(&|e| f.count[e] as f64),
    )?;
    let t: Vec<f64> = (0..nt).map(|k| f.frames.time_us(k)).collect();
    write_npy_f64(dir.join("fields_t_us.npy"), &[nt], &t)
}

/// [`write_maps`]; with `calib` the colour scales are in m/s and m²/s².
pub(crate) fn write_maps_calibrated(
    dir: &Path,
    g: &GridStats,
    calib: Option<&Calibration>,
) -> Result<()> {
    let x_range = (g.xs[0], *g.xs.last().unwrap());
    let y_range = (g.ys[0], *g.ys.last().unwrap());
    let (k1, k2, ky) = match calib {
        Some(c) => {
            let k = 1.0 / (c.px_per_mm * 1000.0);
            let (_, sy) = c.velocity_px_s_to_m_s(0.0, 1.0);
            (k, k * k, sy.signum())
        }
        None => (1.0, 1.0, 1.0),
    };
    let (lv, ls) = if calib.is_some() {
        (" (m/s)", " (m/s)^2")
    } else {
        (" (px/s)", " (px/s)^2")
    };
    let maps: [(&str, String, bool, Vec<f64>); 6] = [
        (
            "count",
            "samples per bin".into(),
            false,
            g.map(|b| b.count as f64),
        ),
        ("u", format!("u{lv}"), false, g.map(|b| b.u * k1)),
        ("v", format!("v{lv}"), true, g.map(|b| b.v * k1 * ky)),
        ("uu", format!("<u'u'>{ls}"), false, g.map(|b| b.uu * k2)),
        ("vv", format!("<v'v'>{ls}"), false, g.map(|b| b.vv * k2)),
        ("uv", format!("<u'v'>{ls}"), true, g.map(|b| b.uv * k2 * ky)),
    ];
    for (name, label, diverging, values) in maps.iter() {
        let title = format!("grid: {name}");
        crate::plot::heatmap(
            &dir.join(format!("map_{name}.png")),
            &crate::plot::Heatmap {
                title: &title,
                values,
                nx: g.spec.nx,
                ny: g.spec.ny,
                x_range,
                y_range,
                colorbar_label: label,
                diverging: *diverging,
                axes_mm: calib,
            },
        )?;
    }
    Ok(())
}
