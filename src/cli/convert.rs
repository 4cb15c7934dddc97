//! `ebptv convert IN OUT`: re-encode a (selected part of a) recording.

use std::path::PathBuf;

use clap::Args;
use ebptv::io::filter::{Filtered, PolaritySelect, Roi, Selection};
use ebptv::io::{self, EventSource, Format};
use ebptv::{Chunk, Geometry};

#[derive(Args, Debug)]
pub struct ConvertArgs {
    /// Input event file.
    pub input: PathBuf,
    /// Output file; the format follows the extension (.csv, .npy, .raw = EVT 3.0) unless --format.
    pub output: PathBuf,
    /// Keep events with t >= this (µs, raw sensor time).
    #[arg(long)]
    pub from_us: Option<i64>,
    /// Keep events with t < this (µs).
    #[arg(long)]
    pub to_us: Option<i64>,
    /// Keep events inside x0,y0,width,height (pixels; coordinates are not shifted).
    #[arg(long)]
    pub roi: Option<String>,
    /// Keep on, off or both polarities.
    #[arg(long, default_value = "both")]
    pub polarity: String,
    /// Output format (csv, npy, evt3, evt2), overriding the extension.
    #[arg(long)]
    pub format: Option<String>,
    /// Input format, overriding detection.
    #[arg(long)]
    pub in_format: Option<String>,
    /// CSV input only: unit of the time column when the header does not say (us, ms, s, ns).
    #[arg(long)]
    pub time_unit: Option<String>,
    /// Sensor geometry WxH for outputs that need one when the input does not state it.
    #[arg(long)]
    pub geometry: Option<String>,
}

fn parse_geometry(s: &str) -> ebptv::Result<Geometry> {
    let bad = || {
        ebptv::Error::param(
            "geometry",
            format!("`{s}`: expected WIDTHxHEIGHT, e.g. 1280x720"),
        )
    };
    let (w, h) = s.split_once(['x', 'X']).ok_or_else(bad)?;
    let (w, h): (u16, u16) = (
        w.trim().parse().map_err(|_| bad())?,
        h.trim().parse().map_err(|_| bad())?,
    );
    if w == 0 || h == 0 {
        return Err(bad());
    }
    Ok(Geometry::new(w, h))
}

pub fn run(args: ConvertArgs) -> anyhow::Result<()> {
    let opts = super::info::open_options(args.in_format.as_deref(), args.time_unit.as_deref())?;
    let out_format = match &args.format {
        Some(f) => Some(Format::from_name(f).ok_or_else(|| {
            ebptv::Error::param("format", format!("`{f}`: expected csv, npy, evt3 or evt2"))
        })?),
        None => io::sniff::format_from_extension(&args.output),
    };
    if let (Ok(a), Ok(b)) = (args.input.canonicalize(), args.output.canonicalize()) {
        if a == b {
            return Err(ebptv::Error::param(
                "output",
                format!("{}: is the input file", args.output.display()),
            )
            .into());
        }
    }
    let selection = Selection {
        from_us: args.from_us,
        to_us: args.to_us,
        roi: args.roi.as_deref().map(str::parse::<Roi>).transpose()?,
        polarity: args.polarity.parse::<PolaritySelect>()?,
    };
    let src = io::open_with(&args.input, &opts)?;
    let needs_geometry = matches!(
        out_format,
        Some(Format::Evt2 | Format::Evt21 | Format::Evt3)
    );
    let geometry = match (
        args.geometry.as_deref().map(parse_geometry).transpose()?,
        src.info().geometry,
    ) {
        (Some(g), _) | (None, Some(g)) => g,
        (None, None) if needs_geometry => {
            return Err(ebptv::Error::param(
                "geometry",
                format!(
                    "{} does not state its sensor geometry and {} needs one: pass --geometry WxH",
                    args.input.display(),
                    args.output.display()
                ),
            )
            .into())
        }
        // CSV and .npy do not store a geometry.
        (None, None) => Geometry::new(u16::MAX, u16::MAX),
    };
    let total = src.info().file_size;
    let mut src = Filtered::new(src, selection)?;
    let mut writer = io::create(&args.output, out_format, geometry)?;
    let pb = super::progress::file_bar(total, "converting");
    let mut chunk = Chunk::default();
    let (mut n_ev, mut n_tr) = (0u64, 0u64);
    while src.next_chunk(&mut chunk)? {
        n_ev += chunk.events.len() as u64;
        n_tr += chunk.triggers.len() as u64;
        writer.write_chunk(&chunk)?;
        pb.set_position(src.bytes_read());
    }
    writer.finish()?;
    pb.finish_and_clear();
    let a = src.anomalies();
    eprintln!(
        "wrote {n_ev} events and {n_tr} triggers to {}",
        args.output.display()
    );
    if a.any_problem() {
        eprintln!("input anomalies: {}", describe_anomalies(&a));
    }
    Ok(())
}

/// The anomalies a reader met, in words (the counts that are not zero).
pub(crate) fn describe_anomalies(a: &ebptv::io::Anomalies) -> String {
    let items = [
        (
            a.words_before_time_base,
            "words before the first time base (skipped)",
        ),
        (a.unknown_word_types, "words of undefined types"),
        (a.vector_without_base, "vector words without a base"),
        (a.out_of_geometry, "events outside the stated geometry"),
        (
            a.truncated_tail_bytes,
            "trailing bytes of an incomplete word",
        ),
        (a.time_loops, "time-counter loops unwrapped"),
        (a.skipped_other_words, "other/IMU/continued words skipped"),
        (a.time_jumps, "clock jumps"),
        (a.time_jump_events, "events dropped with clock jumps"),
    ];
    let parts: Vec<String> = items
        .iter()
        .filter(|(n, _)| *n > 0)
        .map(|(n, what)| format!("{n} {what}"))
        .collect();
    if parts.is_empty() {
        "none".into()
    } else {
        parts.join(", ")
    }
}
