//! PTV-versus-PIV comparison on the same grid.
//!
//! Both methods measure the same recording; their statistics live on
//! different grids (PTV bins, PIV window centres). The PIV field is
//! resampled onto the PTV bin centres by bilinear interpolation between
//! the four surrounding PIV nodes (no extrapolation: bins outside the PIV
//! node hull, or next to a PIV node without valid vectors, are left out).
//! PIV is the smoother field (window averaging), so interpolating it is
//! the gentler direction; resampling the noisier, sparser PTV bins would
//! add error to the reference.
//!
//! For every quantity (`u, v, uu, vv, uv`) the comparison reports the
//! number of bins compared, the mean and rms of `PTV − PIV`, and the rms of
//! each side for scale; difference maps and column-averaged profiles
//! `u(y)`, `v(y)` give the picture. [`compare_to_dir`] is what `ebptv
//! compare` writes.

use std::path::{Path, PathBuf};

use serde::Serialize;

use crate::error::{Error, Result};
use crate::io::atomic::AtomicFile;
use crate::plot::{heatmap, line_plot, Heatmap, LinePlot, Series, SeriesStyle};

/// A table read from a CSV with a header: named columns of numbers.
#[derive(Debug, Clone)]
#[ebptv_macros::testkit]
pub(crate) struct Table {
    /// Column names, in file order.
    pub names: Vec<String>,
    /// Column values, one vector per name (NaN for empty or `nan` cells).
    pub cols: Vec<Vec<f64>>,
}

impl Table {
    /// The column called `name`, if present.
    #[ebptv_macros::testkit]
    pub(crate) fn col(&self, name: &str) -> Option<&[f64]> {
        self.names
            .iter()
            .position(|n| n == name)
            .map(|i| self.cols[i].as_slice())
    }
    /// Number of data rows.
    #[ebptv_macros::testkit]
    pub(crate) fn rows(&self) -> usize {
        self.cols.first().map_or(0, |c| c.len())
    }
}

/// Read a numeric table (Parquet, `.npy`, or CSV with a header line),
/// requiring `required` columns.
#[ebptv_macros::testkit]
pub(crate) fn read_table(path: &Path, required: &[&str]) -> Result<Table> {
    use crate::table::{column_names, read_columns, TableFormat};
    if TableFormat::sniff(path)? != TableFormat::Csv {
        let names =
            column_names(path).ok_or_else(|| Error::corrupt(path, 0, "not a readable table"))?;
        let refs: Vec<&str> = names.iter().map(|s| s.as_str()).collect();
        for r in required {
            if !names.iter().any(|n| n == r) {
                return Err(Error::corrupt(
                    path,
                    0,
                    format!(
                        "missing column `{r}` (columns: {}; expected {})",
                        names.join(","),
                        required.join(",")
                    ),
                ));
            }
        }
        let cols = read_columns(path, &refs)?;
        if cols.first().is_none_or(|c| c.is_empty()) {
            return Err(Error::Empty {
                path: path.to_path_buf(),
                why: "no data rows".into(),
            });
        }
        return Ok(Table { names, cols });
    }
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let mut lines = text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty());
    let (_, header) = lines.next().ok_or_else(|| Error::Empty {
        path: path.to_path_buf(),
        why: "empty CSV file".into(),
    })?;
    let names: Vec<String> = header.split(',').map(|s| s.trim().to_string()).collect();
    for r in required {
        if !names.iter().any(|n| n == r) {
            return Err(Error::corrupt(
                path,
                0,
                format!(
                    "missing column `{r}` (header: {header}; expected {})",
                    required.join(",")
                ),
            ));
        }
    }
    let mut cols = vec![Vec::new(); names.len()];
    let mut offset = header.len() as u64 + 1;
    for (lineno, line) in lines {
        let fields: Vec<&str> = line.split(',').collect();
        if fields.len() != names.len() {
            return Err(Error::corrupt(
                path,
                offset,
                format!(
                    "line {}: {} fields, header has {}",
                    lineno + 1,
                    fields.len(),
                    names.len()
                ),
            ));
        }
        for (c, f) in fields.iter().enumerate() {
            let f = f.trim();
            let v = if f.eq_ignore_ascii_case("nan") || f.is_empty() {
                f64::NAN
            } else {
                f.parse::<f64>().map_err(|_| {
                    Error::corrupt(
                        path,
                        offset,
                        format!("line {}: `{f}` is not a number", lineno + 1),
                    )
                })?
            };
            cols[c].push(v);
        }
        offset += line.len() as u64 + 1;
    }
    if cols[0].is_empty() {
        return Err(Error::Empty {
            path: path.to_path_buf(),
            why: "no data rows".into(),
        });
    }
    Ok(Table { names, cols })
}

/// A regular grid recovered from scattered node coordinates.
#[derive(Debug, Clone, PartialEq)]
pub struct RegularGrid {
    /// Distinct node x coordinates, increasing.
    pub xs: Vec<f64>,
    /// Distinct node y coordinates, increasing.
    pub ys: Vec<f64>,
}

fn uniq(v: &[f64]) -> Vec<f64> {
    let mut u: Vec<f64> = v.iter().copied().filter(|x| x.is_finite()).collect();
    u.sort_by(|a, b| a.partial_cmp(b).unwrap());
    u.dedup_by(|a, b| (*a - *b).abs() < 1e-9);
    u
}

impl RegularGrid {
    pub(crate) fn from_nodes(x: &[f64], y: &[f64]) -> Self {
        RegularGrid {
            xs: uniq(x),
            ys: uniq(y),
        }
    }
    fn index(axis: &[f64], v: f64) -> Option<usize> {
        axis.binary_search_by(|a| a.partial_cmp(&v).unwrap())
            .ok()
            .or_else(|| axis.iter().position(|a| (a - v).abs() < 1e-6))
    }
    /// Fill a `ny × nx` row-major array with `vals` placed at their nodes.
    pub(crate) fn raster(&self, x: &[f64], y: &[f64], vals: &[f64]) -> Vec<f64> {
        let mut out = vec![f64::NAN; self.xs.len() * self.ys.len()];
        for k in 0..x.len() {
            if let (Some(i), Some(j)) = (Self::index(&self.xs, x[k]), Self::index(&self.ys, y[k])) {
                out[j * self.xs.len() + i] = vals[k];
            }
        }
        out
    }
    /// Bilinear interpolation of a rastered field; NaN outside the hull or
    /// when a surrounding node is NaN.
    pub(crate) fn bilinear(&self, field: &[f64], x: f64, y: f64) -> f64 {
        let seg = |axis: &[f64], v: f64| -> Option<(usize, f64)> {
            if axis.len() == 1 {
                return ((axis[0] - v).abs() < 1e-9).then_some((0, 0.0));
            }
            if v < axis[0] || v > axis[axis.len() - 1] {
                return None;
            }
            let i = axis.partition_point(|a| *a <= v).clamp(1, axis.len() - 1) - 1;
            Some((i, (v - axis[i]) / (axis[i + 1] - axis[i])))
        };
        let (Some((i, tx)), Some((j, ty))) = (seg(&self.xs, x), seg(&self.ys, y)) else {
            return f64::NAN;
        };
        let nx = self.xs.len();
        let at = |ii: usize, jj: usize| field[jj.min(self.ys.len() - 1) * nx + ii.min(nx - 1)];
        let (a, b, c, d) = (at(i, j), at(i + 1, j), at(i, j + 1), at(i + 1, j + 1));
        let w = [
            (1.0 - tx) * (1.0 - ty),
            tx * (1.0 - ty),
            (1.0 - tx) * ty,
            tx * ty,
        ];
        let mut acc = 0.0;
        for (v, wt) in [a, b, c, d].iter().zip(w) {
            if wt > 1e-12 {
                if !v.is_finite() {
                    return f64::NAN;
                }
                acc += v * wt;
            }
        }
        acc
    }
}

/// Agreement of one quantity.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct QuantityStats {
    /// Bins compared for this quantity.
    pub n: usize,
    /// Mean of PTV − PIV.
    pub mean_diff: f64,
    /// rms of PTV − PIV.
    pub rms_diff: f64,
    /// rms of the PTV values over the compared bins.
    pub ptv_rms: f64,
    /// rms of the resampled PIV values over the compared bins.
    pub piv_rms: f64,
}

/// The comparison result (serialised as `compare.json`).
#[derive(Debug, Clone, Serialize)]
pub struct Comparison {
    /// How PIV was resampled onto the PTV bins (a sentence).
    pub resampling: String,
    /// PTV bins in the grid table.
    pub ptv_bins: usize,
    /// PTV bins compared for at least one quantity.
    pub compared_bins: usize,
    /// Agreement per quantity (`u`, `v`, `uu`, `vv`, `uv`), in the tables' units.
    pub quantities: Vec<(String, QuantityStats)>,
    /// The PTV grid, and per quantity the difference raster on it.
    #[serde(skip)]
    pub grid: RegularGrid,
    /// Per quantity, PTV − PIV on the PTV grid (row-major, NaN where not compared).
    #[serde(skip)]
    pub diff_maps: Vec<(String, Vec<f64>)>,
    /// Column-averaged profiles: (y, PTV u, PIV u, PTV v, PIV v).
    #[serde(skip)]
    pub profiles: Vec<(f64, f64, f64, f64, f64)>,
}

pub(crate) const QUANTITIES: [&str; 5] = ["u", "v", "uu", "vv", "uv"];

/// Compare PTV bins (the `grid` table: `x,y,count,u,v,uu,vv,uv`) with PIV
/// nodes (the `piv_mean` table: `x,y,u,v,uu,vv,uv,valid`). `min_count`:
/// bins with fewer samples are ignored.
pub(crate) fn compare(ptv: &Table, piv: &Table, min_count: f64) -> Result<Comparison> {
    let c = |t: &Table, n: &str| {
        t.col(n)
            .map(|v| v.to_vec())
            .ok_or_else(|| Error::param("table", format!("missing column {n}")))
    };
    let (px, py, count) = (c(ptv, "x")?, c(ptv, "y")?, c(ptv, "count")?);
    let (qx, qy, valid) = (c(piv, "x")?, c(piv, "y")?, c(piv, "valid")?);
    let piv_grid = RegularGrid::from_nodes(&qx, &qy);
    if piv_grid.xs.len() * piv_grid.ys.len() != qx.len() {
        return Err(Error::param(
            "piv",
            format!(
                "PIV nodes are not a full regular grid ({} rows, {} x {} distinct coordinates)",
                qx.len(),
                piv_grid.xs.len(),
                piv_grid.ys.len()
            ),
        ));
    }
    let ptv_grid = RegularGrid::from_nodes(&px, &py);
    let mut quantities = Vec::new();
    let mut diff_maps = Vec::new();
    let mut resampled: Vec<Vec<f64>> = Vec::new();
    let mut compared = vec![false; px.len()];
    for q in QUANTITIES {
        let pv = c(ptv, q)?;
        let mut qv = c(piv, q)?;
        for k in 0..qv.len() {
            if !(valid[k] > 0.0) {
                qv[k] = f64::NAN;
            }
        }
        let raster = piv_grid.raster(&qx, &qy, &qv);
        let at_ptv: Vec<f64> = (0..px.len())
            .map(|k| piv_grid.bilinear(&raster, px[k], py[k]))
            .collect();
        let mut d = Vec::new();
        let (mut sp, mut sq) = (0.0, 0.0);
        let mut diff = vec![f64::NAN; px.len()];
        for k in 0..px.len() {
            if count[k] >= min_count && pv[k].is_finite() && at_ptv[k].is_finite() {
                diff[k] = pv[k] - at_ptv[k];
                d.push(diff[k]);
                sp += pv[k] * pv[k];
                sq += at_ptv[k] * at_ptv[k];
                compared[k] = true;
            }
        }
        let n = d.len();
        let nf = n.max(1) as f64;
        let stats = QuantityStats {
            n,
            mean_diff: if n > 0 {
                d.iter().sum::<f64>() / nf
            } else {
                f64::NAN
            },
            rms_diff: if n > 0 {
                (d.iter().map(|x| x * x).sum::<f64>() / nf).sqrt()
            } else {
                f64::NAN
            },
            ptv_rms: if n > 0 { (sp / nf).sqrt() } else { f64::NAN },
            piv_rms: if n > 0 { (sq / nf).sqrt() } else { f64::NAN },
        };
        quantities.push((q.to_string(), stats));
        diff_maps.push((q.to_string(), ptv_grid.raster(&px, &py, &diff)));
        resampled.push(at_ptv);
    }
    let compared_bins = compared.iter().filter(|&&b| b).count();
    if compared_bins == 0 {
        return Err(Error::analysis(
            "no PTV bin overlaps a valid PIV node: are both results from the same recording and pixel frame?",
        ));
    }
    // Column-averaged profiles over the bins compared for u and v.
    let (pu, pvv) = (c(ptv, "u")?, c(ptv, "v")?);
    let mut profiles = Vec::new();
    for &y in &ptv_grid.ys {
        let (mut n, mut a, mut b, mut cc, mut dd) = (0.0, 0.0, 0.0, 0.0, 0.0);
        for k in 0..px.len() {
            if (py[k] - y).abs() < 1e-9
                && count[k] >= min_count
                && pu[k].is_finite()
                && pvv[k].is_finite()
                && resampled[0][k].is_finite()
                && resampled[1][k].is_finite()
            {
                n += 1.0;
                a += pu[k];
                b += resampled[0][k];
                cc += pvv[k];
                dd += resampled[1][k];
            }
        }
        if n > 0.0 {
            profiles.push((y, a / n, b / n, cc / n, dd / n));
        }
    }
    Ok(Comparison {
        resampling: "PIV statistics interpolated bilinearly from the PIV nodes to the PTV bin centres; bins outside the PIV node hull or next to a PIV node without valid vectors are skipped".into(),
        ptv_bins: px.len(),
        compared_bins,
        quantities,
        grid: ptv_grid,
        diff_maps,
        profiles,
    })
}

/// The inputs of [`compare_to_dir`].
#[derive(Debug, Clone, PartialEq)]
pub struct CompareOptions {
    /// PTV grid statistics (the `grid` table, any format: x,y,count,u,v,uu,vv,uv).
    pub ptv: PathBuf,
    /// PIV statistics (the `piv_mean` table, any format: x,y,u,v,uu,vv,uv,valid).
    pub piv: PathBuf,
    /// PTV bins with fewer samples are ignored.
    pub min_count: f64,
    /// A `calib.toml`: physical units in `compare.json` and the figures.
    pub calibration: Option<PathBuf>,
}

/// What `ebptv compare` writes: the PTV and PIV statistics compared
/// (`compare`) → `compare.json`, `diff_*.png` and `profiles.png` in `out`
/// (created if missing).
pub fn compare_to_dir(opts: &CompareOptions, out: &Path) -> Result<Comparison> {
    let calib = opts
        .calibration
        .as_deref()
        .map(crate::calib::Calibration::from_file)
        .transpose()?;
    let ptv = read_table(&opts.ptv, &["x", "y", "count", "u", "v", "uu", "vv", "uv"])?;
    let piv = read_table(&opts.piv, &["x", "y", "u", "v", "uu", "vv", "uv", "valid"])?;
    let c = compare(&ptv, &piv, opts.min_count)?;
    crate::io::atomic::create_output_dir(out)?;
    let mut json = serde_json::json!({
        "ptv": opts.ptv.display().to_string(),
        "piv": opts.piv.display().to_string(),
        "resampling": c.resampling,
        "ptv_bins": c.ptv_bins,
        "compared_bins": c.compared_bins,
    });
    for (q, s) in &c.quantities {
        json[q] = serde_json::to_value(s).map_err(|e| Error::analysis(format!("{q}: {e}")))?;
    }
    // Factor of a quantity from px/s or (px/s)² to m/s or m²/s² (signed:
    // v and uv change sign with an upward y axis).
    let factor = |q: &str| -> f64 {
        match &calib {
            None => 1.0,
            Some(cal) => {
                let (k, ky) = cal.velocity_px_s_to_m_s(1.0, 1.0);
                match q {
                    "u" => k,
                    "v" => ky,
                    "uv" => k * ky,
                    _ => k * k,
                }
            }
        }
    };
    if let Some(cal) = &calib {
        let mut phys = serde_json::json!({ "px_per_mm": cal.px_per_mm });
        for (q, s) in &c.quantities {
            let k = factor(q);
            let unit = if q.len() == 1 { "m_s" } else { "m2_s2" };
            phys[q] = serde_json::json!({
                "n": s.n,
                format!("mean_diff_{unit}"): s.mean_diff * k,
                format!("rms_diff_{unit}"): s.rms_diff * k.abs(),
                format!("ptv_rms_{unit}"): s.ptv_rms * k.abs(),
                format!("piv_rms_{unit}"): s.piv_rms * k.abs(),
            });
        }
        json["physical"] = phys;
    }
    let (lv, ls) = if calib.is_some() {
        ("m/s", "(m/s)^2")
    } else {
        ("px/s", "(px/s)^2")
    };
    AtomicFile::write_all_to(
        out.join("compare.json"),
        serde_json::to_string_pretty(&json)
            .map_err(|e| Error::analysis(format!("compare.json: {e}")))?
            .as_bytes(),
    )?;
    let (nx, ny) = (c.grid.xs.len(), c.grid.ys.len());
    let xr = (c.grid.xs[0], *c.grid.xs.last().unwrap());
    let yr = (c.grid.ys[0], *c.grid.ys.last().unwrap());
    for (q, map) in &c.diff_maps {
        let title = format!("PTV - PIV: {q}");
        let k = factor(q);
        let map: Vec<f64> = map.iter().map(|v| v * k).collect();
        heatmap(
            &out.join(format!("diff_{q}.png")),
            &Heatmap {
                title: &title,
                values: &map,
                nx,
                ny,
                x_range: xr,
                y_range: yr,
                colorbar_label: if q.len() == 1 { lv } else { ls },
                diverging: true,
                axes_mm: calib.as_ref(),
            },
        )?;
    }
    let ys: Vec<f64> = c
        .profiles
        .iter()
        .map(|p| calib.as_ref().map_or(p.0, |cal| cal.px_to_mm(0.0, p.0).1))
        .collect();
    let ks = [factor("u"), factor("u"), factor("v"), factor("v")];
    let cols: Vec<Vec<f64>> = (1..5)
        .map(|i| {
            c.profiles
                .iter()
                .map(|p| [p.1, p.2, p.3, p.4][i - 1] * ks[i - 1])
                .collect()
        })
        .collect();
    let (y_label, v_label) = if calib.is_some() {
        ("y (mm)", "velocity (m/s)")
    } else {
        ("y (px)", "velocity (px/s)")
    };
    line_plot(
        &out.join("profiles.png"),
        &LinePlot {
            title: "Column-averaged profiles",
            x_label: y_label,
            y_label: v_label,
            series: vec![
                Series {
                    label: "PTV u",
                    x: &ys,
                    y: &cols[0],
                    style: SeriesStyle::Points,
                },
                Series {
                    label: "PIV u",
                    x: &ys,
                    y: &cols[1],
                    style: SeriesStyle::Line,
                },
                Series {
                    label: "PTV v",
                    x: &ys,
                    y: &cols[2],
                    style: SeriesStyle::Points,
                },
                Series {
                    label: "PIV v",
                    x: &ys,
                    y: &cols[3],
                    style: SeriesStyle::Line,
                },
            ],
            log_x: false,
            log_y: false,
            vlines: vec![],
        },
    )?;
    Ok(c)
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;

    fn table(names: &[&str], rows: Vec<Vec<f64>>) -> Table {
        let mut cols = vec![Vec::new(); names.len()];
        for r in rows {
            for (c, v) in r.into_iter().enumerate() {
                cols[c].push(v);
            }
        }
        Table {
            names: names.iter().map(|s| s.to_string()).collect(),
            cols,
        }
    }

    #[ebptv_macros::unit_test]
    fn linear_fields_agree_exactly_after_bilinear_resampling() {
        // PIV on a 16 px grid, PTV bins on an offset 10 px grid; u = 2x + y.
        let f = |x: f64, y: f64| (2.0 * x + y, -x, 1.0, 2.0, 0.5);
        let mut piv = Vec::new();
        for j in 0..6 {
            for i in 0..8 {
                let (x, y) = (15.5 + 16.0 * i as f64, 15.5 + 16.0 * j as f64);
                let (u, v, uu, vv, uv) = f(x, y);
                piv.push(vec![x, y, u, v, uu, vv, uv, 1.0]);
            }
        }
        let mut ptv = Vec::new();
        for j in 0..12 {
            for i in 0..14 {
                let (x, y) = (5.0 + 10.0 * i as f64, 5.0 + 10.0 * j as f64);
                let (u, v, uu, vv, uv) = f(x, y);
                ptv.push(vec![x, y, 10.0, u + 0.5, v, uu, vv, uv]);
            }
        }
        let piv = table(&["x", "y", "u", "v", "uu", "vv", "uv", "valid"], piv);
        let ptv = table(&["x", "y", "count", "u", "v", "uu", "vv", "uv"], ptv);
        let c = compare(&ptv, &piv, 1.0).unwrap();
        let u = &c.quantities[0].1;
        assert!(
            (u.mean_diff - 0.5).abs() < 1e-9 && (u.rms_diff - 0.5).abs() < 1e-9,
            "{u:?}"
        );
        let v = &c.quantities[1].1;
        assert!(v.rms_diff < 1e-9);
        // Only bins inside the PIV hull [15.5, 127.5] x [15.5, 95.5].
        let inside = (0..14)
            .filter(|i| (15.5..=127.5).contains(&(5.0 + 10.0 * *i as f64)))
            .count()
            * (0..12)
                .filter(|j| (15.5..=95.5).contains(&(5.0 + 10.0 * *j as f64)))
                .count();
        assert_eq!(c.compared_bins, inside);
        assert_eq!(u.n, inside);
    }

    #[ebptv_macros::unit_test]
    fn missing_columns_and_garbage_are_clear_errors() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("grid.csv");
        std::fs::write(&p, "x,y,u\n1,2,3\n").unwrap();
        let e = read_table(&p, &["x", "y", "count"])
            .unwrap_err()
            .to_string();
        assert!(e.contains("grid.csv") && e.contains("count"), "{e}");
        std::fs::write(&p, "x,y\n1,abc\n").unwrap();
        let e = read_table(&p, &["x", "y"]).unwrap_err().to_string();
        assert!(e.contains("abc"), "{e}");
        std::fs::write(&p, "").unwrap();
        assert!(read_table(&p, &["x"]).is_err());
    }
}
