//! `ebptv pulses`: pulse timing and diagnostics of a recording.

use std::path::{Path, PathBuf};

use anyhow::Context;
use clap::Args;
use ebptv::io::atomic::AtomicFile;
use ebptv::io::EventSource;
use ebptv::plot::{self, Heatmap, LinePlot, Series, SeriesStyle};
use ebptv::pulses::{Analyzer, PulseOptions, PulseReport};

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
    let mut opts = options(
        args.pulse_hz,
        args.pulse_hz_range,
        args.trigger_channel,
        args.ignore_triggers,
        args.onset_latency_us,
    );
    opts.require_pulsed = !args.force_pulses;
    let src = ebptv::io::guard::TimeGuard::new(if args.file.as_os_str() == "-" {
        ebptv::pulses::live::open_stdin()?
    } else {
        ebptv::io::open(&args.file)?
    });
    super::print_warnings(&src);
    let mut src = super::progress::Reading::with_bar(src, "reading");
    let mut an = Analyzer::new(opts, src.info().geometry)?;
    let mut chunk = ebptv::Chunk::default();
    while src.next_chunk(&mut chunk)? {
        an.push(&chunk)?;
    }
    src.bar().finish_and_clear();
    let src = src.into_inner();
    let mut report = an
        .finish()
        .with_context(|| format!("{}: pulse analysis", args.file.display()))?;
    (report.time_jumps, report.time_jump_events) = src.jumps();
    if report.time_jumps > 0 {
        eprintln!(
            "warning: {}: the clock jumped {} times by more than {} s; {} events and triggers stamped with the jumped time were dropped",
            args.file.display(),
            report.time_jumps,
            ebptv::io::guard::TIME_JUMP_US / 1_000_000,
            report.time_jump_events
        );
    }
    if !report.pulsed.pulsed {
        eprintln!(
            "warning: {}: {} (going on: --force-pulses)",
            args.file.display(),
            report.not_pulsed_error()
        );
    }
    ebptv::io::atomic::create_output_dir(&args.out)?;
    if let Some(path) = &args.write_mask {
        anyhow::ensure!(
            args.file.as_os_str() != "-",
            "--write-mask reads the recording twice: give a file, not stdin"
        );
        let mut again = ebptv::io::open(&args.file)?;
        let opts = ebptv::pulses::static_mask::StaticMaskOptions::default();
        let mask = ebptv::pulses::static_mask::static_mask(&mut *again, &report, &opts)?;
        mask.write_png(path)?;
        eprintln!("mask: {} static pixels → {}", mask.count(), path.display());
    }
    write_outputs(&report, &args.out)?;
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

/// pulses.json, rate_map.npy, latency.csv and the figures.
pub fn write_outputs(r: &PulseReport, out: &Path) -> anyhow::Result<()> {
    let json = serde_json::to_vec_pretty(r)?;
    AtomicFile::write_all_to(out.join("pulses.json"), &json)?;
    let (w, h) = (r.rate_map.width as usize, r.rate_map.height as usize);
    let rate: Vec<f64> = r.rate_map.rate.iter().map(|&v| v as f64).collect();
    ebptv::io::npy::write_npy_f64(out.join("rate_map.npy"), &[h, w], &rate)?;
    let mut csv = String::from("latency_us,events,cumulative\n");
    for (i, (v, c)) in r
        .latency
        .histogram
        .iter()
        .zip(&r.latency.cumulative)
        .enumerate()
    {
        csv.push_str(&format!("{i},{v},{c}\n"));
    }
    AtomicFile::write_all_to(out.join("latency.csv"), csv.as_bytes())?;

    let lat_x: Vec<f64> = (0..r.latency.histogram.len())
        .map(|i| i as f64 + 0.5)
        .collect();
    plot::line_plot(
        &out.join("latency_histogram.png"),
        &LinePlot {
            title: "Events vs time after the pulse start (folded)",
            x_label: "latency (µs)",
            y_label: "events per µs",
            series: vec![Series {
                label: "events",
                x: &lat_x,
                y: &r.latency.histogram,
                style: SeriesStyle::Steps,
            }],
            log_x: false,
            log_y: false,
            vlines: vec![
                (r.latency.window95_us.0, "95 % window"),
                (r.latency.window95_us.1, ""),
                (r.latency_peak_us, "peak"),
                (
                    r.timing.window_offset_us.rem_euclid(r.timing.period_us),
                    "window boundary",
                ),
            ],
        },
    )?;
    plot::line_plot(
        &out.join("latency_cumulative.png"),
        &LinePlot {
            title: "Cumulative fraction of events after the pulse start",
            x_label: "latency (µs)",
            y_label: "fraction",
            series: vec![Series {
                label: "cumulative",
                x: &lat_x,
                y: &r.latency.cumulative,
                style: SeriesStyle::Line,
            }],
            log_x: false,
            log_y: false,
            vlines: vec![
                (r.latency.window95_us.0, "95 % window"),
                (r.latency.window95_us.1, ""),
            ],
        },
    )?;
    // Time since the start of the recording (its first event), ms: the
    // absolute clock (~1e7 µs) would give every tick the same label.
    let t0 = r.rate_trace_t0_us as f64;
    let ms = |t_us: f64| (t_us - t0) * 1e-3;
    let tx: Vec<f64> = (0..r.rate_trace.len()).map(|i| i as f64 * 1e-3).collect();
    let ty: Vec<f64> = r.rate_trace.iter().map(|&c| c as f64).collect();
    let mut marks = Vec::new();
    if !tx.is_empty() {
        let t1 = t0 + (r.rate_trace.len() - 1) as f64;
        let k0 = ((t0 - r.timing.first_pulse_us) / r.timing.period_us).ceil() as i64;
        let mut k = k0;
        while r.timing.pulse_start(k) <= t1 && marks.len() < 50 {
            marks.push((
                ms(r.timing.pulse_start(k)),
                if k == k0 { "pulse start" } else { "" },
            ));
            k += 1;
        }
    }
    if !tx.is_empty() {
        plot::line_plot(
            &out.join("rate_trace.png"),
            &LinePlot {
                title: "Event rate at the start of the recording",
                x_label: "time since the start of the recording (ms)",
                y_label: "events per µs",
                series: vec![Series {
                    label: "events",
                    x: &tx,
                    y: &ty,
                    style: SeriesStyle::Steps,
                }],
                log_x: false,
                log_y: false,
                vlines: marks,
            },
        )?;
    }
    plot::heatmap(
        &out.join("rate_map.png"),
        &Heatmap {
            title: "Event rate per pixel",
            values: &rate,
            nx: w,
            ny: h,
            x_range: (0.0, w as f64),
            y_range: (0.0, h as f64),
            colorbar_label: "events/(pixel·s)",
            diverging: false,
            axes_mm: None,
        },
    )?;
    Ok(())
}
