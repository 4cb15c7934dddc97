//! NumPy `.npy` writers: events as a structured array, plus small helpers
//! for other stages (dense `f64` arrays, structured tables).
//!
//! Format 1.0 (numpy's `format.py`): `\x93NUMPY`, version `1 0`, a u16
//! little-endian header length, then an ASCII Python dict
//! `{'descr': ..., 'fortran_order': False, 'shape': (...), }` padded with
//! spaces and a final `\n` so that the data starts at a multiple of 64
//! bytes, then the raw little-endian data in C order.
//!
//! The event writer streams: it cannot know the event count when it writes
//! the header, so it reserves room for the widest possible count (20 digits)
//! and rewrites the header in place at [`EventWriter::finish`], padded to the
//! same length. The structured dtype is packed (no alignment padding):
//! `[('t','<i8'),('x','<u2'),('y','<u2'),('p','u1')]`, 13 bytes per event,
//! which `numpy.load` reads in one call. Triggers, if any, go to a sidecar
//! `<stem>_triggers.npy` with `[('t','<i8'),('id','u1'),('p','u1')]`
//! (p = 1 rising, 0 falling), as the CSV writer does.

use std::io::{Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use crate::atomic::AtomicFile;
use crate::error::{Error, Result};
use crate::events::{Chunk, Edge};
use crate::EventWriter;

const MAGIC: &[u8] = b"\x93NUMPY\x01\x00";

/// The header bytes (magic to final `\n`) for a dict with `descr` and
/// `shape`, padded to a multiple of 64 and at least `min_len` bytes.
fn header_bytes(descr: &str, shape: &[usize], min_len: usize) -> Vec<u8> {
    let shape_txt = match shape.len() {
        0 => "()".to_string(),
        1 => format!("({},)", shape[0]),
        _ => format!(
            "({})",
            shape
                .iter()
                .map(|s| s.to_string())
                .collect::<Vec<_>>()
                .join(", ")
        ),
    };
    let mut dict = format!("{{'descr': {descr}, 'fortran_order': False, 'shape': {shape_txt}, }}");
    let unpadded = MAGIC.len() + 2 + dict.len() + 1;
    let total = unpadded.max(min_len).div_ceil(64) * 64;
    dict.push_str(&" ".repeat(total - unpadded));
    dict.push('\n');
    let mut out = Vec::with_capacity(total);
    out.extend_from_slice(MAGIC);
    out.extend_from_slice(&(dict.len() as u16).to_le_bytes());
    out.extend_from_slice(dict.as_bytes());
    debug_assert_eq!(out.len(), total);
    out
}

/// The header of a plain (non-structured) C-order array of dtype `descr`
/// (e.g. `<f4`, `<f8`, `|u1`), for writers that stream the data after it.
pub fn array_header(descr: &str, shape: &[usize]) -> Vec<u8> {
    header_bytes(&format!("'{descr}'"), shape, 0)
}

/// The header of a 1-D array of `rows` records of the (structured) dtype
/// `descr` (e.g. `[('a', '<f8'), ('b', '<i8')]`), padded to at least
/// `min_len` bytes: streaming writers reserve room with `rows =
/// usize::MAX`, then rewrite it in place with the final count and the same
/// `min_len`.
pub fn table_header(descr: &str, rows: usize, min_len: usize) -> Vec<u8> {
    header_bytes(descr, &[rows], min_len)
}

/// A column of a structured table for [`write_npy_table`].
#[derive(Debug, Clone, Copy)]
#[ebptv_macros::testkit]
pub(crate) enum NpyColumn<'a> {
    /// `<f8` values.
    F64(&'a [f64]),
    /// `<f4` values.
    F32(&'a [f32]),
    /// `<i8` values.
    I64(&'a [i64]),
    /// `<i4` values.
    I32(&'a [i32]),
    /// `<u8` values.
    U64(&'a [u64]),
    /// `<u4` values.
    U32(&'a [u32]),
    /// `<u2` values.
    U16(&'a [u16]),
    /// `|u1` values.
    U8(&'a [u8]),
    /// `|b1` values.
    Bool(&'a [bool]),
}

impl NpyColumn<'_> {
    fn len(&self) -> usize {
        match self {
            NpyColumn::F64(v) => v.len(),
            NpyColumn::F32(v) => v.len(),
            NpyColumn::I64(v) => v.len(),
            NpyColumn::I32(v) => v.len(),
            NpyColumn::U64(v) => v.len(),
            NpyColumn::U32(v) => v.len(),
            NpyColumn::U16(v) => v.len(),
            NpyColumn::U8(v) => v.len(),
            NpyColumn::Bool(v) => v.len(),
        }
    }
    fn dtype(&self) -> &'static str {
        match self {
            NpyColumn::F64(_) => "<f8",
            NpyColumn::F32(_) => "<f4",
            NpyColumn::I64(_) => "<i8",
            NpyColumn::I32(_) => "<i4",
            NpyColumn::U64(_) => "<u8",
            NpyColumn::U32(_) => "<u4",
            NpyColumn::U16(_) => "<u2",
            NpyColumn::U8(_) => "|u1",
            NpyColumn::Bool(_) => "|b1",
        }
    }
    fn push_le(&self, i: usize, out: &mut Vec<u8>) {
        match self {
            NpyColumn::F64(v) => out.extend_from_slice(&v[i].to_le_bytes()),
            NpyColumn::F32(v) => out.extend_from_slice(&v[i].to_le_bytes()),
            NpyColumn::I64(v) => out.extend_from_slice(&v[i].to_le_bytes()),
            NpyColumn::I32(v) => out.extend_from_slice(&v[i].to_le_bytes()),
            NpyColumn::U64(v) => out.extend_from_slice(&v[i].to_le_bytes()),
            NpyColumn::U32(v) => out.extend_from_slice(&v[i].to_le_bytes()),
            NpyColumn::U16(v) => out.extend_from_slice(&v[i].to_le_bytes()),
            NpyColumn::U8(v) => out.push(v[i]),
            NpyColumn::Bool(v) => out.push(v[i] as u8),
        }
    }
}

fn valid_field_name(name: &str) -> bool {
    !name.is_empty() && name.chars().all(|c| c.is_ascii_alphanumeric() || c == '_')
}

/// Write a dense C-order `f64` array of the given shape.
pub fn write_npy_f64(path: impl AsRef<Path>, shape: &[usize], data: &[f64]) -> Result<()> {
    let path = path.as_ref();
    let n: usize = shape.iter().product();
    if n != data.len() {
        return Err(Error::param(
            "shape",
            format!(
                "{}: shape {:?} holds {} values but {} were given",
                path.display(),
                shape,
                n,
                data.len()
            ),
        ));
    }
    let mut f = AtomicFile::create(path)?;
    let mut bytes = header_bytes("'<f8'", shape, 0);
    bytes.reserve(data.len() * 8);
    for v in data {
        bytes.extend_from_slice(&v.to_le_bytes());
    }
    f.write_all(&bytes).map_err(|e| Error::io(path, e))?;
    f.commit()
}

/// Write a 1-D structured array (a table numpy loads with named fields)
/// from equally long columns.
#[ebptv_macros::testkit]
pub(crate) fn write_npy_table(path: impl AsRef<Path>, columns: &[(&str, NpyColumn)]) -> Result<()> {
    let path = path.as_ref();
    if columns.is_empty() {
        return Err(Error::param(
            "columns",
            format!("{}: a table needs at least one column", path.display()),
        ));
    }
    let rows = columns[0].1.len();
    for (name, col) in columns {
        if !valid_field_name(name) {
            return Err(Error::param(
                "columns",
                format!(
                    "{}: field name `{name}` is not a plain identifier",
                    path.display()
                ),
            ));
        }
        if col.len() != rows {
            return Err(Error::param(
                "columns",
                format!(
                    "{}: column `{name}` has {} rows, `{}` has {rows}",
                    path.display(),
                    col.len(),
                    columns[0].0
                ),
            ));
        }
    }
    let descr = format!(
        "[{}]",
        columns
            .iter()
            .map(|(n, c)| format!("('{}', '{}')", n, c.dtype()))
            .collect::<Vec<_>>()
            .join(", ")
    );
    let mut f = AtomicFile::create(path)?;
    f.write_all(&header_bytes(&descr, &[rows], 0))
        .map_err(|e| Error::io(path, e))?;
    let mut buf = Vec::with_capacity(1 << 16);
    for i in 0..rows {
        for (_, c) in columns {
            c.push_le(i, &mut buf);
        }
        if buf.len() >= 1 << 16 {
            f.write_all(&buf).map_err(|e| Error::io(path, e))?;
            buf.clear();
        }
    }
    f.write_all(&buf).map_err(|e| Error::io(path, e))?;
    f.commit()
}

/// A parsed `.npy` header (for tests and checks): the `descr` text, the
/// shape, and the byte offset of the data.
#[derive(Debug, Clone, PartialEq)]
pub struct NpyHeader {
    /// The `descr` dtype string.
    pub descr: String,
    /// Whether the array is stored in column-major order.
    pub fortran_order: bool,
    /// The array's shape.
    pub shape: Vec<usize>,
    /// Byte offset of the data after the header.
    pub data_offset: usize,
}

/// Parse the header of a version 1.0 `.npy` byte buffer.
pub fn parse_npy_header(bytes: &[u8]) -> Option<NpyHeader> {
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" || bytes[6] != 1 {
        return None;
    }
    let hlen = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
    let dict = std::str::from_utf8(bytes.get(10..10 + hlen)?).ok()?;
    let descr_start = dict.find("'descr': ")? + 9;
    let fo = dict.find(", 'fortran_order': ")?;
    let descr = dict[descr_start..fo].to_string();
    let fortran_order = dict[fo..].starts_with(", 'fortran_order': True");
    let s0 = dict.find("'shape': (")? + 10;
    let s1 = s0 + dict[s0..].find(')')?;
    let shape = dict[s0..s1]
        .split(',')
        .map(|s| s.trim())
        .filter(|s| !s.is_empty())
        .map(|s| s.parse().ok())
        .collect::<Option<Vec<usize>>>()?;
    Some(NpyHeader {
        descr,
        fortran_order,
        shape,
        data_offset: 10 + hlen,
    })
}

const EVENT_DESCR: &str = "[('t', '<i8'), ('x', '<u2'), ('y', '<u2'), ('p', '|u1')]";
const TRIGGER_DESCR: &str = "[('t', '<i8'), ('id', '|u1'), ('p', '|u1')]";
/// Room for the largest possible count, so the final header never grows.
const RESERVED_SHAPE: [usize; 1] = [usize::MAX];

/// One streaming structured-array file whose row count is patched at the end.
struct StreamingNpy {
    file: AtomicFile,
    descr: &'static str,
    header_len: usize,
    rows: usize,
    buf: Vec<u8>,
}

impl StreamingNpy {
    fn create(path: &Path, descr: &'static str) -> Result<Self> {
        let mut file = AtomicFile::create(path)?;
        let header = header_bytes(descr, &RESERVED_SHAPE, 0);
        file.write_all(&header).map_err(|e| Error::io(path, e))?;
        Ok(StreamingNpy {
            file,
            descr,
            header_len: header.len(),
            rows: 0,
            buf: Vec::new(),
        })
    }
    fn flush_buf(&mut self) -> Result<()> {
        let target = self.file.target().to_path_buf();
        self.file
            .write_all(&self.buf)
            .map_err(|e| Error::io(target, e))?;
        self.buf.clear();
        Ok(())
    }
    fn finish(mut self) -> Result<()> {
        self.flush_buf()?;
        commit_streamed_table(self.file, self.descr, self.rows, self.header_len)
    }
}

/// Finish a streamed 1-D structured array: overwrite its provisional header
/// (written with room for any row count, `header_len` bytes) with the final
/// row count, then commit the file.
pub fn commit_streamed_table(
    mut file: AtomicFile,
    descr: &str,
    rows: usize,
    header_len: usize,
) -> Result<()> {
    let target = file.target().to_path_buf();
    let header = header_bytes(descr, &[rows], header_len);
    if header.len() != header_len {
        return Err(Error::corrupt(
            &target,
            0,
            "npy header outgrew its reserved room (internal error)",
        ));
    }
    file.seek(SeekFrom::Start(0))
        .and_then(|_| file.write_all(&header))
        .map_err(|e| Error::io(&target, e))?;
    file.commit()
}

/// Streaming writer of events to a structured `.npy` (see the module docs).
#[ebptv_macros::testkit]
pub(crate) struct NpyEventWriter {
    events: StreamingNpy,
    triggers: Option<StreamingNpy>,
    trigger_path: PathBuf,
}

impl NpyEventWriter {
    /// Creates a writer for `path`.
    #[ebptv_macros::testkit]
    pub(crate) fn create(path: &Path) -> Result<Self> {
        Ok(NpyEventWriter {
            events: StreamingNpy::create(path, EVENT_DESCR)?,
            triggers: None,
            trigger_path: sidecar_path(path, "_triggers", "npy"),
        })
    }
}

/// `<dir>/<stem><suffix>.<ext>` for a sidecar of `path`.
pub(crate) fn sidecar_path(path: &Path, suffix: &str, ext: &str) -> PathBuf {
    let stem = path
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    path.with_file_name(format!("{stem}{suffix}.{ext}"))
}

impl EventWriter for NpyEventWriter {
    fn write_chunk(&mut self, chunk: &Chunk) -> Result<()> {
        let ev = &chunk.events;
        let w = &mut self.events;
        w.buf.reserve(ev.len() * 13);
        for i in 0..ev.len() {
            w.buf.extend_from_slice(&ev.t[i].to_le_bytes());
            w.buf.extend_from_slice(&ev.x[i].to_le_bytes());
            w.buf.extend_from_slice(&ev.y[i].to_le_bytes());
            w.buf.push(ev.p[i]);
        }
        w.rows += ev.len();
        w.flush_buf()?;
        if !chunk.triggers.is_empty() {
            if self.triggers.is_none() {
                self.triggers = Some(StreamingNpy::create(&self.trigger_path, TRIGGER_DESCR)?);
            }
            let tw = self.triggers.as_mut().expect("created above");
            for tr in &chunk.triggers {
                tw.buf.extend_from_slice(&tr.t.to_le_bytes());
                tw.buf.push(tr.channel);
                tw.buf.push((tr.edge == Edge::Rising) as u8);
            }
            tw.rows += chunk.triggers.len();
            tw.flush_buf()?;
        }
        Ok(())
    }

    fn finish(self: Box<Self>) -> Result<()> {
        let this = *self;
        if let Some(t) = this.triggers {
            t.finish()?;
        }
        this.events.finish()
    }
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;
    use crate::events::{EventChunk, Trigger};

    #[ebptv_macros::unit_test]
    fn header_is_aligned_and_parses() {
        for shape in [vec![0], vec![5], vec![3, 4], vec![usize::MAX]] {
            let h = header_bytes("'<f8'", &shape, 0);
            assert_eq!(h.len() % 64, 0);
            assert_eq!(*h.last().unwrap(), b'\n');
            let p = parse_npy_header(&h).unwrap();
            assert_eq!(p.shape, shape);
            assert_eq!(p.descr, "'<f8'");
            assert_eq!(p.data_offset, h.len());
        }
    }

    #[ebptv_macros::unit_test]
    fn event_writer_patches_count_and_data_decodes() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("ev.npy");
        let mut w: Box<dyn EventWriter> = Box::new(NpyEventWriter::create(&path).unwrap());
        let mut c = Chunk::default();
        let mut expect = Vec::new();
        for k in 0..3i64 {
            c.clear();
            for i in 0..1000i64 {
                let t = k * 1_000_000 + i * 37 - 5;
                c.events
                    .push(t, (i % 1280) as u16, (i % 720) as u16, (i % 2) as u8);
                expect.push((t, (i % 1280) as u16, (i % 720) as u16, (i % 2) as u8));
            }
            c.triggers.push(Trigger {
                t: k,
                channel: 1,
                edge: Edge::Falling,
            });
            w.write_chunk(&c).unwrap();
        }
        assert!(!path.exists(), "nothing under the final name before finish");
        w.finish().unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let h = parse_npy_header(&bytes).unwrap();
        assert_eq!(h.shape, vec![3000]);
        assert_eq!(h.descr, EVENT_DESCR);
        let data = &bytes[h.data_offset..];
        assert_eq!(data.len(), 3000 * 13);
        for (i, rec) in data.chunks_exact(13).enumerate() {
            let t = i64::from_le_bytes(rec[0..8].try_into().unwrap());
            let x = u16::from_le_bytes(rec[8..10].try_into().unwrap());
            let y = u16::from_le_bytes(rec[10..12].try_into().unwrap());
            assert_eq!((t, x, y, rec[12]), expect[i]);
        }
        let tb = std::fs::read(dir.path().join("ev_triggers.npy")).unwrap();
        let th = parse_npy_header(&tb).unwrap();
        assert_eq!(th.shape, vec![3]);
        assert_eq!(tb.len() - th.data_offset, 3 * 10);
    }

    #[ebptv_macros::unit_test]
    fn dropped_writer_leaves_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("ev.npy");
        {
            let mut w = NpyEventWriter::create(&path).unwrap();
            let mut c = Chunk {
                events: EventChunk::default(),
                triggers: vec![],
            };
            c.events.push(1, 2, 3, 1);
            w.write_chunk(&c).unwrap();
        }
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }

    #[ebptv_macros::unit_test]
    fn f64_and_table_writers() {
        let dir = tempfile::tempdir().unwrap();
        let a = dir.path().join("a.npy");
        let data: Vec<f64> = (0..12).map(|i| i as f64 * 0.5).collect();
        write_npy_f64(&a, &[3, 4], &data).unwrap();
        let b = std::fs::read(&a).unwrap();
        let h = parse_npy_header(&b).unwrap();
        assert_eq!(h.shape, vec![3, 4]);
        let back: Vec<f64> = b[h.data_offset..]
            .chunks_exact(8)
            .map(|c| f64::from_le_bytes(c.try_into().unwrap()))
            .collect();
        assert_eq!(back, data);
        assert!(write_npy_f64(&a, &[5], &data).is_err());

        let t = dir.path().join("t.npy");
        let xs = [1.5f64, 2.5];
        let ids = [7u64, 9];
        let ok = [true, false];
        write_npy_table(
            &t,
            &[
                ("x", NpyColumn::F64(&xs)),
                ("id", NpyColumn::U64(&ids)),
                ("ok", NpyColumn::Bool(&ok)),
            ],
        )
        .unwrap();
        let b = std::fs::read(&t).unwrap();
        let h = parse_npy_header(&b).unwrap();
        assert_eq!(h.descr, "[('x', '<f8'), ('id', '<u8'), ('ok', '|b1')]");
        assert_eq!(h.shape, vec![2]);
        let d = &b[h.data_offset..];
        assert_eq!(d.len(), 2 * 17);
        assert_eq!(f64::from_le_bytes(d[17..25].try_into().unwrap()), 2.5);
        assert_eq!(u64::from_le_bytes(d[25..33].try_into().unwrap()), 9);
        assert_eq!(d[33], 0);
        let short = [1i64];
        assert!(write_npy_table(
            &t,
            &[("x", NpyColumn::F64(&xs)), ("y", NpyColumn::I64(&short))]
        )
        .is_err());
        assert!(write_npy_table(&t, &[("bad name", NpyColumn::F64(&xs))]).is_err());
    }
}
