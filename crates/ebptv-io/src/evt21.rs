//! Prophesee EVT 2.1: streaming reader.
//!
//! EVT 2.1 is EVT 2.0 vectorised by 32 pixels: 64-bit words, type in bits
//! 63..60. EVT_NEG (0x0) / EVT_POS (0x1) carry a 32-bit validity mask
//! (bits 31..0), y (42..32), x (53..43, aligned on 32) and the low 6 time
//! bits (59..54): one event at (x + i, y) per set bit i. TIME_HIGH (0x8)
//! carries time bits 33..6 in bits 59..32; EXT_TRIGGER (0xA) the edge
//! (bit 32) and channel (44..40). OTHERS (0xE) / CONTINUED (0xF) are
//! skipped and counted.
//!
//! Word order: the modern little-endian layout is one u64 LE. The `legacy`
//! layout (`endianness=legacy`, and old `% evt 2.1` files) stores the 32-bit
//! half with type/x/y/time first and the mask second. The time clock and its
//! loop rule are those of EVT 2.0.

use std::path::Path;

use crate::error::Result;
use crate::events::{Chunk, Edge, Trigger};
use crate::evt2::TimeBase34;
use crate::raw_header::READ_BUFFER_BYTES;
use crate::raw_reader::{RawReader, WordDecoder};
use crate::{Anomalies, Format};

/// Most events one EVT 2.1 word can produce.
pub(crate) const MAX_EVENTS_PER_WORD: usize = 32;

/// The EVT 2.1 decoder, independent of where the bytes come from.
#[derive(Debug, Clone, Default)]
pub(crate) struct Evt21Decoder {
    legacy: bool,
    have_time_base: bool,
    time: TimeBase34,
    /// Malformed or unexpected words met so far.
    pub anomalies: Anomalies,
}

impl Evt21Decoder {
    /// `legacy`: the two 32-bit halves of each word are swapped.
    pub(crate) fn new(legacy: bool) -> Self {
        Evt21Decoder {
            legacy,
            ..Default::default()
        }
    }

    #[inline(always)]
    fn word(&self, b: &[u8]) -> u64 {
        let lo = u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as u64;
        let hi = u32::from_le_bytes([b[4], b[5], b[6], b[7]]) as u64;
        if self.legacy {
            (lo << 32) | hi
        } else {
            (hi << 32) | lo
        }
    }

    /// Decode whole 64-bit words of `bytes` into `out` until it holds at
    /// least `max_events` events (at most `max_events + 31`) or triggers.
    /// Returns the bytes consumed (a multiple of 8).
    pub(crate) fn decode(&mut self, bytes: &[u8], out: &mut Chunk, max_events: usize) -> usize {
        let total = bytes.len() & !7;
        let mut pos = 0;
        while pos < total {
            let len = out.events.len();
            if len >= max_events || out.triggers.len() >= max_events {
                break;
            }
            let words = ((max_events - len) / MAX_EVENTS_PER_WORD).clamp(1, (total - pos) / 8);
            let end = pos + 8 * words;
            let ev = &mut out.events;
            let n = words * MAX_EVENTS_PER_WORD;
            ev.t.reserve(n);
            ev.x.reserve(n);
            ev.y.reserve(n);
            ev.p.reserve(n);
            self.decode_block(&bytes[pos..end], out);
            pos = end;
        }
        pos
    }

    #[cold]
    fn find_time_base(&mut self, words: &[u8]) -> usize {
        for (i, w) in words.chunks_exact(8).enumerate() {
            let w = self.word(w);
            if w >> 60 == 0x8 {
                self.have_time_base = true;
                self.time.update((w >> 32) as u32);
                return 8 * (i + 1);
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
        let ev = &mut out.events;
        for w in words.chunks_exact(8) {
            let w = self.word(w);
            let kind = (w >> 60) as u32;
            if kind <= 1 {
                let t = base + ((w >> 54) & 0x3F) as i64;
                let x = ((w >> 43) & 0x7FF) as u16;
                let y = ((w >> 32) & 0x7FF) as u16;
                let mut mask = w as u32;
                while mask != 0 {
                    let i = mask.trailing_zeros() as u16;
                    ev.t.push(t);
                    ev.x.push(x.wrapping_add(i));
                    ev.y.push(y);
                    ev.p.push(kind as u8);
                    mask &= mask - 1;
                }
                continue;
            }
            match kind {
                0x8 => {
                    if self.time.update((w >> 32) as u32) {
                        self.anomalies.time_loops += 1;
                    }
                    base = self.time.base as i64;
                }
                0xA => out.triggers.push(Trigger {
                    t: base + ((w >> 54) & 0x3F) as i64,
                    channel: ((w >> 40) & 0x1F) as u8,
                    edge: if (w >> 32) & 1 == 1 {
                        Edge::Rising
                    } else {
                        Edge::Falling
                    },
                }),
                0xE | 0xF => self.anomalies.skipped_other_words += 1,
                _ => self.anomalies.unknown_word_types += 1,
            }
        }
    }
}

/// Streaming EVT 2.1 file reader.
pub(crate) type Evt21Reader = RawReader<Evt21Decoder>;

impl RawReader<Evt21Decoder> {
    /// Open `path` (word order from the header) and prepare to stream chunks
    /// of about `chunk_events` events (at most `chunk_events + 31`).
    pub(crate) fn open(path: &Path, chunk_events: usize) -> Result<Self> {
        Self::open_with_buffer(path, chunk_events, READ_BUFFER_BYTES)
    }

    /// `Evt21Reader::open` with a chosen read-buffer size.
    pub(crate) fn open_with_buffer(
        path: &Path,
        chunk_events: usize,
        buffer_bytes: usize,
    ) -> Result<Self> {
        RawReader::open_format(path, Format::Evt21, 8, chunk_events, buffer_bytes, |h| {
            Evt21Decoder::new(h.evt21_legacy)
        })
    }

    #[cfg(feature = "testkit")]
    /// True when the file uses the legacy (swapped halves) word order.
    pub(crate) fn legacy_word_order(&self) -> bool {
        self.decoder.legacy
    }
}

impl WordDecoder for Evt21Decoder {
    const MAX_EVENTS_PER_WORD: usize = 32;
    fn decode(&mut self, bytes: &[u8], out: &mut Chunk, max_events: usize) -> usize {
        Evt21Decoder::decode(self, bytes, out, max_events)
    }
    fn anomalies(&self) -> &Anomalies {
        &self.anomalies
    }
    fn anomalies_mut(&mut self) -> &mut Anomalies {
        &mut self.anomalies
    }
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;

    #[ebptv_macros::unit_test]
    fn both_word_orders() {
        let words: [u64; 3] = [
            0x8000_0002_0000_0000, // time high 2 → 128
            (1 << 60) | (5 << 54) | (64 << 43) | (9 << 32) | 0x8000_0005, // ON, bits 0, 2, 31
            0xA000_0000_0000_0000 | (3 << 54) | (1 << 40) | (1 << 32), // trigger ch 1 rising
        ];
        for legacy in [false, true] {
            let bytes: Vec<u8> = words
                .iter()
                .flat_map(|&w| {
                    let (hi, lo) = ((w >> 32) as u32, w as u32);
                    let (a, b) = if legacy { (hi, lo) } else { (lo, hi) };
                    a.to_le_bytes().into_iter().chain(b.to_le_bytes())
                })
                .collect();
            let mut d = Evt21Decoder::new(legacy);
            let mut c = Chunk::default();
            assert_eq!(d.decode(&bytes, &mut c, 1000), 24);
            assert_eq!(c.events.x, vec![64, 66, 95]);
            assert_eq!(c.events.y, vec![9; 3]);
            assert_eq!(c.events.t, vec![133; 3]);
            assert_eq!(c.events.p, vec![1; 3]);
            assert_eq!(
                c.triggers,
                vec![Trigger {
                    t: 131,
                    channel: 1,
                    edge: Edge::Rising
                }]
            );
        }
    }
}
