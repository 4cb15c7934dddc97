//! `ebptv grid`: bin tracks onto an Eulerian grid, or merge grid states.

use std::path::{Path, PathBuf};

use anyhow::Context;
use clap::{Args, ValueEnum};
use serde_json::json;

use ebptv::grid::fields::{time_resolved, Frames};
use ebptv::grid::noise::{velocity_noise, NoiseOptions};
use ebptv::grid::profiles::{profile_at_x, wall_fit, WallOptions, WallSide};
use ebptv::grid::{
    self, estimate, io as gio, EstimateOptions, Fit, GridAccumulator, Sample, Weighting,
};
use ebptv::io::atomic::AtomicFile;

#[derive(Copy, Clone, Debug, PartialEq, Eq, ValueEnum)]
pub enum FitArg {
    /// Top-hat mean.
    None,
    /// In-bin linear fit of velocity over position.
    Linear,
    /// In-bin quadratic fit.
    Quadratic,
    /// Gaussian-weighted mean (same as `--weighting gaussian --fit none`).
    Gaussian,
}

#[derive(Copy, Clone, Debug, PartialEq, Eq, ValueEnum)]
pub enum WeightArg {
    Tophat,
    Gaussian,
}

#[derive(Copy, Clone, Debug, PartialEq, Eq, ValueEnum)]
pub enum SideArg {
    Top,
    Bottom,
}

#[derive(Args, Debug)]
pub struct GridArgs {
    /// A tracks table of `ebptv track` (tracks.parquet, .csv or .npy:
    /// `track_id,pulse,t_us,x,y,u,v`, px, px/s). A shell pattern such as
    /// `run1/tracks.*` may also name the run's figure (tracks.png): PNG
    /// files among the paths are skipped.
    #[arg(num_args = 0..)]
    pub tracks: Vec<PathBuf>,
    /// Merge grid states (grid_state.json files or directories holding one)
    /// instead of binning tracks; fit/min-count/noise options apply.
    #[arg(long, num_args = 1.., conflicts_with = "tracks")]
    pub merge: Vec<PathBuf>,
    /// Output directory.
    #[arg(long)]
    pub out: PathBuf,
    /// Bin width (px); also the height unless --bin-h is given.
    #[arg(long, default_value_t = grid::BinOptions::default().bin)]
    pub bin: f64,
    /// Bin height (px), for rectangular bins (e.g. thin bins near a wall).
    #[arg(long)]
    pub bin_h: Option<f64>,
    /// Fraction of a bin shared with its neighbour, in [0, 1).
    #[arg(long, default_value_t = grid::BinOptions::default().overlap)]
    pub overlap: f64,
    /// Lattice origin "x,y" (px); bins of runs to be merged must share it
    /// [default: -0.5,-0.5, pixel corners].
    #[arg(long, value_parser = parse_pair)]
    pub origin: Option<(f64, f64)>,
    /// Estimator of the mean inside a bin.
    #[arg(long, value_enum, default_value_t = FitArg::None)]
    pub fit: FitArg,
    /// Sample weighting inside a bin (combine `gaussian` with a linear fit).
    #[arg(long, value_enum)]
    pub weighting: Option<WeightArg>,
    /// Bins with fewer samples are empty (NaN).
    #[arg(long, default_value_t = grid::DEFAULT_MIN_COUNT)]
    pub min_count: u64,
    /// Velocity measurement noise rms (px/s) to subtract from uu and vv.
    #[arg(long, default_value_t = 0.0)]
    pub noise_rms: f64,
    /// Write a profile (profile.csv) of the bin column nearest this x (px).
    #[arg(long)]
    pub profile_x: Option<f64>,
    /// Wall side for the wall fit (needs --profile-x): top = smallest y.
    #[arg(long, value_enum, requires = "profile_x")]
    pub wall: Option<SideArg>,
    /// Known wall position (px); otherwise estimated from the profile.
    #[arg(long, requires = "wall")]
    pub wall_y: Option<f64>,
    /// Number of near-wall profile points in the wall fit.
    #[arg(long, default_value_t = 3)]
    pub wall_points: usize,
    /// Kinematic viscosity (m²/s) for wall units.
    #[arg(long, default_value_t = 1.0e-6)]
    pub nu: f64,
    /// Image scale (px/mm) for wall units.
    #[arg(long)]
    pub px_per_mm: Option<f64>,
    /// Also write time-resolved fields (fields_{u,v,count,t_us}.npy) every K pulses.
    #[arg(long)]
    pub fields_every: Option<usize>,
    /// Skip the PNG maps.
    #[arg(long)]
    pub no_plots: bool,
    /// A `calib.toml`: grid.csv gains `X_mm,Y_mm,U_m_s,V_m_s,uu_m2_s2,
    /// vv_m2_s2,uv_m2_s2` after the pixel columns, the maps are in m/s,
    /// and its [mask] applies as --mask does.
    #[arg(long)]
    pub calibration: Option<PathBuf>,
    /// Mask image (PNG, non-zero = not flow): bins more than half masked
    /// are empty (NaN). Without it, the `mask.png` that `ebptv track
    /// --mask` left beside the tracks file is used.
    #[arg(long)]
    pub mask: Option<PathBuf>,
}

pub fn parse_pair(s: &str) -> std::result::Result<(f64, f64), String> {
    let v: Vec<&str> = s.split(',').collect();
    if v.len() != 2 {
        return Err(format!("expected \"x,y\", got \"{s}\""));
    }
    let a = v[0]
        .trim()
        .parse::<f64>()
        .map_err(|e| format!("{s}: {e}"))?;
    let b = v[1]
        .trim()
        .parse::<f64>()
        .map_err(|e| format!("{s}: {e}"))?;
    Ok((a, b))
}

/// The one tracks table among `paths`: figures (PNG files, as a pattern
/// like `run1/tracks.*` also names `tracks.png`) are skipped; more than
/// one table is an error (several runs combine through `--merge`).
fn tracks_table(paths: Vec<PathBuf>) -> anyhow::Result<Vec<PathBuf>> {
    if paths.len() <= 1 {
        return Ok(paths);
    }
    let is_png = |p: &Path| -> bool {
        let mut head = [0u8; 8];
        std::fs::File::open(p)
            .and_then(|mut f| std::io::Read::read_exact(&mut f, &mut head))
            .is_ok()
            && head == *b"\x89PNG\r\n\x1a\n"
    };
    let (figures, tables): (Vec<PathBuf>, Vec<PathBuf>) =
        paths.into_iter().partition(|p| is_png(p));
    for f in &figures {
        eprintln!(
            "grid: skipping {} (a figure, not a tracks table)",
            f.display()
        );
    }
    anyhow::ensure!(
        tables.len() <= 1,
        "{} tracks tables given ({}): give one, or bin each and combine their grid states with --merge",
        tables.len(),
        tables
            .iter()
            .map(|p| p.display().to_string())
            .collect::<Vec<_>>()
            .join(", ")
    );
    Ok(tables)
}

/// A tracks table (any format) as samples (through the tracker's reader,
/// which groups rows by track — what the per-track standard errors want);
/// an error when the file holds no track point.
pub use ebptv::grid::read_track_samples;

fn state_path(p: &Path) -> PathBuf {
    if p.is_dir() {
        p.join("grid_state.json")
    } else {
        p.to_path_buf()
    }
}

pub fn run(mut a: GridArgs) -> anyhow::Result<()> {
    a.tracks = tracks_table(std::mem::take(&mut a.tracks))?;
    let (weighting, fit) = match (a.fit, a.weighting) {
        (FitArg::Gaussian, Some(WeightArg::Tophat)) => {
            anyhow::bail!("--fit gaussian contradicts --weighting tophat")
        }
        (FitArg::Gaussian, _) => (Weighting::Gaussian, Fit::None),
        (f, w) => (
            if w == Some(WeightArg::Gaussian) {
                Weighting::Gaussian
            } else {
                Weighting::TopHat
            },
            match f {
                FitArg::None => Fit::None,
                FitArg::Linear => Fit::Linear,
                FitArg::Quadratic => Fit::Quadratic,
                FitArg::Gaussian => unreachable!(),
            },
        ),
    };
    let opt = EstimateOptions {
        fit,
        min_count: a.min_count,
        noise_rms: a.noise_rms,
    };
    opt.validate()?;
    // The mask: --mask, else the tracking run's mask.png beside the tracks.
    let run_mask = a
        .tracks
        .first()
        .and_then(|t| t.parent())
        .map(|d| d.join("mask.png"))
        .filter(|p| a.mask.is_none() && p.is_file());
    if let Some(p) = &run_mask {
        eprintln!("grid: masked by {}", p.display());
    }
    let (calib, mask) = ebptv::calib::load(
        a.calibration.as_deref(),
        a.mask.as_deref().or(run_mask.as_deref()),
    )?;
    ebptv::io::atomic::create_output_dir(&a.out)?;

    let mut samples: Vec<Sample> = Vec::new();
    let acc = if !a.merge.is_empty() {
        let mut acc: Option<GridAccumulator> = None;
        for p in &a.merge {
            let sp = state_path(p);
            let part = gio::load_state(&sp)?;
            match acc.as_mut() {
                None => acc = Some(part),
                Some(m) => m
                    .merge(&part)
                    .with_context(|| format!("merging {}", sp.display()))?,
            }
        }
        acc.expect("at least one state")
    } else {
        let tracks = a
            .tracks
            .first()
            .context("give a tracks file, or --merge STATE...")?;
        let opts = grid::BinOptions {
            bin: a.bin,
            bin_h: a.bin_h,
            overlap: a.overlap,
            origin: a.origin.unwrap_or(grid::BinOptions::default().origin),
            weighting,
        };
        opts.lattice()?; // a bad lattice before the (long) read
        samples = read_track_samples(tracks)?;
        let bar = indicatif::ProgressBar::new(samples.len() as u64);
        if samples.len() < 1_000_000 {
            bar.set_draw_target(indicatif::ProgressDrawTarget::hidden());
        }
        let acc = grid::accumulate(&samples, &opts, &tracks.display().to_string(), &mut |n| {
            bar.inc(n as u64)
        })?;
        bar.finish_and_clear();
        acc
    };

    let mut g = estimate(&acc, &opt)?;
    let masked_bins = mask.as_ref().map(|m| g.apply_mask(m));
    gio::save_state(&a.out.join("grid_state.json"), &acc)?;
    gio::write_grid_csv_calibrated(&a.out.join("grid.csv"), &g, calib.as_ref())?;
    gio::write_extra_csv(&a.out.join("grid_extra.csv"), &g)?;
    gio::write_grid_npy(&a.out, &g)?;
    if !a.no_plots {
        gio::write_maps_calibrated(&a.out, &g, calib.as_ref())?;
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
        "weighting": g.spec.weighting, "fit": opt.fit, "min_count": opt.min_count, "noise_rms": opt.noise_rms,
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
    if !samples.is_empty() {
        match velocity_noise(&samples, &g, &NoiseOptions::default()) {
            Ok(n) => {
                summary["velocity_noise_rms"] = json!(n.noise_rms);
                summary["noise_pairs"] = json!(n.pairs);
                summary["dynamic_range"] = json!(n.dynamic_range);
                eprintln!(
                    "grid: velocity noise {:.1} px/s per sample ({} pairs), dynamic range {:.0}:1",
                    n.noise_rms, n.pairs, n.dynamic_range
                );
            }
            Err(e) => {
                summary["velocity_noise_rms"] = json!(null);
                summary["dynamic_range"] = json!(null);
                eprintln!("grid: no noise estimate: {e}");
            }
        }
    }

    if let Some(px) = a.profile_x {
        let (x_used, prof) = profile_at_x(&g, px);
        let wall = match a.wall {
            Some(side) => {
                let scale = a
                    .px_per_mm
                    .or(calib.as_ref().map(|c| c.px_per_mm))
                    .context("--wall needs --px-per-mm (or --calibration) for wall units")?;
                let side = if side == SideArg::Top {
                    WallSide::Top
                } else {
                    WallSide::Bottom
                };
                Some(wall_fit(
                    &prof,
                    &WallOptions {
                        side,
                        wall_y: a.wall_y,
                        n_fit: a.wall_points,
                        nu_m2_s: a.nu,
                        px_per_mm: scale,
                    },
                )?)
            }
            None => None,
        };
        let mut s = String::from("y,count,u,v,uu,vv,uv");
        if wall.is_some() {
            s.push_str(",y_plus,u_plus,uu_plus");
        }
        s.push('\n');
        for p in &prof {
            s.push_str(&format!(
                "{},{},{},{},{},{},{}",
                p.y, p.count, p.u, p.v, p.uu, p.vv, p.uv
            ));
            if let (Some(w), Some(scale)) =
                (&wall, a.px_per_mm.or(calib.as_ref().map(|c| c.px_per_mm)))
            {
                let (yp, up, uup) = w.inner(p, scale);
                s.push_str(&format!(",{yp},{up},{uup}"));
            }
            s.push('\n');
        }
        let s = s.replace("NaN", "nan");
        AtomicFile::write_all_to(a.out.join("profile.csv"), s.as_bytes())?;
        summary["profile_x"] = json!(x_used);
        if let Some(w) = wall {
            summary["wall"] = serde_json::to_value(w)?;
        }
    }

    if let Some(k) = a.fields_every {
        anyhow::ensure!(
            !samples.is_empty(),
            "--fields-every needs a tracks file (states hold no time series)"
        );
        let frames = Frames::from_samples(&samples, k.max(1))?;
        let f = time_resolved(&samples, &g.spec, &frames, None)?;
        gio::write_fields_npy(&a.out, &g.spec, &f)?;
        summary["fields"] = json!({"frames": frames.n, "step_us": frames.step_us, "window_us": frames.window_us, "t0_us": frames.t0_us});
    }

    AtomicFile::write_all_to(
        a.out.join("grid.json"),
        serde_json::to_string_pretty(&summary)?.as_bytes(),
    )?;
    eprintln!(
        "grid: {} x {} bins ({} valid, ≥ {} samples), {} samples binned, max mean speed {:.1} px/s → {}",
        g.spec.nx,
        g.spec.ny,
        valid,
        opt.min_count,
        acc.total_count(),
        max_speed,
        a.out.display()
    );
    Ok(())
}
