//! What `ebptv grid` does, as one call: a tracks table (or grid states to
//! merge) → the grid files of an output folder ([`grid_to_dir`]).

use std::path::{Path, PathBuf};

use serde_json::json;

use super::fields::{time_resolved, Frames};
use super::noise::{velocity_noise, NoiseEstimate, NoiseOptions};
use super::profiles::{profile_at_x, wall_fit, ProfilePoint, WallFit, WallOptions, WallSide};
use super::{estimate, io as gio, BinOptions, EstimateOptions, GridAccumulator, Sample};
use crate::error::{Error, Result};
use crate::io::atomic::{create_output_dir, AtomicFile};
use crate::table::TableFormat;

/// Where [`grid_to_dir`] takes its statistics from.
#[derive(Clone, Debug, PartialEq)]
pub enum GridInput {
    /// A tracks table of `ebptv track` (Parquet, CSV or npy), binned.
    Tracks(PathBuf),
    /// Grid states (`grid_state.json` files, or folders holding one),
    /// merged in order; their lattices must agree.
    Merge(Vec<PathBuf>),
}

/// A velocity profile through the grid (`profile.csv`) and, with `wall`,
/// a fit of the wall law to its near-wall points.
#[derive(Clone, Debug, PartialEq)]
pub struct ProfileOptions {
    /// The profile is the bin column nearest this x (px).
    pub x: f64,
    /// Side of the wall to fit (top = smallest y); `None`: no wall fit.
    pub wall: Option<WallSide>,
    /// Known wall position (px); `None`: estimated from the profile.
    pub wall_y: Option<f64>,
    /// Near-wall profile points in the fit.
    pub wall_points: usize,
    /// Kinematic viscosity (m²/s) for wall units.
    pub nu_m2_s: f64,
    /// Image scale (px/mm) for wall units; `None`: the calibration's.
    pub px_per_mm: Option<f64>,
}

/// Everything [`grid_to_dir`] needs besides the output folder.
#[derive(Clone, Debug, PartialEq)]
pub struct GridDirOptions {
    /// Tracks to bin, or states to merge.
    pub input: GridInput,
    /// Lattice and weighting (binning a tracks table only).
    pub bin: BinOptions,
    /// The estimator of each bin's statistics.
    pub estimate: EstimateOptions,
    /// Also write `profile.csv` (and a wall fit).
    pub profile: Option<ProfileOptions>,
    /// Also write time-resolved fields every this many pulses (a tracks
    /// table only).
    pub fields_every: Option<usize>,
    /// Write the PNG maps.
    pub plots: bool,
    /// A `calib.toml`: physical columns in the `grid` table, maps in m/s, and its
    /// mask applied.
    pub calibration: Option<PathBuf>,
    /// A mask image (non-zero = not flow); `None`: the `mask.png` beside a
    /// tracks table, when there is one.
    pub mask: Option<PathBuf>,
    /// Format of the `grid` and `grid_extra` tables.
    pub table_format: TableFormat,
}

/// What [`grid_to_dir`] reports to its progress callback as it goes.
#[derive(Clone, Copy, Debug)]
#[non_exhaustive]
pub enum GridProgress<'a> {
    /// The mask found beside the tracks table is applied.
    MaskFound(&'a Path),
    /// The table is read: `samples` are about to be binned.
    Binning {
        /// Samples in the table.
        samples: usize,
    },
    /// After each step of binning: samples binned in it.
    Binned(usize),
}

/// What [`grid_to_dir`] did, besides writing its files.
#[derive(Debug)]
pub struct GridDirRun {
    /// Bins along x.
    pub nx: usize,
    /// Bins along y.
    pub ny: usize,
    /// Bins with a finite mean.
    pub valid_bins: usize,
    /// Samples in the bins.
    pub binned_samples: u64,
    /// Largest mean speed over the valid bins (px/s).
    pub max_mean_speed: f64,
    /// The per-sample velocity noise (tracks input only): the estimate, or
    /// why there is none.
    pub noise: Option<Result<NoiseEstimate>>,
}

/// Bin a tracks table (or merge grid states) and write into `out` (created
/// if missing) what `ebptv grid` writes: `grid_state.json`, the `grid` and
/// `grid_extra` tables (`.parquet`, `.csv` or `.npy`: `table_format`), the
/// `grid_*.npy` arrays, the PNG maps, `grid.json`,
/// and on request `profile.csv` and the time-resolved fields.
pub fn grid_to_dir(
    opts: &GridDirOptions,
    out: &Path,
    on_progress: &mut dyn FnMut(GridProgress<'_>),
) -> Result<GridDirRun> {
    let est = &opts.estimate;
    est.validate()?;
    let tracks = match &opts.input {
        GridInput::Tracks(p) => Some(p.as_path()),
        GridInput::Merge(states) if states.is_empty() => {
            return Err(Error::param("input", "no grid state to merge"))
        }
        GridInput::Merge(_) => None,
    };
    // The mask: the one given, else the tracking run's mask.png beside the tracks.
    let run_mask = tracks
        .and_then(|t| t.parent())
        .map(|d| d.join("mask.png"))
        .filter(|p| opts.mask.is_none() && p.is_file());
    if let Some(p) = &run_mask {
        on_progress(GridProgress::MaskFound(p));
    }
    let (calib, mask) = crate::calib::load(
        opts.calibration.as_deref(),
        opts.mask.as_deref().or(run_mask.as_deref()),
    )?;
    // Checks that need no data, before any output exists.
    if opts.fields_every.is_some() && tracks.is_none() {
        return Err(Error::param(
            "fields_every",
            "time-resolved fields need a tracks table (grid states hold no time series)",
        ));
    }
    if opts.fields_every == Some(0) {
        return Err(Error::param(
            "fields_every",
            "a frame needs at least 1 pulse, got 0",
        ));
    }
    if let Some(p) = &opts.profile {
        if !p.x.is_finite() {
            return Err(Error::param(
                "profile_x",
                format!("must be a finite position (px), got {}", p.x),
            ));
        }
        if let Some(w) = p.wall_y.filter(|w| !w.is_finite()) {
            return Err(Error::param(
                "wall_y",
                format!("must be a finite position (px), got {w}"),
            ));
        }
        if let Some(s) = p.px_per_mm.filter(|s| !(s.is_finite() && *s > 0.0)) {
            return Err(Error::param(
                "px_per_mm",
                format!("scale must be > 0 px/mm, got {s}"),
            ));
        }
    }
    let scale = opts
        .profile
        .as_ref()
        .and_then(|p| p.px_per_mm)
        .or(calib.as_ref().map(|c| c.px_per_mm));
    if opts.profile.as_ref().is_some_and(|p| p.wall.is_some()) && scale.is_none() {
        return Err(Error::param(
            "px_per_mm",
            "a wall fit needs the image scale (px/mm) or a calibration",
        ));
    }
    create_output_dir(out)?;

    let mut samples: Vec<Sample> = Vec::new();
    let acc = match &opts.input {
        GridInput::Tracks(tracks) => {
            opts.bin.lattice()?; // a bad lattice before the (long) read
            samples = super::read_track_samples(tracks)?;
            on_progress(GridProgress::Binning {
                samples: samples.len(),
            });
            super::accumulate(
                &samples,
                &opts.bin,
                &tracks.display().to_string(),
                &mut |n| on_progress(GridProgress::Binned(n)),
            )?
        }
        GridInput::Merge(states) => merge_states(states)?,
    };

    let mut g = estimate(&acc, est)?;
    let masked_bins = mask.as_ref().map(|m| g.apply_mask(m));
    gio::save_state(&out.join("grid_state.json"), &acc)?;
    gio::write_grid_table(out, opts.table_format, &g, calib.as_ref())?;
    gio::write_extra_table(out, opts.table_format, &g)?;
    gio::write_grid_npy(out, &g)?;
    if opts.plots {
        gio::write_maps_calibrated(out, &g, calib.as_ref())?;
    }

    let valid = g.bins.iter().filter(|b| b.u.is_finite()).count();
    let max_speed = g
        .bins
        .iter()
        .filter(|b| b.u.is_finite())
        .map(|b| b.u.hypot(b.v))
        .fold(0.0, f64::max);
    let mut summary = json!({
        "bin_w": g.spec.lattice.bin_w, "bin_h": g.spec.lattice.bin_h, "overlap": g.spec.lattice.overlap,
        "origin": [g.spec.lattice.origin_x, g.spec.lattice.origin_y],
        "weighting": g.spec.weighting, "fit": est.fit, "min_count": est.min_count, "noise_rms": est.noise_rms,
        "nx": g.spec.nx, "ny": g.spec.ny, "valid_bins": valid,
        "binned_samples": acc.total_count(), "rejected_samples": acc.rejected, "max_mean_speed": max_speed,
    });
    if let Some(n) = masked_bins {
        summary["masked_bins"] = json!(n);
    }
    if let Some(c) = &calib {
        summary["px_per_mm"] = json!(c.px_per_mm);
    }
    // Per-sample velocity noise (pairs of samples at one pulse) and the
    // dynamic velocity range; needs the samples, so not after a merge.
    let noise = (!samples.is_empty()).then(|| {
        let n = velocity_noise(&samples, &g, &NoiseOptions::default());
        match &n {
            Ok(n) => {
                summary["velocity_noise_rms"] = json!(n.noise_rms);
                summary["noise_pairs"] = json!(n.pairs);
                summary["dynamic_range"] = json!(n.dynamic_range);
            }
            Err(_) => {
                summary["velocity_noise_rms"] = json!(null);
                summary["dynamic_range"] = json!(null);
            }
        }
        n
    });

    if let Some(p) = &opts.profile {
        let (x_used, prof) = profile_at_x(&g, p.x);
        let wall = match (p.wall, scale) {
            (Some(side), Some(px_per_mm)) => Some(wall_fit(
                &prof,
                &WallOptions {
                    side,
                    wall_y: p.wall_y,
                    n_fit: p.wall_points,
                    nu_m2_s: p.nu_m2_s,
                    px_per_mm,
                },
            )?),
            _ => None,
        };
        AtomicFile::write_all_to(
            out.join("profile.csv"),
            profile_csv(&prof, wall.as_ref(), scale).as_bytes(),
        )?;
        summary["profile_x"] = json!(x_used);
        if let Some(w) = wall {
            summary["wall"] =
                serde_json::to_value(w).map_err(|e| Error::analysis(format!("wall fit: {e}")))?;
        }
    }

    if let Some(k) = opts.fields_every {
        let frames = Frames::from_samples(&samples, k.max(1))?;
        let f = time_resolved(&samples, &g.spec, &frames, None)?;
        gio::write_fields_npy(out, &g.spec, &f)?;
        summary["fields"] = json!({"frames": frames.n, "step_us": frames.step_us, "window_us": frames.window_us, "t0_us": frames.t0_us});
    }

    let text = serde_json::to_string_pretty(&summary)
        .map_err(|e| Error::analysis(format!("grid.json: {e}")))?;
    AtomicFile::write_all_to(out.join("grid.json"), text.as_bytes())?;
    Ok(GridDirRun {
        nx: g.spec.nx,
        ny: g.spec.ny,
        valid_bins: valid,
        binned_samples: acc.total_count(),
        max_mean_speed: max_speed,
        noise,
    })
}

/// The states in `paths` (files, or folders holding `grid_state.json`)
/// merged in order.
fn merge_states(paths: &[PathBuf]) -> Result<GridAccumulator> {
    let mut acc: Option<GridAccumulator> = None;
    for p in paths {
        let sp = if p.is_dir() {
            p.join("grid_state.json")
        } else {
            p.to_path_buf()
        };
        let part = gio::load_state(&sp)?;
        match acc.as_mut() {
            None => acc = Some(part),
            Some(m) => m
                .merge(&part)
                .map_err(|e| Error::analysis(format!("merging {}: {e}", sp.display())))?,
        }
    }
    acc.ok_or_else(|| Error::param("input", "no grid state to merge"))
}

/// `profile.csv`: one row per profile point; with a wall fit and a scale,
/// the wall units too.
fn profile_csv(prof: &[ProfilePoint], wall: Option<&WallFit>, scale: Option<f64>) -> String {
    let mut s = String::from("y,count,u,v,uu,vv,uv");
    if wall.is_some() {
        s.push_str(",y_plus,u_plus,uu_plus");
    }
    s.push('\n');
    for p in prof {
        s.push_str(&format!(
            "{},{},{},{},{},{},{}",
            p.y, p.count, p.u, p.v, p.uu, p.vv, p.uv
        ));
        if let (Some(w), Some(scale)) = (wall, scale) {
            let (yp, up, uup) = w.inner(p, scale);
            s.push_str(&format!(",{yp},{up},{uup}"));
        }
        s.push('\n');
    }
    s.replace("NaN", "nan")
}
