//! `ebptv info FILE [--json]`: one streaming pass, then a table or JSON.

use std::path::PathBuf;

use clap::Args;
use ebptv::io::summary::Summary;
use ebptv::io::{self, Format, OpenOptions};
use ebptv::pulses::{file_info, PulsesProgress};

#[derive(Args, Debug)]
pub struct InfoArgs {
    /// Event file (RAW EVT 2.0/2.1/3.0, DAT, CSV, AEDAT4, ES), or an ebptv
    /// output folder: then how its outputs were made (version, command
    /// line, parameters, input fingerprint, pulse source, date).
    pub file: PathBuf,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
    /// Read as this format instead of detecting it (evt3, evt2, evt21, dat, csv, aedat4, es).
    #[arg(long)]
    pub format: Option<String>,
    /// CSV only: unit of the time column when its header does not say (us, ms, s, ns).
    #[arg(long)]
    pub time_unit: Option<String>,
    /// Bin width for the peak event rate, µs.
    #[arg(long, default_value_t = ebptv::io::summary::DEFAULT_PEAK_BIN_US)]
    pub peak_bin_us: i64,
}

pub(crate) fn open_options(
    format: Option<&str>,
    time_unit: Option<&str>,
) -> anyhow::Result<OpenOptions> {
    let format = match format {
        Some(f) => Some(Format::from_name(f).ok_or_else(|| {
            ebptv::Error::param(
                "format",
                format!("`{f}`: expected evt3, evt2, evt21, dat, csv, aedat4 or es"),
            )
        })?),
        None => None,
    };
    let csv_time_unit = match time_unit {
        Some(u) => Some(u.parse::<io::csv::TimeUnit>()?),
        None => None,
    };
    Ok(OpenOptions {
        format,
        csv_time_unit,
        ..Default::default()
    })
}

pub fn run(args: InfoArgs) -> anyhow::Result<()> {
    // An output folder: how its outputs were made.
    if args.file.is_dir() {
        return match ebptv::provenance::Provenance::read_from_dir(&args.file)? {
            Some(p) if args.json => {
                println!("{}", serde_json::to_string_pretty(&p)?);
                Ok(())
            }
            Some(p) => {
                print!("{}", p.describe());
                Ok(())
            }
            None => Err(anyhow::anyhow!(
                "{}: a folder without a provenance record (no provenance.json, no JSON output with a \"provenance\" key); give an event file or an ebptv output folder",
                args.file.display()
            )),
        };
    }
    if args.peak_bin_us <= 0 {
        return Err(ebptv::Error::param(
            "peak-bin-us",
            format!("{} µs: must be positive", args.peak_bin_us),
        )
        .into());
    }
    let opts = open_options(args.format.as_deref(), args.time_unit.as_deref())?;
    let mut bar = super::progress::ReadBar::new("reading");
    let info = file_info(&args.file, &opts, args.peak_bin_us, &mut |p| match p {
        PulsesProgress::Warning(w) => eprintln!("warning: {w}"),
        PulsesProgress::Opened { file_size } => bar.opened(file_size),
        PulsesProgress::Read {
            bytes,
            events,
            done,
        } => bar.read(bytes, events, done),
        _ => {}
    })?;
    let (summary, rejected, verdict) = (&info.summary, info.rejected_geometry, &info.verdict);
    let text = if args.json {
        let v = info.to_json()?;
        serde_json::to_string_pretty(&v)? + "\n"
    } else {
        let mut t = render(summary);
        if let Some(g) = rejected {
            t = t.replacen(
                "geometry           not stated",
                &format!(
                    "geometry           stated as {}x{}, impossible: ignored",
                    g.width, g.height
                ),
                1,
            );
        }
        t.push_str(&format!(
            "{:<18} {}\n",
            "pulsed light",
            match verdict {
                Ok(v) if v.pulsed => format!(
                    "yes (burst contrast {:.1}, excess {:.0} σ, {:.0} % of events in blocks showing the burst)",
                    v.burst_contrast,
                    v.excess_z,
                    100.0 * v.locked_share
                ),
                Ok(v) => format!("no: {}", v.reason),
                Err(e) => format!("no: {e}"),
            }
        ));
        t
    };
    write_stdout(&text)
}

/// Print, treating a closed pipe (`ebptv info f | head`) as success.
pub(crate) fn write_stdout(text: &str) -> anyhow::Result<()> {
    use std::io::Write;
    let mut out = std::io::stdout().lock();
    match out.write_all(text.as_bytes()).and_then(|_| out.flush()) {
        Err(e) if e.kind() == std::io::ErrorKind::BrokenPipe => Ok(()),
        r => Ok(r?),
    }
}

fn fmt_rate(r: Option<f64>) -> String {
    match r {
        Some(r) if r >= 1e6 => format!("{:.3} Mev/s", r / 1e6),
        Some(r) if r >= 1e3 => format!("{:.3} kev/s", r / 1e3),
        Some(r) => format!("{r:.1} ev/s"),
        None => "-".into(),
    }
}

fn opt<T: std::fmt::Display>(v: Option<T>) -> String {
    v.map_or_else(|| "-".to_string(), |v| v.to_string())
}

fn render(s: &Summary) -> String {
    let mut o = String::new();
    let mut line = |k: &str, v: String| o.push_str(&format!("{k:<18} {v}\n"));
    line("file", s.path.display().to_string());
    line("format", s.format_name.clone());
    if let Some(b) = s.file_bytes {
        line("size", format!("{b} bytes"));
    }
    line(
        "geometry",
        match (s.geometry, s.geometry_from_events) {
            (Some(g), _) if s.geometry_source == "inferred" => {
                format!(
                    "{}x{} (inferred from the header, not stated)",
                    g.width, g.height
                )
            }
            (Some(g), _) => format!("{}x{} (stated in the file)", g.width, g.height),
            (None, Some(e)) => format!(
                "not stated; events span {}x{} (max x+1, max y+1)",
                e.width, e.height
            ),
            (None, None) => "not stated".into(),
        },
    );
    for (k, v) in &s.header {
        line(&format!("  {k}"), v.clone());
    }
    line("events", s.events.to_string());
    line(
        "polarity",
        match s.on_fraction {
            Some(f) => format!(
                "{} ON, {} OFF ({:.1} % ON)",
                s.on_events,
                s.off_events,
                100.0 * f
            ),
            None => "-".into(),
        },
    );
    line(
        "first/last t",
        format!(
            "{} / {} µs (file order)",
            opt(s.first_t_us),
            opt(s.last_t_us)
        ),
    );
    line(
        "time range",
        format!("{} .. {} µs", opt(s.min_t_us), opt(s.max_t_us)),
    );
    line(
        "duration",
        s.duration_us
            .map_or("-".into(), |d| format!("{d} µs ({:.6} s)", d as f64 * 1e-6)),
    );
    line("mean rate", fmt_rate(s.mean_rate_ev_per_s));
    line(
        "peak rate",
        format!(
            "{} (busiest {} µs bin, starting at {} µs)",
            fmt_rate(s.peak_rate_ev_per_s),
            s.peak_bin_us,
            opt(s.peak_bin_start_us)
        ),
    );
    if s.triggers.is_empty() {
        line("triggers", "none".into());
    }
    for t in &s.triggers {
        line(
            &format!("triggers ch {}", t.channel),
            format!(
                "{} rising, {} falling, t {} .. {} µs",
                t.rising, t.falling, t.first_t, t.last_t
            ),
        );
    }
    let a = &s.anomalies;
    let mut notes = Vec::new();
    let mut note = |n: u64, what: &str| {
        if n > 0 {
            notes.push(format!("{n} {what}"));
        }
    };
    note(s.time_steps_back, "events earlier than their predecessor");
    note(a.time_loops, "time-counter loops unwrapped");
    note(
        a.words_before_time_base,
        "words before the first time base skipped",
    );
    note(a.unknown_word_types, "unknown words/packets/types");
    note(a.vector_without_base, "vector words without base");
    note(a.out_of_geometry, "events outside the geometry");
    note(a.truncated_tail_bytes, "bytes of a truncated tail");
    note(a.skipped_other_words, "other words/packets skipped (legal)");
    note(s.late_for_peak, "events too late to bin for the peak rate");
    line(
        "anomalies",
        if notes.is_empty() {
            "none".into()
        } else {
            notes.join("; ")
        },
    );
    line(
        "decoded in",
        format!(
            "{:.3} s ({:.1} Mev/s)",
            s.decode_seconds, s.decode_rate_mev_per_s
        ),
    );
    o
}
