//! What the EVT 2.0 and EVT 3.0 writers share.
//!
//! Both encodings are a header followed by little-endian words in which the
//! time is split into a TIME_HIGH word (sent when the high part changes,
//! stepping through clock loops so a decoder counts them) and a few low bits
//! carried by the event or a TIME_LOW word. What differs is only the word
//! width, the split point and how events are packed, so a writer here is:
//! - [`RawWordWriter`]: the atomic output file, the word buffer and the
//!   TIME_HIGH state, with the checks every encoding makes (coordinates fit
//!   in 11 bits, trigger channel fits its id field, time does not run back
//!   across a loop);
//! - a [`RawEncoder`] per format that packs events and triggers into words;
//! - [`encode_chunk`]: the one loop that interleaves a chunk's triggers with
//!   its events in time order and flushes the words.

use std::io::Write;
use std::path::Path;

use crate::atomic::AtomicFile;
use crate::error::{Error, Result};
use crate::events::{Chunk, EventChunk, Geometry, Trigger};

/// Create a RAW output with the modern header (`% format NAME;height;width`,
/// `% geometry`, `% generator`, `% end`) for the writers; `label` names the
/// encoding in errors ("EVT 3.0"). Both encodings address 11-bit x and y.
pub(crate) fn create_raw_file(
    path: &Path,
    format_name: &str,
    label: &str,
    geometry: Geometry,
) -> Result<AtomicFile> {
    if geometry.width == 0
        || geometry.height == 0
        || geometry.width > 2048
        || geometry.height > 2048
    {
        return Err(Error::param(
            "geometry",
            format!(
                "{}x{}: {label} holds sensors from 1x1 up to 2048x2048",
                geometry.width, geometry.height
            ),
        ));
    }
    let mut file = AtomicFile::create(path)?;
    let header = format!(
        "% format {format_name};height={h};width={w}\n% geometry {w}x{h}\n% generator ebptv {v}\n% end\n",
        w = geometry.width,
        h = geometry.height,
        v = env!("CARGO_PKG_VERSION")
    );
    file.write_all(header.as_bytes())
        .map_err(|e| Error::io(path, e))?;
    Ok(file)
}

/// Sequence of TIME_HIGH values (`bits` wide) that takes a decoder from time
/// high `last` (full value incl. loops, `None` at stream start) to `new`,
/// such that the decoder's loop rule (a drop of at least `max - 10`) counts
/// exactly the loops crossed: each loop boundary is crossed as
/// `max → 0`. Returns `Err` when `new` cannot be reached (time going back
/// across a loop boundary, or by nearly a full loop).
pub(crate) fn time_high_steps(
    last: Option<u64>,
    new: u64,
    bits: u32,
    out: &mut Vec<u32>,
) -> std::result::Result<(), ()> {
    let mask = (1u64 << bits) - 1;
    let mut cur = match last {
        Some(c) => c,
        None => {
            // The decoder starts in loop 0.
            let start = if new >> bits == 0 { new } else { 0 };
            out.push((start & mask) as u32);
            start
        }
    };
    if new < cur {
        if cur >> bits == new >> bits && cur - new < mask - 10 {
            out.push((new & mask) as u32);
            return Ok(());
        }
        return Err(());
    }
    while cur >> bits < new >> bits {
        if cur & mask != mask {
            out.push(mask as u32);
        }
        cur = (cur | mask) + 1;
        out.push(0);
    }
    if cur != new {
        out.push((new & mask) as u32);
    }
    Ok(())
}

/// A word of a RAW encoding, written little-endian.
///
/// # Safety
/// Implemented only for plain unsigned integers (u16, u32): on
/// little-endian targets [`RawWordWriter::flush`] writes the words'
/// memory as their bytes, which needs types without padding.
pub(crate) unsafe trait RawWord: Copy {
    /// Write the word into `out` (exactly its size; the byte order of
    /// big-endian targets).
    #[cfg_attr(target_endian = "little", allow(dead_code))]
    fn put_le(self, out: &mut [u8]);
}

// SAFETY: a plain integer.
unsafe impl RawWord for u16 {
    #[inline]
    fn put_le(self, out: &mut [u8]) {
        out.copy_from_slice(&self.to_le_bytes());
    }
}

// SAFETY: a plain integer.
unsafe impl RawWord for u32 {
    #[inline]
    fn put_le(self, out: &mut [u8]) {
        out.copy_from_slice(&self.to_le_bytes());
    }
}

/// The layout of an encoding's time: `low_bits` travel with each event or
/// TIME_LOW word, the next `high_bits` in TIME_HIGH words.
#[derive(Clone, Copy, Debug)]
pub(crate) struct TimeSplit {
    pub label: &'static str,
    pub low_bits: u32,
    pub high_bits: u32,
    /// Width of the trigger id field.
    pub channel_bits: u32,
}

/// File, word buffer and TIME_HIGH state of a RAW writer.
pub(crate) struct RawWordWriter<W> {
    file: AtomicFile,
    pub words: Vec<W>,
    split: TimeSplit,
    th_scratch: Vec<u32>,
    /// Full time high (`t >> low_bits`) last written, incl. loops.
    time_high: Option<u64>,
    last_t: i64,
}

impl<W: RawWord> RawWordWriter<W> {
    pub(crate) fn create(
        path: &Path,
        format_name: &str,
        split: TimeSplit,
        geometry: Geometry,
    ) -> Result<Self> {
        let file = create_raw_file(path, format_name, split.label, geometry)?;
        Ok(RawWordWriter {
            file,
            words: Vec::with_capacity(1 << 16),
            split,
            th_scratch: Vec::new(),
            time_high: None,
            last_t: 0,
        })
    }

    /// Make `t >> low_bits` the decoder's time base, emitting the TIME_HIGH
    /// words `time_high_word(value)` needed (loops stepped through).
    pub(crate) fn set_time_high(
        &mut self,
        t: i64,
        time_high_word: impl Fn(u32) -> W,
    ) -> Result<()> {
        let label = self.split.label;
        if t < 0 {
            return Err(Error::param(
                "events",
                format!("time {t} µs is negative; {label} stores times from 0"),
            ));
        }
        let th = (t as u64) >> self.split.low_bits;
        if self.time_high != Some(th) {
            self.th_scratch.clear();
            let loop_bits = self.split.low_bits + self.split.high_bits;
            time_high_steps(self.time_high, th, self.split.high_bits, &mut self.th_scratch)
                .map_err(|_| {
                    Error::param(
                        "events",
                        format!(
                            "time steps back from {} µs to {t} µs across a {loop_bits}-bit clock loop; {label} cannot encode that (events must be time-ordered)",
                            self.last_t
                        ),
                    )
                })?;
            self.words
                .extend(self.th_scratch.iter().map(|&v| time_high_word(v)));
            self.time_high = Some(th);
        }
        self.last_t = t;
        Ok(())
    }

    /// Both encodings address x and y with 11 bits.
    pub(crate) fn check_coordinates(&self, x: u16, y: u16) -> Result<()> {
        if x >= 2048 || y >= 2048 {
            return Err(Error::param(
                "events",
                format!(
                    "event at ({x}, {y}) does not fit {}'s 11-bit coordinates",
                    self.split.label
                ),
            ));
        }
        Ok(())
    }

    pub(crate) fn check_trigger_channel(&self, channel: u8) -> Result<()> {
        if u32::from(channel) >= 1 << self.split.channel_bits {
            return Err(Error::param(
                "triggers",
                format!(
                    "channel {channel} does not fit {}'s {}-bit id",
                    self.split.label, self.split.channel_bits
                ),
            ));
        }
        Ok(())
    }

    pub(crate) fn flush(&mut self) -> Result<()> {
        let target = self.file.target().to_path_buf();
        #[cfg(target_endian = "little")]
        {
            // The words' memory is already their little-endian bytes.
            // SAFETY: `W` is u16 or u32 (the only `RawWord`s): plain
            // integers without padding, every byte initialised; the slice
            // covers exactly the words' memory and lives while they are
            // borrowed.
            let bytes = unsafe {
                std::slice::from_raw_parts(
                    self.words.as_ptr().cast::<u8>(),
                    std::mem::size_of_val(&self.words[..]),
                )
            };
            let written = self.file.write_all(bytes);
            self.words.clear();
            written.map_err(|e| Error::io(target, e))
        }
        #[cfg(not(target_endian = "little"))]
        {
            // Fixed-size stores into a sized buffer (no capacity check per
            // word).
            let size = std::mem::size_of::<W>();
            let mut bytes = vec![0u8; self.words.len() * size];
            for (out, &w) in bytes.chunks_exact_mut(size).zip(&self.words) {
                w.put_le(out);
            }
            self.words.clear();
            self.file
                .write_all(&bytes)
                .map_err(|e| Error::io(target, e))
        }
    }

    /// Flush and move the file to its target.
    pub(crate) fn finish(mut self) -> Result<()> {
        self.flush()?;
        self.file.commit()
    }
}

/// Packing of events and triggers into one encoding's words.
pub(crate) trait RawEncoder {
    fn encode_trigger(&mut self, trigger: &Trigger) -> Result<()>;
    /// Encode events from index `i` on (at least one); returns the index of
    /// the first event not yet encoded.
    fn encode_events(&mut self, events: &EventChunk, i: usize) -> Result<usize>;
    fn flush(&mut self) -> Result<()>;
}

/// Encode a time-ordered chunk: each trigger goes in before the first event
/// later than it, the rest after the last event.
pub(crate) fn encode_chunk<E: RawEncoder>(encoder: &mut E, chunk: &Chunk) -> Result<()> {
    let events = &chunk.events;
    let mut triggers = chunk.triggers.iter().peekable();
    let mut i = 0;
    while i < events.len() {
        let t = events.t[i];
        while let Some(tr) = triggers.next_if(|tr| tr.t <= t) {
            encoder.encode_trigger(tr)?;
        }
        i = encoder.encode_events(events, i)?;
    }
    for tr in triggers {
        encoder.encode_trigger(tr)?;
    }
    encoder.flush()
}
