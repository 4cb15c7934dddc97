//! `ebptv monitor`: live pulse diagnostics of a recording being written.

use std::path::PathBuf;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use clap::Args;
use ebptv::pulses::monitor::Follow;

#[derive(Args, Debug)]
pub struct MonitorArgs {
    /// Event file (RAW EVT 2.0/2.1/3.0, DAT, CSV, …), or `-` for a RAW
    /// stream on standard input.
    pub file: PathBuf,
    /// Keep reading as the file grows (RAW), until Ctrl-C or the idle timeout.
    #[arg(long)]
    pub follow: bool,
    /// With --follow: stop when the file has not grown for this long (s).
    #[arg(long, requires = "follow")]
    pub idle_timeout_s: Option<f64>,
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
    if let Some(t) = args.idle_timeout_s {
        if !(t.is_finite() && t > 0.0) {
            anyhow::bail!("invalid parameter `--idle-timeout-s`: {t} s, must be > 0");
        }
    }
    let stdin = args.file.as_os_str() == "-";
    if stdin && args.follow {
        anyhow::bail!("`--follow` is for a file being written; standard input (`-`) is read until the writer closes it");
    }
    let opts = super::pulses::options(
        args.pulse_hz,
        args.pulse_hz_range,
        args.trigger_channel,
        args.ignore_triggers,
        None,
    );
    let stop: Arc<AtomicBool> = super::interrupt_flag();
    let mut src = if stdin {
        ebptv::io::live::open_stdin()?
    } else if args.follow {
        ebptv::io::live::open_growing(&args.file, std::time::Duration::from_secs(10))?
    } else {
        ebptv::io::open(&args.file)?
    };
    let follow = match (args.follow, args.idle_timeout_s) {
        (false, _) => Follow::No,
        (true, None) => Follow::UntilStopped,
        (true, Some(t)) => Follow::UntilIdle(std::time::Duration::from_secs_f64(t)),
    };
    let n = ebptv::pulses::monitor::run(
        &mut src,
        &opts,
        (args.interval_s * 1e6) as i64,
        follow,
        &stop,
        &mut |s| println!("{s}"),
    )?;
    eprintln!("{n} intervals");
    Ok(())
}
