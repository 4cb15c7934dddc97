//! iniVation AEDAT 4.0 reader (event and trigger streams).
//!
//! Layout (dv-processing `IOHeader.fbs`, `FileDataTable.fbs`, `Events.fbs`,
//! `Trigger.fbs`; checked on a DAVIS346 recording):
//! - magic `#!AER-DAT4.0\r\n`, a u32 length, then an `IOHeader` flatbuffer
//!   (file identifier `IOHE`): `compression` (0 none, 1 LZ4, 2 LZ4 high,
//!   3 Zstd, 4 Zstd high), `dataTablePosition` (i64, byte offset of the
//!   trailing packet index, -1 when absent) and `infoNode`, an XML text that
//!   describes the streams: under `outInfo`, one node per stream id with
//!   `typeIdentifier` (`EVTS`, `TRIG`, `FRME`, `IMUS`…) and `sizeX`/`sizeY`.
//! - packets until `dataTablePosition` (or the end of the file): i32 stream
//!   id, i32 byte size, then that many bytes: a *size-prefixed* flatbuffer
//!   compressed as a whole (LZ4 *frame* format, linked blocks; Zstd frame).
//! - `EventPacket { elements: [Event] }` where `Event` is a 16-byte struct
//!   `{t: i64 µs, x: i16, y: i16, on: bool}`;
//!   `TriggerPacket { elements: [Trigger] }` where `Trigger` is a *table*
//!   `{timestamp: i64, type: i8}`.
//!
//! Trigger types map onto [`Trigger`] as (channel, edge): external input
//! rising/falling (1, 2) → channel 0 rising/falling, an external pulse (3)
//! → channel 0 rising; the device's generator (4, 5) → channel 1; APS frame
//! start/end (6, 7) → channel 2 rising/falling; exposure start/end (8, 9) →
//! channel 3. Timestamp resets (0) are skipped and counted
//! (`skipped_other_words`), unknown types counted (`unknown_word_types`).
//! Frame, IMU and other packets are skipped without decompressing them.
//! When the XML declares no stream at all, every packet is decompressed and
//! recognised by its flatbuffer identifier (`EVTS`, `TRIG`) instead.
//!
//! The flatbuffers are parsed by hand with bounds checks on every read (no
//! code generation); a malformed buffer is a [`Error::Corrupt`] naming the
//! packet's byte offset. Memory: one packet at a time; a packet's claimed
//! size is checked against the bytes left in the file before anything is
//! allocated, and decompression stops at `MAX_PACKET_BYTES`.

use std::fs::File;
use std::io::{BufReader, Read, Seek, SeekFrom};
use std::path::Path;

use crate::error::{Error, Result};
use crate::events::{Chunk, Edge, Geometry, Trigger};
use crate::{Anomalies, EventSource, Format, StreamInfo};

pub(crate) const MAGIC: &[u8; 14] = b"#!AER-DAT4.0\r\n";
/// Largest packet, compressed or decompressed, that the reader accepts.
pub(crate) const MAX_PACKET_BYTES: usize = 256 << 20;
/// Largest IOHeader accepted.
const MAX_HEADER_BYTES: u32 = 16 << 20;

/// Packet compression of an AEDAT4 file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
#[ebptv_macros::testkit]
pub(crate) enum Compression {
    /// Packets stored as they are.
    None,
    /// LZ4 frames.
    Lz4,
    /// LZ4 frames at high compression (decoded the same way).
    Lz4High,
    /// Zstandard frames.
    Zstd,
    /// Zstandard frames at high compression (decoded the same way).
    ZstdHigh,
}

impl Compression {
    pub(crate) fn from_code(c: i32) -> Option<Self> {
        Some(match c {
            0 => Compression::None,
            1 => Compression::Lz4,
            2 => Compression::Lz4High,
            3 => Compression::Zstd,
            4 => Compression::ZstdHigh,
            _ => return None,
        })
    }
    /// The compression code the IOHeader stores.
    pub(crate) fn code(self) -> i32 {
        self as i32
    }
    /// The name the IOHeader and summaries use.
    pub(crate) fn name(self) -> &'static str {
        match self {
            Compression::None => "none",
            Compression::Lz4 => "LZ4",
            Compression::Lz4High => "LZ4 high",
            Compression::Zstd => "Zstd",
            Compression::ZstdHigh => "Zstd high",
        }
    }
}

// ---------------------------------------------------------------------------
// Flatbuffer access, bounds-checked.

fn rd_u16(b: &[u8], at: usize) -> Option<u16> {
    Some(u16::from_le_bytes(
        b.get(at..at.checked_add(2)?)?.try_into().ok()?,
    ))
}
fn rd_u32(b: &[u8], at: usize) -> Option<u32> {
    Some(u32::from_le_bytes(
        b.get(at..at.checked_add(4)?)?.try_into().ok()?,
    ))
}
fn rd_i32(b: &[u8], at: usize) -> Option<i32> {
    rd_u32(b, at).map(|v| v as i32)
}
fn rd_i64(b: &[u8], at: usize) -> Option<i64> {
    Some(i64::from_le_bytes(
        b.get(at..at.checked_add(8)?)?.try_into().ok()?,
    ))
}

/// A flatbuffer table: its position and its vtable's position.
#[derive(Clone, Copy)]
struct Table {
    pos: usize,
    vtable: usize,
    vt_len: usize,
}

impl Table {
    fn at(b: &[u8], pos: usize) -> Option<Table> {
        let soff = rd_i32(b, pos)? as i64;
        let vtable = usize::try_from(pos as i64 - soff).ok()?;
        let vt_len = rd_u16(b, vtable)? as usize;
        if vt_len < 4 || vt_len % 2 != 0 || vtable.checked_add(vt_len)? > b.len() {
            return None;
        }
        Some(Table {
            pos,
            vtable,
            vt_len,
        })
    }
    /// Absolute position of field `i`, or `None` when absent (default value).
    fn field(&self, b: &[u8], i: usize) -> Option<usize> {
        let slot = 4 + 2 * i;
        if slot + 2 > self.vt_len {
            return None;
        }
        let off = rd_u16(b, self.vtable + slot)? as usize;
        (off != 0).then_some(self.pos + off)
    }
    /// Follow a uoffset field to a vector: (position of the first element, length).
    fn vector(&self, b: &[u8], i: usize) -> Option<Option<(usize, usize)>> {
        let Some(f) = self.field(b, i) else {
            return Some(None);
        };
        let v = f.checked_add(rd_u32(b, f)? as usize)?;
        let n = rd_u32(b, v)? as usize;
        Some(Some((v + 4, n)))
    }
}

/// Root table of a flatbuffer starting at `base`, checking the identifier.
fn root(b: &[u8], base: usize, ident: &[u8; 4]) -> std::result::Result<Table, String> {
    if b.get(base + 4..base + 8) != Some(&ident[..]) {
        let got = b
            .get(base + 4..base + 8)
            .map(|g| String::from_utf8_lossy(g).into_owned())
            .unwrap_or_default();
        return Err(format!(
            "flatbuffer identifier `{got}`, expected `{}`",
            String::from_utf8_lossy(ident)
        ));
    }
    let r = rd_u32(b, base).ok_or("flatbuffer too short")? as usize;
    Table::at(b, base + r).ok_or_else(|| "flatbuffer root table out of bounds".to_string())
}

// ---------------------------------------------------------------------------
// The XML stream description.

/// One stream declared in the header's XML.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub(crate) struct StreamDecl {
    pub id: i32,
    pub type_identifier: String,
    pub name: String,
    pub size_x: Option<u16>,
    pub size_y: Option<u16>,
}

fn xml_attr_value(tag: &str, name: &str) -> Option<String> {
    let key = format!("{name}=\"");
    let start = tag.find(&key)? + key.len();
    let end = start + tag[start..].find('"')?;
    Some(tag[start..end].to_string())
}

/// Streams under `outInfo` in dv's XML: `<node name="outInfo">` /
/// `<node name="ID">` / `<attr key="typeIdentifier">EVTS</attr>` and
/// `<node name="info">` / `<attr key="sizeX">346</attr>`.
pub(crate) fn parse_streams(xml: &str) -> Vec<StreamDecl> {
    let mut streams: Vec<StreamDecl> = Vec::new();
    let mut stack: Vec<String> = Vec::new();
    let mut rest = xml;
    while let Some(lt) = rest.find('<') {
        rest = &rest[lt..];
        let Some(gt) = rest.find('>') else { break };
        let tag = &rest[..=gt];
        let after = &rest[gt + 1..];
        if tag.starts_with("</node") {
            stack.pop();
        } else if tag.starts_with("<node") {
            let name = xml_attr_value(tag, "name").unwrap_or_default();
            if !tag.ends_with("/>") {
                stack.push(name);
            }
        } else if tag.starts_with("<attr") {
            let key = xml_attr_value(tag, "key").unwrap_or_default();
            let value = after
                .find("</attr>")
                .map(|e| after[..e].trim().to_string())
                .unwrap_or_default();
            let pos = stack.iter().position(|n| n == "outInfo");
            if let Some(pos) = pos {
                if let Some(id) = stack.get(pos + 1).and_then(|s| s.parse::<i32>().ok()) {
                    let depth = stack.len() - pos - 1;
                    let s = match streams.iter_mut().find(|s| s.id == id) {
                        Some(s) => s,
                        None => {
                            streams.push(StreamDecl {
                                id,
                                ..Default::default()
                            });
                            streams.last_mut().expect("just pushed")
                        }
                    };
                    match (depth, key.as_str()) {
                        (1, "typeIdentifier") => s.type_identifier = value,
                        (1, "originalOutputName") => s.name = value,
                        (_, "sizeX") => s.size_x = value.parse().ok(),
                        (_, "sizeY") => s.size_y = value.parse().ok(),
                        _ => {}
                    }
                }
            }
        }
        rest = after;
    }
    streams
}

// ---------------------------------------------------------------------------

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kind {
    Events,
    Triggers,
    Other,
}

/// Reads an AEDAT4 (iniVation) file packet by packet as an [`EventSource`](crate::EventSource).
pub(crate) struct Aedat4Reader {
    info: StreamInfo,
    reader: BufReader<File>,
    compression: Compression,
    streams: Vec<(i32, Kind)>,
    /// Where packets end: the data table or the end of the file.
    end: u64,
    pos: u64,
    chunk_events: usize,
    packet: Vec<u8>,
    raw: Vec<u8>,
    /// Remaining elements of the current event packet: (next element, end).
    cursor: Option<(usize, usize)>,
    anomalies: Anomalies,
    geometry: Option<Geometry>,
}

impl Aedat4Reader {
    /// Opens `path` and reads its IOHeader; `chunk_events` is the target chunk size.
    pub(crate) fn open(path: &Path, chunk_events: usize) -> Result<Self> {
        let file = File::open(path).map_err(|e| Error::io(path, e))?;
        let file_size = file.metadata().map_err(|e| Error::io(path, e))?.len();
        if file_size == 0 {
            return Err(Error::Empty {
                path: path.to_path_buf(),
                why: "file is empty".into(),
            });
        }
        let mut reader = BufReader::with_capacity(1 << 16, file);
        let mut magic = [0u8; 14];
        let n = read_up_to(&mut reader, &mut magic).map_err(|e| Error::io(path, e))?;
        if n < 14 || &magic != MAGIC {
            return Err(Error::UnknownFormat {
                path: path.to_path_buf(),
                why: "does not start with `#!AER-DAT4.0`: not an AEDAT 4.0 file".into(),
            });
        }
        let mut len = [0u8; 4];
        if read_up_to(&mut reader, &mut len).map_err(|e| Error::io(path, e))? < 4 {
            return Err(Error::corrupt(
                path,
                14,
                "file ends before the header length",
            ));
        }
        let hlen = u32::from_le_bytes(len);
        if hlen > MAX_HEADER_BYTES || 18 + hlen as u64 > file_size {
            return Err(Error::corrupt(
                path,
                14,
                format!(
                    "header length {hlen} bytes exceeds the file ({file_size} bytes) or 16 MiB"
                ),
            ));
        }
        let mut hbuf = vec![0u8; hlen as usize];
        reader
            .read_exact(&mut hbuf)
            .map_err(|e| Error::io(path, e))?;
        let bad = |what: String| Error::corrupt(path, 18, format!("IOHeader: {what}"));
        let table = root(&hbuf, 0, b"IOHE").map_err(bad)?;
        let comp_code = match table.field(&hbuf, 0) {
            Some(f) => {
                rd_i32(&hbuf, f).ok_or_else(|| bad("compression field out of bounds".into()))?
            }
            None => 0,
        };
        let compression = Compression::from_code(comp_code)
            .ok_or_else(|| bad(format!("unknown compression type {comp_code}")))?;
        let data_table = match table.field(&hbuf, 1) {
            Some(f) => {
                rd_i64(&hbuf, f).ok_or_else(|| bad("dataTablePosition out of bounds".into()))?
            }
            None => -1,
        };
        let xml = match table
            .vector(&hbuf, 2)
            .ok_or_else(|| bad("infoNode out of bounds".into()))?
        {
            Some((start, n)) => {
                let bytes = hbuf
                    .get(start..start.saturating_add(n))
                    .ok_or_else(|| bad("infoNode out of bounds".into()))?;
                String::from_utf8_lossy(bytes).into_owned()
            }
            None => String::new(),
        };
        let decls = parse_streams(&xml);
        let payload = 18 + hlen as u64;
        let end = if data_table >= payload as i64 && (data_table as u64) <= file_size {
            data_table as u64
        } else {
            file_size
        };
        let mut header = vec![("compression".to_string(), compression.name().to_string())];
        if data_table >= 0 {
            header.push(("dataTablePosition".into(), data_table.to_string()));
        }
        let mut streams = Vec::new();
        let mut geometry = None;
        for d in &decls {
            let kind = match d.type_identifier.as_str() {
                "EVTS" => Kind::Events,
                "TRIG" => Kind::Triggers,
                _ => Kind::Other,
            };
            if kind == Kind::Events && geometry.is_none() {
                if let (Some(w), Some(h)) = (d.size_x, d.size_y) {
                    if w > 0 && h > 0 {
                        geometry = Some(Geometry::new(w, h));
                    }
                }
            }
            streams.push((d.id, kind));
            let size = match (d.size_x, d.size_y) {
                (Some(w), Some(h)) => format!(" {w}x{h}"),
                _ => String::new(),
            };
            header.push((
                format!("stream.{}", d.id),
                format!("{} {}{}", d.type_identifier, d.name, size),
            ));
        }
        if !streams.iter().any(|(_, k)| *k == Kind::Events) {
            header.push((
                "note".into(),
                "the header declares no event (EVTS) stream".into(),
            ));
        }
        Ok(Aedat4Reader {
            info: StreamInfo {
                path: path.to_path_buf(),
                format: Format::Aedat4,
                geometry,
                header,
                payload_offset: payload,
                file_size: Some(file_size),
            },
            reader,
            compression,
            streams,
            end,
            pos: payload,
            chunk_events: chunk_events.max(1),
            packet: Vec::new(),
            raw: Vec::new(),
            cursor: None,
            anomalies: Anomalies::default(),
            geometry,
        })
    }

    fn corrupt(&self, at: u64, what: impl Into<String>) -> Error {
        Error::corrupt(&self.info.path, at, what)
    }

    /// Decompress `self.raw` into `self.packet`, at most MAX_PACKET_BYTES.
    fn decompress(&mut self, at: u64) -> Result<()> {
        self.packet.clear();
        let limit = MAX_PACKET_BYTES as u64 + 1;
        let res = match self.compression {
            Compression::None => {
                std::mem::swap(&mut self.packet, &mut self.raw);
                Ok(0)
            }
            Compression::Lz4 | Compression::Lz4High => {
                lz4_flex::frame::FrameDecoder::new(&self.raw[..])
                    .take(limit)
                    .read_to_end(&mut self.packet)
            }
            Compression::Zstd | Compression::ZstdHigh => {
                let mut src = &self.raw[..];
                match ruzstd::StreamingDecoder::new(&mut src) {
                    Ok(d) => d.take(limit).read_to_end(&mut self.packet),
                    Err(e) => Err(std::io::Error::new(
                        std::io::ErrorKind::InvalidData,
                        e.to_string(),
                    )),
                }
            }
        };
        if let Err(e) = res {
            return Err(self.corrupt(
                at,
                format!(
                    "packet does not decompress ({}): {e}",
                    self.compression.name()
                ),
            ));
        }
        if self.packet.len() > MAX_PACKET_BYTES {
            return Err(self.corrupt(at, "packet decompresses to more than 256 MiB"));
        }
        Ok(())
    }

    /// Read the next packet of a stream we decode; `None` at the end.
    fn next_packet(&mut self) -> Result<Option<(Kind, u64)>> {
        loop {
            if self.pos >= self.end {
                return Ok(None);
            }
            let left = self.end - self.pos;
            if left < 8 {
                self.anomalies.truncated_tail_bytes += left;
                self.pos = self.end;
                return Ok(None);
            }
            let mut h = [0u8; 8];
            self.reader
                .read_exact(&mut h)
                .map_err(|e| Error::io(&self.info.path, e))?;
            let at = self.pos;
            let id = i32::from_le_bytes(h[0..4].try_into().expect("4 bytes"));
            let size = i32::from_le_bytes(h[4..8].try_into().expect("4 bytes"));
            self.pos += 8;
            if size < 0 {
                return Err(self.corrupt(
                    at,
                    format!("packet of stream {id} has a negative size {size}"),
                ));
            }
            let size = size as u64;
            if size > self.end - self.pos {
                // The file was cut inside this packet.
                self.anomalies.truncated_tail_bytes += 8 + (self.end - self.pos);
                self.pos = self.end;
                return Ok(None);
            }
            if size as usize > MAX_PACKET_BYTES {
                return Err(self.corrupt(
                    at,
                    format!("packet of {size} bytes exceeds the 256 MiB limit"),
                ));
            }
            let kind = self.streams.iter().find(|(s, _)| *s == id).map(|(_, k)| *k);
            // Without a stream description, every packet is opened and
            // recognised by its flatbuffer identifier.
            let sniff = self.streams.is_empty();
            match kind {
                Some(Kind::Events | Kind::Triggers) | None if kind.is_some() || sniff => {
                    self.raw.clear();
                    self.raw.resize(size as usize, 0);
                    self.reader
                        .read_exact(&mut self.raw)
                        .map_err(|e| Error::io(&self.info.path, e))?;
                    self.pos += size;
                    self.decompress(at)?;
                    let k = match kind {
                        Some(k) => k,
                        None => match self.packet.get(8..12) {
                            Some(b"EVTS") => Kind::Events,
                            Some(b"TRIG") => Kind::Triggers,
                            _ => {
                                self.anomalies.skipped_other_words += 1;
                                continue;
                            }
                        },
                    };
                    return Ok(Some((k, at)));
                }
                other => {
                    if other.is_none() {
                        self.anomalies.unknown_word_types += 1;
                    } else {
                        self.anomalies.skipped_other_words += 1;
                    }
                    self.reader
                        .seek(SeekFrom::Current(size as i64))
                        .map_err(|e| Error::io(&self.info.path, e))?;
                    self.pos += size;
                }
            }
        }
    }

    /// Locate the elements vector of a size-prefixed packet.
    fn elements(&self, ident: &[u8; 4], at: u64) -> Result<Option<(usize, usize)>> {
        let b = &self.packet;
        let prefix =
            rd_u32(b, 0).ok_or_else(|| self.corrupt(at, "packet shorter than 4 bytes"))? as usize;
        if prefix + 4 > b.len() {
            return Err(self.corrupt(
                at,
                format!("packet size prefix {prefix} exceeds its {} bytes", b.len()),
            ));
        }
        let t = root(b, 4, ident).map_err(|w| self.corrupt(at, w))?;
        t.vector(b, 0)
            .ok_or_else(|| self.corrupt(at, "elements vector out of bounds"))
    }

    fn take_triggers(&mut self, at: u64, out: &mut Vec<Trigger>) -> Result<()> {
        let Some((start, n)) = self.elements(b"TRIG", at)? else {
            return Ok(());
        };
        let b = &self.packet;
        if start
            .checked_add(n.saturating_mul(4))
            .is_none_or(|e| e > b.len())
        {
            return Err(self.corrupt(
                at,
                format!("trigger vector of {n} elements exceeds the packet"),
            ));
        }
        for i in 0..n {
            let slot = start + 4 * i;
            let bad = || self.corrupt(at, format!("trigger {i} of the packet is out of bounds"));
            let tpos = slot
                .checked_add(rd_u32(b, slot).ok_or_else(bad)? as usize)
                .ok_or_else(bad)?;
            let t = Table::at(b, tpos).ok_or_else(bad)?;
            let ts = match t.field(b, 0) {
                Some(f) => rd_i64(b, f).ok_or_else(bad)?,
                None => 0,
            };
            let ty = match t.field(b, 1) {
                Some(f) => *b.get(f).ok_or_else(bad)? as i8,
                None => 0,
            };
            let mapped = match ty {
                1 | 3 => Some((0, Edge::Rising)),
                2 => Some((0, Edge::Falling)),
                4 => Some((1, Edge::Rising)),
                5 => Some((1, Edge::Falling)),
                6 => Some((2, Edge::Rising)),
                7 => Some((2, Edge::Falling)),
                8 => Some((3, Edge::Rising)),
                9 => Some((3, Edge::Falling)),
                _ => None,
            };
            match mapped {
                Some((channel, edge)) => out.push(Trigger {
                    t: ts,
                    channel,
                    edge,
                }),
                None if ty == 0 => self.anomalies.skipped_other_words += 1,
                None => self.anomalies.unknown_word_types += 1,
            }
        }
        Ok(())
    }
}

fn read_up_to<R: Read>(r: &mut R, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut n = 0;
    while n < buf.len() {
        match r.read(&mut buf[n..]) {
            Ok(0) => break,
            Ok(k) => n += k,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(n)
}

const EVENT_BYTES: usize = 16;

impl EventSource for Aedat4Reader {
    fn info(&self) -> &StreamInfo {
        &self.info
    }

    fn next_chunk(&mut self, chunk: &mut Chunk) -> Result<bool> {
        chunk.clear();
        loop {
            if let Some((next, end)) = self.cursor {
                let take = (end - next).min(self.chunk_events - chunk.events.len());
                let ev = &mut chunk.events;
                ev.t.reserve(take);
                ev.x.reserve(take);
                ev.y.reserve(take);
                ev.p.reserve(take);
                for rec in self.packet[next * EVENT_BYTES..(next + take) * EVENT_BYTES]
                    .chunks_exact(EVENT_BYTES)
                {
                    let t = i64::from_le_bytes(rec[0..8].try_into().expect("8 bytes"));
                    let x = i16::from_le_bytes([rec[8], rec[9]]);
                    let y = i16::from_le_bytes([rec[10], rec[11]]);
                    let (x, y) = (x as u16, y as u16);
                    if let Some(g) = self.geometry {
                        if !g.contains(x, y) {
                            self.anomalies.out_of_geometry += 1;
                        }
                    }
                    chunk.events.push(t, x, y, (rec[12] != 0) as u8);
                }
                self.cursor = if next + take < end {
                    Some((next + take, end))
                } else {
                    None
                };
                if chunk.events.len() >= self.chunk_events {
                    return Ok(true);
                }
                continue;
            }
            match self.next_packet()? {
                None => return Ok(!chunk.is_empty()),
                Some((Kind::Triggers, at)) => {
                    let mut tr = std::mem::take(&mut chunk.triggers);
                    let r = self.take_triggers(at, &mut tr);
                    chunk.triggers = tr;
                    r?;
                }
                Some((_, at)) => {
                    if let Some((start, n)) = self.elements(b"EVTS", at)? {
                        let bytes = n.checked_mul(EVENT_BYTES);
                        if bytes
                            .and_then(|k| start.checked_add(k))
                            .is_none_or(|e| e > self.packet.len())
                        {
                            return Err(self.corrupt(
                                at,
                                format!("event vector of {n} elements exceeds the packet"),
                            ));
                        }
                        if start % EVENT_BYTES != 0 {
                            // Re-align so that element i sits at i * 16.
                            self.packet.drain(..start % EVENT_BYTES);
                        }
                        let first = start / EVENT_BYTES;
                        if n > 0 {
                            self.cursor = Some((first, first + n));
                        }
                    }
                }
            }
            if !chunk.triggers.is_empty() && chunk.triggers.len() >= self.chunk_events {
                return Ok(true);
            }
        }
    }

    fn anomalies(&self) -> Anomalies {
        self.anomalies.clone()
    }

    fn bytes_read(&self) -> u64 {
        self.pos
    }
}

// ---------------------------------------------------------------------------
// A minimal writer, for tests and fixtures.

/// Build an AEDAT 4.0 file with one event stream (id 0) and one trigger
/// stream (id 1), `per_packet` elements per packet, packets compressed by
/// `compress` (which must match `compression`). Trigger channels/edges are
/// written as the types the reader maps them from (channel 0–3).
#[ebptv_macros::testkit]
pub(crate) fn encode_aedat4(
    events: &[crate::events::Event],
    triggers: &[Trigger],
    geometry: Geometry,
    compression: Compression,
    per_packet: usize,
    compress: &dyn Fn(&[u8]) -> Vec<u8>,
) -> Vec<u8> {
    let xml = format!(
        "<dv version=\"2.0\">\n<node name=\"outInfo\" path=\"/outInfo/\">\n\
         <node name=\"0\" path=\"/outInfo/0/\">\n<attr key=\"compression\" type=\"string\">{c}</attr>\n\
         <attr key=\"originalOutputName\" type=\"string\">events</attr>\n\
         <attr key=\"typeIdentifier\" type=\"string\">EVTS</attr>\n\
         <node name=\"info\" path=\"/outInfo/0/info/\">\n<attr key=\"sizeX\" type=\"int\">{w}</attr>\n\
         <attr key=\"sizeY\" type=\"int\">{h}</attr>\n</node>\n</node>\n\
         <node name=\"1\" path=\"/outInfo/1/\">\n<attr key=\"compression\" type=\"string\">{c}</attr>\n\
         <attr key=\"originalOutputName\" type=\"string\">triggers</attr>\n\
         <attr key=\"typeIdentifier\" type=\"string\">TRIG</attr>\n</node>\n</node>\n</dv>\n",
        c = compression.name(),
        w = geometry.width,
        h = geometry.height
    );
    // IOHeader: root@0 -> table@20, ident@4, vtable@8.
    let mut hb = Vec::new();
    hb.extend_from_slice(&20u32.to_le_bytes());
    hb.extend_from_slice(b"IOHE");
    for v in [10u16, 20, 4, 12, 8] {
        hb.extend_from_slice(&v.to_le_bytes());
    }
    hb.extend_from_slice(&[0, 0]);
    hb.extend_from_slice(&12i32.to_le_bytes()); // table@20: soffset to vtable@8
    hb.extend_from_slice(&compression.code().to_le_bytes()); // @24
    hb.extend_from_slice(&12u32.to_le_bytes()); // @28 -> string@40
    hb.extend_from_slice(&(-1i64).to_le_bytes()); // @32
    hb.extend_from_slice(&(xml.len() as u32).to_le_bytes()); // @40
    hb.extend_from_slice(xml.as_bytes());
    hb.push(0);
    let mut out = Vec::new();
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&(hb.len() as u32).to_le_bytes());
    out.extend_from_slice(&hb);

    let per_packet = per_packet.max(1);
    let packet_prefix = |ident: &[u8; 4], body: &mut Vec<u8>| {
        // size@0, root@4 -> table@20, ident@8, vtable@12 {6, 8, 4}, table@20
        // {soffset 8, elements uoffset @24 -> vector@28}.
        body.extend_from_slice(&0u32.to_le_bytes());
        body.extend_from_slice(&16u32.to_le_bytes());
        body.extend_from_slice(ident);
        for v in [6u16, 8, 4] {
            body.extend_from_slice(&v.to_le_bytes());
        }
        body.extend_from_slice(&[0, 0]);
        body.extend_from_slice(&8i32.to_le_bytes());
        body.extend_from_slice(&4u32.to_le_bytes());
    };
    let mut push_packet = |stream: i32, mut body: Vec<u8>| {
        let size = (body.len() - 4) as u32;
        body[0..4].copy_from_slice(&size.to_le_bytes());
        let c = compress(&body);
        out.extend_from_slice(&stream.to_le_bytes());
        out.extend_from_slice(&(c.len() as i32).to_le_bytes());
        out.extend_from_slice(&c);
    };
    // Interleave: triggers up to each event packet's last time go first.
    let mut ti = 0;
    let mut ev_packets: Vec<&[crate::events::Event]> = events.chunks(per_packet).collect();
    if ev_packets.is_empty() {
        ev_packets.push(&[]);
    }
    for (k, evs) in ev_packets.iter().enumerate() {
        let limit = if k + 1 == ev_packets.len() {
            i64::MAX
        } else {
            evs.last().map_or(i64::MAX, |e| e.t)
        };
        let mut trs = Vec::new();
        while ti < triggers.len() && triggers[ti].t <= limit && trs.len() < per_packet {
            trs.push(triggers[ti]);
            ti += 1;
        }
        if !evs.is_empty() {
            let mut body = Vec::new();
            packet_prefix(b"EVTS", &mut body);
            body.extend_from_slice(&(evs.len() as u32).to_le_bytes()); // @28, elements @32
            for e in evs.iter() {
                body.extend_from_slice(&e.t.to_le_bytes());
                body.extend_from_slice(&(e.x as i16).to_le_bytes());
                body.extend_from_slice(&(e.y as i16).to_le_bytes());
                body.push(e.p);
                body.extend_from_slice(&[0, 0, 0]);
            }
            push_packet(0, body);
        }
        while !trs.is_empty() {
            let mut body = Vec::new();
            packet_prefix(b"TRIG", &mut body);
            let n = trs.len();
            body.extend_from_slice(&(n as u32).to_le_bytes()); // @28
            let offsets_at = body.len(); // 32
            body.resize(offsets_at + 4 * n, 0);
            // Shared vtable {8, 16, ts@8, type@4}, then 8-aligned tables.
            let vt = body.len();
            for v in [8u16, 16, 8, 4] {
                body.extend_from_slice(&v.to_le_bytes());
            }
            while body.len() % 8 != 0 {
                body.push(0);
            }
            for (i, tr) in trs.iter().enumerate() {
                let tpos = body.len();
                let slot = offsets_at + 4 * i;
                body[slot..slot + 4].copy_from_slice(&((tpos - slot) as u32).to_le_bytes());
                body.extend_from_slice(&((tpos - vt) as i32).to_le_bytes());
                let ty: i8 = match (tr.channel, tr.edge) {
                    (0, Edge::Rising) => 1,
                    (0, Edge::Falling) => 2,
                    (1, Edge::Rising) => 4,
                    (1, Edge::Falling) => 5,
                    (2, Edge::Rising) => 6,
                    (2, Edge::Falling) => 7,
                    (_, Edge::Rising) => 8,
                    (_, Edge::Falling) => 9,
                };
                body.extend_from_slice(&[ty as u8, 0, 0, 0]);
                body.extend_from_slice(&tr.t.to_le_bytes());
            }
            push_packet(1, body);
            trs.clear();
            let limit2 = limit;
            while ti < triggers.len() && triggers[ti].t <= limit2 && trs.len() < per_packet {
                trs.push(triggers[ti]);
                ti += 1;
            }
        }
    }
    out
}

#[cfg(feature = "testkit")]
/// Wrap bytes in a valid Zstd frame made of raw (stored) blocks: lets tests
/// exercise the Zstd path without a Zstd compressor.
pub(crate) fn zstd_stored_frame(data: &[u8]) -> Vec<u8> {
    const MAX_BLOCK: usize = 128 * 1024;
    let mut out = vec![0x28, 0xB5, 0x2F, 0xFD, 0x00, 7 << 3];
    let mut chunks: Vec<&[u8]> = data.chunks(MAX_BLOCK).collect();
    if chunks.is_empty() {
        chunks.push(&[]);
    }
    let last = chunks.len() - 1;
    for (i, c) in chunks.iter().enumerate() {
        let header = (i == last) as u32 | ((c.len() as u32) << 3);
        out.extend_from_slice(&header.to_le_bytes()[..3]);
        out.extend_from_slice(c);
    }
    out
}

/// LZ4 frame compression (as dv writes), for tests and fixtures.
#[ebptv_macros::testkit]
pub(crate) fn lz4_frame(data: &[u8]) -> Vec<u8> {
    use std::io::Write;
    let mut enc = lz4_flex::frame::FrameEncoder::new(Vec::new());
    enc.write_all(data).expect("writing to a Vec");
    enc.finish().expect("writing to a Vec")
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;
    use crate::events::Event;

    fn sample() -> (Vec<Event>, Vec<Trigger>) {
        let events: Vec<Event> = (0..5000i64)
            .map(|i| Event {
                t: 1_600_000_000_000_000 + i * 13,
                x: (i % 346) as u16,
                y: (i % 260) as u16,
                p: (i % 3 == 0) as u8,
            })
            .collect();
        let triggers: Vec<Trigger> = (0..40i64)
            .map(|i| Trigger {
                t: 1_600_000_000_000_000 + i * 1500,
                channel: (i % 4) as u8,
                edge: if i % 2 == 0 {
                    Edge::Rising
                } else {
                    Edge::Falling
                },
            })
            .collect();
        (events, triggers)
    }

    fn read_all(path: &Path, chunk: usize) -> Result<(Vec<Event>, Vec<Trigger>, Aedat4Reader)> {
        let mut r = Aedat4Reader::open(path, chunk)?;
        let mut c = Chunk::default();
        let (mut ev, mut tr) = (Vec::new(), Vec::new());
        while r.next_chunk(&mut c)? {
            assert!(!c.is_empty());
            assert!(c.events.len() <= chunk);
            ev.extend(c.events.iter());
            tr.extend_from_slice(&c.triggers);
        }
        Ok((ev, tr, r))
    }

    #[ebptv_macros::unit_test]
    fn roundtrip_all_compressions() {
        let dir = tempfile::tempdir().unwrap();
        let (events, triggers) = sample();
        let g = Geometry::new(346, 260);
        let none = |b: &[u8]| b.to_vec();
        type Compressor<'a> = &'a dyn Fn(&[u8]) -> Vec<u8>;
        let cases: [(Compression, Compressor); 3] = [
            (Compression::None, &none),
            (Compression::Lz4, &lz4_frame),
            (Compression::Zstd, &zstd_stored_frame),
        ];
        for (comp, f) in cases {
            let p = dir.path().join(format!("{}.aedat4", comp.code()));
            std::fs::write(&p, encode_aedat4(&events, &triggers, g, comp, 700, f)).unwrap();
            for chunk in [100, 1 << 20] {
                let (ev, tr, r) = read_all(&p, chunk).unwrap();
                assert_eq!(ev, events, "{comp:?}");
                assert_eq!(tr, triggers, "{comp:?}");
                assert_eq!(r.info().geometry, Some(g));
                assert!(!r.anomalies().any_problem());
            }
        }
    }

    #[ebptv_macros::unit_test]
    fn packets_recognised_without_stream_description() {
        let dir = tempfile::tempdir().unwrap();
        let (events, triggers) = sample();
        let mut b = encode_aedat4(
            &events,
            &triggers,
            Geometry::new(346, 260),
            Compression::Lz4,
            700,
            &lz4_frame,
        );
        // Blank out the XML's stream nodes (same length, so offsets hold).
        let find = |needle: &[u8]| b.windows(needle.len()).position(|w| w == needle).unwrap();
        let (start, end) = (find(b"<node name=\"outInfo\""), find(b"</dv>"));
        for byte in &mut b[start..end] {
            *byte = b' ';
        }
        let p = dir.path().join("noxml.aedat4");
        std::fs::write(&p, &b).unwrap();
        let (ev, tr, r) = read_all(&p, 1000).unwrap();
        assert!(ev == events, "{} events of {}", ev.len(), events.len());
        assert_eq!(tr, triggers);
        assert_eq!(r.info().geometry, None);
    }

    #[ebptv_macros::unit_test]
    fn xml_streams() {
        let s = parse_streams(
            "<dv><node name=\"outInfo\"><node name=\"0\"><attr key=\"typeIdentifier\" type=\"string\">EVTS</attr>\
             <node name=\"info\"><attr key=\"sizeX\" type=\"int\">346</attr><attr key=\"sizeY\" type=\"int\">260</attr></node></node>\
             <node name=\"3\"><attr key=\"typeIdentifier\" type=\"string\">TRIG</attr></node></node></dv>",
        );
        assert_eq!(s.len(), 2);
        assert_eq!(
            (
                s[0].id,
                s[0].type_identifier.as_str(),
                s[0].size_x,
                s[0].size_y
            ),
            (0, "EVTS", Some(346), Some(260))
        );
        assert_eq!((s[1].id, s[1].type_identifier.as_str()), (3, "TRIG"));
    }

    #[ebptv_macros::unit_test]
    fn bad_inputs() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("x.aedat4");
        std::fs::write(&p, b"").unwrap();
        assert!(matches!(
            Aedat4Reader::open(&p, 10),
            Err(Error::Empty { .. })
        ));
        std::fs::write(&p, b"#!AER-DAT3.1\r\n").unwrap();
        assert!(matches!(
            Aedat4Reader::open(&p, 10),
            Err(Error::UnknownFormat { .. })
        ));
        let mut b = MAGIC.to_vec();
        b.extend_from_slice(&u32::MAX.to_le_bytes());
        std::fs::write(&p, &b).unwrap();
        assert!(Aedat4Reader::open(&p, 10)
            .err()
            .unwrap()
            .to_string()
            .contains("header length"));

        let (events, triggers) = sample();
        let good = encode_aedat4(
            &events,
            &triggers,
            Geometry::new(346, 260),
            Compression::Lz4,
            700,
            &lz4_frame,
        );
        // Header only: no packets, no events, no error.
        let hlen = u32::from_le_bytes(good[14..18].try_into().unwrap()) as usize;
        std::fs::write(&p, &good[..18 + hlen]).unwrap();
        let (ev, _, _) = read_all(&p, 10).unwrap();
        assert!(ev.is_empty());
        // Truncated in the middle of a packet: whole packets delivered, tail counted.
        std::fs::write(&p, &good[..good.len() - 100]).unwrap();
        let (ev, _, r) = read_all(&p, 1 << 20).unwrap();
        assert!(!ev.is_empty() && ev.len() < events.len());
        assert!(r.anomalies().truncated_tail_bytes > 0);
        // A packet that claims a huge size: truncation, no huge allocation.
        let mut huge = good[..18 + hlen].to_vec();
        huge.extend_from_slice(&0i32.to_le_bytes());
        huge.extend_from_slice(&i32::MAX.to_le_bytes());
        huge.extend_from_slice(&[0u8; 64]);
        std::fs::write(&p, &huge).unwrap();
        let (_, _, r) = read_all(&p, 10).unwrap();
        assert_eq!(r.anomalies().truncated_tail_bytes, 72);
        // Garbage compressed data: an error naming the packet offset.
        let mut garbage = good[..18 + hlen].to_vec();
        garbage.extend_from_slice(&0i32.to_le_bytes());
        garbage.extend_from_slice(&16i32.to_le_bytes());
        garbage.extend_from_slice(&[0xAB; 16]);
        std::fs::write(&p, &garbage).unwrap();
        let e = read_all(&p, 10).err().unwrap().to_string();
        assert!(
            e.contains("decompress") && e.contains(&format!("byte {}", 18 + hlen)),
            "{e}"
        );
    }
}
