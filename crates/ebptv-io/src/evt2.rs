//! Prophesee EVT 2.0: streaming reader and writer.
//!
//! EVT 2.0 is a stream of 32-bit little-endian words, type in bits 31..28.
//! CD_OFF (0x0) / CD_ON (0x1) carry x (bits 21..11), y (10..0) and the low 6
//! bits of time (27..22); TIME_HIGH (0x8) carries time bits 33..6;
//! EXT_TRIGGER (0xA) carries the edge (bit 0), the channel (bits 12..8) and
//! the low time bits. OTHERS (0xE), IMU (0xD) and CONTINUED (0xF) words are
//! skipped (counted). Each word stands alone, so the only state is the time
//! base, and a read-buffer boundary never splits anything but a word (which
//! `crate::raw_header::PayloadReader` keeps whole).
//!
//! The 34-bit time wraps after ~4.8 h: a loop is counted only when TIME_HIGH
//! drops by nearly a full cycle (reference decoder's rule, threshold 10
//! TIME_HIGH units). Words before the first TIME_HIGH are skipped and
//! counted. Time is raw sensor time, never clamped or sorted.

use std::path::Path;

use crate::error::Result;
use crate::events::{Chunk, Edge, EventChunk, Geometry, Trigger};
use crate::evt3::RawAppend;
use crate::raw_header::READ_BUFFER_BYTES;
use crate::raw_reader::{RawReader, WordDecoder};
use crate::raw_writer::{encode_chunk, RawEncoder, RawWordWriter, TimeSplit};
use crate::{Anomalies, Format};

const MAX_TIME_BASE: u64 = ((1 << 28) - 1) << 6;
/// Period of the 34-bit clock, µs.
pub(crate) const TIME_LOOP_US: u64 = MAX_TIME_BASE + (1 << 6);
const LOOP_THRESHOLD: u64 = 10 << 6;

/// Unwrap a 28-bit TIME_HIGH field into a full time base (shared by EVT 2.0
/// and EVT 2.1, which use the same clock).
#[derive(Debug, Clone, Default)]
pub(crate) struct TimeBase34 {
    pub base: u64,
    pub loops: u64,
}

impl TimeBase34 {
    /// Returns true when a loop was counted.
    #[inline]
    pub(crate) fn update(&mut self, field: u32) -> bool {
        let mut new_base = ((field as u64 & 0x0FFF_FFFF) << 6) + self.loops * TIME_LOOP_US;
        let looped = self.base > new_base && self.base - new_base >= MAX_TIME_BASE - LOOP_THRESHOLD;
        if looped {
            new_base += TIME_LOOP_US;
            self.loops += 1;
        }
        self.base = new_base;
        looped
    }
}

/// The EVT 2.0 decoder, independent of where the bytes come from.
#[derive(Debug, Clone, Default)]
#[ebptv_macros::testkit]
pub(crate) struct Evt2Decoder {
    have_time_base: bool,
    time: TimeBase34,
    /// Malformed or unexpected words met so far.
    pub anomalies: Anomalies,
}

impl Evt2Decoder {
    /// A decoder at the start of a stream.
    #[ebptv_macros::testkit]
    pub(crate) fn new() -> Self {
        Self::default()
    }

    /// Decode whole 32-bit words of `bytes` into `out` until it holds
    /// `max_events` events or triggers. Returns the bytes consumed (a
    /// multiple of 4).
    #[ebptv_macros::testkit]
    pub(crate) fn decode(&mut self, bytes: &[u8], out: &mut Chunk, max_events: usize) -> usize {
        let total = bytes.len() & !3;
        let mut pos = 0;
        while pos < total {
            let len = out.events.len();
            if len >= max_events || out.triggers.len() >= max_events {
                break;
            }
            let words = (max_events - len).min((total - pos) / 4);
            let end = pos + 4 * words;
            self.decode_block(&bytes[pos..end], out);
            pos = end;
        }
        pos
    }

    #[cold]
    fn find_time_base(&mut self, words: &[u8]) -> usize {
        for (i, w) in words.chunks_exact(4).enumerate() {
            let w = u32::from_le_bytes([w[0], w[1], w[2], w[3]]);
            if w >> 28 == 0x8 {
                self.have_time_base = true;
                self.time.update(w);
                return 4 * (i + 1);
            }
            self.anomalies.words_before_time_base += 1;
        }
        words.len()
    }

    #[inline]
    fn decode_block(&mut self, mut words: &[u8], out: &mut Chunk) {
        if !self.have_time_base {
            let skip = self.find_time_base(words);
            words = &words[skip..];
        }
        let mut base = self.time.base as i64;
        let n = words.len() & !3;
        let mut sink = RawAppend::new(&mut out.events, n / 4);
        let mut pos = 0;
        loop {
            // SAFETY: the sink has room for one event per word of the block
            // (+1 spare); each word keeps at most one.
            pos += unsafe { cd_run(&words[pos..n], base, &mut sink) };
            if pos >= n {
                break;
            }
            let w =
                u32::from_le_bytes([words[pos], words[pos + 1], words[pos + 2], words[pos + 3]]);
            pos += 4;
            match w >> 28 {
                0x8 => {
                    if self.time.update(w) {
                        self.anomalies.time_loops += 1;
                    }
                    base = self.time.base as i64;
                }
                0xA => out.triggers.push(Trigger {
                    t: base + ((w >> 22) & 0x3F) as i64,
                    channel: ((w >> 8) & 0x1F) as u8,
                    edge: if w & 1 == 1 {
                        Edge::Rising
                    } else {
                        Edge::Falling
                    },
                }),
                0xD..=0xF => self.anomalies.skipped_other_words += 1,
                _ => self.anomalies.unknown_word_types += 1,
            }
        }
    }
}

/// A run of CD words (types 0x0 / 0x1), the bulk of any EVT 2.0 stream, in
/// a small never-inlined loop whose state stays in registers. Stops before
/// the first other word; returns the bytes consumed.
///
/// # Safety
/// `sink` must have room for one event per word of `words`.
#[inline(never)]
unsafe fn cd_run(words: &[u8], base: i64, sink: &mut RawAppend) -> usize {
    let mut i = 0;
    while let Some(b) = words.get(i..i + 4) {
        let w = u32::from_le_bytes([b[0], b[1], b[2], b[3]]);
        let kind = w >> 28;
        if kind > 1 {
            break;
        }
        // SAFETY: one event per word (caller's room).
        unsafe {
            sink.write_spare_unchecked(
                base + ((w >> 22) & 0x3F) as i64,
                ((w >> 11) & 0x7FF) as u16,
                (w & 0x7FF) as u16,
                kind as u8,
            )
        };
        sink.advance(1);
        i += 4;
    }
    i
}

/// Streaming EVT 2.0 file reader.
pub(crate) type Evt2Reader = RawReader<Evt2Decoder>;

impl RawReader<Evt2Decoder> {
    /// Open `path`, parse its header, and prepare to stream chunks of at
    /// most `chunk_events` events.
    pub(crate) fn open(path: &Path, chunk_events: usize) -> Result<Self> {
        Self::open_with_buffer(path, chunk_events, READ_BUFFER_BYTES)
    }

    /// `Evt2Reader::open` with a chosen read-buffer size.
    pub(crate) fn open_with_buffer(
        path: &Path,
        chunk_events: usize,
        buffer_bytes: usize,
    ) -> Result<Self> {
        RawReader::open_format(path, Format::Evt2, 4, chunk_events, buffer_bytes, |_| {
            Evt2Decoder::new()
        })
    }
}

impl WordDecoder for Evt2Decoder {
    const MAX_EVENTS_PER_WORD: usize = 1;
    fn decode(&mut self, bytes: &[u8], out: &mut Chunk, max_events: usize) -> usize {
        Evt2Decoder::decode(self, bytes, out, max_events)
    }
    fn anomalies(&self) -> &Anomalies {
        &self.anomalies
    }
    fn anomalies_mut(&mut self) -> &mut Anomalies {
        &mut self.anomalies
    }
}

/// EVT 2.0 writer (through [`AtomicFile`]: nothing appears at the target
/// until [`crate::EventWriter::finish`]).
pub(crate) struct Evt2Writer {
    raw: RawWordWriter<u32>,
}

const EVT2_TIME: TimeSplit = TimeSplit {
    label: "EVT 2.0",
    low_bits: 6,
    high_bits: 28,
    channel_bits: 5,
};

impl Evt2Writer {
    pub(crate) fn create(path: &Path, geometry: Geometry) -> Result<Self> {
        Ok(Evt2Writer {
            raw: RawWordWriter::create(path, "EVT2", EVT2_TIME, geometry)?,
        })
    }

    /// Make `t >> 6` the decoder's time base; returns the low 6 bits.
    fn set_time(&mut self, t: i64) -> Result<u32> {
        self.raw.set_time_high(t, |v| 0x8000_0000 | v)?;
        Ok((t & 0x3F) as u32)
    }
}

impl RawEncoder for Evt2Writer {
    fn encode_trigger(&mut self, tr: &Trigger) -> Result<()> {
        self.raw.check_trigger_channel(tr.channel)?;
        let low = self.set_time(tr.t)?;
        let v = matches!(tr.edge, Edge::Rising) as u32;
        self.raw
            .words
            .push(0xA000_0000 | (low << 22) | ((tr.channel as u32) << 8) | v);
        Ok(())
    }

    fn encode_events(&mut self, ev: &EventChunk, i: usize) -> Result<usize> {
        let (x, y) = (ev.x[i], ev.y[i]);
        self.raw.check_coordinates(x, y)?;
        let low = self.set_time(ev.t[i])?;
        let kind = (ev.p[i] != 0) as u32;
        self.raw
            .words
            .push((kind << 28) | (low << 22) | ((x as u32) << 11) | y as u32);
        Ok(i + 1)
    }

    fn flush(&mut self) -> Result<()> {
        self.raw.flush()
    }
}

impl crate::EventWriter for Evt2Writer {
    fn write_chunk(&mut self, chunk: &Chunk) -> Result<()> {
        encode_chunk(self, chunk)
    }

    fn finish(self: Box<Self>) -> Result<()> {
        self.raw.finish()
    }
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;

    fn decode_all(words: &[u32]) -> (Chunk, Anomalies) {
        let bytes: Vec<u8> = words.iter().flat_map(|w| w.to_le_bytes()).collect();
        let mut d = Evt2Decoder::new();
        let mut c = Chunk::default();
        assert_eq!(d.decode(&bytes, &mut c, 1 << 20), bytes.len());
        (c, d.anomalies)
    }

    #[ebptv_macros::unit_test]
    fn words_of_every_type() {
        let cd = |p: u32, low: u32, x: u32, y: u32| (p << 28) | (low << 22) | (x << 11) | y;
        let (c, a) = decode_all(&[
            cd(1, 0, 1, 1), // before time base
            0x8000_0002,    // base 128
            cd(1, 5, 639, 479),
            cd(0, 63, 3, 4),
            0xA000_0000 | (7 << 22) | (1 << 8), // trigger ch 1 falling at 135
            0xE000_0000,
            0xF000_0000,
            0x3000_0000,
        ]);
        assert_eq!(c.events.t, vec![133, 191]);
        assert_eq!(c.events.x, vec![639, 3]);
        assert_eq!(c.events.y, vec![479, 4]);
        assert_eq!(c.events.p, vec![1, 0]);
        assert_eq!(
            c.triggers,
            vec![Trigger {
                t: 135,
                channel: 1,
                edge: Edge::Falling
            }]
        );
        assert_eq!(a.words_before_time_base, 1);
        assert_eq!(a.skipped_other_words, 2);
        assert_eq!(a.unknown_word_types, 1);
    }

    #[ebptv_macros::unit_test]
    fn loop_of_the_34_bit_clock() {
        let (c, a) = decode_all(&[
            0x8FFF_FFFF,
            0x1000_0000,
            0x8000_0000,
            0x1000_0000,
            0x8000_0100,
            0x1000_0000,
            0x8000_0010,
            0x1000_0000,
        ]);
        assert_eq!(
            c.events.t,
            vec![
                MAX_TIME_BASE as i64,
                TIME_LOOP_US as i64,
                (TIME_LOOP_US + (0x100 << 6)) as i64,
                (TIME_LOOP_US + (0x10 << 6)) as i64
            ]
        );
        assert_eq!(a.time_loops, 1);
    }
}
