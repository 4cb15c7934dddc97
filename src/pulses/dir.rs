//! What `ebptv pulses` does, as one call: a recording → the pulse timing
//! and diagnostics folder ([`pulses_to_dir`]).

use std::path::{Path, PathBuf};

use super::{Analyzer, PulseOptions, PulseReport};
use crate::error::{Error, Result};
use crate::io::atomic::AtomicFile;
use crate::io::EventSource;
use crate::plot::{self, Heatmap, LinePlot, Series, SeriesStyle};
use crate::Chunk;

/// Everything [`pulses_to_dir`] needs besides the input and the output
/// folder.
#[derive(Debug, Clone, Default)]
pub struct PulsesDirOptions {
    /// Pulse timing options (triggers or estimation, the pulsed-light test).
    pub pulses: PulseOptions,
    /// Also write a PNG mask of the static pixels here (a second pass over
    /// the recording, so not from standard input).
    pub write_mask: Option<PathBuf>,
}

/// What [`pulses_to_dir`] reports to its progress callback as it goes.
#[derive(Clone, Copy, Debug)]
#[non_exhaustive]
pub enum PulsesProgress<'a> {
    /// The recording is open; `file_size` is its size in bytes when known.
    Opened {
        /// Size of the input in bytes (`None` on standard input).
        file_size: Option<u64>,
    },
    /// After each chunk read: bytes read and events decoded so far; `done`
    /// on the last chunk.
    Read {
        /// Bytes of the input read so far.
        bytes: u64,
        /// Events decoded so far.
        events: u64,
        /// Whether this was the last chunk.
        done: bool,
    },
    /// A warning about the input (a header it could not use, clock jumps).
    Warning(&'a str),
    /// The events show no pulsed light (why, as the error
    /// `PulseReport::not_pulsed_error`); the analysis goes on because
    /// `require_pulsed` is off.
    NotPulsed(&'a str),
    /// The static-pixel mask was written: `pixels` masked, at `path`.
    MaskWritten {
        /// Pixels in the mask.
        pixels: usize,
        /// The PNG written.
        path: &'a Path,
    },
}

/// Analyse the pulses of `input` (any supported event file; `-` reads a
/// RAW stream from standard input) and write into `out` (created if
/// missing) what `ebptv pulses` writes: `pulses.json`, `rate_map.npy`,
/// `latency.csv` and the figures; optionally the static-pixel mask.
pub fn pulses_to_dir(
    input: &Path,
    opts: &PulsesDirOptions,
    out: &Path,
    on_progress: &mut dyn FnMut(PulsesProgress<'_>),
) -> Result<PulseReport> {
    let stdin = input.as_os_str() == "-";
    let mut src = crate::io::guard::TimeGuard::new(if stdin {
        crate::io::live::open_stdin()?
    } else {
        crate::io::open(input)?
    });
    for w in src.warnings() {
        on_progress(PulsesProgress::Warning(&w));
    }
    on_progress(PulsesProgress::Opened {
        file_size: src.info().file_size,
    });
    let mut an = Analyzer::new(opts.pulses.clone(), src.info().geometry)?;
    let mut chunk = Chunk::default();
    let mut events = 0u64;
    loop {
        let more = src.next_chunk(&mut chunk)?;
        events += chunk.events.len() as u64;
        on_progress(PulsesProgress::Read {
            bytes: src.bytes_read(),
            events,
            done: !more,
        });
        if !more {
            break;
        }
        an.push(&chunk)?;
    }
    let mut report = an
        .finish()
        .map_err(|e| Error::analysis(format!("{}: pulse analysis: {e}", input.display())))?;
    (report.time_jumps, report.time_jump_events) = src.jumps();
    if report.time_jumps > 0 {
        on_progress(PulsesProgress::Warning(&format!(
            "{}: the clock jumped {} times by more than {} s; {} events and triggers stamped with the jumped time were dropped",
            input.display(),
            report.time_jumps,
            crate::io::guard::TIME_JUMP_US / 1_000_000,
            report.time_jump_events
        )));
    }
    if !report.pulsed.pulsed {
        on_progress(PulsesProgress::NotPulsed(
            &report.not_pulsed_error().to_string(),
        ));
    }
    crate::io::atomic::create_output_dir(out)?;
    if let Some(path) = &opts.write_mask {
        if stdin {
            return Err(Error::param(
                "write_mask",
                "the static mask reads the recording twice: give a file, not stdin",
            ));
        }
        let mut again = crate::io::open(input)?;
        let mopts = super::static_mask::StaticMaskOptions::default();
        let mask = super::static_mask::static_mask(&mut *again, &report, &mopts)?;
        mask.write_png(path)?;
        on_progress(PulsesProgress::MaskWritten {
            pixels: mask.count(),
            path,
        });
    }
    write_outputs(&report, out)?;
    Ok(report)
}

/// pulses.json, rate_map.npy, latency.csv and the figures.
fn write_outputs(r: &PulseReport, out: &Path) -> Result<()> {
    let json =
        serde_json::to_vec_pretty(r).map_err(|e| Error::analysis(format!("pulses.json: {e}")))?;
    AtomicFile::write_all_to(out.join("pulses.json"), &json)?;
    let (w, h) = (r.rate_map.width as usize, r.rate_map.height as usize);
    let rate: Vec<f64> = r.rate_map.rate.iter().map(|&v| v as f64).collect();
    crate::io::npy::write_npy_f64(out.join("rate_map.npy"), &[h, w], &rate)?;
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

/// What `ebptv info` reports on an event file ([`file_info`]).
#[derive(Debug)]
pub struct FileInfo {
    /// Format, geometry, counts, rates and triggers (one streaming pass).
    pub summary: crate::io::summary::Summary,
    /// A geometry the header stated but that cannot be (ignored).
    pub rejected_geometry: Option<crate::Geometry>,
    /// The pulsed-light test on the first events, or why it could not run.
    pub verdict: std::result::Result<super::PulsedVerdict, String>,
}

impl FileInfo {
    /// What `ebptv info --json` prints: the summary with the verdict under
    /// `pulsed`.
    pub(crate) fn to_json(&self) -> Result<serde_json::Value> {
        super::info_json(&self.summary, &self.verdict)
    }
}

/// Summarise the event file `path` (read with `opts`; the peak rate over
/// bins of `peak_bin_us`) and test it for pulsed light. `on_progress`
/// receives the reader's warnings, then [`PulsesProgress::Opened`] and
/// [`PulsesProgress::Read`] as the file is read.
pub fn file_info(
    path: &Path,
    opts: &crate::io::OpenOptions,
    peak_bin_us: i64,
    on_progress: &mut (dyn FnMut(PulsesProgress<'_>) + Send),
) -> Result<FileInfo> {
    if peak_bin_us <= 0 {
        return Err(Error::param(
            "peak_bin_us",
            format!("{peak_bin_us} µs: must be positive"),
        ));
    }
    let src = crate::io::open_with(path, opts)?;
    for w in src.warnings() {
        on_progress(PulsesProgress::Warning(&w));
    }
    let rejected_geometry = src.rejected_geometry();
    on_progress(PulsesProgress::Opened {
        file_size: src.info().file_size,
    });
    let summary = crate::io::summary::summarize(
        &mut crate::io::Observed::new(src, |r| {
            on_progress(PulsesProgress::Read {
                bytes: r.bytes,
                events: r.events,
                done: r.done,
            });
            Ok(())
        }),
        peak_bin_us,
        |_| {},
    )?;
    let verdict = super::file_verdict(path, opts).map_err(|e| e.to_string());
    Ok(FileInfo {
        summary,
        rejected_geometry,
        verdict,
    })
}
