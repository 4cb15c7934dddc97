//! Prophesee EVT 3.0: streaming reader and writer.
//!
//! EVT 3.0 is a stateful stream of 16-bit little-endian words (type in bits
//! 15..12). The decoder keeps the state the format relies on: the time base
//! (TIME_HIGH, with 24-bit loops unwrapped), the current time (TIME_LOW),
//! the current row (ADDR_Y), and the vector base x and polarity
//! (VECT_BASE_X). ADDR_X emits one event; VECT_12 / VECT_8 emit one event per
//! set bit at base_x + i and advance base_x by 12 / 8, each word on its own
//! (a vector run may be any length, and may straddle a read buffer: all state
//! lives in `Evt3Decoder`, none in the buffer).
//!
//! Time is reported exactly as the sensor wrote it: TIME_LOW may step back
//! inside one TIME_HIGH (several event sources share the bus) and is neither
//! clamped nor sorted. Only TIME_HIGH dropping by at least
//! `(4095 - 10) << 12` µs counts as a loop of the 24-bit clock, the rule of
//! Prophesee's reference decoder. Words before the first TIME_HIGH carry no
//! usable time and are skipped; they, unknown word types, vectors with no
//! base, and a truncated last word are counted in [`Anomalies`].
//!
//! Speed (BENCHMARKS.md: ~370 Mev/s on one core, 4x the `evt3`
//! crate): the decoder walks a `&[u8]` slice of a fixed 1 MB read buffer
//! and appends through `RawAppend` into chunk capacity reserved per block
//! (12 events per word), so there is no per-event capacity check. The bulk
//! of the words goes through `fast_run`, a small never-inlined loop whose
//! state stays in registers: two ADDR_Y + ADDR_X pairs per 64-bit load (the
//! commonest pattern of sparse data), other ADDR_X / ADDR_Y / TIME_LOW words
//! branch-free, vector words in place. TIME_HIGH, triggers, EM/OTHERS and
//! malformed words take the plain `match` in `decode_block`. The
//! out-of-geometry check is a separate vectorised pass per chunk.
//!
//! The writer (`Evt3Writer`) takes time-ordered chunks (events sharing a
//! timestamp and row grouped, as the simulator and cameras produce them) and
//! uses VECT_BASE_X + VECT_12/VECT_8 for runs of increasing x where that
//! saves words, ADDR_X otherwise, so the reader gives back exactly the same
//! events in the same order.

use std::path::Path;

use crate::error::{Error, Result};
use crate::events::{Chunk, Edge, EventChunk, Geometry, Trigger};
use crate::raw_header::READ_BUFFER_BYTES;
use crate::raw_reader::{RawReader, WordDecoder};
#[cfg(feature = "testkit")]
use crate::raw_writer::encode_chunk;
#[cfg(feature = "testkit")]
use crate::raw_writer::time_high_steps;
use crate::raw_writer::{RawEncoder, RawWordWriter, TimeSplit};
use crate::{Anomalies, Format, StreamInfo};

/// Most events one EVT 3.0 word can produce (VECT_12).
pub(crate) const MAX_EVENTS_PER_WORD: usize = 12;

const TIME_HIGH_BITS: u32 = 12;
/// Largest time base a TIME_HIGH can express, µs.
const MAX_TIME_BASE: u64 = ((1 << 12) - 1) << 12;
/// Period of the 24-bit clock, µs.
pub(crate) const TIME_LOOP_US: u64 = MAX_TIME_BASE + (1 << 12);
/// Tolerance of the loop detection (reference decoder's value), µs.
const LOOP_THRESHOLD: u64 = 10 << 12;

const ROW_CD: u8 = 1;
const ROW_EM: u8 = 2;
/// Word kinds handled on the branch-free fast path: ADDR_Y, ADDR_X, TIME_LOW.
const FAST_KINDS: u16 = (1 << 0x0) | (1 << 0x2) | (1 << 0x6);

/// The EVT 3.0 decoding state machine, independent of where the bytes come
/// from (files through `Evt3Reader`, memory in tests and tools).
#[derive(Debug, Clone, Default)]
#[ebptv_macros::testkit]
pub(crate) struct Evt3Decoder {
    have_time_base: bool,
    /// Current time base including unwrapped loops, µs.
    time_base: u64,
    loops: u64,
    current_time: i64,
    y: u16,
    /// 0: no ADDR_Y yet; [`ROW_CD`] after ADDR_Y; [`ROW_EM`] after EM_Y
    /// (exposure-measurement events follow, not CD).
    row: u8,
    vector: VectorState,
    /// Malformed or unexpected words met so far.
    pub anomalies: Anomalies,
}

impl Evt3Decoder {
    /// A decoder at the start of a stream.
    #[ebptv_macros::testkit]
    pub(crate) fn new() -> Self {
        Self::default()
    }

    /// Decode whole 16-bit words from `bytes` (a trailing odd byte is left
    /// alone) into `out`, stopping once `out` holds at least `max_events`
    /// events (at most `max_events + 11`) or triggers. Returns the number of
    /// bytes consumed (always even).
    #[ebptv_macros::testkit]
    pub(crate) fn decode(&mut self, bytes: &[u8], out: &mut Chunk, max_events: usize) -> usize {
        let total = bytes.len() & !1;
        let mut pos = 0;
        while pos < total {
            let len = out.events.len();
            if len >= max_events || out.triggers.len() >= max_events {
                break;
            }
            // Words that cannot overflow the chunk even if all are VECT_12.
            let words = ((max_events - len) / MAX_EVENTS_PER_WORD).clamp(1, (total - pos) / 2);
            let end = pos + 2 * words;
            reserve(&mut out.events, words * MAX_EVENTS_PER_WORD);
            self.decode_block(&bytes[pos..end], out);
            pos = end;
        }
        pos
    }

    /// Skip to the first TIME_HIGH, counting the skipped words. Returns the
    /// index of the first word not consumed.
    #[cold]
    fn find_time_base(&mut self, words: &[u8]) -> usize {
        for (i, w) in words.chunks_exact(2).enumerate() {
            let w = u16::from_le_bytes([w[0], w[1]]);
            if w >> 12 == 0x8 {
                self.have_time_base = true;
                self.time_base = ((w & 0xFFF) as u64) << TIME_HIGH_BITS;
                self.current_time = self.time_base as i64;
                return 2 * (i + 1);
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
        // Local copies of the hot state so it lives in registers.
        let mut t = self.current_time;
        let mut y = self.y;
        let mut row = self.row;
        let mut vs = self.vector;
        let mut time_base = self.time_base;
        let mut sink = RawAppend::new(&mut out.events, words.len() / 2 * MAX_EVENTS_PER_WORD);
        let n = words.len() & !1;
        let mut pos = 0;
        loop {
            if row == ROW_CD {
                // SAFETY: the sink has room for MAX_EVENTS_PER_WORD events
                // per word of this block (+1 spare); the words before `pos`
                // kept at most that many each, and the run keeps at most
                // one per word.
                pos += unsafe {
                    fast_run(&words[pos..], &mut t, &mut y, &mut vs, time_base, &mut sink)
                };
            }
            if pos >= n {
                break;
            }
            let w = u16::from_le_bytes([words[pos], words[pos + 1]]);
            pos += 2;
            match w >> 12 {
                0x0 => {
                    y = w & 0x7FF;
                    row = ROW_CD;
                }
                0x2 => {
                    if row == ROW_EM {
                        self.anomalies.skipped_other_words += 1;
                    } else {
                        self.anomalies.vector_without_base += 1;
                    }
                }
                0x6 => t = (time_base + (w & 0xFFF) as u64) as i64,
                kind @ (0x4 | 0x5) => {
                    let (mut mask, n) = if kind == 0x4 {
                        (w & 0xFFF, 12)
                    } else {
                        (w & 0xFF, 8)
                    };
                    if vs.have_base & (row == ROW_CD) {
                        while mask != 0 {
                            let i = mask.trailing_zeros() as u16;
                            sink.push(t, vs.base_x.wrapping_add(i), y, vs.polarity);
                            mask &= mask - 1;
                        }
                    } else {
                        self.vector_without_base(row, vs.have_base);
                    }
                    vs.base_x = vs.base_x.wrapping_add(n);
                }
                0x3 => {
                    vs.base_x = w & 0x7FF;
                    vs.polarity = ((w >> 11) & 1) as u8;
                    vs.have_base = true;
                }
                0x8 => {
                    self.time_high(w);
                    time_base = self.time_base;
                    t = time_base as i64;
                }
                0xA => out.triggers.push(Trigger {
                    t,
                    channel: ((w >> 8) & 0xF) as u8,
                    edge: if w & 1 == 1 {
                        Edge::Rising
                    } else {
                        Edge::Falling
                    },
                }),
                0x1 => {
                    // EM_Y: the following X/VECT words are exposure
                    // measurements, not CD events.
                    row = ROW_EM;
                    self.anomalies.skipped_other_words += 1;
                }
                0x7 | 0xE | 0xF => self.anomalies.skipped_other_words += 1,
                _ => self.anomalies.unknown_word_types += 1,
            }
        }
        drop(sink);
        self.current_time = t;
        self.y = y;
        self.row = row;
        self.vector = vs;
    }

    #[cold]
    fn vector_without_base(&mut self, row: u8, have_base: bool) {
        if row == ROW_EM && have_base {
            self.anomalies.skipped_other_words += 1;
        } else {
            self.anomalies.vector_without_base += 1;
        }
    }

    #[inline]
    fn time_high(&mut self, w: u16) {
        let mut new_base = (((w & 0xFFF) as u64) << TIME_HIGH_BITS) + self.loops * TIME_LOOP_US;
        if self.time_base > new_base && self.time_base - new_base >= MAX_TIME_BASE - LOOP_THRESHOLD
        {
            new_base += TIME_LOOP_US;
            self.loops += 1;
            self.anomalies.time_loops += 1;
        }
        self.time_base = new_base;
    }
}

/// The fast path of the EVT 3.0 decoder: a run of ADDR_X / ADDR_Y /
/// TIME_LOW words inside a CD row (nearly all words of sparse data), with no
/// data-dependent branch: each word writes a candidate event speculatively,
/// kept only for an ADDR_X, and selects the new row / time. It stops before
/// the first other word and returns the bytes consumed.
///
/// A separate, never-inlined function on purpose: with only its own few
/// variables live, the state stays in registers (inlined into the full
/// decoder, the row was spilled to the stack and every word paid a
/// store-to-load round trip on it).
///
/// # Safety
/// `sink` must have room for one kept event per word of `bytes`, plus the
/// spare slot.
#[inline(never)]
unsafe fn fast_run(
    bytes: &[u8],
    t: &mut i64,
    y: &mut u16,
    vector: &mut VectorState,
    time_base: u64,
    sink: &mut RawAppend,
) -> usize {
    let (mut tt, mut yy) = (*t, *y);
    let mut vs = *vector;
    let n = bytes.len() & !1;
    let mut i = 0;
    while i < n {
        // The commonest pair by far in sparse data is ADDR_Y then ADDR_X
        // (each event in a new row): two such pairs per 64-bit load, then
        // one pair per 32-bit load, then single words.
        while let Some(b8) = bytes.get(i..i + 8) {
            let v = u64::from_le_bytes(b8.try_into().expect("8 bytes"));
            if v & 0xF000_F000_F000_F000 != 0x2000_0000_2000_0000 {
                break;
            }
            let y0 = (v & 0x7FF) as u16;
            yy = ((v >> 32) & 0x7FF) as u16;
            // SAFETY: two kept events for four words (caller's room).
            unsafe {
                sink.write_spare_unchecked(
                    tt,
                    ((v >> 16) & 0x7FF) as u16,
                    y0,
                    ((v >> 27) & 1) as u8,
                );
                sink.advance(1);
                sink.write_spare_unchecked(
                    tt,
                    ((v >> 48) & 0x7FF) as u16,
                    yy,
                    ((v >> 59) & 1) as u8,
                );
                sink.advance(1);
            }
            i += 8;
        }
        if let Some(b4) = bytes.get(i..i + 4) {
            let v = u32::from_le_bytes(b4.try_into().expect("4 bytes"));
            if v & 0xF000_F000 == 0x2000_0000 {
                yy = (v & 0x7FF) as u16;
                // SAFETY: one kept event for two words (caller's room).
                unsafe {
                    sink.write_spare_unchecked(
                        tt,
                        ((v >> 16) & 0x7FF) as u16,
                        yy,
                        ((v >> 27) & 1) as u8,
                    )
                };
                sink.advance(1);
                i += 4;
                continue;
            }
        }
        if i >= n {
            break;
        }
        let w = u16::from_le_bytes([bytes[i], bytes[i + 1]]);
        let kind = w >> 12;
        if (1u16 << kind) & FAST_KINDS == 0 {
            // Vector words (dense rows) stay on the fast path too; a vector
            // with no base yet goes to the slow path to be counted.
            if kind == 0x3 {
                vs.base_x = w & 0x7FF;
                vs.polarity = ((w >> 11) & 1) as u8;
                vs.have_base = true;
                i += 2;
                continue;
            }
            if (kind == 0x4 || kind == 0x5) && vs.have_base {
                let (mut mask, width) = if kind == 0x4 {
                    (w & 0xFFF, 12)
                } else {
                    (w & 0xFF, 8)
                };
                while mask != 0 {
                    let bit = mask.trailing_zeros() as u16;
                    // SAFETY: at most MAX_EVENTS_PER_WORD kept events per
                    // word (caller's room).
                    unsafe {
                        sink.write_spare_unchecked(tt, vs.base_x.wrapping_add(bit), yy, vs.polarity)
                    };
                    sink.advance(1);
                    mask &= mask - 1;
                }
                vs.base_x = vs.base_x.wrapping_add(width);
                i += 2;
                continue;
            }
            break;
        }
        // SAFETY: at most one kept event per word so far (caller's room).
        unsafe { sink.write_spare_unchecked(tt, w & 0x7FF, yy, ((w >> 11) & 1) as u8) };
        sink.advance((kind == 0x2) as usize);
        yy = if kind == 0x0 { w & 0x7FF } else { yy };
        let low_time = (time_base + (w & 0xFFF) as u64) as i64;
        tt = if kind == 0x6 { low_time } else { tt };
        i += 2;
    }
    *t = tt;
    *y = yy;
    *vector = vs;
    i
}

/// The vector base the VECT_12 / VECT_8 words build on.
#[derive(Debug, Clone, Copy, Default)]
struct VectorState {
    base_x: u16,
    polarity: u8,
    have_base: bool,
}

/// Appends to an [`EventChunk`] through pointers into capacity reserved up
/// front, so the hot loops keep the length in a register, write the four
/// columns without per-push capacity checks, and can write a candidate
/// event *speculatively* (at the current end, kept only if `advance`d).
///
/// Safety rests on one invariant, checked on every write: nothing is written
/// at or beyond `len + room + 1` slots reserved in [`RawAppend::new`]. The
/// lengths are set once, on drop; everything below them was written.
pub(crate) struct RawAppend<'a> {
    chunk: &'a mut EventChunk,
    t: *mut i64,
    x: *mut u16,
    y: *mut u16,
    p: *mut u8,
    len: usize,
    /// One past the last writable slot.
    end: usize,
}

impl<'a> RawAppend<'a> {
    /// Room for `room` appended events plus one speculative slot.
    #[inline]
    pub(crate) fn new(chunk: &'a mut EventChunk, room: usize) -> Self {
        reserve(chunk, room + 1);
        let len = chunk.len();
        RawAppend {
            t: chunk.t.as_mut_ptr(),
            x: chunk.x.as_mut_ptr(),
            y: chunk.y.as_mut_ptr(),
            p: chunk.p.as_mut_ptr(),
            chunk,
            len,
            end: len + room + 1,
        }
    }

    /// Write an event in the slot after the last kept one, without keeping
    /// it (see [`RawAppend::advance`]).
    ///
    /// # Safety
    /// `len < end`: the caller has kept fewer than `room + 1` events (the
    /// decoders guarantee it by construction: a block of `k` words reserves
    /// `k * MAX_EVENTS_PER_WORD` and no word keeps more than that many).
    #[inline(always)]
    pub(crate) unsafe fn write_spare_unchecked(&mut self, t: i64, x: u16, y: u16, p: u8) {
        debug_assert!(self.len < self.end);
        // SAFETY: len < end <= capacity of all four vectors (reserved in
        // `new`, and the vectors are exclusively borrowed since).
        unsafe {
            self.t.add(self.len).write(t);
            self.x.add(self.len).write(x);
            self.y.add(self.len).write(y);
            self.p.add(self.len).write(p);
        }
    }

    /// Keep the last `write_spare`d event (`k` = 1) or not (`k` = 0).
    #[inline(always)]
    pub(crate) fn advance(&mut self, k: usize) {
        self.len += k;
    }

    /// Append one event (checked: panics rather than overflow the room).
    #[inline(always)]
    pub(crate) fn push(&mut self, t: i64, x: u16, y: u16, p: u8) {
        if self.len >= self.end {
            overflow();
        }
        // SAFETY: checked just above.
        unsafe { self.write_spare_unchecked(t, x, y, p) };
        self.len += 1;
    }
}

impl Drop for RawAppend<'_> {
    fn drop(&mut self) {
        // The kept events are at most `end - 1` <= capacity, all written.
        let len = self.len;
        // SAFETY: every slot below `len` was written by `write_spare`, and
        // `len` <= capacity; the element types are plain integers.
        unsafe {
            self.chunk.t.set_len(len);
            self.chunk.x.set_len(len);
            self.chunk.y.set_len(len);
            self.chunk.p.set_len(len);
        }
    }
}

#[cold]
#[inline(never)]
fn overflow() -> ! {
    panic!("RawAppend: more events than the room reserved (decoder bug)")
}

#[inline]
fn reserve(ev: &mut EventChunk, n: usize) {
    ev.t.reserve(n);
    ev.x.reserve(n);
    ev.y.reserve(n);
    ev.p.reserve(n);
}

/// Count events outside `geometry` (kept, reported). Two vectorised max
/// reductions decide the common case (all inside) without a per-event test.
pub(crate) fn count_out_of_geometry(ev: &EventChunk, geometry: Option<Geometry>) -> u64 {
    let Some(g) = geometry else { return 0 };
    let max_x = ev.x.iter().copied().max().unwrap_or(0);
    let max_y = ev.y.iter().copied().max().unwrap_or(0);
    if max_x < g.width && max_y < g.height {
        return 0;
    }
    ev.x.iter()
        .zip(&ev.y)
        .filter(|&(&x, &y)| x >= g.width || y >= g.height)
        .count() as u64
}

/// Streaming EVT 3.0 file reader.
pub(crate) type Evt3Reader = RawReader<Evt3Decoder>;

impl RawReader<Evt3Decoder> {
    /// Open `path`, parse its header, and prepare to stream chunks of about
    /// `chunk_events` events (at most `chunk_events + 11`).
    pub(crate) fn open(path: &Path, chunk_events: usize) -> Result<Self> {
        Self::open_with_buffer(path, chunk_events, READ_BUFFER_BYTES)
    }

    /// `Evt3Reader::open` with a chosen read-buffer size (tests use tiny
    /// buffers to exercise sequences straddling refills).
    pub(crate) fn open_with_buffer(
        path: &Path,
        chunk_events: usize,
        buffer_bytes: usize,
    ) -> Result<Self> {
        RawReader::open_format(path, Format::Evt3, 2, chunk_events, buffer_bytes, |_| {
            Evt3Decoder::new()
        })
    }
}

/// A reader refuses a file whose header names another encoding.
pub(crate) fn check_header_format(path: &Path, said: Option<Format>, reader: Format) -> Result<()> {
    match said {
        Some(f) if f != reader => Err(Error::corrupt(
            path,
            0,
            format!(
                "the header says {} but the file is being read as {}",
                f.name(),
                reader.name()
            ),
        )),
        _ => Ok(()),
    }
}

/// A zero-byte file is an error (there is nothing to read, not even a
/// header); a header-only file is a valid, empty recording.
pub(crate) fn check_not_empty(info: &StreamInfo) -> Result<()> {
    if info.file_size == Some(0) {
        return Err(Error::Empty {
            path: info.path.clone(),
            why: "the file is empty (0 bytes)".into(),
        });
    }
    Ok(())
}

impl WordDecoder for Evt3Decoder {
    const MAX_EVENTS_PER_WORD: usize = MAX_EVENTS_PER_WORD;
    fn decode(&mut self, bytes: &[u8], out: &mut Chunk, max_events: usize) -> usize {
        Evt3Decoder::decode(self, bytes, out, max_events)
    }
    fn anomalies(&self) -> &Anomalies {
        &self.anomalies
    }
    fn anomalies_mut(&mut self) -> &mut Anomalies {
        &mut self.anomalies
    }
}

// ---------------------------------------------------------------- writer

/// EVT 3.0 writer (through [`AtomicFile`]: nothing appears at the target
/// until [`crate::EventWriter::finish`]).
pub(crate) struct Evt3Writer {
    raw: RawWordWriter<u16>,
    /// Time of the last TIME_LOW written.
    time: Option<i64>,
    y: Option<u16>,
    xs: Vec<u16>,
}

const EVT3_TIME: TimeSplit = TimeSplit {
    label: "EVT 3.0",
    low_bits: 12,
    high_bits: 12,
    channel_bits: 4,
};

impl Evt3Writer {
    /// Creates a writer for `path`, a RAW file of `geometry`.
    pub(crate) fn create(path: &Path, geometry: Geometry) -> Result<Self> {
        Ok(Evt3Writer {
            raw: RawWordWriter::create(path, "EVT3", EVT3_TIME, geometry)?,
            time: None,
            y: None,
            xs: Vec::new(),
        })
    }

    fn set_time(&mut self, t: i64) -> Result<()> {
        if self.time == Some(t) {
            return Ok(());
        }
        self.raw.set_time_high(t, |v| 0x8000 | v as u16)?;
        self.raw.words.push(0x6000 | (t as u16 & 0xFFF));
        self.time = Some(t);
        Ok(())
    }

    fn set_y(&mut self, y: u16) {
        if self.y != Some(y) {
            self.raw.words.push(y & 0x7FF);
            self.y = Some(y);
        }
    }

    /// Encode `self.xs` (strictly increasing, same t, y, polarity `p`):
    /// the plain definition of [`encode_row_run`].
    fn encode_row_run(&mut self, p: u8) {
        let xs = std::mem::take(&mut self.xs);
        let words = &mut self.raw.words;
        let pbit = (p as u16 & 1) << 11;
        let mut i = 0;
        while i < xs.len() {
            let base = xs[i];
            // Events in the first 12-wide window decide whether a vector pays.
            let in_window = xs[i..].iter().take_while(|&&x| x < base + 12).count();
            if in_window < 3 {
                words.push(0x2000 | pbit | xs[i]);
                i += 1;
                continue;
            }
            words.push(0x3000 | pbit | base);
            let mut block = base;
            // Each further 12-wide block with at least one event costs one word.
            while i < xs.len() && xs[i] < block + 12 {
                let mut mask = 0u16;
                while i < xs.len() && xs[i] < block + 12 {
                    mask |= 1 << (xs[i] - block);
                    i += 1;
                }
                if mask < 0x100 && (i >= xs.len() || xs[i] >= block + 12) {
                    words.push(0x5000 | mask);
                    block += 8;
                } else {
                    words.push(0x4000 | mask);
                    block += 12;
                }
            }
        }
        self.xs = xs;
        self.xs.clear();
    }

    /// The words of a time-ordered chunk, exactly those of
    /// [`encode_chunk`] through the [`RawEncoder`] methods (the
    /// reference, `write_chunk_reference` in the tests), in one loop: the
    /// state (current time, row, output) in locals, a run of same-(t, y, p)
    /// events with increasing x found in place (no copy of its x), runs of
    /// one or two events (most of them) as ADDR_X words directly; TIME_HIGH
    /// steps, triggers and the errors through the reference's methods.
    fn encode_chunk_fast(&mut self, chunk: &Chunk) -> Result<()> {
        let ev = &chunk.events;
        let n = ev.len();
        let (ts, xs, ys, ps) = (&ev.t[..n], &ev.x[..n], &ev.y[..n], &ev.p[..n]);
        let mut triggers = chunk.triggers.iter();
        let mut next_trigger = triggers.next();
        // An event takes at most three words (TIME_LOW, ADDR_Y, ADDR_X) or
        // fewer in a vector, plus TIME_HIGH steps now and then.
        self.raw.words.reserve(3 * n + 64);
        let mut words = std::mem::take(&mut self.raw.words);
        let mut y_now = self.y;
        let mut i = 0;
        while i < n {
            let t = ts[i];
            let (x, y, p) = (xs[i], ys[i], ps[i]);
            let trigger_due = next_trigger.is_some_and(|tr| tr.t <= t);
            if trigger_due || self.time != Some(t) || x >= 2048 || y >= 2048 {
                // The rare cases through the reference's methods (their
                // words go to `self.raw.words`).
                self.raw.words = words;
                self.y = y_now;
                while let Some(tr) = next_trigger.filter(|tr| tr.t <= t) {
                    self.encode_trigger(tr)?;
                    next_trigger = triggers.next();
                }
                self.raw.check_coordinates(x, y)?;
                self.set_time(t)?;
                words = std::mem::take(&mut self.raw.words);
            }
            if y_now != Some(y) {
                words.push(y);
                y_now = Some(y);
            }
            let mut j = i + 1;
            while j < n
                && ts[j] == t
                && ys[j] == y
                && ps[j] == p
                && xs[j] > xs[j - 1]
                && xs[j] < 2048
            {
                j += 1;
            }
            let pbit = (p as u16 & 1) << 11;
            if j - i < 3 {
                // No vector pays for fewer than three events.
                for &x in &xs[i..j] {
                    words.push(0x2000 | pbit | x);
                }
            } else {
                encode_row_run(&xs[i..j], pbit, &mut words);
            }
            i = j;
        }
        self.raw.words = words;
        self.y = y_now;
        for tr in next_trigger.into_iter().chain(triggers) {
            self.encode_trigger(tr)?;
        }
        self.raw.flush()
    }

    /// [`crate::EventWriter::write_chunk`] through the plain
    /// [`encode_chunk`] loop (the reference the fast path is tested
    /// against).
    #[cfg(feature = "testkit")]
    pub(crate) fn write_chunk_reference(&mut self, chunk: &Chunk) -> Result<()> {
        encode_chunk(self, chunk)
    }
}

/// Encode `xs` (strictly increasing x of events with the same t, y and
/// polarity bit `pbit`) after their ADDR_Y: VECT_BASE_X + VECT_12/VECT_8
/// words where a 12-wide window holds three events or more, ADDR_X words
/// otherwise. The words of the reference `Evt3Writer::encode_row_run`,
/// which counts the window's events for each one (most runs of the
/// simulator are sparse saturated rows: one comparison instead).
fn encode_row_run(xs: &[u16], pbit: u16, words: &mut Vec<u16>) {
    let mut i = 0;
    while i < xs.len() {
        let base = xs[i];
        // A vector pays when the 12-wide window from `base` holds three
        // events or more: as x increases strictly, when the event two
        // further on is in it.
        if xs.get(i + 2).is_none_or(|&x| x >= base + 12) {
            words.push(0x2000 | pbit | base);
            i += 1;
            continue;
        }
        words.push(0x3000 | pbit | base);
        let mut block = base;
        // Each further 12-wide block with at least one event costs one word.
        while i < xs.len() && xs[i] < block + 12 {
            let mut mask = 0u16;
            while i < xs.len() && xs[i] < block + 12 {
                mask |= 1 << (xs[i] - block);
                i += 1;
            }
            if mask < 0x100 && (i >= xs.len() || xs[i] >= block + 12) {
                words.push(0x5000 | mask);
                block += 8;
            } else {
                words.push(0x4000 | mask);
                block += 12;
            }
        }
    }
}

impl RawEncoder for Evt3Writer {
    fn encode_trigger(&mut self, tr: &Trigger) -> Result<()> {
        self.raw.check_trigger_channel(tr.channel)?;
        self.set_time(tr.t)?;
        let v = matches!(tr.edge, Edge::Rising) as u16;
        self.raw.words.push(0xA000 | ((tr.channel as u16) << 8) | v);
        Ok(())
    }

    /// One run of events with the same t, y, p and increasing x.
    fn encode_events(&mut self, ev: &EventChunk, i: usize) -> Result<usize> {
        let (t, y, p) = (ev.t[i], ev.y[i], ev.p[i]);
        self.raw.check_coordinates(ev.x[i], y)?;
        self.set_time(t)?;
        self.set_y(y);
        self.xs.clear();
        self.xs.push(ev.x[i]);
        let n = ev.len();
        let mut j = i + 1;
        while j < n
            && ev.t[j] == t
            && ev.y[j] == y
            && ev.p[j] == p
            && ev.x[j] > ev.x[j - 1]
            && ev.x[j] < 2048
        {
            self.xs.push(ev.x[j]);
            j += 1;
        }
        self.encode_row_run(p);
        Ok(j)
    }

    fn flush(&mut self) -> Result<()> {
        self.raw.flush()
    }
}

impl crate::EventWriter for Evt3Writer {
    fn write_chunk(&mut self, chunk: &Chunk) -> Result<()> {
        self.encode_chunk_fast(chunk)
    }

    fn finish(self: Box<Self>) -> Result<()> {
        self.raw.finish()
    }
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;

    fn decode_all(words: &[u16]) -> (Chunk, Anomalies) {
        let bytes: Vec<u8> = words.iter().flat_map(|w| w.to_le_bytes()).collect();
        let mut d = Evt3Decoder::new();
        let mut c = Chunk::default();
        let used = d.decode(&bytes, &mut c, usize::MAX / 2);
        assert_eq!(used, bytes.len());
        (c, d.anomalies)
    }

    #[ebptv_macros::unit_test]
    fn words_of_every_type() {
        let (c, a) = decode_all(&[
            0x2005, // ADDR_X before time base: skipped
            0x8001, // TIME_HIGH 1 → 4096
            0x6010, // TIME_LOW 16 → 4112
            0x0007, // y = 7
            0x2803, // x = 3, ON
            0x3010, // base x = 16, OFF
            0x4805, // VECT_12 bits 0, 2, 11 → 16, 18, 27
            0x5003, // VECT_8 bits 0, 1 → 28, 29
            0x6005, // TIME_LOW back to 5 (legal)
            0xA101, // trigger id 1 rising
            0xE000, 0x7000, 0xF000, // OTHERS + continued
            0x9000, // unknown
        ]);
        assert_eq!(c.events.x, vec![3, 16, 18, 27, 28, 29]);
        assert_eq!(c.events.y, vec![7; 6]);
        assert_eq!(c.events.p, vec![1, 0, 0, 0, 0, 0]);
        assert_eq!(c.events.t, vec![4112; 6]);
        assert_eq!(
            c.triggers,
            vec![Trigger {
                t: 4101,
                channel: 1,
                edge: Edge::Rising
            }]
        );
        assert_eq!(a.words_before_time_base, 1);
        assert_eq!(a.skipped_other_words, 3);
        assert_eq!(a.unknown_word_types, 1);
    }

    #[ebptv_macros::unit_test]
    fn time_high_loop() {
        let (c, a) = decode_all(&[0x8FFF, 0x0001, 0x6FFF, 0x2001, 0x8000, 0x6002, 0x2002]);
        assert_eq!(
            c.events.t,
            vec![(4095 << 12) + 4095, TIME_LOOP_US as i64 + 2]
        );
        assert_eq!(a.time_loops, 1);
        // A smaller step back is not a loop.
        let (c, a) = decode_all(&[0x8800, 0x0001, 0x2001, 0x8100, 0x2002]);
        assert_eq!(c.events.t, vec![0x800 << 12, 0x100 << 12]);
        assert_eq!(a.time_loops, 0);
    }

    #[ebptv_macros::unit_test]
    fn vector_without_base_is_counted() {
        let (c, a) = decode_all(&[0x8000, 0x0003, 0x4FFF, 0x2001]);
        assert_eq!(c.events.len(), 1);
        assert_eq!(a.vector_without_base, 1);
    }

    /// Random time-ordered chunks shaped like the simulator's output
    /// (runs sharing t, y, p with increasing x, dense saturated rows,
    /// repeats and decreasing x, jumps across TIME_HIGH and 24-bit loops,
    /// triggers before, between, at the time of and after events).
    fn random_chunks(seed: u64) -> Vec<Chunk> {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
        let mut t = rng.gen_range(0..5000i64);
        let mut chunks = Vec::new();
        for _ in 0..6 {
            let mut c = Chunk::default();
            let t_first = t;
            for _ in 0..rng.gen_range(0..3000) {
                t += match rng.gen_range(0..100) {
                    0..=59 => 0,
                    60..=94 => rng.gen_range(0..40),
                    95..=97 => rng.gen_range(0..20_000),
                    _ => rng.gen_range(0..(1 << 26)),
                };
                let y = rng.gen_range(0..720u16);
                let p = rng.gen_range(0..2u8);
                match rng.gen_range(0..10) {
                    0..=5 => {
                        // A particle image's row: a few neighbours.
                        let mut x = rng.gen_range(0..1270u16);
                        for _ in 0..rng.gen_range(1..6) {
                            c.events.push(t, x, y, p);
                            x += rng.gen_range(1..4);
                        }
                    }
                    6 | 7 => {
                        // A saturated row.
                        let mut x = rng.gen_range(0..200u16);
                        while x < 1280 && rng.gen_bool(0.97) {
                            c.events.push(t, x, y, p);
                            x += rng.gen_range(1..30);
                        }
                    }
                    _ => {
                        for _ in 0..rng.gen_range(1..5) {
                            c.events.push(t, rng.gen_range(0..1280), y, p);
                        }
                    }
                }
            }
            for _ in 0..rng.gen_range(0..20) {
                let at = match rng.gen_range(0..4) {
                    0 => t_first - rng.gen_range(0..10),
                    1 if !c.events.is_empty() => c.events.t[rng.gen_range(0..c.events.len())],
                    2 => t + rng.gen_range(0..100),
                    _ => rng.gen_range(t_first..=t),
                };
                c.triggers.push(Trigger {
                    t: at.max(0),
                    channel: rng.gen_range(0..16),
                    edge: if rng.gen() {
                        Edge::Rising
                    } else {
                        Edge::Falling
                    },
                });
            }
            c.triggers.sort_by_key(|tr| tr.t);
            chunks.push(c);
        }
        chunks
    }

    /// Write `chunks` with the fast path or the reference; the file's
    /// bytes, or the first error's text.
    fn write_file(chunks: &[Chunk], fast: bool) -> std::result::Result<Vec<u8>, String> {
        use crate::EventWriter;
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("w.raw");
        let mut w = Box::new(Evt3Writer::create(&path, Geometry::new(1280, 720)).unwrap());
        for c in chunks {
            let r = if fast {
                w.write_chunk(c)
            } else {
                w.write_chunk_reference(c)
            };
            r.map_err(|e| e.to_string())?;
        }
        w.finish().map_err(|e| e.to_string())?;
        Ok(std::fs::read(&path).unwrap())
    }

    #[ebptv_macros::unit_test]
    fn fast_encoder_writes_the_reference_bytes() {
        for seed in 0..12 {
            let chunks = random_chunks(seed);
            let fast = write_file(&chunks, true).unwrap();
            assert!(fast == write_file(&chunks, false).unwrap(), "seed {seed}");
            // And the decoder gives back what went in.
            let header_end = fast
                .windows(6)
                .position(|w| w == b"% end\n")
                .map(|p| p + 6)
                .unwrap();
            let mut d = Evt3Decoder::new();
            let mut back = Chunk::default();
            d.decode(&fast[header_end..], &mut back, usize::MAX / 2);
            let mut want = Chunk::default();
            for c in &chunks {
                want.events.extend_from(&c.events);
            }
            assert_eq!(back.events.t, want.events.t, "seed {seed}");
            assert_eq!(back.events.x, want.events.x, "seed {seed}");
            assert_eq!(back.events.y, want.events.y, "seed {seed}");
            assert_eq!(back.events.p, want.events.p, "seed {seed}");
            let n_triggers: usize = chunks.iter().map(|c| c.triggers.len()).sum();
            assert_eq!(back.triggers.len(), n_triggers, "seed {seed}");
        }
        // Bad input: both paths fail with the same error at the same event.
        let mut chunks = random_chunks(99);
        let k = chunks[2].events.len() / 2;
        chunks[2].events.x[k] = 2048;
        let e = write_file(&chunks, true).unwrap_err();
        assert!(e.contains("11-bit"), "{e}");
        assert_eq!(e, write_file(&chunks, false).unwrap_err());
        let mut chunks = random_chunks(98);
        chunks[3].events.y[0] = 4000;
        assert_eq!(
            write_file(&chunks, true).unwrap_err(),
            write_file(&chunks, false).unwrap_err()
        );
        let mut chunks = random_chunks(97);
        chunks[1].triggers.push(Trigger {
            t: i64::MAX / 4,
            channel: 16,
            edge: Edge::Rising,
        });
        let e = write_file(&chunks, true).unwrap_err();
        assert!(e.contains("channel"), "{e}");
        assert_eq!(e, write_file(&chunks, false).unwrap_err());
        let mut chunks = random_chunks(96);
        chunks[4].events.t[0] = -3;
        assert_eq!(
            write_file(&chunks, true).unwrap_err(),
            write_file(&chunks, false).unwrap_err()
        );
    }

    #[ebptv_macros::unit_test]
    fn time_high_steps_cross_loops() {
        let mut v = Vec::new();
        time_high_steps(Some(100), (2 << 12) + 50, 12, &mut v).unwrap();
        assert_eq!(v, vec![4095, 0, 4095, 0, 50]);
        v.clear();
        time_high_steps(None, (1 << 12) + 7, 12, &mut v).unwrap();
        assert_eq!(v, vec![0, 4095, 0, 7]);
        v.clear();
        assert!(time_high_steps(Some(1 << 12), 4095, 12, &mut v).is_err());
        assert!(time_high_steps(Some(4095), 2, 12, &mut v).is_err());
        v.clear();
        time_high_steps(Some(300), 200, 12, &mut v).unwrap();
        assert_eq!(v, vec![200]);
    }
}
