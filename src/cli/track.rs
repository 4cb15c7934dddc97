//! `ebptv track`: recording (or a particles table) → particles → tracks.

use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;

use clap::Args;

use super::progress::ReadRate;
use ebptv::table::TableFormat;
use ebptv::track::{track_to_dir_with, TrackConfig, TrackProgress, TrackStage};

#[derive(Args, Debug)]
pub struct TrackArgs {
    /// A recording (any supported event format) or a particles table
    /// (Parquet, CSV or .npy with `pulse,t_us,x,y,n_events`: linking only).
    pub input: PathBuf,
    /// Output directory (created if missing). It also receives
    /// `params.toml`, every option of the run, for --params.
    #[arg(long)]
    pub out: PathBuf,
    /// Largest distance (px) a particle moves between two pulses: new
    /// tracks look this far for their second position, and no track looks
    /// further. Set it a little above the fastest motion [default: 10].
    #[arg(long)]
    pub max_disp: Option<f64>,
    /// Pulses in a row a track may miss and still go on; the missed
    /// positions are filled in and marked `interpolated` [default: 1].
    #[arg(long)]
    pub gap: Option<u32>,
    /// Shortest track kept, in detections (at least 4); shorter ones that
    /// move with their neighbours are kept too [default: 5].
    #[arg(long)]
    pub min_length: Option<usize>,
    /// Events on pixels at most this far apart (px) make one particle
    /// image [default: 1.5].
    #[arg(long)]
    pub radius: Option<f64>,
    /// Mean flow `U,V` (px/s): new tracks look for their second position
    /// where this flow carries the first, which helps in fast flows.
    #[arg(long, value_delimiter = ',', num_args = 2)]
    pub prior: Option<Vec<f64>>,
    /// Pulse frequency (Hz), needed when the recording has no trigger
    /// channel and the pulse times are found from the events.
    #[arg(long)]
    pub pulse_hz: Option<f64>,
    /// Find the pulse times from the events even when the recording has
    /// trigger events.
    #[arg(long)]
    pub ignore_triggers: bool,
    /// Track even when the events show no bursts locked to pulses (see
    /// `ebptv pulses`).
    #[arg(long)]
    pub force_pulses: bool,
    /// A `calib.toml` (scale, origin, y axis, optional `[mask]` table):
    /// tracks.csv gains `X_mm,Y_mm,U_m_s,V_m_s` after the pixel columns.
    #[arg(long)]
    pub calibration: Option<PathBuf>,
    /// Pixels that are not flow: a PNG of the sensor's size (non-zero =
    /// masked; walls, models, reflections: no track is stitched across
    /// them) or a list of hot pixels, one `x,y` per line. Their events are
    /// ignored. (OFF events too: `[cluster] on_only = false` in --params.)
    #[arg(long)]
    pub mask: Option<PathBuf>,
    /// Also bin the tracks onto a grid in one go, into OUT/grid: the options
    /// of `ebptv grid` as one string, e.g. --grid "--bin 16 --fit linear"
    /// (an empty string takes grid's defaults).
    #[arg(long, allow_hyphen_values = true)]
    pub grid: Option<String>,
    /// Read every option of the run from a TOML file: the tracker's parts
    /// ([track.gates], [track.init], [track.stitch], [track.fit]), the
    /// clustering (`[cluster]`) and run options such as the table format,
    /// the plot window, batching and the sliced linker ([run]). Keys left
    /// out take their defaults; options given here override the file. A
    /// run's OUT/params.toml is such a file.
    #[arg(long)]
    pub params: Option<PathBuf>,
}

/// `tables`: the top-level `--table-format` (over the params file's).
pub fn run(
    args: TrackArgs,
    tables: Option<TableFormat>,
    command_line: &[String],
) -> anyhow::Result<()> {
    let mut config = config_of(&args)?;
    if let Some(f) = tables {
        config.run.table_format = f;
    }
    let grid = args.grid.clone();
    let out = args.out.clone();
    // Check the grid options before the (long) tracking run.
    let grid_cli = grid
        .map(|g| {
            // The grid tables in the run's table format.
            let mut argv = vec![
                "ebptv".to_string(),
                "--table-format".into(),
                config.run.table_format.ext().into(),
                "grid".into(),
            ];
            let tracks = out.join(config.run.table_format.file_name("tracks"));
            argv.push(tracks.display().to_string());
            argv.extend(["--out".into(), out.join("grid").display().to_string()]);
            argv.extend(g.split_whitespace().map(String::from));
            <super::Cli as clap::Parser>::try_parse_from(&argv)
                .map(|cli| (cli, argv))
                .map_err(|e| anyhow::anyhow!("--grid \"{g}\": {e}"))
        })
        .transpose()?;
    run_tracking(args, &config, command_line)?;
    match grid_cli {
        Some((cli, argv)) => super::run(cli, &argv),
        None => Ok(()),
    }
}

/// The run's full set of options: the --params file (or the defaults),
/// then the command-line options over it.
fn config_of(args: &TrackArgs) -> anyhow::Result<TrackConfig> {
    let mut c = match &args.params {
        Some(p) => TrackConfig::read(p)?,
        None => TrackConfig::default(),
    };
    if let Some(v) = args.max_disp {
        c.track.max_disp = v;
    }
    if let Some(v) = args.gap {
        c.track.max_gap = v;
    }
    if let Some(v) = args.min_length {
        c.track.min_length = v;
    }
    if let Some(v) = args.radius {
        c.cluster.radius = v;
    }
    if let Some(p) = &args.prior {
        c.run.prior = Some([p[0], p[1]]);
    }
    if args.pulse_hz.is_some() {
        c.run.pulse_hz = args.pulse_hz;
    }
    c.run.ignore_triggers |= args.ignore_triggers;
    c.run.force_pulses |= args.force_pulses;
    if args.calibration.is_some() {
        c.run.calibration = args.calibration.clone();
    }
    if let Some(m) = &args.mask {
        c.run.set_mask_file(m)?;
    }
    Ok(c)
}

fn run_tracking(
    args: TrackArgs,
    config: &TrackConfig,
    command_line: &[String],
) -> anyhow::Result<()> {
    let size = std::fs::metadata(&args.input).ok().map(|m| m.len());
    let bar = super::progress::file_bar(size, "pulse timing");
    let reading = Mutex::new(ReadRate::default());
    let counts = [AtomicU64::new(0), AtomicU64::new(0)];
    let on_progress = |p: TrackProgress<'_>| match p {
        TrackProgress::Stage { stage, .. } => {
            if stage == TrackStage::Tracking {
                bar.reset();
                bar.set_prefix("tracking");
            }
            bar.set_message("");
            *reading.lock().unwrap_or_else(|e| e.into_inner()) = ReadRate::default();
        }
        TrackProgress::Read {
            stage,
            bytes,
            events,
            done,
        } => {
            if bar.is_hidden() {
                return;
            }
            let note = (stage == TrackStage::Tracking).then(|| {
                format!(
                    "{} particles, {} active tracks",
                    counts[0].load(Ordering::Relaxed),
                    counts[1].load(Ordering::Relaxed)
                )
            });
            let mut r = reading.lock().unwrap_or_else(|e| e.into_inner());
            r.show(&bar, bytes, events, done, note);
        }
        TrackProgress::Pulse {
            particles,
            active_tracks,
        } => {
            counts[0].store(particles, Ordering::Relaxed);
            counts[1].store(active_tracks as u64, Ordering::Relaxed);
        }
        TrackProgress::Warning(w) => bar.suspend(|| eprintln!("warning: {w}")),
        TrackProgress::Writing => bar.finish_and_clear(),
    };
    let result = track_to_dir_with(&args.input, config, &args.out, &on_progress, command_line);
    // A note for the terminal, not for logs: shown only where the bar is.
    let on_terminal = !bar.is_hidden();
    bar.finish_and_clear();
    let run = result?;
    if run.unassigned_events > 0 && on_terminal {
        eprintln!(
            "{} events could not be attributed to a pulse",
            run.unassigned_events
        );
    }
    let s = &run.summary;
    eprintln!(
        "{} pulses, {} particles, {} tracks ({:.1} % of particles on tracks, mean length {:.1}) → {}",
        s.pulses,
        s.particles,
        s.tracks,
        100.0 * s.fraction_on_tracks,
        s.mean_track_length,
        args.out.display()
    );
    Ok(())
}
