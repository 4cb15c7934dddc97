//! `ebptv convert IN OUT`: re-encode a (selected part of a) recording.

use std::path::PathBuf;

use clap::Args;
use ebptv::io::filter::{PolaritySelect, Roi, Selection};
use ebptv::io::{convert_file, ConvertOptions, ConvertProgress, Format};
use ebptv::Geometry;

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
    let open = super::info::open_options(args.in_format.as_deref(), args.time_unit.as_deref())?;
    let format = match &args.format {
        Some(f) => Some(Format::from_name(f).ok_or_else(|| {
            ebptv::Error::param("format", format!("`{f}`: expected csv, npy, evt3 or evt2"))
        })?),
        None => None,
    };
    let opts = ConvertOptions {
        open,
        format,
        selection: Selection {
            from_us: args.from_us,
            to_us: args.to_us,
            roi: args.roi.as_deref().map(str::parse::<Roi>).transpose()?,
            polarity: args.polarity.parse::<PolaritySelect>()?,
        },
        geometry: args.geometry.as_deref().map(parse_geometry).transpose()?,
    };
    let mut pb: Option<indicatif::ProgressBar> = None;
    let done = convert_file(&args.input, &args.output, &opts, &mut |p| match p {
        ConvertProgress::Opened { file_size } => {
            pb = Some(super::progress::file_bar(file_size, "converting"))
        }
        ConvertProgress::Read { bytes } => {
            if let Some(b) = &pb {
                b.set_position(bytes)
            }
        }
        _ => {}
    })?;
    if let Some(b) = pb {
        b.finish_and_clear();
    }
    eprintln!(
        "wrote {} events and {} triggers to {}",
        done.events,
        done.triggers,
        args.output.display()
    );
    if done.anomalies.any_problem() {
        eprintln!("input anomalies: {}", describe_anomalies(&done.anomalies));
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
