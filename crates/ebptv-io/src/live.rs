//! Live input for `ebptv monitor` and `ebptv pulses`: a Prophesee RAW
//! stream read from standard input or from a file that is still being
//! written.
//!
//! The file readers of this crate treat the first end of file as the end
//! of the recording. A recording in progress ends there only for now: the
//! acquisition software keeps appending. `LiveRaw` decodes RAW words from
//! any `Read` and, when the read returns 0 bytes, reports "no events now"
//! (`Ok(false)`) *without* latching the end: the next call reads again and
//! picks up what was appended. A partial word at the current end is kept
//! and completed by the next read. On a pipe (stdin) a read blocks until
//! data arrives and 0 bytes means the writer closed it: the true end.
//!
//! Only RAW (EVT 2.0 / 2.1 / 3.0) can be read this way: its `% key value`
//! header names the encoding before the first event, so the format is
//! known from the stream itself. Other formats need the file (extension,
//! seeking) and get a clear error.

use std::io::Read;
use std::path::{Path, PathBuf};

use crate::error::{Error, Result};
use crate::events::Chunk;
use crate::evt2::Evt2Decoder;
use crate::evt21::Evt21Decoder;
use crate::evt3::Evt3Decoder;
use crate::raw_header::{interpret, parse_percent_header, MAX_HEADER_BYTES};
use crate::raw_reader::WordDecoder;
use crate::{EventSource, Format, StreamInfo};

/// Read buffer of a live stream (bytes).
const LIVE_BUFFER_BYTES: usize = 1 << 20;

/// A RAW stream decoded from a `Read` that may grow (see the module doc).
pub(crate) struct LiveRaw<D> {
    info: StreamInfo,
    reader: Box<dyn Read + Send>,
    decoder: D,
    buf: Vec<u8>,
    start: usize,
    end: usize,
    word_bytes: usize,
    chunk_events: usize,
    consumed: u64,
}

impl<D: WordDecoder> LiveRaw<D> {
    /// Pull whatever is readable now (one read call).
    fn fill(&mut self) -> Result<usize> {
        if self.start > 0 {
            self.buf.copy_within(self.start..self.end, 0);
            self.end -= self.start;
            self.start = 0;
        }
        loop {
            match self.reader.read(&mut self.buf[self.end..]) {
                Ok(n) => {
                    self.end += n;
                    return Ok(n);
                }
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => return Err(Error::io(&self.info.path, e)),
            }
        }
    }
}

impl<D: WordDecoder> EventSource for LiveRaw<D> {
    fn info(&self) -> &StreamInfo {
        &self.info
    }

    /// The next events available now; `Ok(false)` when nothing is readable
    /// at the moment (a later call may deliver more).
    fn next_chunk(&mut self, chunk: &mut Chunk) -> Result<bool> {
        chunk.clear();
        let mut short_read = false;
        loop {
            let whole = (self.end - self.start) / self.word_bytes * self.word_bytes;
            if whole > 0 {
                let used = self.decoder.decode(
                    &self.buf[self.start..self.start + whole],
                    chunk,
                    self.chunk_events,
                );
                self.start += used;
                self.consumed += used as u64;
                if chunk.events.len() >= self.chunk_events
                    || chunk.triggers.len() >= self.chunk_events
                {
                    break;
                }
            }
            // A short read means the stream has no more right now: deliver
            // what there is instead of blocking on a pipe for a full chunk.
            if short_read && !chunk.is_empty() {
                break;
            }
            let space = self.buf.len() - (self.end - self.start);
            let got = self.fill()?;
            if got == 0 {
                break;
            }
            short_read = got < space;
        }
        Ok(!chunk.is_empty())
    }

    fn anomalies(&self) -> crate::Anomalies {
        self.decoder.anomalies().clone()
    }

    fn bytes_read(&self) -> u64 {
        self.info.payload_offset + self.consumed
    }
}

/// Read the `% ...` header from `reader`; returns it with the payload bytes
/// that came along. `wait` is called when the reader has no more bytes yet
/// (a growing file); it returns false to give up.
fn read_header(
    reader: &mut dyn Read,
    name: &Path,
    wait: &mut dyn FnMut() -> bool,
) -> Result<(crate::raw_header::RawHeader, Vec<u8>)> {
    let mut buf: Vec<u8> = Vec::new();
    let mut tmp = vec![0u8; 64 * 1024];
    loop {
        let n = match reader.read(&mut tmp) {
            Ok(n) => n,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(Error::io(name, e)),
        };
        buf.extend_from_slice(&tmp[..n]);
        let (entries, off) = parse_percent_header(&buf);
        // The header is complete once payload bytes follow it.
        if off < buf.len() || buf.len() >= MAX_HEADER_BYTES {
            let header = interpret(entries, off as u64);
            let rest = buf[off..].to_vec();
            return Ok((header, rest));
        }
        if n == 0 && !wait() {
            let (entries, off) = parse_percent_header(&buf);
            if buf.is_empty() {
                return Err(Error::UnknownFormat {
                    path: name.to_path_buf(),
                    why: "the stream is empty".into(),
                });
            }
            return Ok((interpret(entries, off as u64), Vec::new()));
        }
    }
}

/// Open a live RAW stream from `reader` (`name` for messages, e.g. "-" or
/// the path). `wait` is called while the header is incomplete and no bytes
/// are readable; returning false gives up.
pub(crate) fn open_reader(
    mut reader: Box<dyn Read + Send>,
    name: &Path,
    chunk_events: usize,
    wait: &mut dyn FnMut() -> bool,
) -> Result<Box<dyn EventSource>> {
    let (header, rest) = read_header(&mut *reader, name, wait)?;
    let format = header.format.ok_or_else(|| Error::UnknownFormat {
        path: name.to_path_buf(),
        why: "the stream does not start with a Prophesee RAW header naming its encoding \
              (`% format EVT3`, `% evt 3.0`, ...): only RAW EVT 2.0/2.1/3.0 can be read \
              from a pipe or followed while it grows; give other formats as a finished file"
            .into(),
    })?;
    let info = StreamInfo {
        path: PathBuf::from(name),
        format,
        geometry: header.geometry,
        header: header.entries.clone(),
        payload_offset: header.payload_offset,
        file_size: None,
    };
    fn build<D: WordDecoder + 'static>(
        info: StreamInfo,
        reader: Box<dyn Read + Send>,
        decoder: D,
        word_bytes: usize,
        rest: Vec<u8>,
        chunk_events: usize,
    ) -> Box<dyn EventSource> {
        let mut buf = vec![0u8; LIVE_BUFFER_BYTES.max(rest.len() + word_bytes)];
        buf[..rest.len()].copy_from_slice(&rest);
        Box::new(LiveRaw {
            info,
            reader,
            decoder,
            buf,
            start: 0,
            end: rest.len(),
            word_bytes,
            chunk_events: chunk_events.max(1),
            consumed: 0,
        })
    }
    Ok(match format {
        Format::Evt3 => build(info, reader, Evt3Decoder::new(), 2, rest, chunk_events),
        Format::Evt2 => build(info, reader, Evt2Decoder::new(), 4, rest, chunk_events),
        Format::Evt21 => build(
            info,
            reader,
            Evt21Decoder::new(header.evt21_legacy),
            8,
            rest,
            chunk_events,
        ),
        other => {
            return Err(Error::UnknownFormat {
                path: name.to_path_buf(),
                why: format!(
                    "{} cannot be read as a live stream; only RAW EVT 2.0/2.1/3.0",
                    other.name()
                ),
            })
        }
    })
}

/// Standard input as a live RAW stream (`-` on the command line).
pub fn open_stdin() -> Result<Box<dyn EventSource>> {
    open_reader(
        Box::new(std::io::stdin()),
        Path::new("-"),
        crate::DEFAULT_CHUNK_EVENTS,
        &mut || false,
    )
}

/// A RAW file that is still being written, read from its start; waits up
/// to `header_wait` for its header to be complete.
pub fn open_growing(path: &Path, header_wait: std::time::Duration) -> Result<Box<dyn EventSource>> {
    let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let t0 = std::time::Instant::now();
    open_reader(
        Box::new(file),
        path,
        crate::DEFAULT_CHUNK_EVENTS,
        &mut || {
            std::thread::sleep(std::time::Duration::from_millis(50));
            t0.elapsed() < header_wait
        },
    )
}
