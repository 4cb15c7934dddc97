//! # ebptv-io — streaming readers and writers of event-camera files
//!
//! Prophesee RAW (EVT 2.0, 2.1, 3.0) and DAT, iniVation AEDAT 4, Event
//! Stream (`.es`), CSV and NumPy `.npy`, with the external triggers, read
//! in bounded chunks without a vendor SDK. [`open`] tells the format from
//! the file's content; each call to [`EventSource::next_chunk`] fills a
//! caller-owned [`Chunk`] with events (columns `t`, `x`, `y`, `p`) and
//! triggers:
//!
//! ```
//! use ebptv_io::{create, open, sniff, Chunk, Edge, EventChunk, Format, Geometry, Trigger};
//!
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! let dir = tempfile::tempdir()?;
//! let path = dir.path().join("recording.raw");
//!
//! // Write 1000 events and 10 trigger edges as EVT 3.0.
//! let mut chunk = Chunk::default();
//! for i in 0..1000u16 {
//!     chunk.events.push(i as i64 * 10, i % 640, i % 480, (i % 2) as u8);
//! }
//! for k in 0..10 {
//!     let edge = if k % 2 == 0 { Edge::Rising } else { Edge::Falling };
//!     chunk.triggers.push(Trigger { t: k * 1000, channel: 0, edge });
//! }
//! let mut writer = create(&path, None, Geometry::new(640, 480))?;
//! writer.write_chunk(&chunk)?;
//! writer.finish()?;
//!
//! // Read it back: the format comes from the content, memory stays bounded.
//! assert_eq!(sniff::detect_format(&path)?, Format::Evt3);
//! let mut source = open(&path)?;
//! let (mut events, mut triggers) = (0, 0);
//! let mut buf = Chunk { events: EventChunk::with_capacity(1 << 16), triggers: Vec::new() };
//! while source.next_chunk(&mut buf)? {
//!     events += buf.events.len();
//!     triggers += buf.triggers.len();
//! }
//! assert_eq!((events, triggers), (1000, 10));
//! assert_eq!(source.info().geometry, Some(Geometry::new(640, 480)));
//! # Ok(())
//! # }
//! ```
//!
//! Every reader implements [`EventSource`]: an iterator of [`Chunk`]s filled
//! into a caller-owned buffer, so memory stays bounded by the chunk size
//! whatever the file size. [`open`] sniffs the format from the file's content
//! (header, magic) and falls back on the extension; [`create`] picks a writer
//! from the extension. Writers write to a temporary file beside the target
//! and rename it on [`EventWriter::finish`], so an interrupted run never
//! leaves a half-written file under the final name.
//!
//! One file per format: `evt2`, `evt21`, `evt3` (Prophesee RAW), `dat`
//! (Prophesee DAT), `csv`, `aedat4` (iniVation), `es` (Event Stream), `npy`
//! (write only). `raw_header` parses the `% key value` header shared by RAW
//! and DAT files and infers format and geometry of old files. `filter` wraps
//! any source with a time range, an ROI and a polarity selection. `live`
//! reads a RAW stream that is still being written (stdin, a growing file).
//! Errors ([`Error`]) name the file and, for malformed content, the byte
//! offset.

#![warn(missing_docs)]

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

// Unit tests name the crate `ebptv_io`, as a user does.
#[cfg(feature = "testkit")]
extern crate self as ebptv_io;

pub mod error;
pub mod events;

pub use error::{Error, Result};
pub use events::{Chunk, Edge, Event, EventChunk, Geometry, Trigger};

/// File formats ebptv knows.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Format {
    /// Prophesee RAW, EVT 2.0.
    Evt2,
    /// Prophesee RAW, EVT 2.1.
    Evt21,
    /// Prophesee RAW, EVT 3.0.
    Evt3,
    /// Prophesee DAT.
    Dat,
    /// Text, one event per line.
    Csv,
    /// iniVation AEDAT4.
    Aedat4,
    /// Event Stream (`.es`).
    Es,
    /// NumPy structured array (`.npy`).
    Npy,
}

impl Format {
    /// The format's name as shown to users.
    pub fn name(&self) -> &'static str {
        match self {
            Format::Evt2 => "EVT 2.0",
            Format::Evt21 => "EVT 2.1",
            Format::Evt3 => "EVT 3.0",
            Format::Dat => "DAT",
            Format::Csv => "CSV",
            Format::Aedat4 => "AEDAT 4.0",
            Format::Es => "Event Stream",
            Format::Npy => "NumPy .npy",
        }
    }

    /// Parse a user-given format name (`evt3`, `evt2`, `evt21`, `dat`, `csv`,
    /// `aedat4`, `es`, `npy`).
    pub fn from_name(s: &str) -> Option<Format> {
        Some(match s.to_ascii_lowercase().as_str() {
            "evt2" | "evt2.0" => Format::Evt2,
            "evt21" | "evt2.1" => Format::Evt21,
            "evt3" | "evt3.0" | "raw" => Format::Evt3,
            "dat" => Format::Dat,
            "csv" | "txt" => Format::Csv,
            "aedat4" | "aedat" => Format::Aedat4,
            "es" => Format::Es,
            "npy" => Format::Npy,
            _ => return None,
        })
    }
}

/// What is known about a stream before its first event: format, geometry,
/// the parsed header.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct StreamInfo {
    /// The file the stream reads.
    pub path: PathBuf,
    /// The file's encoding.
    pub format: Format,
    /// Sensor geometry; inferred (e.g. from `% system_ID`) when the header
    /// does not state it. `None` when nothing tells it (then the max x/y seen
    /// is the best guess and callers must say so).
    pub geometry: Option<Geometry>,
    /// Header key/value pairs in file order (RAW/DAT `% key value` lines,
    /// AEDAT4 stream description...).
    pub header: Vec<(String, String)>,
    /// Byte offset where the payload starts.
    pub payload_offset: u64,
    /// File size in bytes (for progress reporting), when known.
    pub file_size: Option<u64>,
}

/// Things a decoder met and skipped, counted and reported rather than
/// silently dropped.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Anomalies {
    /// Words before the first TIME_HIGH (no usable time), skipped.
    pub words_before_time_base: u64,
    /// Words of a type the format does not define.
    pub unknown_word_types: u64,
    /// EVT3 vector words with no preceding VECT_BASE_X / ADDR_Y.
    pub vector_without_base: u64,
    /// Events with x/y outside the declared geometry (kept, counted).
    pub out_of_geometry: u64,
    /// Trailing bytes that do not form a whole word/record.
    pub truncated_tail_bytes: u64,
    /// Time-counter loops (wraps) detected and unwrapped.
    pub time_loops: u64,
    /// Skipped OTHERS / IMU / CONTINUED words (legal, not errors).
    pub skipped_other_words: u64,
    /// Runs of events whose time jumped by more than
    /// [`guard::TIME_JUMP_US`] against the clock ([`guard::TimeGuard`]).
    #[serde(default)]
    pub time_jumps: u64,
    /// Events and triggers dropped with those jumps.
    #[serde(default)]
    pub time_jump_events: u64,
}

impl Anomalies {
    /// True when the decoder met something a user should hear about.
    pub fn any_problem(&self) -> bool {
        self.unknown_word_types > 0
            || self.vector_without_base > 0
            || self.out_of_geometry > 0
            || self.truncated_tail_bytes > 0
            || self.time_jumps > 0
    }
}

/// A streaming source of events and triggers.
pub trait EventSource: Send {
    /// What is known about the stream before its first event.
    fn info(&self) -> &StreamInfo;

    /// Clear `chunk` and fill it with the next events and triggers.
    /// Returns `Ok(false)` at the end of the stream (chunk left empty).
    /// A chunk may hold only triggers, but never returns empty before the end.
    fn next_chunk(&mut self, chunk: &mut Chunk) -> Result<bool>;

    /// Anomalies met so far.
    fn anomalies(&self) -> Anomalies {
        Anomalies::default()
    }

    /// Bytes consumed so far (progress bars).
    fn bytes_read(&self) -> u64 {
        0
    }

    /// What the user should hear about the file before its events
    /// (an impossible stated geometry, a self-contradicting header).
    fn warnings(&self) -> Vec<String> {
        Vec::new()
    }

    /// A stated geometry that was dropped as impossible (`guard::Checked`).
    fn rejected_geometry(&self) -> Option<Geometry> {
        None
    }
}

impl EventSource for Box<dyn EventSource> {
    fn info(&self) -> &StreamInfo {
        (**self).info()
    }
    fn next_chunk(&mut self, chunk: &mut Chunk) -> Result<bool> {
        (**self).next_chunk(chunk)
    }
    fn anomalies(&self) -> Anomalies {
        (**self).anomalies()
    }
    fn bytes_read(&self) -> u64 {
        (**self).bytes_read()
    }
    fn warnings(&self) -> Vec<String> {
        (**self).warnings()
    }
    fn rejected_geometry(&self) -> Option<Geometry> {
        (**self).rejected_geometry()
    }
}

/// How far a read has come, handed to an [`Observed`] source's hook after
/// each chunk.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ReadState {
    /// Bytes of the file consumed so far.
    pub bytes: u64,
    /// Events decoded so far.
    pub events: u64,
    /// True after the last chunk.
    pub done: bool,
}

/// A source that calls `hook` with the [`ReadState`] after each chunk: the
/// one way a long read reports progress and lets a caller stop it (an
/// error from the hook ends the read with that error). Every other method
/// passes through.
pub struct Observed<S, F> {
    inner: S,
    events: u64,
    hook: F,
}

impl<S: EventSource, F: FnMut(ReadState) -> Result<()>> Observed<S, F> {
    /// Wrap `inner`; `hook` runs after each chunk.
    pub fn new(inner: S, hook: F) -> Self {
        Observed {
            inner,
            events: 0,
            hook,
        }
    }
}

impl<S: EventSource, F: FnMut(ReadState) -> Result<()> + Send> EventSource for Observed<S, F> {
    fn info(&self) -> &StreamInfo {
        self.inner.info()
    }
    fn next_chunk(&mut self, chunk: &mut Chunk) -> Result<bool> {
        let more = self.inner.next_chunk(chunk)?;
        self.events += chunk.events.len() as u64;
        (self.hook)(ReadState {
            bytes: self.inner.bytes_read(),
            events: self.events,
            done: !more,
        })?;
        Ok(more)
    }
    fn anomalies(&self) -> Anomalies {
        self.inner.anomalies()
    }
    fn bytes_read(&self) -> u64 {
        self.inner.bytes_read()
    }
    fn warnings(&self) -> Vec<String> {
        self.inner.warnings()
    }
    fn rejected_geometry(&self) -> Option<Geometry> {
        self.inner.rejected_geometry()
    }
}

/// Options for [`open_with`].
#[derive(Debug, Clone, Default)]
pub struct OpenOptions {
    /// Force a format instead of sniffing it.
    pub format: Option<Format>,
    /// Events per chunk (default `DEFAULT_CHUNK_EVENTS`).
    pub chunk_events: Option<usize>,
    /// For CSV: the unit of the time column when the header does not say.
    pub csv_time_unit: Option<csv::TimeUnit>,
}

/// Default number of events per chunk: large enough to amortise per-chunk
/// work, small enough (~13 MB) to keep memory bounded.
pub(crate) const DEFAULT_CHUNK_EVENTS: usize = 1 << 20;

/// Open an event file, sniffing its format.
pub fn open(path: impl AsRef<Path>) -> Result<Box<dyn EventSource>> {
    open_with(path, &OpenOptions::default())
}

/// Open an event file with options.
pub fn open_with(path: impl AsRef<Path>, opts: &OpenOptions) -> Result<Box<dyn EventSource>> {
    let path = path.as_ref();
    let format = match opts.format {
        Some(f) => f,
        None => sniff::detect_format(path)?,
    };
    let chunk = opts.chunk_events.unwrap_or(DEFAULT_CHUNK_EVENTS).max(1);
    let src: Box<dyn EventSource> = match format {
        Format::Evt2 => Box::new(evt2::Evt2Reader::open(path, chunk)?),
        Format::Evt21 => Box::new(evt21::Evt21Reader::open(path, chunk)?),
        Format::Evt3 => Box::new(evt3::Evt3Reader::open(path, chunk)?),
        Format::Dat => Box::new(dat::DatReader::open(path, chunk)?),
        Format::Csv => Box::new(csv::CsvReader::open(path, chunk, opts.csv_time_unit)?),
        Format::Aedat4 => Box::new(aedat4::Aedat4Reader::open(path, chunk)?),
        Format::Es => Box::new(es::EsReader::open(path, chunk)?),
        Format::Npy => {
            return Err(Error::UnknownFormat {
                path: path.to_path_buf(),
                why: ".npy is an output format of ebptv; read it with numpy".into(),
            })
        }
    };
    if opts.format.is_none() {
        guard::check_header(src.info())?;
    }
    Ok(Box::new(guard::Checked::new(src)))
}

/// [`open`] for the stages that map time to pulses: the source behind a
/// [`guard::TimeGuard`] (events whose time jumped are dropped and counted;
/// a jump that stays is an error).
pub fn open_for_analysis(path: impl AsRef<Path>) -> Result<Box<dyn EventSource>> {
    Ok(Box::new(guard::TimeGuard::new(open(path)?)))
}

/// A sink for events and triggers.
pub trait EventWriter {
    /// Appends the events and triggers of `chunk`.
    fn write_chunk(&mut self, chunk: &Chunk) -> Result<()>;
    /// Flush and move the file to its final name. Without this call the
    /// temporary file is removed (on drop) and nothing appears at the target.
    fn finish(self: Box<Self>) -> Result<()>;
}

/// Create a writer for `path`; the format comes from `format` or else from
/// the extension (`.raw` = EVT 3.0).
pub fn create(
    path: impl AsRef<Path>,
    format: Option<Format>,
    geometry: Geometry,
) -> Result<Box<dyn EventWriter>> {
    let path = path.as_ref();
    let format = match format {
        Some(f) => f,
        None => sniff::format_from_extension(path).ok_or_else(|| {
            Error::param(
                "output",
                format!(
                    "{}: cannot tell the output format from the extension; use .raw (EVT 3.0), .csv or .npy, or name the format",
                    path.display()
                ),
            )
        })?,
    };
    match format {
        Format::Evt3 => Ok(Box::new(evt3::Evt3Writer::create(path, geometry)?)),
        Format::Evt2 => Ok(Box::new(evt2::Evt2Writer::create(path, geometry)?)),
        Format::Csv => Ok(Box::new(csv::CsvWriter::create(path)?)),
        Format::Npy => Ok(Box::new(npy::NpyEventWriter::create(path)?)),
        other => Err(Error::param(
            "output",
            format!(
                "writing {} is not supported; write .raw (EVT 3.0), EVT 2.0, .csv or .npy",
                other.name()
            ),
        )),
    }
}

pub mod aedat4;
pub mod atomic;
mod convert;
pub use convert::{convert_file, ConvertOptions, ConvertProgress, Converted};
pub mod csv;
pub mod dat;
pub mod es;
pub mod evt2;
pub(crate) mod evt21;
pub mod evt3;
pub mod filter;
pub mod guard;
pub mod live;
pub mod npy;
pub mod raw_header;
pub(crate) mod raw_reader;
pub(crate) mod raw_writer;
pub mod sniff;
pub mod summary;

#[cfg(feature = "testkit")]
pub(crate) mod tests;

// The unit tests, indexed for tests/unit.rs (`unit_tests`; build.rs,
// `ebptv-testgen`); test kit only.
#[cfg(feature = "testkit")]
include!(concat!(env!("OUT_DIR"), "/unit_index.rs"));
