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
pub mod pulses;
pub mod simulate;
pub mod spectra;
pub mod track;

#[derive(Parser, Debug)]
#[command(
    name = "ebptv",
    version,
    about = "Event-based particle tracking velocimetry for pulsed illumination"
)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Simulate a small recording and run every stage on it, scored against the truth.
    Demo(demo::DemoArgs),
    /// Summarise an event file: format, geometry, counts, rates, triggers.
    Info(info::InfoArgs),
    /// Convert an event file (optionally a time range / ROI / polarity) to CSV, .npy or RAW.
    Convert(convert::ConvertArgs),
    /// Simulate a pulsed event-camera recording with ground truth.
    Simulate(simulate::SimulateArgs),
    /// Pulse timing (triggers or estimated), latency and saturation diagnostics → pulses.json + figures.
    Pulses(pulses::PulsesArgs),
    /// Live pulse diagnostics of a recording being written (--follow; Ctrl-C stops).
    Monitor(monitor::MonitorArgs),
    /// Particle tracking: a recording (or a particles.csv) → particles.csv,
    /// tracks.csv, summary.json, tracks.png.
    Track(track::TrackArgs),
    /// Bin tracks onto an Eulerian grid (means, stresses, errors), or merge grid states.
    Grid(grid::GridArgs),
    /// Velocity spectra at points or along a line from tracks (Welch PSD, peak, noise floor).
    Spectra(spectra::SpectraArgs),
    /// Multi-frame correlation PIV on pulsed pseudo-images of a recording.
    Piv(piv::PivArgs),
    /// Correlation PIV on ordinary image pairs or sequences (PNG, TIFF).
    PivImages(piv_images::PivImagesArgs),
    /// Compare PTV grid statistics with PIV statistics on the same grid.
    Compare(compare::CompareArgs),
    /// Model check: measured vs simulated signatures → the missing effects,
    /// fitted (model_check.json, model.toml, report.md, PNGs).
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

/// Print the warnings of an opened source (impossible geometry, a header
/// contradicting itself).
pub fn print_warnings(src: &dyn ebptv::io::EventSource) {
    for w in src.warnings() {
        eprintln!("warning: {w}");
    }
}

pub fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Demo(a) => demo::run(a),
        Command::Info(a) => info::run(a),
        Command::Convert(a) => convert::run(a),
        Command::Simulate(a) => simulate::run(a),
        Command::Pulses(a) => pulses::run(a),
        Command::Monitor(a) => monitor::run(a),
        Command::Track(a) => track::run(a),
        Command::Grid(a) => grid::run(a),
        Command::Spectra(a) => spectra::run(a),
        Command::Piv(a) => piv::run(a),
        Command::PivImages(a) => piv_images::run(a),
        Command::Compare(a) => compare::run(a),
        Command::ModelCheck(a) => model_check::run(a),
    }
}
