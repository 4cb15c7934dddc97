use std::path::PathBuf;

use clap::Args;

#[derive(Args, Debug)]
pub struct InfoArgs {
    /// Event file (RAW EVT 2.0/2.1/3.0, DAT, CSV, AEDAT4, ES).
    pub file: PathBuf,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
}

pub fn run(args: InfoArgs) -> anyhow::Result<()> {
    let _src = ebptv::io::open(&args.file)?;
    anyhow::bail!("info not implemented yet")
}
