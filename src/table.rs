//! Row tables of the analysis stages (particles, tracks, …) in Parquet,
//! CSV or `.npy`, and a reader of all three.
//!
//! A table is a list of typed columns over a row type (`Col`): a name and
//! a function that reads the column's value from a row. Adding a column is
//! one more entry in that list; the Parquet schema, the `.npy` dtype and
//! the written values all follow from it.
//!
//! `TableWriter` streams: rows are gathered column by column into row
//! groups of `ROW_GROUP_ROWS` rows, each written out (Parquet) or
//! interleaved into records (`.npy`) when full, so memory stays bounded
//! whatever the row count. The file appears under its name only at
//! `TableWriter::finish` (through [`AtomicFile`]).
//!
//! Parquet files hold required (non-null) `INT64` and `DOUBLE` columns,
//! snappy-compressed Parquet 1.0 pages, floats PLAIN and integers
//! DELTA_BINARY_PACKED: what pandas/pyarrow, polars, DuckDB and MATLAB's
//! `parquetread` (Arrow inside) read without extra codecs.

use std::io::{BufReader, Read, Write};
use std::path::Path;
use std::sync::Arc;

use parquet::basic::{Compression, Encoding, Repetition, Type as PhysicalType};
use parquet::column::reader::ColumnReader;
use parquet::data_type::{DoubleType, Int64Type};
use parquet::file::metadata::KeyValue;
use parquet::file::properties::WriterProperties;
use parquet::file::reader::{FileReader, SerializedFileReader};
use parquet::file::writer::SerializedFileWriter;
use parquet::schema::types::{ColumnPath, Type as SchemaType};
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::io::atomic::AtomicFile;

/// Rows per Parquet row group (and per `.npy` write): ~3.5 MB of buffered
/// values for a 7-column table.
pub(crate) const ROW_GROUP_ROWS: usize = 1 << 16;

/// The file format of the row tables (`particles`, `tracks`, the grid,
/// PIV vectors, the simulation's truth).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum TableFormat {
    /// Apache Parquet (`.parquet`), snappy-compressed columns.
    #[default]
    Parquet,
    /// Comma-separated text with a header line (`.csv`).
    Csv,
    /// A NumPy structured array (`.npy`).
    Npy,
}

impl TableFormat {
    /// The file extension (without the dot).
    #[ebptv_macros::testkit]
    pub(crate) fn ext(self) -> &'static str {
        match self {
            TableFormat::Parquet => "parquet",
            TableFormat::Csv => "csv",
            TableFormat::Npy => "npy",
        }
    }

    /// `stem.ext` for this format, e.g. `tracks.parquet`.
    #[ebptv_macros::testkit]
    pub(crate) fn file_name(self, stem: &str) -> String {
        format!("{stem}.{}", self.ext())
    }

    /// The format of an existing table file, from its first bytes
    /// (`PAR1`, `\x93NUMPY`; anything else is read as CSV).
    pub(crate) fn sniff(path: &Path) -> Result<TableFormat> {
        let mut f = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
        let mut head = [0u8; 6];
        let mut n = 0;
        while n < head.len() {
            match f.read(&mut head[n..]) {
                Ok(0) => break,
                Ok(k) => n += k,
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) => return Err(Error::io(path, e)),
            }
        }
        Ok(if head[..n].starts_with(b"PAR1") {
            TableFormat::Parquet
        } else if head[..n].starts_with(b"\x93NUMPY") {
            TableFormat::Npy
        } else {
            TableFormat::Csv
        })
    }
}

/// How a column's value is read from a row, and its type in the file.
#[ebptv_macros::testkit]
pub(crate) enum Getter<R> {
    /// A 64-bit signed integer (Parquet `INT64`, npy `<i8`).
    I64(fn(&R) -> i64),
    /// A 64-bit float (Parquet `DOUBLE`, npy `<f8`).
    F64(fn(&R) -> f64),
}

/// One column of a table over rows of type `R`.
#[ebptv_macros::testkit]
pub(crate) struct Col<R> {
    /// Column name in the table's header.
    pub name: &'static str,
    /// How a row gives this column's value.
    pub get: Getter<R>,
}

impl<R> Col<R> {
    pub(crate) const fn i64(name: &'static str, get: fn(&R) -> i64) -> Self {
        Col {
            name,
            get: Getter::I64(get),
        }
    }
    pub(crate) const fn f64(name: &'static str, get: fn(&R) -> f64) -> Self {
        Col {
            name,
            get: Getter::F64(get),
        }
    }
}

/// A column's buffered values.
enum Values {
    I64(Vec<i64>),
    F64(Vec<f64>),
}

/// Rows gathered column by column.
struct Batch<R: 'static> {
    cols: &'static [Col<R>],
    values: Vec<Values>,
    rows: usize,
}

impl<R> Batch<R> {
    fn new(cols: &'static [Col<R>]) -> Self {
        let values = cols
            .iter()
            .map(|c| match c.get {
                Getter::I64(_) => Values::I64(Vec::with_capacity(ROW_GROUP_ROWS)),
                Getter::F64(_) => Values::F64(Vec::with_capacity(ROW_GROUP_ROWS)),
            })
            .collect();
        Batch {
            cols,
            values,
            rows: 0,
        }
    }

    fn push(&mut self, row: &R) {
        for (c, v) in self.cols.iter().zip(&mut self.values) {
            match (&c.get, v) {
                (Getter::I64(f), Values::I64(v)) => v.push(f(row)),
                (Getter::F64(f), Values::F64(v)) => v.push(f(row)),
                _ => unreachable!("buffers are made from the columns"),
            }
        }
        self.rows += 1;
    }

    fn clear(&mut self) {
        for v in &mut self.values {
            match v {
                Values::I64(v) => v.clear(),
                Values::F64(v) => v.clear(),
            }
        }
        self.rows = 0;
    }
}

/// The compression of the Parquet tables.
pub(crate) const PARQUET_COMPRESSION: Compression = Compression::SNAPPY;

fn parquet_err(path: &Path, e: parquet::errors::ParquetError) -> Error {
    match e {
        parquet::errors::ParquetError::External(inner) => {
            match inner.downcast::<std::io::Error>() {
                Ok(io) => Error::io(path, *io),
                Err(other) => Error::io(path, std::io::Error::other(other.to_string())),
            }
        }
        e => Error::io(path, std::io::Error::other(e.to_string())),
    }
}

/// A streaming Parquet (or `.npy`) writer of a table over rows of type `R`.
#[ebptv_macros::testkit]
pub(crate) struct TableWriter<R: 'static> {
    batch: Batch<R>,
    out: Sink,
}

enum Sink {
    Parquet(Box<SerializedFileWriter<AtomicFile>>),
    Npy {
        file: AtomicFile,
        descr: String,
        header_len: usize,
        rows: usize,
        buf: Vec<u8>,
    },
}

impl<R> TableWriter<R> {
    /// A Parquet file at `path` with the columns `cols`.
    pub(crate) fn parquet(path: &Path, cols: &'static [Col<R>]) -> Result<Self> {
        Self::parquet_with(path, cols, PARQUET_COMPRESSION)
    }

    /// A Parquet file with the given compression (for measurements).
    #[ebptv_macros::testkit]
    pub(crate) fn parquet_with(
        path: &Path,
        cols: &'static [Col<R>],
        compression: Compression,
    ) -> Result<Self> {
        let fields = cols
            .iter()
            .map(|c| {
                let ty = match c.get {
                    Getter::I64(_) => PhysicalType::INT64,
                    Getter::F64(_) => PhysicalType::DOUBLE,
                };
                SchemaType::primitive_type_builder(c.name, ty)
                    .with_repetition(Repetition::REQUIRED)
                    .build()
                    .map(Arc::new)
            })
            .collect::<std::result::Result<Vec<_>, _>>()
            .map_err(|e| parquet_err(path, e))?;
        let schema = SchemaType::group_type_builder("schema")
            .with_fields(fields)
            .build()
            .map_err(|e| parquet_err(path, e))?;
        // No dictionaries: float columns rarely repeat a value (a
        // dictionary would be built and dropped for every page), and the
        // integer columns (ids, pulses, counts) run in steps of 0 or 1, which
        // DELTA_BINARY_PACKED stores in a few bits per value at a fraction
        // of a dictionary's hashing.
        let mut props = WriterProperties::builder()
            .set_compression(compression)
            .set_max_row_group_row_count(Some(ROW_GROUP_ROWS))
            .set_dictionary_enabled(false);
        for c in cols {
            if let Getter::I64(_) = c.get {
                props = props
                    .set_column_encoding(ColumnPath::from(c.name), Encoding::DELTA_BINARY_PACKED);
            }
        }
        let props = props.build();
        let file = AtomicFile::create(path)?;
        let w = SerializedFileWriter::new(file, Arc::new(schema), Arc::new(props))
            .map_err(|e| parquet_err(path, e))?;
        Ok(TableWriter {
            batch: Batch::new(cols),
            out: Sink::Parquet(Box::new(w)),
        })
    }

    /// A `.npy` file at `path`: a 1-D structured array with one field per
    /// column (`<i8` or `<f8`), its length patched in at the end.
    pub(crate) fn npy(path: &Path, cols: &'static [Col<R>]) -> Result<Self> {
        let descr = npy_descr(cols);
        let mut file = AtomicFile::create(path)?;
        let header = crate::io::npy::table_header(&descr, usize::MAX, 0);
        file.write_all(&header).map_err(|e| Error::io(path, e))?;
        Ok(TableWriter {
            batch: Batch::new(cols),
            out: Sink::Npy {
                file,
                descr,
                header_len: header.len(),
                rows: 0,
                buf: Vec::new(),
            },
        })
    }

    /// Records `key = value` in the file's metadata (Parquet
    /// `key_value_metadata`; `.npy` has no place for it and ignores it).
    pub(crate) fn add_metadata(&mut self, key: &str, value: &str) {
        if let Sink::Parquet(w) = &mut self.out {
            w.append_key_value_metadata(KeyValue::new(key.to_string(), value.to_string()));
        }
    }

    /// Appends the rows.
    #[ebptv_macros::testkit]
    pub(crate) fn write<'r>(&mut self, rows: impl IntoIterator<Item = &'r R>) -> Result<()>
    where
        R: 'r,
    {
        for r in rows {
            self.push(r)?;
        }
        Ok(())
    }

    /// Appends one row.
    #[inline]
    pub(crate) fn push(&mut self, row: &R) -> Result<()> {
        self.batch.push(row);
        if self.batch.rows >= ROW_GROUP_ROWS {
            self.flush()?;
        }
        Ok(())
    }

    fn flush(&mut self) -> Result<()> {
        if self.batch.rows == 0 {
            return Ok(());
        }
        match &mut self.out {
            Sink::Parquet(w) => {
                let path = w.inner().target().to_path_buf();
                let pe = |e| parquet_err(&path, e);
                let mut rg = w.next_row_group().map_err(pe)?;
                for v in &self.batch.values {
                    let mut col = rg
                        .next_column()
                        .map_err(pe)?
                        .ok_or_else(|| Error::analysis("parquet schema has fewer columns"))?;
                    match v {
                        Values::I64(v) => {
                            col.typed::<Int64Type>()
                                .write_batch(v, None, None)
                                .map_err(pe)?;
                        }
                        Values::F64(v) => {
                            col.typed::<DoubleType>()
                                .write_batch(v, None, None)
                                .map_err(pe)?;
                        }
                    }
                    col.close().map_err(pe)?;
                }
                rg.close().map_err(pe)?;
            }
            Sink::Npy {
                file, rows, buf, ..
            } => {
                buf.clear();
                buf.reserve(self.batch.rows * 8 * self.batch.values.len());
                for i in 0..self.batch.rows {
                    for v in &self.batch.values {
                        match v {
                            Values::I64(v) => buf.extend_from_slice(&v[i].to_le_bytes()),
                            Values::F64(v) => buf.extend_from_slice(&v[i].to_le_bytes()),
                        }
                    }
                }
                file.write_all(buf)
                    .map_err(|e| Error::io(file.target(), e))?;
                *rows += self.batch.rows;
            }
        }
        self.batch.clear();
        Ok(())
    }

    /// Writes the last rows and the footer, and gives the file its name.
    #[ebptv_macros::testkit]
    pub(crate) fn finish(mut self) -> Result<()> {
        self.flush()?;
        match self.out {
            Sink::Parquet(w) => {
                let path = w.inner().target().to_path_buf();
                let file = w.into_inner().map_err(|e| parquet_err(&path, e))?;
                file.commit()
            }
            Sink::Npy {
                file,
                descr,
                header_len,
                rows,
                ..
            } => crate::io::npy::commit_streamed_table(file, &descr, rows, header_len),
        }
    }
}

/// Writes the table `stem` into `dir` in `format` (`stem.parquet`,
/// `stem.csv` or `stem.npy`) and returns its path. Parquet and `.npy` are
/// written from `cols` over `rows`; CSV by `csv`, the table's own text
/// writer, so that the CSV contract (number formatting included) stays
/// what it is. `rows` is not consumed for CSV.
pub(crate) fn write_table<R, I>(
    dir: &Path,
    stem: &str,
    format: TableFormat,
    cols: &'static [Col<R>],
    rows: I,
    csv: impl FnOnce(&Path) -> Result<()>,
) -> Result<std::path::PathBuf>
where
    I: IntoIterator<Item = R>,
{
    let path = dir.join(format.file_name(stem));
    let mut w = match format {
        TableFormat::Csv => {
            csv(&path)?;
            return Ok(path);
        }
        TableFormat::Parquet => TableWriter::parquet(&path, cols)?,
        TableFormat::Npy => TableWriter::npy(&path, cols)?,
    };
    for r in rows {
        w.push(&r)?;
    }
    w.finish()?;
    Ok(path)
}

fn npy_descr<R>(cols: &[Col<R>]) -> String {
    let fields: Vec<String> = cols
        .iter()
        .map(|c| {
            let t = match c.get {
                Getter::I64(_) => "<i8",
                Getter::F64(_) => "<f8",
            };
            format!("('{}', '{t}')", c.name)
        })
        .collect();
    format!("[{}]", fields.join(", "))
}

/// The column names of a table file of any format (`None` for a CSV
/// without a header line or a file that cannot be read).
pub(crate) fn column_names(path: &Path) -> Option<Vec<String>> {
    match TableFormat::sniff(path).ok()? {
        TableFormat::Parquet => {
            let f = std::fs::File::open(path).ok()?;
            let r = SerializedFileReader::new(f).ok()?;
            let schema = r.metadata().file_metadata().schema_descr_ptr();
            Some(
                schema
                    .columns()
                    .iter()
                    .map(|c| c.name().to_string())
                    .collect(),
            )
        }
        TableFormat::Npy => {
            let mut head = vec![0u8; 4096];
            let mut f = std::fs::File::open(path).ok()?;
            let n = f.read(&mut head).ok()?;
            let h = crate::io::npy::parse_npy_header(&head[..n])?;
            Some(
                parse_npy_fields(&h.descr)?
                    .into_iter()
                    .map(|f| f.0)
                    .collect(),
            )
        }
        TableFormat::Csv => {
            let f = std::fs::File::open(path).ok()?;
            let mut line = String::new();
            std::io::BufRead::read_line(&mut BufReader::new(f), &mut line).ok()?;
            Some(
                line.trim()
                    .trim_start_matches('\u{feff}')
                    .split(',')
                    .map(|c| c.trim().to_string())
                    .collect(),
            )
        }
    }
}

/// The fields of a structured npy `descr`: name and dtype, e.g.
/// `[('x', '<f8'), ('n', '<i8')]`.
fn parse_npy_fields(descr: &str) -> Option<Vec<(String, String)>> {
    let d = descr.trim();
    let inner = d.strip_prefix('[')?.strip_suffix(']')?;
    let mut out = Vec::new();
    for part in inner.split(')') {
        let part = part.trim().trim_start_matches(',').trim();
        if part.is_empty() {
            continue;
        }
        let part = part.strip_prefix('(')?;
        let mut it = part
            .split(',')
            .map(|s| s.trim().trim_matches('\'').trim_matches('"'));
        let name = it.next()?.to_string();
        let ty = it.next()?.to_string();
        if it.next().is_some_and(|s| !s.is_empty()) {
            return None; // sub-array fields are not table columns
        }
        out.push((name, ty));
    }
    Some(out)
}

/// The columns `names` of a Parquet or `.npy` table, as f64 (integer
/// columns converted), in the order asked. Missing columns are an error
/// naming the file.
pub(crate) fn read_columns(path: &Path, names: &[&str]) -> Result<Vec<Vec<f64>>> {
    match TableFormat::sniff(path)? {
        TableFormat::Parquet => read_parquet_columns(path, names),
        TableFormat::Npy => read_npy_columns(path, names),
        TableFormat::Csv => Err(Error::analysis(format!(
            "{}: a CSV file, not a Parquet or .npy table",
            path.display()
        ))),
    }
}

fn missing(path: &Path, names: &[&str], have: &[String]) -> Error {
    let miss: Vec<&str> = names
        .iter()
        .filter(|n| !have.iter().any(|h| h == *n))
        .copied()
        .collect();
    Error::corrupt(
        path,
        0,
        format!(
            "missing column(s) {} (columns are {}, expected {})",
            miss.join(", "),
            have.join(","),
            names.join(",")
        ),
    )
}

fn read_parquet_columns(path: &Path, names: &[&str]) -> Result<Vec<Vec<f64>>> {
    let bad = |e: parquet::errors::ParquetError| {
        Error::corrupt(path, 0, format!("not a readable Parquet table: {e}"))
    };
    let f = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let reader = SerializedFileReader::new(f).map_err(bad)?;
    let meta = reader.metadata();
    let schema = meta.file_metadata().schema_descr_ptr();
    let have: Vec<String> = schema
        .columns()
        .iter()
        .map(|c| c.name().to_string())
        .collect();
    let mut idx = Vec::with_capacity(names.len());
    for n in names {
        match schema
            .columns()
            .iter()
            .position(|c| c.name() == *n && c.max_rep_level() == 0)
        {
            Some(i) => idx.push(i),
            None => return Err(missing(path, names, &have)),
        }
    }
    let rows = meta.file_metadata().num_rows().max(0) as usize;
    let mut out: Vec<Vec<f64>> = names.iter().map(|_| Vec::with_capacity(rows)).collect();
    let mut defs = Vec::new();
    for g in 0..meta.num_row_groups() {
        let rg = reader.get_row_group(g).map_err(bad)?;
        let n = rg.metadata().num_rows().max(0) as usize;
        for (k, &i) in idx.iter().enumerate() {
            let max_def = schema.column(i).max_def_level();
            let col = rg.get_column_reader(i).map_err(bad)?;
            let dst = &mut out[k];
            let start = dst.len();
            let name = names[k];
            defs.clear();
            let def = (max_def > 0).then_some(&mut defs);
            macro_rules! read_as_f64 {
                ($r:expr, $t:ty) => {{
                    let mut r = $r;
                    let mut vals: Vec<$t> = Vec::with_capacity(n);
                    let mut def = def;
                    let mut got = 0;
                    while got < n {
                        let (recs, _, _) = r
                            .read_records(n - got, def.as_deref_mut(), None, &mut vals)
                            .map_err(bad)?;
                        if recs == 0 {
                            break;
                        }
                        got += recs;
                    }
                    if max_def > 0 {
                        // Optional column: nulls come back as NaN.
                        let mut it = vals.into_iter();
                        for &d in defs.iter() {
                            dst.push(if d == max_def {
                                it.next().map_or(f64::NAN, |v| v as f64)
                            } else {
                                f64::NAN
                            });
                        }
                    } else {
                        dst.extend(vals.into_iter().map(|v| v as f64));
                    }
                }};
            }
            match col {
                ColumnReader::Int64ColumnReader(r) => read_as_f64!(r, i64),
                ColumnReader::Int32ColumnReader(r) => read_as_f64!(r, i32),
                ColumnReader::DoubleColumnReader(r) => read_as_f64!(r, f64),
                ColumnReader::FloatColumnReader(r) => read_as_f64!(r, f32),
                _ => {
                    return Err(Error::corrupt(
                        path,
                        0,
                        format!("column `{name}` is not numeric"),
                    ))
                }
            }
            if dst.len() - start != n {
                return Err(Error::corrupt(
                    path,
                    0,
                    format!(
                        "column `{name}`: {} values in row group {g}, expected {n}",
                        dst.len() - start
                    ),
                ));
            }
        }
    }
    Ok(out)
}

fn read_npy_columns(path: &Path, names: &[&str]) -> Result<Vec<Vec<f64>>> {
    let bytes = std::fs::read(path).map_err(|e| Error::io(path, e))?;
    let h = crate::io::npy::parse_npy_header(&bytes)
        .ok_or_else(|| Error::corrupt(path, 0, "not a readable .npy header"))?;
    let fields = parse_npy_fields(&h.descr).ok_or_else(|| {
        Error::corrupt(
            path,
            0,
            format!("dtype {} is not a table of named fields", h.descr),
        )
    })?;
    if h.shape.len() != 1 {
        return Err(Error::corrupt(
            path,
            0,
            format!("a table is a 1-D array; shape is {:?}", h.shape),
        ));
    }
    let mut offs = Vec::with_capacity(fields.len());
    let mut rec = 0usize;
    for (name, ty) in &fields {
        let size = ty
            .trim_start_matches(['<', '>', '|', '='])
            .get(1..)
            .and_then(|s| s.parse::<usize>().ok())
            .ok_or_else(|| Error::corrupt(path, 0, format!("field `{name}`: dtype {ty}")))?;
        offs.push(rec);
        rec += size;
    }
    let have: Vec<String> = fields.iter().map(|f| f.0.clone()).collect();
    let rows = h.shape[0];
    let data = &bytes[h.data_offset.min(bytes.len())..];
    if data.len() < rows.saturating_mul(rec) {
        return Err(Error::corrupt(
            path,
            bytes.len() as u64,
            format!("truncated: {rows} records of {rec} bytes do not fit"),
        ));
    }
    let mut out = Vec::with_capacity(names.len());
    for n in names {
        let Some(k) = fields.iter().position(|f| f.0 == *n) else {
            return Err(missing(path, names, &have));
        };
        let ty = fields[k].1.as_str();
        let off = offs[k];
        let le = !ty.starts_with('>');
        let kind = ty.trim_start_matches(['<', '>', '|', '=']);
        let get = |i: usize, w: usize| &data[i * rec + off..i * rec + off + w];
        macro_rules! col {
            ($t:ty, $w:expr) => {
                (0..rows)
                    .map(|i| {
                        let b: [u8; $w] = get(i, $w).try_into().expect("width");
                        (if le {
                            <$t>::from_le_bytes(b)
                        } else {
                            <$t>::from_be_bytes(b)
                        }) as f64
                    })
                    .collect::<Vec<f64>>()
            };
        }
        let v = match kind {
            "f8" => col!(f64, 8),
            "f4" => col!(f32, 4),
            "i8" => col!(i64, 8),
            "u8" => col!(u64, 8),
            "i4" => col!(i32, 4),
            "u4" => col!(u32, 4),
            "i2" => col!(i16, 2),
            "u2" => col!(u16, 2),
            "i1" => col!(i8, 1),
            "u1" => col!(u8, 1),
            _ => {
                return Err(Error::corrupt(
                    path,
                    0,
                    format!("field `{n}` has dtype {ty}, not a number"),
                ))
            }
        };
        out.push(v);
    }
    Ok(out)
}

/// The key/value metadata of a Parquet file (for tests and checks).
#[ebptv_macros::testkit]
pub(crate) fn parquet_metadata(path: &Path) -> Result<Vec<(String, Option<String>)>> {
    let f = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
    let r = SerializedFileReader::new(f)
        .map_err(|e| Error::corrupt(path, 0, format!("not a readable Parquet file: {e}")))?;
    Ok(r.metadata()
        .file_metadata()
        .key_value_metadata()
        .map(|kv| {
            kv.iter()
                .map(|k| (k.key.clone(), k.value.clone()))
                .collect()
        })
        .unwrap_or_default())
}

/// Columns of the simulator's truth table (`truth_particles`):
/// `pulse,t_us,particle_id,x,y,u,v` (µs, px, px/s).
static TRUTH_COLUMNS: [Col<crate::sim::TruthSample>; 7] = [
    Col::i64("pulse", |r| r.pulse),
    Col::f64("t_us", |r| r.t_us),
    Col::i64("particle_id", |r| r.particle_id as i64),
    Col::f64("x", |r| r.x),
    Col::f64("y", |r| r.y),
    Col::f64("u", |r| r.u),
    Col::f64("v", |r| r.v),
];

impl crate::sim::TruthTable for TableWriter<crate::sim::TruthSample> {
    fn write(&mut self, rows: &[crate::sim::TruthSample]) -> Result<()> {
        TableWriter::write(self, rows)
    }
    fn finish(self: Box<Self>) -> Result<()> {
        TableWriter::finish(*self)
    }
}

/// What `ebptv simulate` writes ([`crate::sim::write_recording`]), the
/// truth as the table `truth_particles` in `tables` (CSV: the simulator's
/// own `truth_particles.csv`, values rounded as its contract says;
/// Parquet and `.npy` keep every bit). Returns the summary and the truth
/// table's path.
pub fn write_recording(
    sc: &crate::sim::Scenario,
    seed: u64,
    dir: &Path,
    format: crate::io::Format,
    tables: TableFormat,
    progress: impl FnMut(u64, u64),
) -> Result<(crate::sim::RecordingSummary, std::path::PathBuf)> {
    let path = dir.join(tables.file_name("truth_particles"));
    let make = |d: &Path| -> Result<Box<dyn crate::sim::TruthTable>> {
        let p = d.join(tables.file_name("truth_particles"));
        Ok(match tables {
            TableFormat::Npy => Box::new(TableWriter::npy(&p, &TRUTH_COLUMNS)?),
            _ => Box::new(TableWriter::parquet(&p, &TRUTH_COLUMNS)?),
        })
    };
    let truth: Option<crate::sim::TruthTableMaker<'_>> = match tables {
        TableFormat::Csv => None,
        _ => Some(&make),
    };
    let summary = crate::sim::write_recording_with(sc, seed, dir, format, truth, progress)?;
    Ok((summary, path))
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;

    #[derive(Clone, Copy)]
    struct Row {
        id: i64,
        x: f64,
    }
    static COLS: [Col<Row>; 2] = [Col::i64("id", |r| r.id), Col::f64("x", |r| r.x)];

    fn rows(n: usize) -> Vec<Row> {
        (0..n)
            .map(|i| Row {
                id: i as i64 - 5,
                x: i as f64 * 0.25 - 1e-9,
            })
            .collect()
    }

    #[ebptv_macros::unit_test]
    fn parquet_and_npy_roundtrip_over_several_row_groups() {
        let dir = tempfile::tempdir().unwrap();
        let n = 2 * ROW_GROUP_ROWS + 17;
        let data = rows(n);
        for fmt in [TableFormat::Parquet, TableFormat::Npy] {
            let p = dir.path().join(fmt.file_name("t"));
            let mut w = match fmt {
                TableFormat::Parquet => TableWriter::parquet(&p, &COLS).unwrap(),
                _ => TableWriter::npy(&p, &COLS).unwrap(),
            };
            w.write(&data).unwrap();
            assert!(!p.exists(), "appears only when finished");
            w.finish().unwrap();
            assert_eq!(TableFormat::sniff(&p).unwrap(), fmt);
            assert_eq!(column_names(&p).unwrap(), vec!["id", "x"]);
            let c = read_columns(&p, &["x", "id"]).unwrap();
            assert_eq!(c[0].len(), n);
            for (i, r) in data.iter().enumerate() {
                assert_eq!((c[1][i], c[0][i]), (r.id as f64, r.x), "{fmt:?} row {i}");
            }
            let e = read_columns(&p, &["id", "y"]).unwrap_err().to_string();
            assert!(e.contains("missing column(s) y") && e.contains("t."), "{e}");
        }
        let r =
            SerializedFileReader::new(std::fs::File::open(dir.path().join("t.parquet")).unwrap())
                .unwrap();
        assert_eq!(r.metadata().num_row_groups(), 3);
    }

    #[ebptv_macros::unit_test]
    fn parquet_key_value_metadata() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("m.parquet");
        let mut w = TableWriter::parquet(&p, &COLS).unwrap();
        w.add_metadata("ebptv.test", "{\"a\": 1}");
        w.write(&rows(3)).unwrap();
        w.add_metadata("second", "2");
        w.finish().unwrap();
        let kv = parquet_metadata(&p).unwrap();
        assert!(
            kv.contains(&("ebptv.test".into(), Some("{\"a\": 1}".into()))),
            "{kv:?}"
        );
        assert!(kv.contains(&("second".into(), Some("2".into()))), "{kv:?}");
    }

    #[ebptv_macros::unit_test]
    fn empty_tables_and_bad_files() {
        let dir = tempfile::tempdir().unwrap();
        for fmt in [TableFormat::Parquet, TableFormat::Npy] {
            let p = dir.path().join(fmt.file_name("e"));
            let w = match fmt {
                TableFormat::Parquet => TableWriter::parquet(&p, &COLS).unwrap(),
                _ => TableWriter::npy(&p, &COLS).unwrap(),
            };
            w.finish().unwrap();
            let c = read_columns(&p, &["id", "x"]).unwrap();
            assert!(c[0].is_empty() && c[1].is_empty(), "{fmt:?}");
        }
        // Dropped unfinished: no file.
        let p = dir.path().join("gone.parquet");
        let mut w = TableWriter::parquet(&p, &COLS).unwrap();
        w.write(&rows(10)).unwrap();
        drop(w);
        assert!(!p.exists());
        // A truncated Parquet file is an error naming the file.
        let good = dir.path().join("e.parquet");
        let bytes = std::fs::read(&good).unwrap();
        let cut = dir.path().join("cut.parquet");
        std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
        let e = read_columns(&cut, &["id"]).unwrap_err().to_string();
        assert!(e.contains("cut.parquet"), "{e}");
        // A truncated npy as well.
        let p = dir.path().join("n.npy");
        let mut w = TableWriter::npy(&p, &COLS).unwrap();
        w.write(&rows(100)).unwrap();
        w.finish().unwrap();
        let bytes = std::fs::read(&p).unwrap();
        std::fs::write(&p, &bytes[..bytes.len() - 5]).unwrap();
        let e = read_columns(&p, &["id"]).unwrap_err().to_string();
        assert!(e.contains("n.npy") && e.contains("truncated"), "{e}");
    }

    #[ebptv_macros::unit_test]
    fn truth_tables_hold_the_csv_values_in_every_format() {
        let dir = tempfile::tempdir().unwrap();
        let mut sc = crate::sim::presets::preset("demo").unwrap();
        sc.duration_s = 0.002;
        let mut tables = Vec::new();
        for fmt in [TableFormat::Csv, TableFormat::Parquet, TableFormat::Npy] {
            let d = dir.path().join(fmt.ext());
            let (summary, path) =
                write_recording(&sc, 4, &d, crate::io::Format::Evt3, fmt, |_, _| {}).unwrap();
            assert_eq!(path, d.join(fmt.file_name("truth_particles")));
            assert_eq!(TableFormat::sniff(&path).unwrap(), fmt);
            let t = crate::compare::read_table(&path, &[]).unwrap();
            assert_eq!(t.rows() as u64, summary.stats.truth_samples);
            assert_eq!(
                t.names,
                ["pulse", "t_us", "particle_id", "x", "y", "u", "v"]
            );
            tables.push(t);
        }
        assert!(tables[0].rows() > 100);
        // The CSV rounds to its decimals; Parquet and .npy keep every bit.
        let decimals = [0, 3, 0, 4, 4, 3, 3];
        for (k, d) in decimals.iter().enumerate() {
            let tol = 0.5 * 10f64.powi(-d) * (1.0 + 1e-9);
            for (a, b) in tables[0].cols[k].iter().zip(&tables[1].cols[k]) {
                assert!((a - b).abs() <= tol, "{}: {a} vs {b}", tables[0].names[k]);
            }
            assert_eq!(tables[1].cols[k], tables[2].cols[k]);
        }
    }

    #[ebptv_macros::unit_test]
    fn npy_fields_parse() {
        assert_eq!(
            parse_npy_fields("[('t', '<i8'), ('x', '<u2'), ('p', '|u1')]").unwrap(),
            vec![
                ("t".to_string(), "<i8".to_string()),
                ("x".into(), "<u2".into()),
                ("p".into(), "|u1".into())
            ]
        );
        assert!(parse_npy_fields("'<f8'").is_none());
    }
}
