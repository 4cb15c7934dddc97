//! `ebptv monitor`: live pulse diagnostics of a recording being written.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use clap::Args;

#[derive(Args, Debug)]
pub struct MonitorArgs {
    /// Event file being written (RAW EVT 2.0/2.1/3.0, DAT, CSV, …).
    pub file: PathBuf,
    /// Keep reading as the file grows, until Ctrl-C.
    #[arg(long)]
    pub follow: bool,
    /// Reporting interval (s of recording time).
    #[arg(long, default_value_t = 1.0)]
    pub interval_s: f64,
    /// Nominal pulse frequency (Hz) when the recording has no triggers.
    #[arg(long)]
    pub pulse_hz: Option<f64>,
    /// Frequency search range A..B (Hz).
    #[arg(long, value_parser = super::pulses::parse_range)]
    pub pulse_hz_range: Option<(f64, f64)>,
    /// Trigger channel carrying the laser pulses.
    #[arg(long)]
    pub trigger_channel: Option<u8>,
    /// Estimate pulses from events even when triggers are recorded.
    #[arg(long)]
    pub ignore_triggers: bool,
}

pub fn run(args: MonitorArgs) -> anyhow::Result<()> {
    if !(args.interval_s.is_finite() && args.interval_s >= 0.01) {
        anyhow::bail!(
            "invalid parameter `--interval-s`: {} s, must be ≥ 0.01",
            args.interval_s
        );
    }
    if args.file.as_os_str() == "-" {
        anyhow::bail!(
            "reading from stdin is not supported yet: give the file being written and --follow"
        );
    }
    let opts = super::pulses::options(
        args.pulse_hz,
        args.pulse_hz_range,
        args.trigger_channel,
        args.ignore_triggers,
        None,
    );
    let stop = Arc::new(AtomicBool::new(false));
    {
        let stop = stop.clone();
        ctrlc::set_handler(move || stop.store(true, Ordering::Relaxed))?;
    }
    let mut src = ebptv::io::open(&args.file)?;
    let n = ebptv::pulses::monitor::run(
        &mut src,
        &opts,
        (args.interval_s * 1e6) as i64,
        args.follow,
        &stop,
        &mut |s| println!("{s}"),
    )?;
    eprintln!("{n} intervals");
    Ok(())
}
