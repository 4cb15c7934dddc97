//! `ebptv grid`: bin tracks onto an Eulerian grid, or merge grid states.

use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};

use anyhow::Context;
use clap::{Args, ValueEnum};
use serde_json::json;

use ebptv::grid::fields::{time_resolved, Frames};
use ebptv::grid::profiles::{profile_at_x, wall_fit, WallOptions, WallSide};
use ebptv::grid::{
    self, estimate, io as gio, EstimateOptions, Fit, GridAccumulator, GridSpec, Lattice, Sample,
    Weighting,
};
use ebptv::io::atomic::AtomicFile;
use ebptv::{Error, Result};

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
    /// tracks.csv (`track_id,pulse,t_us,x,y,u,v`, px, px/s), rows grouped by track.
    pub tracks: Option<PathBuf>,
    /// Merge grid states (grid_state.json files or directories holding one)
    /// instead of binning tracks; fit/min-count/noise options apply.
    #[arg(long, num_args = 1.., conflicts_with = "tracks")]
    pub merge: Vec<PathBuf>,
    /// Output directory.
    #[arg(long)]
    pub out: PathBuf,
    /// Bin width (px); also the height unless --bin-h is given.
    #[arg(long, default_value_t = 16.0)]
    pub bin: f64,
    /// Bin height (px), for rectangular bins (e.g. thin bins near a wall).
    #[arg(long)]
    pub bin_h: Option<f64>,
    /// Fraction of a bin shared with its neighbour, in [0, 1).
    #[arg(long, default_value_t = 0.0)]
    pub overlap: f64,
    /// Lattice origin "x,y" (px); bins of runs to be merged must share it.
    #[arg(long, default_value = "-0.5,-0.5", value_parser = parse_pair)]
    pub origin: (f64, f64),
    /// Estimator of the mean inside a bin.
    #[arg(long, value_enum, default_value_t = FitArg::None)]
    pub fit: FitArg,
    /// Sample weighting inside a bin (combine `gaussian` with a linear fit).
    #[arg(long, value_enum)]
    pub weighting: Option<WeightArg>,
    /// Bins with fewer samples are empty (NaN).
    #[arg(long, default_value_t = 10)]
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
    /// Also write time-resolved fields (fields.csv) every K pulses.
    #[arg(long)]
    pub fields_every: Option<usize>,
    /// Skip the PNG maps.
    #[arg(long)]
    pub no_plots: bool,
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

/// Minimal reader of `tracks.csv` (`track_id,pulse,t_us,x,y,u,v`; columns
/// found by name, extra columns ignored). Temporary until the tracker's
/// reader lands in main.
pub fn read_tracks_csv(path: &Path) -> Result<Vec<Sample>> {
    let f = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let mut lines = BufReader::new(f).lines();
    let header = match lines.next() {
        Some(h) => h.map_err(|e| Error::io(path, e))?,
        None => {
            return Err(Error::Empty {
                path: path.into(),
                why: "tracks file is empty (no header)".into(),
            })
        }
    };
    let cols: Vec<String> = header
        .split(',')
        .map(|c| c.trim().to_ascii_lowercase())
        .collect();
    let col = |name: &str| {
        cols.iter().position(|c| c == name).ok_or_else(|| {
            Error::corrupt(
                path,
                0,
                format!("header lacks column `{name}` (expected track_id,pulse,t_us,x,y,u,v)"),
            )
        })
    };
    let (ci, ct, cx, cy, cu, cv) = (
        col("track_id")?,
        col("t_us")?,
        col("x")?,
        col("y")?,
        col("u")?,
        col("v")?,
    );
    let mut out = Vec::new();
    let mut offset = header.len() as u64 + 1;
    for (k, line) in lines.enumerate() {
        let line = line.map_err(|e| Error::io(path, e))?;
        let len = line.len() as u64 + 1;
        if line.trim().is_empty() {
            offset += len;
            continue;
        }
        let f: Vec<&str> = line.split(',').collect();
        let get = |c: usize| -> Result<f64> {
            f.get(c)
                .and_then(|s| s.trim().parse::<f64>().ok())
                .ok_or_else(|| {
                    Error::corrupt(
                        path,
                        offset,
                        format!("line {}: bad or missing value in column {}", k + 2, cols[c]),
                    )
                })
        };
        let id = f
            .get(ci)
            .and_then(|s| s.trim().parse::<u64>().ok())
            .ok_or_else(|| Error::corrupt(path, offset, format!("line {}: bad track_id", k + 2)))?;
        out.push(Sample {
            track_id: id,
            t_us: get(ct)?,
            x: get(cx)?,
            y: get(cy)?,
            u: get(cu)?,
            v: get(cv)?,
        });
        offset += len;
    }
    if out.is_empty() {
        return Err(Error::Empty {
            path: path.into(),
            why: "tracks file has a header but no track points".into(),
        });
    }
    Ok(out)
}

fn state_path(p: &Path) -> PathBuf {
    if p.is_dir() {
        p.join("grid_state.json")
    } else {
        p.to_path_buf()
    }
}

pub fn run(a: GridArgs) -> anyhow::Result<()> {
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
    std::fs::create_dir_all(&a.out)
        .with_context(|| format!("creating output directory {}", a.out.display()))?;

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
            .as_ref()
            .context("give a tracks file, or --merge STATE...")?;
        let lattice = Lattice::with_origin(
            a.bin,
            a.bin_h.unwrap_or(a.bin),
            a.overlap,
            a.origin.0,
            a.origin.1,
        )?;
        samples = read_tracks_csv(tracks)?;
        let (x0, x1, y0, y1) = grid::extent(&samples, &tracks.display().to_string())?;
        let spec = GridSpec::covering(lattice, weighting, x0, x1, y0, y1)?;
        let mut acc = GridAccumulator::new(spec);
        let bar = indicatif::ProgressBar::new(samples.len() as u64);
        if samples.len() < 1_000_000 {
            bar.set_draw_target(indicatif::ProgressDrawTarget::hidden());
        }
        for chunk in samples.chunks(1 << 16) {
            acc.add_all(chunk);
            bar.inc(chunk.len() as u64);
        }
        bar.finish_and_clear();
        acc
    };

    let g = estimate(&acc, &opt)?;
    gio::save_state(&a.out.join("grid_state.json"), &acc)?;
    gio::write_grid_csv(&a.out.join("grid.csv"), &g)?;
    gio::write_extra_csv(&a.out.join("grid_extra.csv"), &g)?;
    if !a.no_plots {
        gio::write_maps(&a.out, &g)?;
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

    if let Some(px) = a.profile_x {
        let (x_used, prof) = profile_at_x(&g, px);
        let wall = match a.wall {
            Some(side) => {
                let scale = a
                    .px_per_mm
                    .context("--wall needs --px-per-mm for wall units")?;
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
            if let (Some(w), Some(scale)) = (&wall, a.px_per_mm) {
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
        let mut file = AtomicFile::create(a.out.join("fields.csv"))?;
        let mut s = String::from("frame,t_us,x,y,count,u,v\n");
        let nt = frames.n;
        for (slot, &b) in f.bins.iter().enumerate() {
            let (x, y) = (g.xs[b % g.spec.nx], g.ys[b / g.spec.nx]);
            for k in 0..nt {
                let c = f.count[slot * nt + k];
                if c > 0 {
                    s.push_str(&format!(
                        "{},{},{},{},{},{},{}\n",
                        k,
                        frames.time_us(k),
                        x,
                        y,
                        c,
                        f.u[slot * nt + k],
                        f.v[slot * nt + k]
                    ));
                }
            }
            if s.len() > 1 << 22 {
                file.write_all(s.as_bytes())?;
                s.clear();
            }
        }
        file.write_all(s.as_bytes())?;
        file.commit()?;
        summary["fields"] = json!({"frames": nt, "step_us": frames.step_us, "window_us": frames.window_us, "t0_us": frames.t0_us});
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
