//! Prophesee DAT reader (CD event files and external-trigger files).
//!
//! Layout (Prophesee's `dat_events_tools`, openeb's DAT writer):
//! ASCII header lines starting with `% ` (`% Date`, `% Version 2`,
//! `% Height 720`, `% Width 1280` — the geometry lines are often missing),
//! then two bytes: the event type and the event size, then fixed-size
//! little-endian records of `size` (= 8) bytes:
//!
//! | type | record |
//! |---|---|
//! | 0x00 Event2d, 0x0C CD | `u32 t`, `u32 w`: x = w[13..0], y = w[27..14], p = w[31..28] |
//! | 0x0E external trigger | `u32 t`, `u32 w`: p = w[3..0] (1 rising, 0 falling), id = w[31..26] |
//!
//! The 32-bit microsecond clock wraps after 2^32 µs ≈ 71.6 min; a drop of
//! more than half the range between consecutive records is counted as a
//! loop and unwrapped (`Anomalies::time_loops`), smaller steps back are kept
//! as they are (raw sensor time, never sorted).
//!
//! The header is parsed by `raw_header::parse_percent_header` (shared
//! with RAW files). Files without any `% ` header line are refused: every Prophesee tool
//! writes one, and without it arbitrary bytes would decode as plausible
//! events. Memory is bounded by the chunk size: records are read in blocks
//! of `chunk_events` records.

use std::fs::File;
use std::io::{BufReader, Read, Seek, SeekFrom};
use std::path::Path;

use crate::error::{Error, Result};
use crate::events::{Chunk, Edge, Geometry, Trigger};
use crate::{raw_header, Anomalies, EventSource, Format, StreamInfo};

/// Event type byte of a DAT file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum DatEventType {
    /// 0x00: Event2d (x, y, p) — the type of most CD files.
    Event2d,
    /// 0x0C: CD event.
    Cd,
    /// 0x0E: external trigger.
    ExtTrigger,
}

impl DatEventType {
    fn from_byte(b: u8) -> Option<Self> {
        match b {
            0x00 => Some(DatEventType::Event2d),
            0x0C => Some(DatEventType::Cd),
            0x0E => Some(DatEventType::ExtTrigger),
            _ => None,
        }
    }
}

const RECORD_BYTES: usize = 8;

/// Geometry from `Width`/`Height` header keys (case-insensitive), when both
/// are present and valid.
pub(crate) fn geometry_from_header(header: &[(String, String)]) -> Option<Geometry> {
    let get = |name: &str| {
        header
            .iter()
            .find(|(k, _)| k.eq_ignore_ascii_case(name))
            .and_then(|(_, v)| v.parse::<u16>().ok())
    };
    match (get("Width"), get("Height")) {
        (Some(w), Some(h)) if w > 0 && h > 0 => Some(Geometry::new(w, h)),
        _ => None,
    }
}

pub(crate) struct DatReader {
    info: StreamInfo,
    reader: BufReader<File>,
    event_type: DatEventType,
    buf: Vec<u8>,
    /// Bytes of a partial record carried to the next read.
    carry: usize,
    offset: u64,
    last_raw_t: Option<u32>,
    loops: u64,
    anomalies: Anomalies,
    done: bool,
}

impl DatReader {
    pub(crate) fn open(path: &Path, chunk_events: usize) -> Result<Self> {
        let mut file = File::open(path).map_err(|e| Error::io(path, e))?;
        let file_size = file.metadata().ok().map(|m| m.len());
        if file_size == Some(0) {
            return Err(Error::Empty {
                path: path.to_path_buf(),
                why: "file is empty".into(),
            });
        }
        // The `%` header is the one RAW files use: parse it with the shared
        // parser, then continue right after it.
        let mut head = Vec::new();
        (&mut file)
            .take(raw_header::MAX_HEADER_BYTES as u64)
            .read_to_end(&mut head)
            .map_err(|e| Error::io(path, e))?;
        let (header, header_len) = raw_header::parse_percent_header(&head);
        let header_len = header_len as u64;
        drop(head);
        file.seek(SeekFrom::Start(header_len))
            .map_err(|e| Error::io(path, e))?;
        let mut reader = BufReader::with_capacity(1 << 16, file);
        if header_len == 0 {
            return Err(Error::UnknownFormat {
                path: path.to_path_buf(),
                why: "no `% ` header line: not a Prophesee DAT file".into(),
            });
        }
        let mut ts = [0u8; 2];
        let got = read_up_to(&mut reader, &mut ts).map_err(|e| Error::io(path, e))?;
        if got < 2 {
            return Err(Error::corrupt(
                path,
                header_len + got as u64,
                "header only: the event type and size bytes after the `%` header are missing",
            ));
        }
        let event_type = DatEventType::from_byte(ts[0]).ok_or_else(|| {
            Error::corrupt(
                path,
                header_len,
                format!(
                    "unsupported DAT event type 0x{:02X} (known: 0x00 Event2d, 0x0C CD, 0x0E trigger)",
                    ts[0]
                ),
            )
        })?;
        if ts[1] as usize != RECORD_BYTES {
            return Err(Error::corrupt(
                path,
                header_len + 1,
                format!("DAT event size {} bytes, expected 8", ts[1]),
            ));
        }
        let mut header = header;
        header.push((
            "event_type".into(),
            match event_type {
                DatEventType::Event2d => "0x00 Event2d",
                DatEventType::Cd => "0x0C CD",
                DatEventType::ExtTrigger => "0x0E external trigger",
            }
            .into(),
        ));
        let geometry = geometry_from_header(&header);
        let chunk_events = chunk_events.max(1);
        Ok(DatReader {
            info: StreamInfo {
                path: path.to_path_buf(),
                format: Format::Dat,
                geometry,
                header,
                payload_offset: header_len + 2,
                file_size,
            },
            reader,
            event_type,
            buf: vec![0u8; chunk_events.min(1 << 20) * RECORD_BYTES],
            carry: 0,
            offset: header_len + 2,
            last_raw_t: None,
            loops: 0,
            anomalies: Anomalies::default(),
            done: false,
        })
    }

    #[inline]
    fn unwrap_time(&mut self, raw: u32) -> i64 {
        if let Some(last) = self.last_raw_t {
            if raw < last && last - raw > (1u32 << 31) {
                self.loops += 1;
                self.anomalies.time_loops += 1;
            }
        }
        self.last_raw_t = Some(raw);
        ((self.loops << 32) | raw as u64) as i64
    }
}

/// Read until `buf` is full or end of file; returns the bytes read.
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

impl EventSource for DatReader {
    fn info(&self) -> &StreamInfo {
        &self.info
    }

    fn next_chunk(&mut self, chunk: &mut Chunk) -> Result<bool> {
        chunk.clear();
        while !self.done {
            let mut buf = std::mem::take(&mut self.buf);
            let got = read_up_to(&mut self.reader, &mut buf[self.carry..])
                .map_err(|e| Error::io(&self.info.path, e));
            let got = match got {
                Ok(g) => g,
                Err(e) => {
                    self.buf = buf;
                    return Err(e);
                }
            };
            let avail = self.carry + got;
            let whole = avail / RECORD_BYTES * RECORD_BYTES;
            if got == 0 || avail < buf.len() {
                // End of file reached within this read.
                self.done = true;
                self.anomalies.truncated_tail_bytes += (avail - whole) as u64;
            }
            let geometry = self.info.geometry;
            let ev = &mut chunk.events;
            let n = whole / RECORD_BYTES;
            ev.t.reserve(n);
            ev.x.reserve(n);
            ev.y.reserve(n);
            ev.p.reserve(n);
            for rec in buf[..whole].chunks_exact(RECORD_BYTES) {
                let raw_t = u32::from_le_bytes([rec[0], rec[1], rec[2], rec[3]]);
                let w = u32::from_le_bytes([rec[4], rec[5], rec[6], rec[7]]);
                let t = self.unwrap_time(raw_t);
                match self.event_type {
                    DatEventType::Event2d | DatEventType::Cd => {
                        let x = (w & 0x3FFF) as u16;
                        let y = ((w >> 14) & 0x3FFF) as u16;
                        let p = ((w >> 28) != 0) as u8;
                        if let Some(g) = geometry {
                            if !g.contains(x, y) {
                                self.anomalies.out_of_geometry += 1;
                            }
                        }
                        chunk.events.push(t, x, y, p);
                    }
                    DatEventType::ExtTrigger => {
                        let edge = if w & 0xF != 0 {
                            Edge::Rising
                        } else {
                            Edge::Falling
                        };
                        let channel = (w >> 26) as u8;
                        chunk.triggers.push(Trigger { t, channel, edge });
                    }
                }
            }
            self.offset += whole as u64;
            // Keep a partial record for the next read (only possible before EOF
            // when the OS returned a short read; read_up_to avoids that).
            buf.copy_within(whole..avail, 0);
            self.carry = if self.done { 0 } else { avail - whole };
            self.buf = buf;
            if !chunk.is_empty() {
                return Ok(true);
            }
        }
        Ok(false)
    }

    fn anomalies(&self) -> Anomalies {
        self.anomalies.clone()
    }

    fn bytes_read(&self) -> u64 {
        self.offset
    }
}

/// Encode CD events as a DAT file (type 0x0C) — used by tests and small
/// tools; times must fit in 32 bits after subtracting nothing (they are
/// written modulo 2^32, as a camera would).
#[ebptv_macros::testkit]
pub(crate) fn encode_dat_cd(
    events: &[crate::events::Event],
    geometry: Option<Geometry>,
) -> Vec<u8> {
    let mut out = Vec::new();
    out.extend_from_slice(b"% Data file containing CD events.\n% Version 2\n");
    if let Some(g) = geometry {
        out.extend_from_slice(format!("% Height {}\n% Width {}\n", g.height, g.width).as_bytes());
    }
    out.push(0x0C);
    out.push(8);
    for e in events {
        out.extend_from_slice(&(e.t as u64 as u32).to_le_bytes());
        let w = (e.x as u32 & 0x3FFF) | ((e.y as u32 & 0x3FFF) << 14) | ((e.p as u32 & 0xF) << 28);
        out.extend_from_slice(&w.to_le_bytes());
    }
    out
}

/// Encode triggers as a DAT trigger file (type 0x0E).
#[ebptv_macros::testkit]
pub(crate) fn encode_dat_triggers(triggers: &[Trigger]) -> Vec<u8> {
    let mut out = Vec::new();
    out.extend_from_slice(b"% Data file containing external trigger events.\n% Version 2\n");
    out.push(0x0E);
    out.push(8);
    for tr in triggers {
        out.extend_from_slice(&(tr.t as u64 as u32).to_le_bytes());
        let w = (tr.edge == Edge::Rising) as u32 | ((tr.channel as u32 & 0x3F) << 26);
        out.extend_from_slice(&w.to_le_bytes());
    }
    out
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;
    use crate::events::Event;

    fn read_all(
        path: &Path,
        chunk: usize,
    ) -> Result<(Vec<Event>, Vec<Trigger>, Anomalies, StreamInfo)> {
        let mut r = DatReader::open(path, chunk)?;
        let mut c = Chunk::default();
        let mut ev = Vec::new();
        let mut tr = Vec::new();
        while r.next_chunk(&mut c)? {
            assert!(!c.is_empty());
            assert!(c.events.len() <= chunk);
            ev.extend(c.events.iter());
            tr.extend_from_slice(&c.triggers);
        }
        Ok((ev, tr, r.anomalies(), r.info().clone()))
    }

    /// The plain reference: decode the whole byte buffer record by record.
    fn reference_decode(bytes: &[u8], payload: usize) -> Vec<Event> {
        let mut out = Vec::new();
        let mut loops = 0i64;
        let mut last: Option<u32> = None;
        let mut i = payload;
        while i + 8 <= bytes.len() {
            let t = u32::from_le_bytes(bytes[i..i + 4].try_into().unwrap());
            let w = u32::from_le_bytes(bytes[i + 4..i + 8].try_into().unwrap());
            if let Some(l) = last {
                if (l as i64 - t as i64) > (1i64 << 31) {
                    loops += 1;
                }
            }
            last = Some(t);
            out.push(Event {
                t: loops * (1i64 << 32) + t as i64,
                x: (w % (1 << 14)) as u16,
                y: ((w / (1 << 14)) % (1 << 14)) as u16,
                p: (w / (1 << 28) > 0) as u8,
            });
            i += 8;
        }
        out
    }

    #[ebptv_macros::unit_test]
    fn roundtrip_with_wrap_and_chunking() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.dat");
        // Times cross the 32-bit wrap once: 2^32 - 500 .. 2^32 + 500.
        let base = (1i64 << 32) - 500;
        let events: Vec<Event> = (0..1000)
            .map(|i| Event {
                t: base + i,
                x: (i % 1280) as u16,
                y: (i % 720) as u16,
                p: (i % 3 == 0) as u8,
            })
            .collect();
        let bytes = encode_dat_cd(&events, Some(Geometry::new(1280, 720)));
        std::fs::write(&path, &bytes).unwrap();
        for chunk in [1, 7, 1000, 5000] {
            let (ev, tr, an, info) = read_all(&path, chunk).unwrap();
            assert!(tr.is_empty());
            assert_eq!(info.geometry, Some(Geometry::new(1280, 720)));
            assert_eq!(an.time_loops, 1);
            // The first record starts the clock at its raw value (no loop yet),
            // so times equal the originals minus nothing: base < 2^32.
            assert_eq!(ev, events);
            let reference = reference_decode(&bytes, info.payload_offset as usize);
            assert_eq!(ev, reference);
        }
    }

    #[ebptv_macros::unit_test]
    fn triggers_file() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("trig.dat");
        let trig: Vec<Trigger> = (0..50)
            .map(|i| Trigger {
                t: 100 * i,
                channel: (i % 3) as u8,
                edge: if i % 2 == 0 {
                    Edge::Rising
                } else {
                    Edge::Falling
                },
            })
            .collect();
        std::fs::write(&path, encode_dat_triggers(&trig)).unwrap();
        let (ev, tr, _, _) = read_all(&path, 16).unwrap();
        assert!(ev.is_empty());
        assert_eq!(tr, trig);
    }

    #[ebptv_macros::unit_test]
    fn bad_inputs_are_errors_or_counted() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("x.dat");
        std::fs::write(&p, b"").unwrap();
        assert!(matches!(DatReader::open(&p, 10), Err(Error::Empty { .. })));
        std::fs::write(&p, b"% Version 2\n").unwrap();
        let e = DatReader::open(&p, 10).err().unwrap().to_string();
        assert!(e.contains("header only"), "{e}");
        std::fs::write(&p, b"% Version 2").unwrap();
        assert!(DatReader::open(&p, 10).is_err());
        std::fs::write(&p, b"hello, this is text\n").unwrap();
        let e = DatReader::open(&p, 10).err().unwrap().to_string();
        assert!(e.contains("not a Prophesee DAT"), "{e}");
        std::fs::write(&p, b"% Version 2\n\x07\x08").unwrap();
        assert!(DatReader::open(&p, 10)
            .err()
            .unwrap()
            .to_string()
            .contains("event type 0x07"));
        std::fs::write(&p, b"% Version 2\n\x00\x10").unwrap();
        assert!(DatReader::open(&p, 10)
            .err()
            .unwrap()
            .to_string()
            .contains("size 16"));
        // A truncated last record is counted, the whole ones delivered.
        let mut bytes = encode_dat_cd(
            &[Event {
                t: 1,
                x: 2,
                y: 3,
                p: 1,
            }; 3],
            None,
        );
        bytes.extend_from_slice(&[1, 2, 3]);
        std::fs::write(&p, &bytes).unwrap();
        let (ev, _, an, info) = read_all(&p, 2).unwrap();
        assert_eq!(ev.len(), 3);
        assert_eq!(an.truncated_tail_bytes, 3);
        assert_eq!(info.geometry, None);
    }

    #[ebptv_macros::unit_test]
    fn out_of_geometry_counted() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("g.dat");
        let ev = [
            Event {
                t: 1,
                x: 5,
                y: 5,
                p: 1,
            },
            Event {
                t: 2,
                x: 50,
                y: 5,
                p: 0,
            },
        ];
        std::fs::write(&p, encode_dat_cd(&ev, Some(Geometry::new(10, 10)))).unwrap();
        let (got, _, an, _) = read_all(&p, 10).unwrap();
        assert_eq!(got, ev);
        assert_eq!(an.out_of_geometry, 1);
    }
}
