//! The `ebptv` command line: parses arguments, calls the library, shows
//! progress and writes files. No analysis lives here.

use ebptv::cli;

use clap::Parser;

fn main() {
    let args = cli::Cli::parse();
    // The shared pool's threads carry the program's name, so a profile
    // (`benches/stage_budget.sh`) tells its work from the stages' own threads.
    let _ = rayon::ThreadPoolBuilder::new()
        .thread_name(|i| format!("ebptv-pool-{i}"))
        .build_global();
    // A failed or interrupted run leaves nothing: the outputs it committed,
    // its temporaries and the output folders it created are removed.
    ebptv::io::atomic::track_run();
    cli::install_interrupt_handler();
    let command_line: Vec<String> = std::env::args().collect();
    if let Err(e) = cli::run(args, &command_line) {
        ebptv::io::atomic::rollback();
        eprintln!("error: {e:#}");
        std::process::exit(1);
    }
}
