//! Event Stream (`.es`, neuromorphic-paris / sepia) reader, DVS and ATIS types.
//!
//! Layout (Event Stream specification 2.x): `Event Stream` (12 ASCII bytes),
//! version major, minor, patch (3 bytes), stream type (1 byte: 0 generic,
//! 1 DVS, 2 ATIS, 3 display, 4 color), then for DVS/ATIS the width and height
//! (u16 little-endian each), then a byte-oriented state machine:
//!
//! DVS (type 1): in the idle state `0xFF` = overflow (time += 127 µs),
//! `0xFE` = reset (ignored); any other byte is byte 0 of an event:
//! bits 7..1 = time delta (µs), bit 0 = is_increase; then x (u16 LE) and
//! y (u16 LE). Time is the running sum of deltas from 0.
//!
//! ATIS (type 2): idle bytes `0b111111xy` with xy != 0 are overflows of
//! `xy * 63` µs, `0xFC` = reset; byte 0 holds the delta in bits 7..2,
//! polarity in bit 1 and `is_tc` in bit 0; threshold-crossing (`is_tc`)
//! events are exposure measurements, not contrast events: counted as
//! skipped, not delivered.
//!
//! Only version 2 is supported (version 1 files have another layout). The
//! file is read in blocks; a partial event at a block boundary is carried
//! in the decoder state, so memory is bounded by the chunk size.

use std::fs::File;
use std::io::Read;
use std::path::Path;

use crate::error::{Error, Result};
use crate::events::{Chunk, Geometry};
use crate::{Anomalies, EventSource, Format, StreamInfo};

const MAGIC: &[u8; 12] = b"Event Stream";
const HEADER_BYTES: usize = 20;
const READ_BLOCK: usize = 1 << 16;

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum EsType {
    Dvs,
    Atis,
}

/// The byte state machine, kept across read blocks.
#[derive(Debug, Clone, Default)]
struct Decoder {
    state: u8,
    t: i64,
    p: u8,
    is_tc: bool,
    x: u16,
    y: u16,
}

pub(crate) struct EsReader {
    info: StreamInfo,
    file: File,
    kind: EsType,
    chunk_events: usize,
    buf: Vec<u8>,
    pos: usize,
    len: usize,
    offset: u64,
    dec: Decoder,
    anomalies: Anomalies,
    eof: bool,
}

impl EsReader {
    pub(crate) fn open(path: &Path, chunk_events: usize) -> Result<Self> {
        let mut file = File::open(path).map_err(|e| Error::io(path, e))?;
        let file_size = file.metadata().ok().map(|m| m.len());
        let mut head = [0u8; HEADER_BYTES];
        let mut n = 0;
        while n < HEADER_BYTES {
            let k = file.read(&mut head[n..]).map_err(|e| Error::io(path, e))?;
            if k == 0 {
                break;
            }
            n += k;
        }
        if n == 0 {
            return Err(Error::Empty {
                path: path.to_path_buf(),
                why: "file is empty".into(),
            });
        }
        if n < 12 || &head[..12] != MAGIC {
            return Err(Error::UnknownFormat {
                path: path.to_path_buf(),
                why: "does not start with `Event Stream`: not an Event Stream (.es) file".into(),
            });
        }
        if n < 16 {
            return Err(Error::corrupt(
                path,
                n as u64,
                "Event Stream header truncated",
            ));
        }
        let (major, minor, patch) = (head[12], head[13], head[14]);
        if major != 2 {
            return Err(Error::corrupt(
                path,
                12,
                format!("Event Stream version {major}.{minor}.{patch} not supported (only 2.x)"),
            ));
        }
        let kind = match head[15] {
            1 => EsType::Dvs,
            2 => EsType::Atis,
            0 => {
                return Err(Error::corrupt(
                    path,
                    15,
                    "Event Stream of generic events: no pixel events to read",
                ))
            }
            3 => {
                return Err(Error::corrupt(
                    path,
                    15,
                    "Event Stream of display events: not camera data",
                ))
            }
            4 => {
                return Err(Error::corrupt(
                    path,
                    15,
                    "Event Stream of color events: not supported",
                ))
            }
            other => {
                return Err(Error::corrupt(
                    path,
                    15,
                    format!("unknown Event Stream type {other}"),
                ))
            }
        };
        if n < HEADER_BYTES {
            return Err(Error::corrupt(
                path,
                n as u64,
                "Event Stream header truncated (no width/height)",
            ));
        }
        let width = u16::from_le_bytes([head[16], head[17]]);
        let height = u16::from_le_bytes([head[18], head[19]]);
        let geometry = (width > 0 && height > 0).then(|| Geometry::new(width, height));
        let header = vec![
            ("version".to_string(), format!("{major}.{minor}.{patch}")),
            (
                "type".to_string(),
                if kind == EsType::Dvs { "dvs" } else { "atis" }.to_string(),
            ),
            ("width".to_string(), width.to_string()),
            ("height".to_string(), height.to_string()),
        ];
        Ok(EsReader {
            info: StreamInfo {
                path: path.to_path_buf(),
                format: Format::Es,
                geometry,
                header,
                payload_offset: HEADER_BYTES as u64,
                file_size,
            },
            file,
            kind,
            chunk_events: chunk_events.max(1),
            buf: vec![0u8; READ_BLOCK],
            pos: 0,
            len: 0,
            offset: HEADER_BYTES as u64,
            dec: Decoder::default(),
            anomalies: Anomalies::default(),
            eof: false,
        })
    }
}

impl EventSource for EsReader {
    fn info(&self) -> &StreamInfo {
        &self.info
    }

    fn next_chunk(&mut self, chunk: &mut Chunk) -> Result<bool> {
        chunk.clear();
        let geometry = self.info.geometry;
        loop {
            if self.pos == self.len {
                if self.eof {
                    break;
                }
                let k = self
                    .file
                    .read(&mut self.buf)
                    .map_err(|e| Error::io(&self.info.path, e))?;
                if k == 0 {
                    self.eof = true;
                    if self.dec.state != 0 {
                        // A partial event at the end of the file.
                        self.anomalies.truncated_tail_bytes += self.dec.state as u64;
                        self.dec.state = 0;
                    }
                    break;
                }
                self.pos = 0;
                self.len = k;
            }
            let d = &mut self.dec;
            let kind = self.kind;
            let mut i = self.pos;
            let end = self.len;
            while i < end && chunk.events.len() < self.chunk_events {
                let b = self.buf[i];
                i += 1;
                match d.state {
                    0 => match kind {
                        EsType::Dvs => {
                            if b == 0xFF {
                                d.t += 127;
                            } else if b != 0xFE {
                                d.t += (b >> 1) as i64;
                                d.p = b & 1;
                                d.state = 1;
                            }
                        }
                        EsType::Atis => {
                            if b & 0xFC == 0xFC {
                                d.t += 63 * (b & 0x3) as i64;
                            } else {
                                d.t += (b >> 2) as i64;
                                d.p = (b >> 1) & 1;
                                d.is_tc = b & 1 == 1;
                                d.state = 1;
                            }
                        }
                    },
                    1 => {
                        d.x = b as u16;
                        d.state = 2;
                    }
                    2 => {
                        d.x |= (b as u16) << 8;
                        d.state = 3;
                    }
                    3 => {
                        d.y = b as u16;
                        d.state = 4;
                    }
                    _ => {
                        d.y |= (b as u16) << 8;
                        d.state = 0;
                        if d.is_tc {
                            self.anomalies.skipped_other_words += 1;
                        } else {
                            if let Some(g) = geometry {
                                if !g.contains(d.x, d.y) {
                                    self.anomalies.out_of_geometry += 1;
                                }
                            }
                            chunk.events.push(d.t, d.x, d.y, d.p);
                        }
                    }
                }
            }
            self.offset += (i - self.pos) as u64;
            self.pos = i;
            if chunk.events.len() >= self.chunk_events {
                break;
            }
        }
        Ok(!chunk.is_empty())
    }

    fn anomalies(&self) -> Anomalies {
        self.anomalies.clone()
    }

    fn bytes_read(&self) -> u64 {
        self.offset
    }
}

/// Encode events as an Event Stream 2.0.0 DVS file. Events must be sorted
/// by time with `t >= 0` (the format stores non-negative deltas); used by
/// tests and small tools.
#[ebptv_macros::testkit]
pub(crate) fn encode_es_dvs(events: &[crate::events::Event], geometry: Geometry) -> Vec<u8> {
    let mut out = Vec::with_capacity(HEADER_BYTES + events.len() * 5);
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&[2, 0, 0, 1]);
    out.extend_from_slice(&geometry.width.to_le_bytes());
    out.extend_from_slice(&geometry.height.to_le_bytes());
    let mut prev = 0i64;
    for e in events {
        let mut dt = (e.t - prev).max(0);
        prev = e.t.max(prev);
        while dt >= 127 {
            out.push(0xFF);
            dt -= 127;
        }
        out.push(((dt as u8) << 1) | (e.p & 1));
        out.extend_from_slice(&e.x.to_le_bytes());
        out.extend_from_slice(&e.y.to_le_bytes());
    }
    out
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;
    use crate::events::Event;

    fn read_all(path: &Path, chunk: usize) -> Result<(Vec<Event>, Anomalies)> {
        let mut r = EsReader::open(path, chunk)?;
        let mut c = Chunk::default();
        let mut out = Vec::new();
        while r.next_chunk(&mut c)? {
            assert!(c.events.len() <= chunk);
            out.extend(c.events.iter());
        }
        Ok((out, r.anomalies()))
    }

    #[ebptv_macros::unit_test]
    fn roundtrip_dvs_across_blocks() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("a.es");
        // Enough events to straddle several 64 KiB read blocks, with gaps
        // needing overflow bytes.
        let mut t = 0i64;
        let events: Vec<Event> = (0..40_000u32)
            .map(|i| {
                t += (i as i64 * 7919) % 400;
                Event {
                    t,
                    x: (i % 320) as u16,
                    y: (i % 240) as u16,
                    p: (i % 2) as u8,
                }
            })
            .collect();
        std::fs::write(&p, encode_es_dvs(&events, Geometry::new(320, 240))).unwrap();
        for chunk in [1000, 1 << 20] {
            let (got, an) = read_all(&p, chunk).unwrap();
            assert_eq!(got, events);
            assert!(!an.any_problem());
        }
    }

    #[ebptv_macros::unit_test]
    fn bad_inputs() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("b.es");
        std::fs::write(&p, b"").unwrap();
        assert!(matches!(EsReader::open(&p, 10), Err(Error::Empty { .. })));
        std::fs::write(&p, b"Not an event stream at all").unwrap();
        assert!(matches!(
            EsReader::open(&p, 10),
            Err(Error::UnknownFormat { .. })
        ));
        std::fs::write(&p, b"Event Stream\x02\x00\x00").unwrap();
        assert!(EsReader::open(&p, 10).is_err());
        std::fs::write(&p, b"Event Stream\x01\x00\x00\x01\x40\x01\xf0\x00").unwrap();
        assert!(EsReader::open(&p, 10)
            .err()
            .unwrap()
            .to_string()
            .contains("version 1.0.0"));
        // Truncated last event is counted.
        let mut bytes = encode_es_dvs(
            &[Event {
                t: 3,
                x: 1,
                y: 2,
                p: 1,
            }],
            Geometry::new(4, 4),
        );
        bytes.extend_from_slice(&[0x02, 0x01]);
        std::fs::write(&p, &bytes).unwrap();
        let (ev, an) = read_all(&p, 10).unwrap();
        assert_eq!(ev.len(), 1);
        assert_eq!(an.truncated_tail_bytes, 2);
    }
}
