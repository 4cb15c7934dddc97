//! Subcommands. Each file parses one subcommand's arguments and calls the
//! library.

use clap::{Parser, Subcommand};

pub mod convert;
pub mod info;
pub mod monitor;
pub mod pulses;
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
    /// Summarise an event file: format, geometry, counts, rates, triggers.
    Info(info::InfoArgs),
    /// Convert an event file (optionally a time range / ROI / polarity) to CSV, .npy or RAW.
    Convert(convert::ConvertArgs),
    /// Particle tracking: a recording (or a particles.csv) → particles.csv,
    /// tracks.csv, summary.json, tracks.png.
    Track(track::TrackArgs),
    /// Pulse timing (triggers or estimated), latency and saturation diagnostics → pulses.json + figures.
    Pulses(pulses::PulsesArgs),
    /// Live pulse diagnostics of a recording being written (--follow; Ctrl-C stops).
    Monitor(monitor::MonitorArgs),
}

pub fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Info(a) => info::run(a),
        Command::Convert(a) => convert::run(a),
        Command::Track(a) => track::run(a),
        Command::Pulses(a) => pulses::run(a),
        Command::Monitor(a) => monitor::run(a),
    }
}
