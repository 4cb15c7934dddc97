//! Prophesee `% key value` headers, and the bounded payload reader the RAW
//! decoders share.
//!
//! A Prophesee RAW (and DAT) file starts with ASCII lines `% key value`. Modern
//! files name the encoding and geometry (`% format EVT3;height=720;width=1280`,
//! `% geometry 1280x720`) and close the header with `% end`; older files only
//! say `% evt 3.0` and `% system_ID 48`, and have no `% end`, so the header is
//! the run of lines starting with `%`. The format and geometry of such files
//! are inferred from the system id, as Prophesee's own reader does
//! (`infer_from_system_id`).
//!
//! Binary payload bytes can happen to be `%` (0x25), so a line only counts as
//! a header line when it is printable ASCII and ends with a newline within
//! `MAX_HEADER_LINE` bytes; the first line that is not is payload.
//!
//! `PayloadReader` reads the payload through one fixed-size buffer (a few
//! MB whatever the file size) and keeps an incomplete trailing word for the
//! next refill, so decoders see whole words only and multi-word sequences
//! may straddle refills freely (their state lives in the decoder).

use std::fs::File;
use std::io::{Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

use crate::error::{Error, Result};
use crate::events::Geometry;
use crate::{Format, StreamInfo};

/// Longest line accepted as a header line.
pub(crate) const MAX_HEADER_LINE: usize = 4096;
/// How much of a file is read to find its header.
pub(crate) const MAX_HEADER_BYTES: usize = 1 << 20;

/// Parse the `%` header at the start of `bytes`.
///
/// Returns the `(key, value)` pairs in file order and the offset of the first
/// payload byte. A line `% key value` gives `("key", "value")`; a line with
/// only a key gives an empty value; `% end` closes the header (and is not
/// returned). Lines that start with `%` but are not printable text are
/// payload, not header.
pub(crate) fn parse_percent_header(bytes: &[u8]) -> (Vec<(String, String)>, usize) {
    let mut entries = Vec::new();
    let mut pos = 0;
    while pos < bytes.len() && bytes[pos] == b'%' {
        let rest = &bytes[pos..];
        let limit = rest.len().min(MAX_HEADER_LINE);
        // A header-only file may lack the final newline: a printable last
        // line that runs to the end of the bytes is still a header line.
        let (line, advance) = match rest[..limit].iter().position(|&b| b == b'\n') {
            Some(nl) => (&rest[..nl], nl + 1),
            None if rest.len() < MAX_HEADER_LINE => (rest, rest.len()),
            None => break,
        };
        let line = line.strip_suffix(b"\r").unwrap_or(line);
        if !line
            .iter()
            .all(|&b| (0x20..0x7f).contains(&b) || b == b'\t')
        {
            break;
        }
        pos += advance;
        // Safe: checked printable ASCII above.
        let text = std::str::from_utf8(&line[1..]).unwrap_or("").trim();
        if text == "end" {
            break;
        }
        if text.is_empty() {
            continue;
        }
        let (k, v) = match text.find([' ', '\t']) {
            Some(i) => (&text[..i], text[i..].trim()),
            None => (text, ""),
        };
        entries.push((k.to_string(), v.to_string()));
    }
    (entries, pos)
}

/// What a RAW header says (or implies) about the payload.
#[derive(Debug, Clone, PartialEq)]
#[ebptv_macros::testkit]
pub(crate) struct RawHeader {
    /// The header's `% key value` lines, in file order.
    pub entries: Vec<(String, String)>,
    /// Byte offset of the first payload word.
    pub payload_offset: u64,
    /// The encoding, when the header names or implies it.
    pub format: Option<Format>,
    /// The sensor geometry, when the header states or implies it.
    pub geometry: Option<Geometry>,
    /// EVT 2.1 only: the two 32-bit halves of each 64-bit word are swapped
    /// (`endianness=legacy`, and the default of old `% evt 2.1` files).
    pub evt21_legacy: bool,
}

impl RawHeader {
    #[cfg(feature = "testkit")]
    /// Look up a header value by key (case-insensitive), first occurrence.
    pub(crate) fn get(&self, key: &str) -> Option<&str> {
        get(&self.entries, key)
    }
}

fn get<'a>(entries: &'a [(String, String)], key: &str) -> Option<&'a str> {
    entries
        .iter()
        .find(|(k, _)| k.eq_ignore_ascii_case(key))
        .map(|(_, v)| v.as_str())
}

/// Format and geometry implied by an old header's `% system_ID`.
///
/// 0x15 Gen3 (640x480, EVT 2.0); 0x1F, 0x27 Gen4/4.1 EVK2 (1280x720,
/// EVT 2.0); 0x30, 0x31, 0x32 Gen4.1 / IMX636 (1280x720, EVT 3.0).
pub(crate) fn infer_from_system_id(id: u32) -> Option<(Format, Geometry)> {
    match id {
        0x15 => Some((Format::Evt2, Geometry::new(640, 480))),
        0x1F | 0x27 => Some((Format::Evt2, Geometry::new(1280, 720))),
        0x30..=0x32 => Some((Format::Evt3, Geometry::new(1280, 720))),
        _ => None,
    }
}

fn parse_format_name(name: &str) -> Option<Format> {
    match name.trim().to_ascii_uppercase().as_str() {
        "EVT3" | "EVT3.0" | "EVT30" => Some(Format::Evt3),
        "EVT2" | "EVT2.0" | "EVT20" => Some(Format::Evt2),
        "EVT21" | "EVT2.1" => Some(Format::Evt21),
        _ => None,
    }
}

fn parse_geometry(s: &str) -> Option<Geometry> {
    let (w, h) = s.trim().split_once(['x', 'X'])?;
    Some(Geometry::new(
        w.trim().parse().ok()?,
        h.trim().parse().ok()?,
    ))
}

fn parse_int(s: &str) -> Option<u32> {
    let s = s.trim();
    match s.strip_prefix("0x").or_else(|| s.strip_prefix("0X")) {
        Some(hex) => u32::from_str_radix(hex, 16).ok(),
        None => s.parse().ok(),
    }
}

/// Interpret parsed header entries: format, geometry, EVT 2.1 word order.
/// Explicit statements (`% format`, `% geometry`) win over inference.
pub(crate) fn interpret(entries: Vec<(String, String)>, payload_offset: u64) -> RawHeader {
    let mut format = None;
    let mut geometry = None;
    let mut legacy = None;
    if let Some(v) = get(&entries, "format") {
        let mut parts = v.split(';');
        format = parts.next().and_then(parse_format_name);
        let (mut w, mut h) = (None, None);
        for opt in parts {
            if let Some((k, val)) = opt.split_once('=') {
                match k.trim().to_ascii_lowercase().as_str() {
                    "width" => w = val.trim().parse::<u16>().ok(),
                    "height" => h = val.trim().parse::<u16>().ok(),
                    "endianness" => legacy = Some(val.trim().eq_ignore_ascii_case("legacy")),
                    _ => {}
                }
            }
        }
        if let (Some(w), Some(h)) = (w, h) {
            geometry = Some(Geometry::new(w, h));
        }
    }
    if geometry.is_none() {
        geometry = get(&entries, "geometry").and_then(parse_geometry);
    }
    if geometry.is_none() {
        let w = get(&entries, "width").and_then(|v| v.parse::<u16>().ok());
        let h = get(&entries, "height").and_then(|v| v.parse::<u16>().ok());
        if let (Some(w), Some(h)) = (w, h) {
            geometry = Some(Geometry::new(w, h));
        }
    }
    let mut old_style = false;
    if format.is_none() {
        if let Some(v) = get(&entries, "evt") {
            format = match v.trim() {
                "2.0" | "2" => Some(Format::Evt2),
                "2.1" => Some(Format::Evt21),
                "3.0" | "3" => Some(Format::Evt3),
                _ => None,
            };
            old_style = true;
        }
    }
    if let Some((f, g)) = get(&entries, "system_ID")
        .and_then(parse_int)
        .and_then(infer_from_system_id)
    {
        if format.is_none() {
            format = Some(f);
            old_style = true;
        }
        if geometry.is_none() {
            geometry = Some(g);
        }
    }
    RawHeader {
        entries,
        payload_offset,
        format,
        geometry,
        evt21_legacy: legacy.unwrap_or(old_style),
    }
}

/// Read and interpret the header of the file at `path`. Reads 64 KB (any
/// real header is far shorter), more only while the header runs on, up to
/// `MAX_HEADER_BYTES` (1 MiB).
#[ebptv_macros::testkit]
pub(crate) fn read_raw_header(path: &Path) -> Result<RawHeader> {
    let mut f = File::open(path).map_err(|e| Error::io(path, e))?;
    let mut buf = Vec::new();
    let mut want = 64 * 1024;
    loop {
        let have = buf.len();
        (&mut f)
            .take((want - have) as u64)
            .read_to_end(&mut buf)
            .map_err(|e| Error::io(path, e))?;
        let (entries, off) = parse_percent_header(&buf);
        // The header ended inside what was read (or the file ended).
        if off < buf.len() || buf.len() < want || want >= MAX_HEADER_BYTES {
            return Ok(interpret(entries, off as u64));
        }
        want = (want * 4).min(MAX_HEADER_BYTES);
    }
}

/// The [`StreamInfo`] of a RAW file of a known format.
pub(crate) fn stream_info(path: &Path, format: Format, header: &RawHeader) -> Result<StreamInfo> {
    let size = std::fs::metadata(path)
        .map_err(|e| Error::io(path, e))?
        .len();
    Ok(StreamInfo {
        path: path.to_path_buf(),
        format,
        geometry: header.geometry,
        header: header.entries.clone(),
        payload_offset: header.payload_offset,
        file_size: Some(size),
    })
}

/// Default size of the payload read buffer.
pub(crate) const READ_BUFFER_BYTES: usize = 1 << 20;

/// Reads a RAW payload through one fixed-size buffer, handing out whole
/// words (`word_bytes` = 2, 4 or 8) and carrying a partial word over to the
/// next refill.
pub(crate) struct PayloadReader {
    path: PathBuf,
    file: File,
    buf: Vec<u8>,
    /// Valid bytes are `buf[start..end]`.
    start: usize,
    end: usize,
    word_bytes: usize,
    eof: bool,
    /// Payload bytes consumed by the decoder so far (file offset minus header).
    consumed: u64,
    payload_offset: u64,
}

impl PayloadReader {
    /// Opens a RAW file and reads its header.
    pub(crate) fn open(
        path: &Path,
        payload_offset: u64,
        word_bytes: usize,
        buffer_bytes: usize,
    ) -> Result<Self> {
        let mut file = File::open(path).map_err(|e| Error::io(path, e))?;
        file.seek(SeekFrom::Start(payload_offset))
            .map_err(|e| Error::io(path, e))?;
        // No bigger than the payload (small files, many opens), whole words.
        let payload = file
            .metadata()
            .map(|m| m.len().saturating_sub(payload_offset))
            .unwrap_or(u64::MAX);
        let want = (buffer_bytes as u64).min(payload + word_bytes as u64) as usize;
        let cap = (want.max(word_bytes) / word_bytes) * word_bytes;
        Ok(PayloadReader {
            path: path.to_path_buf(),
            file,
            buf: vec![0; cap],
            start: 0,
            end: 0,
            word_bytes,
            eof: false,
            consumed: 0,
            payload_offset,
        })
    }

    /// The buffered whole words not yet consumed, refilling the buffer when
    /// fewer than one word remains. Empty only at the end of the file.
    pub(crate) fn words(&mut self) -> Result<&[u8]> {
        if self.end - self.start < self.word_bytes && !self.eof {
            self.refill()?;
        }
        let n = (self.end - self.start) / self.word_bytes * self.word_bytes;
        Ok(&self.buf[self.start..self.start + n])
    }

    /// Mark `n` bytes (a whole number of words) of the last `words()` slice
    /// consumed.
    #[inline]
    pub(crate) fn consume(&mut self, n: usize) {
        debug_assert!(n % self.word_bytes == 0 && self.start + n <= self.end);
        self.start += n;
        self.consumed += n as u64;
    }

    fn refill(&mut self) -> Result<()> {
        // Move the partial word (if any) to the front, then fill the rest.
        let rem = self.end - self.start;
        self.buf.copy_within(self.start..self.end, 0);
        self.start = 0;
        self.end = rem;
        while self.end < self.buf.len() {
            match self.file.read(&mut self.buf[self.end..]) {
                Ok(0) => {
                    self.eof = true;
                    break;
                }
                Ok(n) => {
                    self.end += n;
                    // Enough for a big batch: let the decoder run.
                    if self.end - self.start >= self.word_bytes && self.end >= self.buf.len() / 2 {
                        break;
                    }
                }
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => return Err(Error::io(&self.path, e)),
            }
        }
        Ok(())
    }

    /// At end of file: the bytes left over that do not form a whole word.
    pub(crate) fn trailing_partial_bytes(&self) -> u64 {
        if self.eof {
            ((self.end - self.start) % self.word_bytes) as u64
        } else {
            0
        }
    }

    /// File offset of the next unconsumed byte.
    pub(crate) fn file_offset(&self) -> u64 {
        self.payload_offset + self.consumed
    }
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;

    #[ebptv_macros::unit_test]
    fn modern_header() {
        let bytes = b"% camera_integrator_name Prophesee\n% format EVT3;height=720;width=1280\n% geometry 1280x720\n% end\n\x01\x02";
        let (e, off) = parse_percent_header(bytes);
        assert_eq!(off, bytes.len() - 2);
        let h = interpret(e, off as u64);
        assert_eq!(h.format, Some(Format::Evt3));
        assert_eq!(h.geometry, Some(Geometry::new(1280, 720)));
        assert_eq!(h.get("camera_integrator_name"), Some("Prophesee"));
    }

    #[ebptv_macros::unit_test]
    fn old_header_infers_from_system_id() {
        let bytes = b"% Date 2020-01-01 10:00:00\n% evt 3.0\n% system_ID 48\n\x00\x80";
        let (e, off) = parse_percent_header(bytes);
        assert_eq!(off, bytes.len() - 2);
        let h = interpret(e, off as u64);
        assert_eq!(h.format, Some(Format::Evt3));
        assert_eq!(h.geometry, Some(Geometry::new(1280, 720)));
        let (e, _) = parse_percent_header(b"% system_ID 21\n");
        let h = interpret(e, 0);
        assert_eq!(h.format, Some(Format::Evt2));
        assert_eq!(h.geometry, Some(Geometry::new(640, 480)));
    }

    #[ebptv_macros::unit_test]
    fn evt21_word_order() {
        let (e, _) = parse_percent_header(
            b"% format EVT21;endianness=legacy;height=720;width=1280\n% end\n",
        );
        let h = interpret(e, 0);
        assert_eq!(h.format, Some(Format::Evt21));
        assert!(h.evt21_legacy);
        let (e, _) = parse_percent_header(b"% format EVT21;height=720;width=1280\n% end\n");
        assert!(!interpret(e, 0).evt21_legacy);
        let (e, _) = parse_percent_header(b"% evt 2.1\n");
        assert!(interpret(e, 0).evt21_legacy);
    }

    #[ebptv_macros::unit_test]
    fn binary_percent_byte_is_payload() {
        // A payload word starting with 0x25 ('%') followed by binary bytes.
        let bytes = b"% evt 3.0\n%\x80\x01\x02\n";
        let (e, off) = parse_percent_header(bytes);
        assert_eq!(e.len(), 1);
        assert_eq!(off, 10);
        let (e, off) = parse_percent_header(b"");
        assert!(e.is_empty());
        assert_eq!(off, 0);
        // A header-only file without a final newline.
        let (e, off) = parse_percent_header(b"% evt 3.0");
        assert_eq!(off, 9);
        assert_eq!(e[0], ("evt".to_string(), "3.0".to_string()));
    }
}
