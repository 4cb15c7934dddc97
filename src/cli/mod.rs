//! Subcommands. Each file parses one subcommand's arguments and calls the
//! library.

use clap::{Parser, Subcommand};

pub mod convert;
pub mod info;
pub mod model_check;
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
    /// Model check: measured vs simulated signatures → the missing effects,
    /// fitted (model_check.json, model.toml, report.md, PNGs).
    ModelCheck(model_check::ModelCheckArgs),
}

pub fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Info(a) => info::run(a),
        Command::Convert(a) => convert::run(a),
        Command::Track(a) => track::run(a),
        Command::ModelCheck(a) => model_check::run(a),
    }
}
