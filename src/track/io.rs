//! Files of the PTV stage: the `particles` and `tracks` tables (Parquet by
//! default, or CSV / `.npy`: [`TableFormat`]) and `summary.json`.
//!
//! Writers go through [`AtomicFile`]; readers take any of the three
//! formats (sniffed from the file's first bytes), check the columns (by
//! name, any order, extra columns ignored) and every value, and report the
//! file and line (CSV) or row of the first problem.

use std::collections::BTreeMap;
use std::io::{BufRead, BufReader, Write};
use std::path::Path;

use serde::{Deserialize, Serialize};

use super::{Track, TrackPoint, TrackerStats};
use crate::cluster::Particle;
use crate::decimal::{push_fixed, push_int, RevDigits};
use crate::error::{Error, Result};
use crate::io::atomic::AtomicFile;
use crate::table::{Col, TableFormat, TableWriter};

/// Columns of `particles.csv`.
pub(crate) const PARTICLES_HEADER: &str = "pulse,t_us,x,y,n_events";
/// Columns of `tracks.csv`.
pub(crate) const TRACKS_HEADER: &str = "track_id,pulse,t_us,x,y,u,v";

/// The columns of the `particles` table in Parquet and `.npy` (the
/// `particles.csv` columns; µs, px).
#[ebptv_macros::testkit]
pub(crate) static PARTICLE_COLUMNS: [Col<Particle>; 5] = [
    Col::i64("pulse", |p| p.pulse),
    Col::f64("t_us", |p| p.t_us),
    Col::f64("x", |p| p.x),
    Col::f64("y", |p| p.y),
    Col::i64("n_events", |p| p.n_events as i64),
];

/// One row of the `tracks` table: a point and the id of its track.
#[derive(Debug, Clone, Copy)]
#[ebptv_macros::testkit]
pub(crate) struct TrackRow {
    /// Id of the track.
    pub id: u64,
    /// The point (µs, px, px/s).
    pub p: TrackPoint,
    /// `X_mm, Y_mm, U_m_s, V_m_s` when the run is calibrated (read only by
    /// `TRACK_COLUMNS_CALIBRATED`).
    pub phys: [f64; 4],
}

/// The columns of the `tracks` table in Parquet and `.npy` (the
/// `tracks.csv` columns; µs, px, px/s): the first seven of
/// `TRACK_COLUMNS_CALIBRATED`.
#[ebptv_macros::testkit]
pub(crate) static TRACK_COLUMNS: &[Col<TrackRow>] = TRACK_COLUMNS_CALIBRATED.split_at(7).0;

/// The `tracks` columns followed by the physical columns of a calibrated
/// run ([`crate::calib::Calibration::point_columns`]: mm, m/s).
pub(crate) static TRACK_COLUMNS_CALIBRATED: [Col<TrackRow>; 11] = [
    Col::i64("track_id", |r| r.id as i64),
    Col::i64("pulse", |r| r.p.pulse),
    Col::f64("t_us", |r| r.p.t_us),
    Col::f64("x", |r| r.p.x),
    Col::f64("y", |r| r.p.y),
    Col::f64("u", |r| r.p.u),
    Col::f64("v", |r| r.p.v),
    Col::f64("X_mm", |r| r.phys[0]),
    Col::f64("Y_mm", |r| r.phys[1]),
    Col::f64("U_m_s", |r| r.phys[2]),
    Col::f64("V_m_s", |r| r.phys[3]),
];

/// Streaming writer of the `particles` table in any [`TableFormat`].
pub(crate) enum ParticlesWriter {
    /// `particles.csv`.
    Csv(ParticlesCsvWriter),
    /// `particles.parquet` or `particles.npy`.
    Table(TableWriter<Particle>),
}

impl ParticlesWriter {
    /// `dir/particles.<ext>`.
    pub(crate) fn create(dir: &Path, format: TableFormat) -> Result<Self> {
        let path = dir.join(format.file_name("particles"));
        Ok(match format {
            TableFormat::Csv => ParticlesWriter::Csv(ParticlesCsvWriter::create(&path)?),
            TableFormat::Parquet => {
                ParticlesWriter::Table(TableWriter::parquet(&path, &PARTICLE_COLUMNS)?)
            }
            TableFormat::Npy => ParticlesWriter::Table(TableWriter::npy(&path, &PARTICLE_COLUMNS)?),
        })
    }
    pub(crate) fn write(&mut self, particles: &[Particle]) -> Result<()> {
        match self {
            ParticlesWriter::Csv(w) => w.write(particles),
            ParticlesWriter::Table(w) => w.write(particles),
        }
    }
    /// Records `key = value` in the file's metadata (Parquet only; CSV and
    /// `.npy` have no place for it).
    pub(crate) fn add_metadata(&mut self, key: &str, value: &str) {
        if let ParticlesWriter::Table(w) = self {
            w.add_metadata(key, value);
        }
    }
    pub(crate) fn finish(self) -> Result<()> {
        match self {
            ParticlesWriter::Csv(w) => w.finish(),
            ParticlesWriter::Table(w) => w.finish(),
        }
    }
}

/// Streaming writer of the `tracks` table in any [`TableFormat`].
pub(crate) enum TracksWriter {
    /// `tracks.csv`.
    Csv(TracksCsvWriter),
    /// `tracks.parquet` or `tracks.npy`, with the calibration whose
    /// physical columns end each row, if any.
    Table(TableWriter<TrackRow>, Option<crate::calib::Calibration>),
}

impl TracksWriter {
    /// `dir/tracks.<ext>`, whose rows end with the physical columns of
    /// `calib` when one is given.
    pub(crate) fn create_calibrated(
        dir: &Path,
        format: TableFormat,
        calib: Option<crate::calib::Calibration>,
    ) -> Result<Self> {
        let path = dir.join(format.file_name("tracks"));
        let cols: &'static [Col<TrackRow>] = if calib.is_some() {
            &TRACK_COLUMNS_CALIBRATED
        } else {
            TRACK_COLUMNS
        };
        Ok(match format {
            TableFormat::Csv => {
                TracksWriter::Csv(TracksCsvWriter::create_calibrated(&path, calib)?)
            }
            TableFormat::Parquet => TracksWriter::Table(TableWriter::parquet(&path, cols)?, calib),
            TableFormat::Npy => TracksWriter::Table(TableWriter::npy(&path, cols)?, calib),
        })
    }

    pub(crate) fn write(&mut self, tracks: &[Track]) -> Result<()> {
        match self {
            TracksWriter::Csv(w) => w.write(tracks),
            TracksWriter::Table(w, calib) => {
                for t in tracks {
                    for &p in &t.points {
                        let phys = calib
                            .as_ref()
                            .map_or([f64::NAN; 4], |c| c.point_values(p.x, p.y, p.u, p.v));
                        w.push(&TrackRow { id: t.id, p, phys })?;
                    }
                }
                Ok(())
            }
        }
    }
    /// Records `key = value` in the file's metadata (Parquet only).
    pub(crate) fn add_metadata(&mut self, key: &str, value: &str) {
        if let TracksWriter::Table(w, _) = self {
            w.add_metadata(key, value);
        }
    }
    pub(crate) fn finish(self) -> Result<()> {
        match self {
            TracksWriter::Csv(w) => w.finish(),
            TracksWriter::Table(w, _) => w.finish(),
        }
    }
}

fn werr(path: &Path, e: std::io::Error) -> Error {
    Error::io(path, e)
}

/// Formatted rows are handed to the file in blocks of at least this many
/// bytes: as large as [`AtomicFile`]'s buffer, so the blocks go to the
/// kernel directly instead of being copied through it first.
const WRITE_BLOCK: usize = 1 << 20;
/// Row buffers hold a block plus the rows of one more track or pulse.
const BLOCK_CAPACITY: usize = WRITE_BLOCK + (1 << 16);

/// Hands `buf` to the file once it holds at least `min` bytes (0: always),
/// then empties it.
fn write_block(file: &mut AtomicFile, buf: &mut Vec<u8>, min: usize) -> Result<()> {
    if buf.len() >= min {
        file.write_all(buf).map_err(|e| werr(file.target(), e))?;
        buf.clear();
    }
    Ok(())
}

/// Streaming writer of `particles.csv` (`pulse,t_us,x,y,n_events`; µs and
/// px): rows are appended as pulses are clustered; the file appears under
/// its name only on `ParticlesCsvWriter::finish`.
pub(crate) struct ParticlesCsvWriter {
    file: AtomicFile,
    /// Rows are formatted into this buffer, then written in one call.
    line: Vec<u8>,
    /// `pulse,t_us,` of the last pulse, and its pulse and `t_us` bits.
    prefix: Vec<u8>,
    prefix_of: Option<(i64, u64)>,
}

impl ParticlesCsvWriter {
    pub(crate) fn create(path: &Path) -> Result<Self> {
        let mut file = AtomicFile::create(path)?;
        writeln!(file, "{PARTICLES_HEADER}").map_err(|e| werr(path, e))?;
        Ok(ParticlesCsvWriter {
            file,
            line: Vec::with_capacity(BLOCK_CAPACITY),
            prefix: Vec::with_capacity(64),
            prefix_of: None,
        })
    }
    pub(crate) fn write(&mut self, particles: &[Particle]) -> Result<()> {
        for p in particles {
            // All particles of a pulse share pulse and t_us: their text
            // is formatted once.
            if self.prefix_of != Some((p.pulse, p.t_us.to_bits())) {
                self.prefix.clear();
                push_int(&mut self.prefix, p.pulse);
                self.prefix.push(b',');
                write!(self.prefix, "{}", p.t_us).expect("writing to memory");
                self.prefix.push(b',');
                self.prefix_of = Some((p.pulse, p.t_us.to_bits()));
            }
            if self.push_row(p) {
                continue;
            }
            self.line.extend_from_slice(&self.prefix);
            push_fixed(&mut self.line, p.x, 4);
            self.line.push(b',');
            push_fixed(&mut self.line, p.y, 4);
            self.line.push(b',');
            push_int(&mut self.line, p.n_events as i64);
            self.line.push(b'\n');
        }
        write_block(&mut self.file, &mut self.line, WRITE_BLOCK)?;
        Ok(())
    }

    /// Append the row of `p` built right to left in one buffer (as
    /// [`TracksCsvWriter`] does); false (nothing appended) when x or y
    /// needs `core::fmt` or the prefix is unusually long.
    #[inline]
    fn push_row(&mut self, p: &Particle) -> bool {
        let mut row = RevDigits::<128>::new();
        row.byte(b'\n');
        row.u64(p.n_events as u64);
        for v in [p.y, p.x] {
            row.byte(b',');
            if !row.fixed(v, 4) {
                return false;
            }
        }
        if self.prefix.len() > row.room() {
            return false;
        }
        row.bytes(&self.prefix);
        self.line.extend_from_slice(row.as_slice());
        true
    }

    pub(crate) fn finish(mut self) -> Result<()> {
        write_block(&mut self.file, &mut self.line, 0)?;
        self.file.commit()
    }
}

/// Streaming writer of `tracks.csv` (`track_id,pulse,t_us,x,y,u,v`; µs, px,
/// px/s), one row per track point.
pub(crate) struct TracksCsvWriter {
    file: AtomicFile,
    line: Vec<u8>,
    t_text: TimeTextCache,
    /// Physical columns after the pixel ones, when calibrated.
    calib: Option<crate::calib::Calibration>,
}

/// `t_us` as text (`{}`, the shortest round-trip form), cached per pulse:
/// every point of a pulse shares its time, and the shortest-float
/// formatter was ~5 % of a full-frame run. Direct-mapped by pulse index,
/// checked by the value's bits, so a stale slot is never used.
struct TimeTextCache {
    slots: Vec<(u64, u8, [u8; 31])>,
    /// The text of an uncacheable value.
    spill: Vec<u8>,
}

impl TimeTextCache {
    const SLOTS: usize = 4096;

    fn new() -> Self {
        TimeTextCache {
            slots: vec![(0, 0, [0; 31]); Self::SLOTS],
            spill: Vec::new(),
        }
    }

    /// The cached text of `t_us` at `pulse` (formatted on a miss).
    fn text(&mut self, pulse: i64, t_us: f64) -> &[u8] {
        let i = pulse.rem_euclid(Self::SLOTS as i64) as usize;
        let bits = t_us.to_bits();
        let slot = &self.slots[i];
        if !(slot.1 > 0 && slot.0 == bits) {
            let text = t_us.to_string();
            let slot = &mut self.slots[i];
            if text.len() > slot.2.len() {
                // Longer than any finite f64's shortest form: not cached.
                slot.1 = 0;
                self.spill = text.into_bytes();
                return &self.spill;
            }
            slot.0 = bits;
            slot.1 = text.len() as u8;
            slot.2[..text.len()].copy_from_slice(text.as_bytes());
        }
        let slot = &self.slots[i];
        &slot.2[..slot.1 as usize]
    }

    fn push(&mut self, out: &mut Vec<u8>, pulse: i64, t_us: f64) {
        let slot = &mut self.slots[pulse.rem_euclid(Self::SLOTS as i64) as usize];
        let bits = t_us.to_bits();
        if slot.1 > 0 && slot.0 == bits {
            out.extend_from_slice(&slot.2[..slot.1 as usize]);
            return;
        }
        let start = out.len();
        write!(out, "{t_us}").expect("writing to memory");
        let text = &out[start..];
        if text.len() <= slot.2.len() {
            slot.0 = bits;
            slot.1 = text.len() as u8;
            slot.2[..text.len()].copy_from_slice(text);
        }
    }
}

impl TracksCsvWriter {
    #[cfg(feature = "testkit")]
    fn create(path: &Path) -> Result<Self> {
        Self::create_calibrated(path, None)
    }

    /// A writer whose rows end with the physical columns of `calib`
    /// ([`crate::calib::Calibration::point_columns`]) when one is given.
    pub(crate) fn create_calibrated(
        path: &Path,
        calib: Option<crate::calib::Calibration>,
    ) -> Result<Self> {
        let mut file = AtomicFile::create(path)?;
        let extra = match calib {
            Some(_) => crate::calib::header_suffix(crate::calib::Calibration::point_columns()),
            None => String::new(),
        };
        writeln!(file, "{TRACKS_HEADER}{extra}").map_err(|e| werr(path, e))?;
        Ok(TracksCsvWriter {
            file,
            line: Vec::with_capacity(BLOCK_CAPACITY),
            t_text: TimeTextCache::new(),
            calib,
        })
    }
    pub(crate) fn write(&mut self, tracks: &[Track]) -> Result<()> {
        for t in tracks {
            for p in &t.points {
                if self.calib.is_none() && self.push_row(t.id, p) {
                    continue;
                }
                push_int(&mut self.line, t.id as i64);
                self.line.push(b',');
                push_int(&mut self.line, p.pulse);
                self.line.push(b',');
                self.t_text.push(&mut self.line, p.pulse, p.t_us);
                self.line.push(b',');
                push_fixed(&mut self.line, p.x, 4);
                self.line.push(b',');
                push_fixed(&mut self.line, p.y, 4);
                self.line.push(b',');
                push_fixed(&mut self.line, p.u, 3);
                self.line.push(b',');
                push_fixed(&mut self.line, p.v, 3);
                if let Some(c) = &self.calib {
                    crate::calib::push_values(&mut self.line, &c.point_values(p.x, p.y, p.u, p.v));
                }
                self.line.push(b'\n');
            }
            write_block(&mut self.file, &mut self.line, WRITE_BLOCK)?;
        }
        Ok(())
    }

    /// Append the row of point `p` of track `id`, built right to left in
    /// one buffer and appended with one copy; false (nothing appended)
    /// when a value needs `core::fmt` (near a rounding tie, huge, not
    /// finite): the caller then formats the row field by field.
    #[inline]
    fn push_row(&mut self, id: u64, p: &TrackPoint) -> bool {
        let mut row = RevDigits::<160>::new();
        row.byte(b'\n');
        // Unrolled (constant decimals).
        if !(row.fixed(p.v, 3)
            && {
                row.byte(b',');
                row.fixed(p.u, 3)
            }
            && {
                row.byte(b',');
                row.fixed(p.y, 4)
            }
            && {
                row.byte(b',');
                row.fixed(p.x, 4)
            })
        {
            return false;
        }
        row.byte(b',');
        let t = self.t_text.text(p.pulse, p.t_us);
        // Two integers (≤ 20 digits and a sign each, 8-byte stores) and
        // two commas follow.
        if t.len() + 60 > row.room() {
            return false;
        }
        row.bytes(t);
        row.byte(b',');
        row.i64(p.pulse);
        row.byte(b',');
        row.i64(id as i64); // as the field-by-field path writes it
        self.line.extend_from_slice(row.as_slice());
        true
    }

    pub(crate) fn finish(mut self) -> Result<()> {
        write_block(&mut self.file, &mut self.line, 0)?;
        self.file.commit()
    }
}

/// Fields of `tracks.npy`: the `tracks.csv` columns.
const TRACKS_NPY_DESCR: &str = "[('track_id', '<u8'), ('pulse', '<i8'), ('t_us', '<f8'), \
('x', '<f8'), ('y', '<f8'), ('u', '<f8'), ('v', '<f8')]";

/// Streaming writer of `tracks.npy`: a 1-D structured array with the
/// `tracks.csv` columns (`track_id` u64, `pulse` i64, the rest f64), the
/// same records as [`write_tracks_npy`]. Rows go to disk as tracks arrive
/// (memory does not grow with the recording); the header is written with
/// room for any row count and patched with the real one at
/// `TracksNpyWriter::finish`.
pub(crate) struct TracksNpyWriter {
    file: AtomicFile,
    header_len: usize,
    rows: usize,
    buf: Vec<u8>,
}

impl TracksNpyWriter {
    pub(crate) fn create(path: &Path) -> Result<Self> {
        let mut file = AtomicFile::create(path)?;
        let header = crate::io::npy::table_header(TRACKS_NPY_DESCR, usize::MAX, 0);
        file.write_all(&header).map_err(|e| werr(path, e))?;
        Ok(TracksNpyWriter {
            file,
            header_len: header.len(),
            rows: 0,
            buf: Vec::with_capacity(BLOCK_CAPACITY),
        })
    }

    pub(crate) fn write(&mut self, tracks: &[Track]) -> Result<()> {
        for t in tracks {
            for p in &t.points {
                let mut rec = [0u8; 56];
                rec[..8].copy_from_slice(&t.id.to_le_bytes());
                rec[8..16].copy_from_slice(&p.pulse.to_le_bytes());
                for (k, v) in [p.t_us, p.x, p.y, p.u, p.v].into_iter().enumerate() {
                    rec[16 + 8 * k..24 + 8 * k].copy_from_slice(&v.to_le_bytes());
                }
                self.buf.extend_from_slice(&rec);
            }
            self.rows += t.points.len();
            write_block(&mut self.file, &mut self.buf, WRITE_BLOCK)?;
        }
        Ok(())
    }

    pub(crate) fn finish(mut self) -> Result<()> {
        write_block(&mut self.file, &mut self.buf, 0)?;
        crate::io::npy::commit_streamed_table(
            self.file,
            TRACKS_NPY_DESCR,
            self.rows,
            self.header_len,
        )
    }
}

/// Write `tracks.npy` in one go, column by column through
/// [`crate::io::npy::write_npy_table`] (the reference of
/// [`TracksNpyWriter`]).
#[cfg(feature = "testkit")]
fn write_tracks_npy(path: &Path, tracks: &[Track]) -> Result<()> {
    use crate::io::npy::NpyColumn;
    let pts = || {
        tracks
            .iter()
            .flat_map(|t| t.points.iter().map(move |p| (t.id, p)))
    };
    let id: Vec<u64> = pts().map(|(id, _)| id).collect();
    let pulse: Vec<i64> = pts().map(|(_, p)| p.pulse).collect();
    let col = |f: fn(&TrackPoint) -> f64| pts().map(|(_, p)| f(p)).collect::<Vec<f64>>();
    let (t, x, y, u, v) = (
        col(|p| p.t_us),
        col(|p| p.x),
        col(|p| p.y),
        col(|p| p.u),
        col(|p| p.v),
    );
    crate::io::npy::write_npy_table(
        path,
        &[
            ("track_id", NpyColumn::U64(&id)),
            ("pulse", NpyColumn::I64(&pulse)),
            ("t_us", NpyColumn::F64(&t)),
            ("x", NpyColumn::F64(&x)),
            ("y", NpyColumn::F64(&y)),
            ("u", NpyColumn::F64(&u)),
            ("v", NpyColumn::F64(&v)),
        ],
    )
}

/// Write `particles.csv` in one go.
#[ebptv_macros::testkit]
pub(crate) fn write_particles_csv(path: &Path, particles: &[Particle]) -> Result<()> {
    let mut w = ParticlesCsvWriter::create(path)?;
    w.write(particles)?;
    w.finish()
}

/// Write `tracks.csv` in one go.
#[cfg(feature = "testkit")]
fn write_tracks_csv(path: &Path, tracks: &[Track]) -> Result<()> {
    let mut w = TracksCsvWriter::create(path)?;
    w.write(tracks)?;
    w.finish()
}

/// A column-checked reader of a table in any [`TableFormat`], yielding the
/// requested columns as f64, row by row. CSV is read line by line;
/// Parquet and `.npy` columns are read whole.
struct CsvColumns<'a> {
    path: &'a Path,
    src: RowSource,
    names: &'a [&'a str],
    /// The line (CSV) or row (Parquet, `.npy`) of the last row read.
    line_no: u64,
    buf: Vec<f64>,
}

enum RowSource {
    Csv {
        lines: std::io::Lines<BufReader<std::fs::File>>,
        idx: Vec<usize>,
    },
    Columns(Vec<Vec<f64>>),
}

impl<'a> CsvColumns<'a> {
    fn open(path: &'a Path, names: &'a [&'a str]) -> Result<Self> {
        if TableFormat::sniff(path)? != TableFormat::Csv {
            let cols = crate::table::read_columns(path, names)?;
            return Ok(CsvColumns {
                path,
                src: RowSource::Columns(cols),
                names,
                line_no: 0,
                buf: Vec::new(),
            });
        }
        let file = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
        let mut lines = BufReader::new(file).lines();
        let header = match lines.next() {
            None => {
                return Err(Error::corrupt(
                    path,
                    0,
                    "empty file: expected a header line",
                ))
            }
            Some(h) => h.map_err(|e| Error::io(path, e))?,
        };
        let cols: Vec<&str> = header
            .trim()
            .trim_start_matches('\u{feff}')
            .split(',')
            .map(|c| c.trim())
            .collect();
        let mut idx = Vec::new();
        let mut missing = Vec::new();
        for n in names {
            match cols.iter().position(|c| c == n) {
                Some(i) => idx.push(i),
                None => missing.push(*n),
            }
        }
        if !missing.is_empty() {
            return Err(Error::corrupt(
                path,
                0,
                format!(
                    "line 1: missing column(s) {} (header is `{}`, expected {})",
                    missing.join(", "),
                    header.trim(),
                    names.join(",")
                ),
            ));
        }
        Ok(CsvColumns {
            path,
            src: RowSource::Csv { lines, idx },
            names,
            line_no: 1,
            buf: Vec::new(),
        })
    }

    /// `line N` (CSV) or `row N` (Parquet, `.npy`, counted from 1).
    fn at(&self) -> String {
        match self.src {
            RowSource::Csv { .. } => format!("line {}", self.line_no),
            RowSource::Columns(_) => format!("row {}", self.line_no),
        }
    }

    /// Next data row's values (skips blank lines), or `None` at the end.
    fn next_row(&mut self) -> Result<Option<&[f64]>> {
        let (lines, idx) = match &mut self.src {
            RowSource::Csv { lines, idx } => (lines, idx),
            RowSource::Columns(cols) => {
                let i = self.line_no as usize;
                if cols.first().is_none_or(|c| i >= c.len()) {
                    return Ok(None);
                }
                self.line_no += 1;
                self.buf.clear();
                self.buf.extend(cols.iter().map(|c| c[i]));
                if let Some(k) = self.buf.iter().position(|v| !v.is_finite()) {
                    return Err(Error::corrupt(
                        self.path,
                        0,
                        format!(
                            "row {}: `{}` is {}, not a finite number",
                            self.line_no, self.names[k], self.buf[k]
                        ),
                    ));
                }
                return Ok(Some(&self.buf));
            }
        };
        loop {
            let Some(line) = lines.next() else {
                return Ok(None);
            };
            self.line_no += 1;
            let line = line.map_err(|e| Error::io(self.path, e))?;
            if line.trim().is_empty() {
                continue;
            }
            let fields: Vec<&str> = line.split(',').collect();
            self.buf.clear();
            for (k, &i) in idx.iter().enumerate() {
                let raw = fields.get(i).map(|s| s.trim()).ok_or_else(|| {
                    Error::corrupt(
                        self.path,
                        0,
                        format!(
                            "line {}: too few fields (no `{}`)",
                            self.line_no, self.names[k]
                        ),
                    )
                })?;
                let v: f64 = raw.parse().map_err(|_| {
                    Error::corrupt(
                        self.path,
                        0,
                        format!(
                            "line {}: `{}` = `{raw}` is not a number",
                            self.line_no, self.names[k]
                        ),
                    )
                })?;
                if !v.is_finite() {
                    return Err(Error::corrupt(
                        self.path,
                        0,
                        format!(
                            "line {}: `{}` is {raw}, not a finite number",
                            self.line_no, self.names[k]
                        ),
                    ));
                }
                self.buf.push(v);
            }
            return Ok(Some(&self.buf));
        }
    }

    fn int(&self, v: f64, col: usize) -> Result<i64> {
        if v.fract() != 0.0 || v.abs() > 9.0e15 {
            return Err(Error::corrupt(
                self.path,
                0,
                format!(
                    "{}: `{}` = {v} is not an integer",
                    self.at(),
                    self.names[col]
                ),
            ));
        }
        Ok(v as i64)
    }
}

/// Read a `particles` table (Parquet, CSV or `.npy`). Columns by name
/// (extra columns ignored); missing columns, unparsable values or NaN/inf
/// are errors naming the line or row.
#[ebptv_macros::testkit]
pub(crate) fn read_particles(path: &Path) -> Result<Vec<Particle>> {
    let names = ["pulse", "t_us", "x", "y", "n_events"];
    let mut r = CsvColumns::open(path, &names)?;
    let mut out = Vec::new();
    while let Some(row) = r.next_row()? {
        let row: [f64; 5] = row.try_into().expect("five columns");
        let pulse = r.int(row[0], 0)?;
        let n_events = r.int(row[4], 4)?;
        if n_events < 0 || n_events > u32::MAX as i64 {
            return Err(Error::corrupt(
                path,
                0,
                format!("{}: n_events = {n_events} out of range", r.at()),
            ));
        }
        out.push(Particle {
            pulse,
            t_us: row[1],
            x: row[2],
            y: row[3],
            n_events: n_events as u32,
            n_pixels: 0,
            extent_x: 0.0,
            extent_y: 0.0,
            first_latency_us: 0.0,
        });
    }
    Ok(out)
}

/// Read a `tracks` table (Parquet, CSV or `.npy`) into tracks (rows
/// grouped by `track_id`, points sorted by pulse). Accelerations are not
/// in the file and come back as 0; points are not marked interpolated.
#[ebptv_macros::testkit]
pub(crate) fn read_tracks(path: &Path) -> Result<Vec<Track>> {
    let names = ["track_id", "pulse", "t_us", "x", "y", "u", "v"];
    let mut r = CsvColumns::open(path, &names)?;
    let mut by_id: BTreeMap<u64, Vec<TrackPoint>> = BTreeMap::new();
    while let Some(row) = r.next_row()? {
        let row: [f64; 7] = row.try_into().expect("seven columns");
        let id = r.int(row[0], 0)?;
        if id < 0 {
            return Err(Error::corrupt(
                path,
                0,
                format!("{}: negative track_id {id}", r.at()),
            ));
        }
        let pulse = r.int(row[1], 1)?;
        by_id.entry(id as u64).or_default().push(TrackPoint {
            pulse,
            t_us: row[2],
            x: row[3],
            y: row[4],
            u: row[5],
            v: row[6],
            ax: 0.0,
            ay: 0.0,
            interpolated: false,
        });
    }
    Ok(by_id
        .into_iter()
        .map(|(id, mut points)| {
            points.sort_by_key(|p| p.pulse);
            Track { id, points }
        })
        .collect())
}

/// `summary.json`: what the PTV stage found.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Summary {
    /// Pulses processed.
    pub pulses: u64,
    /// Particles (detections) found.
    pub particles: u64,
    /// Tracks kept.
    pub tracks: u64,
    /// Detections on kept tracks.
    pub particles_on_tracks: u64,
    /// `particles_on_tracks / particles`.
    pub fraction_on_tracks: f64,
    /// Mean number of points per kept track (0 without tracks).
    pub mean_track_length: f64,
    /// Histogram of track lengths (points per track): `[lower, upper)` bin
    /// edges and counts.
    pub length_histogram: Vec<(u64, u64, u64)>,
    /// Mean speed |(u, v)| over all track points (px/s; 0 without points).
    pub mean_speed_px_s: f64,
    /// The tracker's counters.
    pub tracker: TrackerStats,
    /// How the run was made ([`crate::provenance`]), when recorded.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub provenance: Option<serde_json::Value>,
}

/// Accumulates what [`Summary`] needs while tracks stream past.
#[derive(Debug, Clone, Default)]
pub(crate) struct SummaryAcc {
    lengths: Vec<u64>,
    speed_sum: f64,
    points: u64,
}

impl SummaryAcc {
    pub(crate) fn add(&mut self, tracks: &[Track]) {
        for t in tracks {
            self.lengths.push(t.points.len() as u64);
            self.points += t.points.len() as u64;
            self.speed_sum += t.points.iter().map(|p| p.u.hypot(p.v)).sum::<f64>();
        }
    }
    pub(crate) fn summary(&self, stats: &TrackerStats) -> Summary {
        Summary::from_parts(&self.lengths, self.speed_sum, self.points, stats)
    }
}

impl Summary {
    /// The summary of a finished set of tracks and the tracker's counters
    /// (no provenance).
    #[cfg_attr(not(feature = "python"), allow(dead_code))]
    pub(crate) fn new(tracks: &[Track], stats: &TrackerStats) -> Self {
        let mut acc = SummaryAcc::default();
        acc.add(tracks);
        acc.summary(stats)
    }

    fn from_parts(lens: &[u64], speed_sum: f64, npts: u64, stats: &TrackerStats) -> Self {
        let max_len = lens.iter().copied().max().unwrap_or(0);
        let mut hist = Vec::new();
        // Bins 4-8, 8-16, 16-32, ...: lengths span orders of magnitude.
        let mut lo = 1u64;
        while lo <= max_len {
            let hi = lo * 2;
            let c = lens.iter().filter(|&&l| l >= lo && l < hi).count() as u64;
            hist.push((lo, hi, c));
            lo = hi;
        }
        Summary {
            pulses: stats.pulses,
            particles: stats.particles,
            tracks: lens.len() as u64,
            particles_on_tracks: stats.particles_on_tracks,
            fraction_on_tracks: if stats.particles > 0 {
                stats.particles_on_tracks as f64 / stats.particles as f64
            } else {
                0.0
            },
            mean_track_length: if lens.is_empty() {
                0.0
            } else {
                npts as f64 / lens.len() as f64
            },
            length_histogram: hist,
            mean_speed_px_s: if npts > 0 {
                speed_sum / npts as f64
            } else {
                0.0
            },
            tracker: stats.clone(),
            provenance: None,
        }
    }
}

/// Write `summary.json` atomically.
pub(crate) fn write_summary_json(path: &Path, summary: &Summary) -> Result<()> {
    let bytes = serde_json::to_vec_pretty(summary)
        .map_err(|e| Error::analysis(format!("summary.json: {e}")))?;
    AtomicFile::write_all_to(path, &bytes)
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;

    #[ebptv_macros::unit_test]
    fn particles_roundtrip_and_errors() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("particles.csv");
        let p = Particle {
            pulse: 4,
            t_us: 800.5,
            x: 1.25,
            y: 7.5,
            n_events: 2,
            n_pixels: 2,
            extent_x: 2.0,
            extent_y: 1.0,
            first_latency_us: 3.0,
        };
        write_particles_csv(&path, &[p]).unwrap();
        let back = read_particles(&path).unwrap();
        assert_eq!(
            (
                back[0].pulse,
                back[0].t_us,
                back[0].x,
                back[0].y,
                back[0].n_events
            ),
            (4, 800.5, 1.25, 7.5, 2)
        );

        std::fs::write(&path, "pulse,t_us,x,n_events\n1,2,3,4\n").unwrap();
        let e = read_particles(&path).unwrap_err().to_string();
        assert!(
            e.contains("missing column(s) y") && e.contains("particles.csv"),
            "{e}"
        );
        std::fs::write(&path, "pulse,t_us,x,y,n_events\n1,2,3,4,1\n2,3,NaN,4,1\n").unwrap();
        let e = read_particles(&path).unwrap_err().to_string();
        assert!(e.contains("line 3") && e.contains("`x`"), "{e}");
        std::fs::write(&path, "pulse,t_us,x,y,n_events\n1.5,2,3,4,1\n").unwrap();
        assert!(read_particles(&path)
            .unwrap_err()
            .to_string()
            .contains("not an integer"));
        std::fs::write(&path, "").unwrap();
        assert!(read_particles(&path)
            .unwrap_err()
            .to_string()
            .contains("empty"));
    }

    #[ebptv_macros::unit_test]
    fn tracks_roundtrip() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("tracks.csv");
        let pt = |pulse: i64, x: f64| TrackPoint {
            pulse,
            t_us: pulse as f64 * 100.0,
            x,
            y: 2.0,
            u: 1000.5,
            v: -3.25,
            ax: 0.0,
            ay: 0.0,
            interpolated: false,
        };
        let tracks = vec![
            Track {
                id: 0,
                points: vec![pt(0, 1.0), pt(1, 2.0)],
            },
            Track {
                id: 7,
                points: vec![pt(3, 5.0)],
            },
        ];
        write_tracks_csv(&path, &tracks).unwrap();
        assert_eq!(read_tracks(&path).unwrap(), tracks);
        std::fs::write(&path, "track_id,pulse,t_us,x,y,u\n").unwrap();
        assert!(read_tracks(&path)
            .unwrap_err()
            .to_string()
            .contains("missing column(s) v"));
    }

    /// Tracks with varied times, including pulses that share a slot of
    /// the time-text cache (pulse mod 4096) with different times and one
    /// time written at two pulses.
    fn varied_tracks() -> Vec<Track> {
        let mut tracks = Vec::new();
        for id in 0..40u64 {
            let start = (id as i64 * 997) % 9000 - 100;
            let points = (0..60)
                .map(|k| {
                    let pulse = start + k;
                    TrackPoint {
                        pulse,
                        t_us: pulse as f64 * 199.999_7 + (id % 3) as f64 * 1e-3 + 0.1,
                        x: 0.1 * pulse as f64 + id as f64,
                        y: 1279.99995 - 0.3 * k as f64,
                        u: -1234.5678 * k as f64,
                        v: 0.0005 * id as f64,
                        ax: 0.0,
                        ay: 0.0,
                        interpolated: k % 7 == 0,
                    }
                })
                .collect();
            tracks.push(Track { id, points });
        }
        tracks
    }

    #[ebptv_macros::unit_test]
    fn tracks_csv_matches_core_fmt() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("tracks.csv");
        // Enough rows for several write blocks, and values the row
        // formatter hands to `core::fmt` (not finite, huge, ties).
        let mut tracks = Vec::new();
        for copy in 0..12u64 {
            tracks.extend(varied_tracks().into_iter().map(|mut t| {
                t.id += 1000 * copy;
                t
            }));
        }
        let mut odd = varied_tracks().remove(3);
        odd.id = u64::MAX - 5;
        for (k, p) in odd.points.iter_mut().enumerate() {
            match k % 6 {
                0 => p.u = f64::NAN,
                1 => p.x = f64::INFINITY,
                2 => p.y = -0.0,
                3 => p.v = 3.0e20,
                4 => p.t_us = -1e-300,
                _ => p.x = 0.00005,
            }
        }
        tracks.push(odd);
        let mut w = TracksCsvWriter::create(&path).unwrap();
        for chunk in tracks.chunks(7) {
            w.write(chunk).unwrap();
        }
        w.finish().unwrap();
        let mut want = format!("{TRACKS_HEADER}\n");
        for t in &tracks {
            for p in &t.points {
                want += &format!(
                    "{},{},{},{:.4},{:.4},{:.3},{:.3}\n",
                    t.id as i64, p.pulse, p.t_us, p.x, p.y, p.u, p.v
                );
            }
        }
        assert_eq!(std::fs::read_to_string(&path).unwrap(), want);
    }

    /// particles.csv through the row formatter against `format!` row by
    /// row: several write blocks, pulses sharing and changing times,
    /// positions at every magnitude up to and past 10^4 px (8 digits at
    /// 4 decimals), rounding ties, non-finite and huge values, large
    /// counts and negative pulses.
    #[ebptv_macros::unit_test]
    fn particles_csv_matches_core_fmt() {
        use rand::{Rng, SeedableRng};
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("particles.csv");
        let mut rng = rand_pcg::Pcg64::seed_from_u64(11);
        let special = [
            f64::NAN,
            f64::INFINITY,
            -0.0,
            0.00005,
            1279.99995,
            9999.99995,
            12345.678949,
            3.0e20,
            -7.25,
        ];
        let mut pulses = Vec::new();
        for pulse in -3..2500i64 {
            let t_us = pulse as f64 * 199.999_7 + 0.1;
            let n = rng.gen_range(0..60);
            let ps: Vec<Particle> = (0..n)
                .map(|i| {
                    let mag = 10f64.powi(rng.gen_range(-5..6));
                    let mut xy = [rng.gen_range(0.0..1.0) * mag, rng.gen_range(0.0..1280.0)];
                    if i % 17 == 0 {
                        xy[i % 2] = special[(pulse as usize + i) % special.len()];
                    }
                    if i % 5 == 0 {
                        xy[1] = (xy[1] * 1e4).round() / 1e4 + 0.00005; // near a tie
                    }
                    Particle {
                        pulse,
                        t_us,
                        x: xy[0],
                        y: xy[1],
                        n_events: if i == 3 {
                            u32::MAX
                        } else {
                            rng.gen_range(1..200)
                        },
                        n_pixels: 1,
                        extent_x: 1.0,
                        extent_y: 1.0,
                        first_latency_us: 0.0,
                    }
                })
                .collect();
            pulses.push(ps);
        }
        let mut w = ParticlesCsvWriter::create(&path).unwrap();
        for ps in &pulses {
            w.write(ps).unwrap();
        }
        w.finish().unwrap();
        let mut want = format!("{PARTICLES_HEADER}\n");
        for p in pulses.iter().flatten() {
            want += &format!(
                "{},{},{:.4},{:.4},{}\n",
                p.pulse, p.t_us, p.x, p.y, p.n_events
            );
        }
        let got = std::fs::read_to_string(&path).unwrap();
        assert!(got.len() > 2 * WRITE_BLOCK, "{} bytes", got.len());
        assert_eq!(got, want);
    }

    #[ebptv_macros::unit_test]
    fn streamed_tracks_npy_matches_the_table_writer() {
        let dir = tempfile::tempdir().unwrap();
        let tracks = varied_tracks();
        let (a, b) = (dir.path().join("a.npy"), dir.path().join("b.npy"));
        write_tracks_npy(&a, &tracks).unwrap();
        let mut w = TracksNpyWriter::create(&b).unwrap();
        for chunk in tracks.chunks(9) {
            w.write(chunk).unwrap();
        }
        w.write(&[]).unwrap();
        w.finish().unwrap();
        let (a, b) = (std::fs::read(a).unwrap(), std::fs::read(b).unwrap());
        let (ha, hb) = (
            crate::io::npy::parse_npy_header(&a).unwrap(),
            crate::io::npy::parse_npy_header(&b).unwrap(),
        );
        assert_eq!(hb.shape, vec![40 * 60]);
        assert_eq!((&ha.descr, &ha.shape), (&hb.descr, &hb.shape));
        assert_eq!(hb.data_offset % 64, 0);
        assert_eq!(b.len() - hb.data_offset, 40 * 60 * 56);
        assert_eq!(a[ha.data_offset..], b[hb.data_offset..]);
        // Nothing written: a valid empty array.
        let c = dir.path().join("c.npy");
        TracksNpyWriter::create(&c).unwrap().finish().unwrap();
        let c = std::fs::read(c).unwrap();
        let hc = crate::io::npy::parse_npy_header(&c).unwrap();
        assert_eq!((hc.shape, c.len()), (vec![0], hc.data_offset));
    }

    #[ebptv_macros::unit_test]
    fn summary_histogram() {
        let mk = |n: usize| Track {
            id: 0,
            points: vec![
                TrackPoint {
                    pulse: 0,
                    t_us: 0.0,
                    x: 0.0,
                    y: 0.0,
                    u: 3.0,
                    v: 4.0,
                    ax: 0.0,
                    ay: 0.0,
                    interpolated: false
                };
                n
            ],
        };
        let s = Summary::new(
            &[mk(5), mk(6), mk(20)],
            &TrackerStats {
                particles: 40,
                particles_on_tracks: 30,
                ..Default::default()
            },
        );
        assert_eq!(s.tracks, 3);
        assert!((s.fraction_on_tracks - 0.75).abs() < 1e-12);
        assert!((s.mean_speed_px_s - 5.0).abs() < 1e-12);
        let c: Vec<u64> = s.length_histogram.iter().map(|h| h.2).collect();
        assert_eq!(c, vec![0, 0, 2, 0, 1]);
    }
}
