//! Subcommands. Each file parses one subcommand's arguments and calls the
//! library.

use clap::{Parser, Subcommand};

pub mod info;

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
}

pub fn run(cli: Cli) -> anyhow::Result<()> {
    match cli.command {
        Command::Info(a) => info::run(a),
    }
}
