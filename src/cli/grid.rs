//! `ebptv grid`: bin tracks onto an Eulerian grid, or merge grid states.

use std::path::{Path, PathBuf};

use anyhow::Context;
use clap::{Args, ValueEnum};

use ebptv::grid::{
    self, grid_to_dir, EstimateOptions, Fit, GridDirOptions, GridInput, GridProgress,
    ProfileOptions, WallSide, Weighting,
};

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
    /// Number of near-wall profile points in the wall fit (needs --wall).
    #[arg(long, default_value_t = 3, requires = "wall")]
    pub wall_points: usize,
    /// Kinematic viscosity (m²/s) for wall units (needs --wall).
    #[arg(long, default_value_t = 1.0e-6, requires = "wall")]
    pub nu: f64,
    /// Image scale (px/mm) of the profile and of wall units (needs --profile-x).
    #[arg(long, requires = "profile_x")]
    pub px_per_mm: Option<f64>,
    /// Also write time-resolved fields (fields_{u,v,count,t_us}.npy) every K pulses.
    #[arg(long)]
    pub fields_every: Option<usize>,
    /// Skip the PNG maps.
    #[arg(long)]
    pub no_plots: bool,
    /// A `calib.toml`: the grid table gains `X_mm,Y_mm,U_m_s,V_m_s,uu_m2_s2,
    /// vv_m2_s2,uv_m2_s2` after the pixel columns, the maps are in m/s,
    /// and its `[mask]` table applies as --mask does.
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

pub fn run(mut a: GridArgs, tables: Option<ebptv::table::TableFormat>) -> anyhow::Result<()> {
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
    let input = if !a.merge.is_empty() {
        anyhow::ensure!(
            a.fields_every.is_none(),
            "--fields-every needs a tracks file (states hold no time series)"
        );
        GridInput::Merge(a.merge)
    } else {
        GridInput::Tracks(
            a.tracks
                .into_iter()
                .next()
                .context("give a tracks file, or --merge STATE...")?,
        )
    };
    anyhow::ensure!(
        a.wall.is_none() || a.px_per_mm.is_some() || a.calibration.is_some(),
        "--wall needs --px-per-mm (or --calibration) for wall units"
    );
    let opts = GridDirOptions {
        input,
        bin: grid::BinOptions {
            bin: a.bin,
            bin_h: a.bin_h,
            overlap: a.overlap,
            origin: a.origin.unwrap_or(grid::BinOptions::default().origin),
            weighting,
        },
        estimate: EstimateOptions {
            fit,
            min_count: a.min_count,
            noise_rms: a.noise_rms,
        },
        profile: a.profile_x.map(|x| ProfileOptions {
            x,
            wall: a.wall.map(|side| match side {
                SideArg::Top => WallSide::Top,
                SideArg::Bottom => WallSide::Bottom,
            }),
            wall_y: a.wall_y,
            wall_points: a.wall_points,
            nu_m2_s: a.nu,
            px_per_mm: a.px_per_mm,
        }),
        fields_every: a.fields_every,
        plots: !a.no_plots,
        calibration: a.calibration,
        mask: a.mask,
        table_format: tables.unwrap_or_default(),
    };
    let bar = indicatif::ProgressBar::hidden();
    let r = grid_to_dir(&opts, &a.out, &mut |p| match p {
        GridProgress::MaskFound(m) => eprintln!("grid: masked by {}", m.display()),
        GridProgress::Binning { samples } => {
            bar.set_length(samples as u64);
            if samples >= 1_000_000 {
                bar.set_draw_target(indicatif::ProgressDrawTarget::stderr());
            }
        }
        GridProgress::Binned(n) => bar.inc(n as u64),
    })?;
    bar.finish_and_clear();
    match &r.noise {
        Some(Ok(n)) => eprintln!(
            "grid: velocity noise {:.1} px/s per sample ({} pairs), dynamic range {:.0}:1",
            n.noise_rms, n.pairs, n.dynamic_range
        ),
        Some(Err(e)) => eprintln!("grid: no noise estimate: {e}"),
        None => {}
    }
    eprintln!(
        "grid: {} x {} bins ({} valid, ≥ {} samples), {} samples binned, max mean speed {:.1} px/s → {}",
        r.nx,
        r.ny,
        r.valid_bins,
        a.min_count,
        r.binned_samples,
        r.max_mean_speed,
        a.out.display()
    );
    Ok(())
}
