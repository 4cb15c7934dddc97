//! Subcommands. Each file parses one subcommand's arguments and calls the
//! library.

use clap::{Parser, Subcommand};

pub mod compare;
pub mod info;
pub mod piv;
pub mod piv_images;

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
    /// Multi-frame correlation PIV on pulsed pseudo-images of a recording.
    Piv(piv::PivArgs),
    /// Correlation PIV on ordinary image pairs or sequences (PNG, TIFF).
    PivImages(piv_images::PivImagesArgs),
    /// Compare PTV grid statistics with PIV statistics on the same grid.
    Compare(compare::CompareArgs),
}

pub fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Info(a) => info::run(a),
        Command::Piv(a) => piv::run(a),
        Command::PivImages(a) => piv_images::run(a),
        Command::Compare(a) => compare::run(a),
    }
}
