//! The `ebptv` command line: parses arguments, calls the library, shows
//! progress and writes files. No analysis lives here.

mod cli;

use clap::Parser;

fn main() {
    let args = cli::Cli::parse();
    // A failed or interrupted run leaves nothing: the outputs it committed,
    // its temporaries and the output folders it created are removed.
    ebptv::io::atomic::track_run();
    cli::install_interrupt_handler();
    if let Err(e) = cli::run(args) {
        ebptv::io::atomic::rollback();
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}
