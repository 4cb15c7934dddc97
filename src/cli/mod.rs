//! Subcommands. Each file parses one subcommand's arguments and calls the
//! library.

use clap::{Parser, Subcommand};

pub mod compare;
pub mod convert;
pub mod demo;
pub mod grid;
pub mod info;
pub mod model_check;
pub mod monitor;
pub mod piv;
pub mod piv_images;
pub mod progress;
pub mod provenance;
pub mod pulses;
pub mod simulate;
pub mod spectra;
pub mod track;

#[derive(Parser, Debug)]
#[command(
    name = "ebptv",
    version,
    about = "Event-based particle tracking velocimetry for pulsed illumination",
    after_help = "Start with `ebptv demo --out demo` (no data needed). On a recording: `ebptv info FILE`, then `ebptv pulses FILE --out DIR`, then `ebptv track FILE --out DIR`, then `ebptv grid` or `ebptv spectra` on its tracks table (tracks.parquet; `ebptv --table-format csv track …` writes CSV).\n\nExamples:\n  ebptv demo --out demo\n  ebptv info recording.raw\n  ebptv track recording.raw --out run1\n  ebptv grid run1/tracks.parquet --out run1/grid"
)]
pub struct Cli {
    /// Format of the row tables the command writes (particles, tracks,
    /// grid, PIV means and vectors, simulated truth): parquet (default),
    /// csv or npy. Placed right after `ebptv`, e.g.
    /// `ebptv --table-format csv track …`.
    #[arg(long, value_enum)]
    pub table_format: Option<ebptv::table::TableFormat>,
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Simulate a small recording and run every stage on it, scored against the truth.
    #[command(
        after_help = "Start here: it needs no data, runs in seconds and shows every output the other commands write, with their errors against the known truth.\n\nExamples:\n  ebptv demo --out demo\n  ebptv demo --out demo --seconds 0.2"
    )]
    Demo(demo::DemoArgs),
    /// Summarise an event file: format, geometry, counts, rates, triggers.
    #[command(
        after_help = "Use it first on a new recording, to see its format, size, event rate and whether it holds laser trigger words; then run `ebptv pulses` and `ebptv track`.\n\nExamples:\n  ebptv info recording.raw\n  ebptv info recording.raw --json"
    )]
    Info(info::InfoArgs),
    /// Convert an event file (optionally a time range / ROI / polarity) to CSV, .npy or RAW.
    #[command(
        after_help = "Use it to hand events to other tools (CSV, NumPy) or to cut a recording down to a time window or region for tracking.\n\nExamples:\n  ebptv convert recording.raw events.csv --from-us 1000000 --to-us 1100000\n  ebptv convert recording.raw roi.raw --roi 200,100,400,300"
    )]
    Convert(convert::ConvertArgs),
    /// Simulate a pulsed event-camera recording with ground truth.
    #[command(
        after_help = "Use it to make a recording with known particle paths, to test settings or check the accuracy to expect from an experiment.\n\nExamples:\n  ebptv simulate --preset demo --out sim\n  ebptv simulate --preset rib_wake --seconds 0.5 --out wake"
    )]
    Simulate(simulate::SimulateArgs),
    /// Pulse timing (triggers or estimated), latency and saturation diagnostics → pulses.json + figures.
    #[command(
        after_help = "Use it to check the laser timing of a recording (trigger words or the pulse rate estimated from the events): the tracker relies on it.\n\nExamples:\n  ebptv pulses recording.raw --out pulses\n  ebptv pulses recording.raw --pulse-hz 5000 --ignore-triggers --out pulses\n  ebptv pulses recording.raw --write-mask mask.png --out pulses"
    )]
    Pulses(pulses::PulsesArgs),
    /// Live pulse diagnostics of a recording being written (--follow; Ctrl-C stops).
    #[command(
        after_help = "Use it during an experiment, on a file the camera is still writing, to see the pulse rate and saturation live.\n\nExamples:\n  ebptv monitor recording.raw --follow\n  ebptv monitor recording.raw --follow --idle-timeout-s 10"
    )]
    Monitor(monitor::MonitorArgs),
    /// Particle tracking: a recording (or a particles table) → particles and
    /// tracks tables (Parquet), summary.json, tracks.png.
    #[command(
        after_help = "The main measurement: run it on a recording after `ebptv info` and `ebptv pulses`, then bin the tracks with `ebptv grid`. Its tables are Parquet; `ebptv --table-format csv track …` writes CSV instead (npy: NumPy arrays).\n\nExamples:\n  ebptv track recording.raw --out run1\n  ebptv track recording.raw --pulse-hz 5000 --max-disp 12 --out run1\n  ebptv track recording.raw --params run1/params.toml --out run2\n  ebptv track recording.raw --calibration calib.toml --mask mask.png --out run1"
    )]
    Track(track::TrackArgs),
    /// Bin tracks onto an Eulerian grid (means, stresses, errors), or merge grid states.
    #[command(
        after_help = "Use it on the tracks of `ebptv track` for mean velocity, Reynolds stresses and their errors on a regular grid.\n\nExamples:\n  ebptv grid run1/tracks.parquet --bin 16 --out run1/grid\n  ebptv grid --merge run1/grid run2/grid --out all\n  ebptv grid run1/tracks.parquet --calibration calib.toml --out run1/grid"
    )]
    Grid(grid::GridArgs),
    /// Velocity spectra at points or along a line from tracks (Welch PSD, peak, noise floor).
    #[command(
        after_help = "Use it on the tracks of `ebptv track` to find a frequency in the flow (vortex shedding, pulsation) at chosen points or along a line.\n\nExamples:\n  ebptv spectra run1/tracks.parquet --point 400,180 --out run1/spectra\n  ebptv spectra run1/tracks.parquet --line 300,100,300,260 --component v --out run1/line"
    )]
    Spectra(spectra::SpectraArgs),
    /// Multi-frame correlation PIV on pulsed pseudo-images of a recording.
    #[command(
        after_help = "Use it for a dense velocity field from a recording when tracks are too sparse, or to cross-check `ebptv track` with `ebptv compare`.\n\nExamples:\n  ebptv piv recording.raw --window 32 --out run1/piv"
    )]
    Piv(piv::PivArgs),
    /// Correlation PIV on ordinary image pairs or sequences (PNG, TIFF).
    #[command(
        after_help = "Use it on frames from an ordinary PIV camera, or to compare with other PIV software on the same images.\n\nExamples:\n  ebptv piv-images a.tif b.tif --window 32 --out piv\n  ebptv piv-images stack.tif --sequence --out piv\n  ebptv piv-images 'frames/img*.bmp' --passes 3 --out piv"
    )]
    PivImages(piv_images::PivImagesArgs),
    /// Compare PTV grid statistics with PIV statistics on the same grid.
    #[command(
        after_help = "Use it after `ebptv grid` and `ebptv piv` on the same recording, to see where PTV and PIV statistics differ.\n\nExamples:\n  ebptv compare --ptv run1/grid/grid.parquet --piv run1/piv/piv_mean.parquet --out run1/compare"
    )]
    Compare(compare::CompareArgs),
    /// Model check: measured vs simulated signatures → the missing effects,
    /// fitted (model_check.json, model.toml, report.md, PNGs).
    #[command(
        after_help = "Use it to find which sensor effects a simulation misses for your recording, so that simulated accuracy figures can be trusted for it.\n\nExamples:\n  ebptv model-check recording.raw --out check"
    )]
    ModelCheck(model_check::ModelCheckArgs),
}

/// Set by a command that stops cleanly on Ctrl-C (`monitor`); otherwise
/// Ctrl-C removes what the run wrote and exits with 130.
static INTERRUPT_FLAG: std::sync::OnceLock<std::sync::Arc<std::sync::atomic::AtomicBool>> =
    std::sync::OnceLock::new();

pub fn install_interrupt_handler() {
    let _ = ctrlc::set_handler(|| match INTERRUPT_FLAG.get() {
        Some(flag) => flag.store(true, std::sync::atomic::Ordering::Relaxed),
        None => {
            eprintln!("interrupted: the outputs of this run are removed");
            ebptv::io::atomic::rollback_and_exit(130)
        }
    });
}

/// Ctrl-C sets the returned flag instead of ending the process.
pub fn interrupt_flag() -> std::sync::Arc<std::sync::atomic::AtomicBool> {
    INTERRUPT_FLAG
        .get_or_init(|| std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false)))
        .clone()
}

/// Run a parsed command line; `command_line` is what was typed (recorded
/// with the outputs, `ebptv::provenance`).
pub fn run(cli: Cli, command_line: &[String]) -> anyhow::Result<()> {
    let plan = provenance::plan(&cli.command);
    let tables = cli.table_format;
    match cli.command {
        Command::Demo(a) => demo::run(a, tables),
        Command::Info(a) => info::run(a),
        Command::Convert(a) => convert::run(a),
        Command::Simulate(a) => simulate::run(a, tables),
        Command::Pulses(a) => pulses::run(a),
        Command::Monitor(a) => monitor::run(a),
        Command::Track(a) => track::run(a, tables, command_line),
        Command::Grid(a) => grid::run(a, tables),
        Command::Spectra(a) => spectra::run(a),
        Command::Piv(a) => piv::run(a, tables),
        Command::PivImages(a) => piv_images::run(a, tables),
        Command::Compare(a) => compare::run(a),
        Command::ModelCheck(a) => model_check::run(a),
    }?;
    match plan {
        Some(p) => p.record(command_line),
        None => Ok(()),
    }
}
