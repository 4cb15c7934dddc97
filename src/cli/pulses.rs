//! `ebptv pulses`: pulse timing and diagnostics of a recording.

use std::path::PathBuf;

use clap::Args;
use ebptv::pulses::{pulses_to_dir, PulseOptions, PulseReport, PulsesDirOptions, PulsesProgress};

#[derive(Args, Debug)]
pub struct PulsesArgs {
    /// Event file (RAW EVT 2.0/2.1/3.0, DAT, CSV, AEDAT4, ES), or `-` for a
    /// RAW stream on standard input.
    pub file: PathBuf,
    /// Nominal pulse frequency (Hz) when estimating from events (±2 % searched).
    #[arg(long, conflicts_with = "pulse_hz_range")]
    pub pulse_hz: Option<f64>,
    /// Frequency search range A..B (Hz) when estimating from events.
    #[arg(long, value_parser = parse_range)]
    pub pulse_hz_range: Option<(f64, f64)>,
    /// Trigger channel carrying the laser pulses (default: the regular one).
    #[arg(long)]
    pub trigger_channel: Option<u8>,
    /// Estimate pulses from the events even when triggers are recorded.
    #[arg(long, conflicts_with = "trigger_channel")]
    pub ignore_triggers: bool,
    /// Known delay from the light pulse to the burst onset (µs), subtracted
    /// from estimated pulse starts.
    #[arg(long)]
    pub onset_latency_us: Option<f64>,
    /// Go on even when the events show no bursts locked to pulses (the
    /// pulsed-light test of `PulsedVerdict` fails).
    #[arg(long)]
    pub force_pulses: bool,
    /// Output directory.
    #[arg(long)]
    pub out: PathBuf,
    /// Also write a mask of the static pixels (PNG, 255 = masked; a second
    /// pass over the file): pixels with events in more than half of the
    /// pulses (walls, model edges, reflections lit by every pulse) and the
    /// hot pixels. Pass it to `ebptv track --mask`.
    #[arg(long)]
    pub write_mask: Option<PathBuf>,
}

pub fn parse_range(s: &str) -> Result<(f64, f64), String> {
    let (a, b) = s
        .split_once("..")
        .ok_or_else(|| format!("`{s}`: expected A..B, e.g. 4000..6000"))?;
    let a: f64 = a
        .trim()
        .parse()
        .map_err(|_| format!("`{a}` is not a number"))?;
    let b: f64 = b
        .trim()
        .parse()
        .map_err(|_| format!("`{b}` is not a number"))?;
    Ok((a, b))
}

pub fn options(
    pulse_hz: Option<f64>,
    range: Option<(f64, f64)>,
    ch: Option<u8>,
    ignore: bool,
    onset: Option<f64>,
) -> PulseOptions {
    PulseOptions {
        pulse_hz,
        pulse_hz_range: range,
        trigger_channel: ch,
        ignore_triggers: ignore,
        onset_latency_us: onset,
        require_pulsed: false,
    }
}

pub fn run(args: PulsesArgs) -> anyhow::Result<()> {
    let mut pulses = options(
        args.pulse_hz,
        args.pulse_hz_range,
        args.trigger_channel,
        args.ignore_triggers,
        args.onset_latency_us,
    );
    pulses.require_pulsed = !args.force_pulses;
    anyhow::ensure!(
        args.write_mask.is_none() || args.file.as_os_str() != "-",
        "--write-mask reads the recording twice: give a file, not stdin"
    );
    let opts = PulsesDirOptions {
        pulses,
        write_mask: args.write_mask.clone(),
    };
    let mut bar = super::progress::ReadBar::new("reading");
    let report = pulses_to_dir(&args.file, &opts, &args.out, &mut |p| match p {
        PulsesProgress::Opened { file_size } => bar.opened(file_size),
        PulsesProgress::Read {
            bytes,
            events,
            done,
        } => bar.read(bytes, events, done),
        PulsesProgress::Warning(w) => eprintln!("warning: {w}"),
        PulsesProgress::NotPulsed(why) => eprintln!(
            "warning: {}: {why} (going on: --force-pulses)",
            args.file.display()
        ),
        PulsesProgress::MaskWritten { pixels, path } => {
            eprintln!("mask: {pixels} static pixels → {}", path.display())
        }
    })?;
    print_summary(&report);
    Ok(())
}

fn print_summary(r: &PulseReport) {
    println!(
        "pulses: {} from {:?}, period {:.4} µs ({:.3} Hz), pulse 0 at {:.2} µs, window offset {:.1} µs",
        r.pulses,
        r.timing.source,
        r.timing.period_us,
        1e6 / r.timing.period_us,
        r.timing.first_pulse_us,
        r.timing.window_offset_us
    );
    println!(
        "latency: peak {:.1} µs, FWHM {:.1} µs, 95 % in {:.0}..{:.0} µs, contrast {:.1}, random {:.1} %",
        r.latency_peak_us,
        r.latency_fwhm_us,
        r.latency_window95_us.0,
        r.latency_window95_us.1,
        r.burst_contrast,
        100.0 * r.random_event_fraction
    );
    println!(
        "events: {} over {:.3} s ({:.2} Mev/s), {} unattributable; ppp {:.4}, image {:.2} px, {:.2} events/particle",
        r.events,
        r.duration_s,
        r.event_rate_hz * 1e-6,
        r.unattributed_events,
        r.particles.ppp,
        r.particles.mean_image_size_px,
        r.particles.events_per_particle
    );
    if let Some(f) = &r.triggers.fit {
        println!(
            "triggers: channel {}, {} used, {} missing, {} spurious, jitter {:.2} µs",
            f.channel, f.rising_used, f.missing, f.spurious, f.residual_rms_us
        );
    }
    println!(
        "saturation: {}; {:.1} % of events share (row, t), {:.1} % in flagged windows; {} hot pixels",
        if r.saturated { "SATURATED" } else { "ok" },
        100.0 * r.saturation_shared_fraction,
        100.0 * r.saturation.saturated_event_fraction,
        r.rate_map.hot_pixels.len()
    );
}
