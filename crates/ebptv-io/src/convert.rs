//! What `ebptv convert` does, as one call: an event file (a selected part
//! of it) re-encoded into another format ([`convert_file`]).

use std::path::Path;

use crate::filter::{Filtered, Selection};
use crate::{Anomalies, Chunk, Error, EventSource, Format, Geometry, OpenOptions, Result};

/// Everything [`convert_file`] needs besides the two paths.
#[derive(Debug, Clone, Default)]
pub struct ConvertOptions {
    /// How to read the input (format, CSV time unit).
    pub open: OpenOptions,
    /// Output format; `None`: from the output's extension.
    pub format: Option<Format>,
    /// The events and triggers kept (time range, ROI, polarity).
    pub selection: Selection,
    /// Sensor geometry for RAW outputs when the input states none.
    pub geometry: Option<Geometry>,
}

/// What [`convert_file`] reports to its progress callback as it goes.
#[derive(Clone, Copy, Debug)]
#[non_exhaustive]
pub enum ConvertProgress {
    /// The input is open; `file_size` is its size in bytes when known.
    Opened {
        /// Size of the input in bytes.
        file_size: Option<u64>,
    },
    /// After each chunk written: bytes of the input read so far.
    Read {
        /// Bytes read.
        bytes: u64,
    },
}

/// What [`convert_file`] wrote.
#[derive(Debug, Clone)]
pub struct Converted {
    /// Events written.
    pub events: u64,
    /// Trigger words written.
    pub triggers: u64,
    /// What the reader met in the input (skipped words, clock loops, …).
    pub anomalies: Anomalies,
}

/// Re-encode the events and triggers of `input` that `opts.selection`
/// keeps into `output` (written atomically), in `opts.format` or the
/// format of its extension.
pub fn convert_file(
    input: &Path,
    output: &Path,
    opts: &ConvertOptions,
    on_progress: &mut dyn FnMut(ConvertProgress),
) -> Result<Converted> {
    let out_format = opts
        .format
        .or_else(|| crate::sniff::format_from_extension(output));
    if let (Ok(a), Ok(b)) = (input.canonicalize(), output.canonicalize()) {
        if a == b {
            return Err(Error::param(
                "output",
                format!("{}: is the input file", output.display()),
            ));
        }
    }
    let src = crate::open_with(input, &opts.open)?;
    let needs_geometry = matches!(
        out_format,
        Some(Format::Evt2 | Format::Evt21 | Format::Evt3)
    );
    let geometry = match (opts.geometry, src.info().geometry) {
        (Some(g), _) | (None, Some(g)) => g,
        (None, None) if needs_geometry => {
            return Err(Error::param(
                "geometry",
                format!(
                    "{} does not state its sensor geometry and {} needs one: pass --geometry WxH",
                    input.display(),
                    output.display()
                ),
            ))
        }
        // CSV and .npy do not store a geometry.
        (None, None) => Geometry::new(u16::MAX, u16::MAX),
    };
    let total = src.info().file_size;
    let mut src = Filtered::new(src, opts.selection.clone())?;
    let mut writer = crate::create(output, out_format, geometry)?;
    on_progress(ConvertProgress::Opened { file_size: total });
    let mut chunk = Chunk::default();
    let (mut events, mut triggers) = (0u64, 0u64);
    while src.next_chunk(&mut chunk)? {
        events += chunk.events.len() as u64;
        triggers += chunk.triggers.len() as u64;
        writer.write_chunk(&chunk)?;
        on_progress(ConvertProgress::Read {
            bytes: src.bytes_read(),
        });
    }
    writer.finish()?;
    Ok(Converted {
        events,
        triggers,
        anomalies: src.anomalies(),
    })
}
