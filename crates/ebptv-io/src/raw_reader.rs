//! The streaming shell shared by the Prophesee RAW readers.
//!
//! EVT 2.0, 2.1 and 3.0 differ only in how words become events; reading
//! whole words through a fixed buffer, stopping at the chunk size, counting
//! a truncated tail once and events outside the geometry is the same for
//! all three. `RawReader` does that part; each format supplies a
//! [`WordDecoder`] (`Evt2Decoder`, `Evt21Decoder`, `Evt3Decoder`), and
//! `Evt2Reader` etc. are `RawReader`s of their decoder.

use crate::error::Result;
use crate::events::Chunk;
use std::path::Path;

use crate::evt3::{check_header_format, check_not_empty, count_out_of_geometry};
use crate::raw_header::{read_raw_header, stream_info, PayloadReader, RawHeader};
use crate::{Anomalies, EventSource, Format, StreamInfo};

/// Decodes a run of whole words of one RAW encoding.
pub(crate) trait WordDecoder: Send {
    /// Most events one word can yield (pre-allocated beyond the chunk size).
    const MAX_EVENTS_PER_WORD: usize;
    /// Decode words from `bytes` (whole words only) into `out` until about
    /// `max_events` events are there; returns the bytes consumed.
    fn decode(&mut self, bytes: &[u8], out: &mut Chunk, max_events: usize) -> usize;
    /// Malformed or unexpected words met so far.
    fn anomalies(&self) -> &Anomalies;
    /// Mutable access to the anomaly counts.
    fn anomalies_mut(&mut self) -> &mut Anomalies;
}

/// A RAW file streamed through a [`WordDecoder`].
pub(crate) struct RawReader<D> {
    pub(crate) info: StreamInfo,
    pub(crate) payload: PayloadReader,
    pub(crate) decoder: D,
    chunk_events: usize,
    out_of_geometry: u64,
    tail_reported: bool,
}

impl<D: WordDecoder> RawReader<D> {
    /// Open a RAW file of `format` (`word_bytes` per word): parse and check
    /// its header, refuse a 0-byte file, build the decoder from the header.
    pub(crate) fn open_format(
        path: &Path,
        format: Format,
        word_bytes: usize,
        chunk_events: usize,
        buffer_bytes: usize,
        decoder: impl FnOnce(&RawHeader) -> D,
    ) -> Result<Self> {
        let header = read_raw_header(path)?;
        check_header_format(path, header.format, format)?;
        let info = stream_info(path, format, &header)?;
        check_not_empty(&info)?;
        let payload = PayloadReader::open(path, header.payload_offset, word_bytes, buffer_bytes)?;
        Ok(RawReader::new(
            info,
            payload,
            decoder(&header),
            chunk_events,
        ))
    }

    pub(crate) fn new(
        info: StreamInfo,
        payload: PayloadReader,
        decoder: D,
        chunk_events: usize,
    ) -> Self {
        RawReader {
            info,
            payload,
            decoder,
            chunk_events: chunk_events.max(1),
            out_of_geometry: 0,
            tail_reported: false,
        }
    }
}

impl<D: WordDecoder> EventSource for RawReader<D> {
    fn info(&self) -> &StreamInfo {
        &self.info
    }

    fn next_chunk(&mut self, chunk: &mut Chunk) -> Result<bool> {
        chunk.clear();
        let want = self.chunk_events + D::MAX_EVENTS_PER_WORD;
        let ev = &mut chunk.events;
        if ev.t.capacity() < want {
            ev.t.reserve(want);
            ev.x.reserve(want);
            ev.y.reserve(want);
            ev.p.reserve(want);
        }
        loop {
            let words = self.payload.words()?;
            if words.is_empty() {
                if !self.tail_reported {
                    self.tail_reported = true;
                    self.decoder.anomalies_mut().truncated_tail_bytes +=
                        self.payload.trailing_partial_bytes();
                }
                break;
            }
            let used = self.decoder.decode(words, chunk, self.chunk_events);
            self.payload.consume(used);
            if chunk.events.len() >= self.chunk_events || chunk.triggers.len() >= self.chunk_events
            {
                break;
            }
        }
        self.out_of_geometry += count_out_of_geometry(&chunk.events, self.info.geometry);
        Ok(!chunk.is_empty())
    }

    fn anomalies(&self) -> Anomalies {
        let mut a = self.decoder.anomalies().clone();
        a.out_of_geometry = self.out_of_geometry;
        a
    }

    fn bytes_read(&self) -> u64 {
        self.payload.file_offset()
    }
}
