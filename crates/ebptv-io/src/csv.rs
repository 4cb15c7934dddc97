//! CSV events: reader (columns by header name) and writer (`t,x,y,p`).
//!
//! # Reading
//! Columns are found by their header names, case-insensitive, in any order;
//! extra columns are ignored:
//! - time: `t`, `ts`, `time`, `timestamp`, optionally with a unit suffix
//!   (`t_us`, `t_ms`, `t_s`, `t_ns`, `timestamp_s`, `time[us]`, `t(s)` …);
//! - `x`; `y`;
//! - polarity: `p`, `pol`, `polarity`, `on`, `is_increase`, `sign`
//!   (values `1`/`0`, `1`/`-1`, `true`/`false`, `on`/`off`; > 0 is ON).
//!
//! The separator is `,`, else tab, else `;`, else runs of spaces, chosen from
//! the first line. Lines starting with `#` or `%` are comments; a comment
//! such as `% geometry 1280x720` or `%geometry:1280,720` gives the geometry.
//!
//! **Time unit.** From the header name's suffix, else from
//! [`crate::OpenOptions::csv_time_unit`], else microseconds *assumed*.
//! A fractional time value (`0.000123`) with an assumed unit is an error
//! rather than a silent guess: name the column (`t_s`) or pass the unit.
//! Seconds are converted exactly from their decimal digits (no float
//! rounding), rounded to the nearest microsecond.
//!
//! **No header line.** A file whose first line is all numbers is assumed to
//! be openeb's `x,y,p,t` (t in µs, or the unit passed). That assumption is
//! recorded in [`StreamInfo::header`] (`columns`), and checked on every row:
//! a polarity other than -1/0/1 or a fractional time is an error naming the
//! line and telling the user to add a header line.
//!
//! **Triggers.** openeb writes triggers to a separate CSV (`p,id,t`). The
//! reader picks up `<stem>_triggers.csv` beside the event file when it
//! exists (header names `t`, `id`/`channel`, `p`/`edge`/`value`; without a
//! header: openeb's `p,id,t`) and delivers its triggers interleaved by time:
//! with each event chunk come the triggers up to the chunk's last event time.
//! `read_trigger_csv` reads such a file on its own.
//!
//! # Writing
//! `CsvWriter` writes `t,x,y,p` (t in µs, p 1 = ON / 0 = OFF) with a
//! header line, and the triggers to `<stem>_triggers.csv` with `t,id,p`
//! (p 1 = rising, 0 = falling). Both go through [`AtomicFile`]. When the
//! stream holds no trigger, a `<stem>_triggers.csv` left from an earlier
//! output of the same name is removed, so the reader never pairs new events
//! with stale triggers.

use std::fs::File;
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};

use crate::atomic::AtomicFile;
use crate::error::{Error, Result};
use crate::events::{Chunk, Edge, Geometry, Trigger, OFF, ON};
use crate::npy::sidecar_path;
use crate::{EventSource, Format, StreamInfo};

/// Unit of a CSV time column.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TimeUnit {
    /// Times in µs.
    Microseconds,
    /// Times in s.
    Seconds,
    /// Times in ms.
    Milliseconds,
    /// Times in ns.
    Nanoseconds,
}

impl TimeUnit {
    /// Power of ten that turns a value in this unit into microseconds.
    fn exponent_to_us(self) -> i32 {
        match self {
            TimeUnit::Seconds => 6,
            TimeUnit::Milliseconds => 3,
            TimeUnit::Microseconds => 0,
            TimeUnit::Nanoseconds => -3,
        }
    }
    /// The unit's name as written in headers and options.
    pub(crate) fn name(self) -> &'static str {
        match self {
            TimeUnit::Seconds => "s",
            TimeUnit::Milliseconds => "ms",
            TimeUnit::Microseconds => "us",
            TimeUnit::Nanoseconds => "ns",
        }
    }
    fn from_suffix(s: &str) -> Option<TimeUnit> {
        Some(match s {
            "us" | "µs" | "usec" | "micros" | "microseconds" => TimeUnit::Microseconds,
            "ms" | "msec" | "millis" | "milliseconds" => TimeUnit::Milliseconds,
            "s" | "sec" | "secs" | "seconds" => TimeUnit::Seconds,
            "ns" | "nsec" | "nanos" | "nanoseconds" => TimeUnit::Nanoseconds,
            _ => return None,
        })
    }
}

impl std::str::FromStr for TimeUnit {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        TimeUnit::from_suffix(&s.to_ascii_lowercase())
            .ok_or_else(|| Error::param("time-unit", format!("`{s}`: expected us, ms, s or ns")))
    }
}

/// Longest accepted line: a longer one is not an event CSV.
const MAX_LINE: u64 = 1 << 16;

/// Reads text lines with line numbers, skipping blank and comment lines.
struct LineReader {
    path: PathBuf,
    reader: BufReader<File>,
    line: Vec<u8>,
    line_no: u64,
    /// Byte range of the current (trimmed) line in `line`.
    cur: (usize, usize),
    offset: u64,
    /// Geometry found in a comment line.
    geometry: Option<Geometry>,
}

impl LineReader {
    fn open(path: &Path) -> Result<(Self, Option<u64>)> {
        let file = File::open(path).map_err(|e| Error::io(path, e))?;
        let size = file.metadata().ok().map(|m| m.len());
        Ok((
            LineReader {
                path: path.to_path_buf(),
                reader: BufReader::with_capacity(1 << 16, file),
                line: Vec::with_capacity(128),
                line_no: 0,
                cur: (0, 0),
                offset: 0,
                geometry: None,
            },
            size,
        ))
    }

    /// The next non-blank, non-comment line (trimmed), or `None` at the end.
    fn next_line(&mut self) -> Result<Option<&str>> {
        Ok(if self.advance()? {
            Some(self.current())
        } else {
            None
        })
    }

    /// The current line, trimmed (valid after `advance` returned true).
    fn current(&self) -> &str {
        std::str::from_utf8(&self.line[self.cur.0..self.cur.1]).unwrap_or("")
    }

    /// Move to the next non-blank, non-comment line; false at the end.
    fn advance(&mut self) -> Result<bool> {
        loop {
            self.line.clear();
            let n = std::io::Read::take(&mut self.reader, MAX_LINE)
                .read_until(b'\n', &mut self.line)
                .map_err(|e| Error::io(&self.path, e))?;
            if n == 0 {
                return Ok(false);
            }
            self.line_no += 1;
            let start = self.offset;
            self.offset += n as u64;
            if n as u64 == MAX_LINE && self.line.last() != Some(&b'\n') {
                return Err(Error::corrupt(
                    &self.path,
                    start,
                    format!(
                        "line {}: longer than 64 KiB: not an event CSV",
                        self.line_no
                    ),
                ));
            }
            let Ok(full) = std::str::from_utf8(&self.line) else {
                return Err(Error::corrupt(
                    &self.path,
                    start,
                    format!(
                        "line {}: not text (invalid UTF-8): not an event CSV",
                        self.line_no
                    ),
                ));
            };
            let text = full.trim().trim_start_matches('\u{feff}');
            if text.is_empty() {
                continue;
            }
            if text.starts_with('#') || text.starts_with('%') {
                if self.geometry.is_none() {
                    self.geometry = geometry_from_comment(text);
                }
                continue;
            }
            let begin = text.as_ptr() as usize - full.as_ptr() as usize;
            self.cur = (begin, begin + text.len());
            return Ok(true);
        }
    }

    fn err(&self, what: impl std::fmt::Display) -> Error {
        Error::corrupt(
            &self.path,
            self.offset,
            format!("line {}: {what}", self.line_no),
        )
    }
}

/// `% geometry 1280x720`, `%geometry:1280,720`, `# width 640 height 480`.
fn geometry_from_comment(text: &str) -> Option<Geometry> {
    let lower = text.to_ascii_lowercase();
    if !(lower.contains("geometry") || (lower.contains("width") && lower.contains("height"))) {
        return None;
    }
    let nums: Vec<u16> = lower
        .split(|c: char| !c.is_ascii_digit())
        .filter(|s| !s.is_empty())
        .filter_map(|s| s.parse().ok())
        .collect();
    match nums[..] {
        [w, h] if w > 0 && h > 0 => Some(Geometry::new(w, h)),
        _ => None,
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Sep {
    Char(char),
    Whitespace,
}

impl Sep {
    fn detect(line: &str) -> Sep {
        for c in [',', '\t', ';'] {
            if line.contains(c) {
                return Sep::Char(c);
            }
        }
        Sep::Whitespace
    }
    /// Split `line` into trimmed fields.
    fn split<'a>(self, line: &'a str, out: &mut Vec<&'a str>) {
        out.clear();
        match self {
            Sep::Char(c) => out.extend(line.split(c).map(|s| s.trim().trim_matches('"'))),
            Sep::Whitespace => out.extend(line.split_whitespace()),
        }
    }

    /// Split into the first `MAX_FIELDS` fields without allocating; returns
    /// the number of fields found (capped).
    fn split_fixed<'a>(self, line: &'a str, out: &mut [&'a str; MAX_FIELDS]) -> usize {
        let mut n = 0;
        let mut put = |s: &'a str| {
            if n < MAX_FIELDS {
                out[n] = s;
                n += 1;
            }
        };
        match self {
            Sep::Char(c) => line.split(c).for_each(|s| put(s.trim().trim_matches('"'))),
            Sep::Whitespace => line.split_whitespace().for_each(put),
        }
        n
    }
}

/// Columns beyond this one are never used (the needed ones must come first).
const MAX_FIELDS: usize = 32;

/// Split a header name into its base and unit: `t_us` → (`t`, us).
fn name_and_unit(raw: &str) -> (String, Option<TimeUnit>) {
    let name: String = raw
        .trim()
        .trim_matches('"')
        .to_lowercase()
        .chars()
        .map(|c| {
            if matches!(c, '(' | '[' | ' ' | '-') {
                '_'
            } else {
                c
            }
        })
        .filter(|c| !matches!(c, ')' | ']'))
        .collect();
    if let Some((base, suffix)) = name.rsplit_once('_') {
        if let Some(u) = TimeUnit::from_suffix(suffix) {
            return (base.trim_end_matches('_').to_string(), Some(u));
        }
    }
    (name, None)
}

fn is_time_name(base: &str) -> bool {
    matches!(base, "t" | "ts" | "time" | "timestamp" | "timestamps")
}

/// Where the columns are and what the time unit is.
#[derive(Debug, Clone)]
struct Layout {
    t: usize,
    x: usize,
    y: usize,
    p: usize,
    min_fields: usize,
    unit: TimeUnit,
    /// Fractional times allowed only when the unit was stated.
    unit_stated: bool,
    has_header: bool,
    sep: Sep,
}

fn resolve_unit(
    lr: &LineReader,
    from_name: Option<TimeUnit>,
    from_opts: Option<TimeUnit>,
    tname: &str,
) -> Result<(TimeUnit, bool, String)> {
    match (from_name, from_opts) {
        (Some(a), Some(b)) if a != b => Err(Error::param(
            "time-unit",
            format!(
                "{}: the time column `{tname}` says {} but {} was requested",
                lr.path.display(),
                a.name(),
                b.name()
            ),
        )),
        (Some(a), _) => Ok((
            a,
            true,
            format!("{} (from the column name `{tname}`)", a.name()),
        )),
        (None, Some(b)) => Ok((b, true, format!("{} (as requested)", b.name()))),
        (None, None) => Ok((
            TimeUnit::Microseconds,
            false,
            "us (assumed: the file does not say)".into(),
        )),
    }
}

fn is_numeric_field(s: &str) -> bool {
    !s.is_empty() && s.parse::<f64>().is_ok()
}

/// A layout, header notes, and the first data line of a header-less file.
type DetectedLayout = (Layout, Vec<(String, String)>, Option<String>);

/// Read the first line and work out the layout; returns the layout, header
/// notes for [`StreamInfo::header`], and the first data line when the file
/// has no header line.
fn detect_layout(
    lr: &mut LineReader,
    unit_opt: Option<TimeUnit>,
    trigger_file: bool,
) -> Result<Option<DetectedLayout>> {
    let first = match lr.next_line()? {
        Some(l) => l.to_string(),
        None => return Ok(None),
    };
    let sep = Sep::detect(&first);
    let mut fields = Vec::new();
    sep.split(&first, &mut fields);
    let mut notes = Vec::new();
    if fields.iter().all(|f| is_numeric_field(f)) {
        // No header line: openeb's order.
        let (order, (t, x, y, p)) = if trigger_file {
            ("p,id,t", (2, 1, 0, 0))
        } else {
            ("x,y,p,t", (3, 0, 1, 2))
        };
        if fields.len() < 3 || (!trigger_file && fields.len() < 4) {
            return Err(lr.err(format!(
                "no header line and {} columns: cannot tell which is which; add a header line such as `t,x,y,p`",
                fields.len()
            )));
        }
        let (unit, stated, unit_note) = resolve_unit(lr, None, unit_opt, "t")?;
        notes.push((
            "columns".into(),
            format!("{order} (assumed: no header line; openeb's order)"),
        ));
        notes.push(("time_unit".into(), unit_note));
        let layout = Layout {
            t,
            x,
            y,
            p,
            min_fields: if trigger_file { 3 } else { 4 },
            unit,
            unit_stated: stated,
            has_header: false,
            sep,
        };
        return Ok(Some((layout, notes, Some(first))));
    }
    let mut t = None;
    let mut x = None;
    let mut y = None;
    let mut p = None;
    let mut tname = String::new();
    let mut name_unit = None;
    let mut ignored = Vec::new();
    for (i, f) in fields.iter().enumerate() {
        let (base, unit) = name_and_unit(f);
        let slot = if is_time_name(&base) {
            if t.is_none() {
                tname = f.to_string();
                name_unit = unit;
            }
            &mut t
        } else if unit.is_some() {
            ignored.push(f.to_string());
            continue;
        } else if !trigger_file && matches!(base.as_str(), "x" | "x_px" | "xpos" | "col" | "column")
        {
            &mut x
        } else if !trigger_file && matches!(base.as_str(), "y" | "y_px" | "ypos" | "row") {
            &mut y
        } else if trigger_file
            && matches!(
                base.as_str(),
                "id" | "channel" | "ch" | "trigger_id" | "source"
            )
        {
            &mut x
        } else if (!trigger_file
            && matches!(
                base.as_str(),
                "p" | "pol" | "polarity" | "polarities" | "on" | "is_increase" | "sign"
            ))
            || (trigger_file
                && matches!(
                    base.as_str(),
                    "p" | "edge" | "value" | "polarity" | "rising" | "pol"
                ))
        {
            &mut p
        } else {
            ignored.push(f.to_string());
            continue;
        };
        if slot.is_some() {
            return Err(lr.err(format!("column `{f}` appears twice in the header")));
        }
        *slot = Some(i);
    }
    let need: &[(&str, Option<usize>)] = if trigger_file {
        &[("time (t)", t), ("id", x), ("p (edge)", p)]
    } else {
        &[("time (t)", t), ("x", x), ("y", y), ("polarity (p)", p)]
    };
    let missing: Vec<&str> = need
        .iter()
        .filter(|(_, c)| c.is_none())
        .map(|(n, _)| *n)
        .collect();
    if !missing.is_empty() {
        return Err(lr.err(format!(
            "header `{first}` lacks the column(s) {}; expected names like {}",
            missing.join(", "),
            if trigger_file {
                "`t,id,p`"
            } else {
                "`t,x,y,p` (or `timestamp`, `polarity`, `on`)"
            }
        )));
    }
    let (t, x, p) = (t.unwrap(), x.unwrap(), p.unwrap());
    let y = y.unwrap_or(x);
    let (unit, stated, unit_note) = resolve_unit(lr, name_unit, unit_opt, &tname)?;
    notes.push(("columns".into(), first.clone()));
    notes.push(("time_unit".into(), unit_note));
    if !ignored.is_empty() {
        notes.push(("ignored_columns".into(), ignored.join(",")));
    }
    let min_fields = [t, x, y, p].into_iter().max().unwrap_or(0) + 1;
    if min_fields > MAX_FIELDS {
        return Err(lr.err(format!(
            "the event columns must be among the first {MAX_FIELDS} columns"
        )));
    }
    Ok(Some((
        Layout {
            t,
            x,
            y,
            p,
            min_fields,
            unit,
            unit_stated: stated,
            has_header: true,
            sep,
        },
        notes,
        None,
    )))
}

/// Parse a decimal time in `unit` to microseconds, exactly (no floats for
/// plain decimals), rounding half away from zero.
fn parse_time_us(s: &str, unit: TimeUnit) -> Option<(i64, bool)> {
    let exp = unit.exponent_to_us();
    // Fast path: a plain integer in µs (the common case, and our own output).
    if exp == 0 {
        if let Ok(v) = s.parse::<i64>() {
            return Some((v, false));
        }
    }
    let (neg, body) = match s.as_bytes().first()? {
        b'-' => (true, &s[1..]),
        b'+' => (false, &s[1..]),
        _ => (false, s),
    };
    if body.contains(['e', 'E']) {
        // Scientific notation: fall back on f64 (documented precision).
        let v: f64 = s.parse().ok()?;
        let us = (v * 10f64.powi(exp)).round();
        if !us.is_finite() || us.abs() > 9.0e18 {
            return None;
        }
        return Some((us as i64, true));
    }
    let (int_part, frac_part) = body.split_once('.').unwrap_or((body, ""));
    if int_part.is_empty() && frac_part.is_empty() {
        return None;
    }
    if !int_part.bytes().all(|b| b.is_ascii_digit())
        || !frac_part.bytes().all(|b| b.is_ascii_digit())
    {
        return None;
    }
    let fractional = body.contains('.');
    // value = digits * 10^(exp - frac_len); keep 1 extra digit for rounding.
    let digits: String = format!("{int_part}{frac_part}");
    let digits = digits.trim_start_matches('0');
    if digits.len() > 36 {
        return None;
    }
    let mantissa: i128 = if digits.is_empty() {
        0
    } else {
        digits.parse().ok()?
    };
    let shift = exp - frac_part.len() as i32;
    let us: i128 = if shift >= 0 {
        mantissa.checked_mul(10i128.checked_pow(shift as u32)?)?
    } else {
        let div = 10i128.checked_pow((-shift) as u32)?;
        (mantissa + div / 2) / div
    };
    let us = if neg { -us } else { us };
    Some((i64::try_from(us).ok()?, fractional))
}

fn parse_polarity(s: &str) -> Option<u8> {
    match s {
        "1" | "+1" => Some(ON),
        "0" | "-1" => Some(OFF),
        _ => match s.to_ascii_lowercase().as_str() {
            "true" | "on" | "pos" | "+" => Some(ON),
            "false" | "off" | "neg" | "-" => Some(OFF),
            // Numbers: only -1, 0 and 1 (written as 1.0 etc.); 7 is not a
            // polarity but a sign of a wrong column or a damaged file.
            other => other
                .parse::<f64>()
                .ok()
                .filter(|v| *v == 1.0 || *v == 0.0 || *v == -1.0)
                .map(|v| (v > 0.0) as u8),
        },
    }
}

/// Strict polarity for header-less files: only -1, 0, 1 prove the assumed order.
fn is_plain_polarity(s: &str) -> bool {
    matches!(s, "0" | "1" | "-1" | "+1")
}

/// Streaming CSV event reader (see the module docs).
#[ebptv_macros::testkit]
pub(crate) struct CsvReader {
    info: StreamInfo,
    lines: LineReader,
    layout: Layout,
    pending_first: Option<String>,
    chunk_events: usize,
    triggers: Option<TriggerStream>,
    events_done: bool,
}

impl CsvReader {
    /// Opens a CSV event file; `unit` overrides the time unit read from the header or guessed from the values.
    pub fn open(path: &Path, chunk_events: usize, unit: Option<TimeUnit>) -> Result<Self> {
        let (mut lines, file_size) = LineReader::open(path)?;
        if file_size == Some(0) {
            return Err(Error::Empty {
                path: path.to_path_buf(),
                why: "file is empty".into(),
            });
        }
        let (layout, mut notes, pending_first) = detect_layout(&mut lines, unit, false)?
            .ok_or_else(|| Error::Empty {
                path: path.to_path_buf(),
                why: "no data lines (only blank or comment lines)".into(),
            })?;
        let tpath = sidecar_path(path, "_triggers", "csv");
        let triggers = if tpath.is_file() {
            notes.push(("triggers_file".into(), tpath.display().to_string()));
            TriggerStream::open(&tpath, unit)?
        } else {
            None
        };
        notes.insert(
            0,
            (
                "header_line".into(),
                if layout.has_header { "yes" } else { "no" }.into(),
            ),
        );
        Ok(CsvReader {
            info: StreamInfo {
                path: path.to_path_buf(),
                format: Format::Csv,
                geometry: lines.geometry,
                header: notes,
                payload_offset: 0,
                file_size,
            },
            lines,
            layout,
            pending_first,
            chunk_events: chunk_events.max(1),
            triggers,
            events_done: false,
        })
    }
}

/// Parse one event row into `chunk`; errors name the line via `lines`.
fn parse_event_row(lay: &Layout, lines: &LineReader, line: &str, chunk: &mut Chunk) -> Result<()> {
    let mut f = [""; MAX_FIELDS];
    let nf = lay.sep.split_fixed(line, &mut f);
    if nf < lay.min_fields {
        return Err(lines.err(format!(
            "{} fields, expected at least {} (`{}`)",
            nf,
            lay.min_fields,
            truncate(line)
        )));
    }
    let (t, fractional) = parse_time_us(f[lay.t], lay.unit)
        .ok_or_else(|| lines.err(format!("time `{}` is not a number", truncate(f[lay.t]))))?;
    if fractional && !lay.unit_stated {
        return Err(lines.err(format!(
                "time `{}` has a fractional part but the file does not state its unit (assumed µs{}); name the column `t_s`/`t_us` or pass the time unit",
                f[lay.t],
                if lay.has_header { "" } else { ", no header line" }
            )));
    }
    let x: u16 = f[lay.x].parse().map_err(|_| {
        lines.err(format!(
            "x `{}` is not a pixel coordinate (0..65535)",
            truncate(f[lay.x])
        ))
    })?;
    let y: u16 = f[lay.y].parse().map_err(|_| {
        lines.err(format!(
            "y `{}` is not a pixel coordinate (0..65535)",
            truncate(f[lay.y])
        ))
    })?;
    if !lay.has_header && !is_plain_polarity(f[lay.p]) {
        return Err(lines.err(format!(
                "no header line, so openeb's order x,y,p,t was assumed, but the polarity column holds `{}`; add a header line naming the columns (e.g. `t,x,y,p`)",
                truncate(f[lay.p])
            )));
    }
    let p = parse_polarity(f[lay.p]).ok_or_else(|| {
        lines.err(format!(
            "polarity `{}` is not 0/1, -1/1 or true/false",
            truncate(f[lay.p])
        ))
    })?;
    chunk.events.push(t, x, y, p);
    Ok(())
}

fn truncate(s: &str) -> String {
    if s.len() <= 40 {
        s.to_string()
    } else {
        let mut end = 40;
        while !s.is_char_boundary(end) {
            end -= 1;
        }
        format!("{}…", &s[..end])
    }
}

impl EventSource for CsvReader {
    fn info(&self) -> &StreamInfo {
        &self.info
    }

    fn next_chunk(&mut self, chunk: &mut Chunk) -> Result<bool> {
        chunk.clear();
        if let Some(first) = self.pending_first.take() {
            parse_event_row(&self.layout, &self.lines, &first, chunk)?;
        }
        while !self.events_done && chunk.events.len() < self.chunk_events {
            if !self.lines.advance()? {
                self.events_done = true;
                break;
            }
            parse_event_row(&self.layout, &self.lines, self.lines.current(), chunk)?;
        }
        if let Some(ts) = self.triggers.as_mut() {
            let limit = if self.events_done {
                i64::MAX
            } else {
                chunk.events.t.last().copied().unwrap_or(i64::MIN)
            };
            ts.take_until(limit, self.chunk_events, &mut chunk.triggers)?;
        }
        Ok(!chunk.is_empty())
    }

    fn bytes_read(&self) -> u64 {
        self.lines.offset
    }
}

/// A trigger CSV read one row at a time.
struct TriggerStream {
    lines: LineReader,
    layout: Layout,
    peeked: Option<Trigger>,
    pending_first: Option<String>,
}

impl TriggerStream {
    fn open(path: &Path, unit: Option<TimeUnit>) -> Result<Option<Self>> {
        let (mut lines, _) = LineReader::open(path)?;
        let Some((layout, _, pending_first)) = detect_layout(&mut lines, unit, true)? else {
            return Ok(None);
        };
        Ok(Some(TriggerStream {
            lines,
            layout,
            peeked: None,
            pending_first,
        }))
    }

    fn parse(&self, line: &str) -> Result<Trigger> {
        let lay = &self.layout;
        let mut f = Vec::with_capacity(4);
        lay.sep.split(line, &mut f);
        if f.len() < lay.min_fields {
            return Err(self.lines.err(format!(
                "{} fields, expected {} (`{}`)",
                f.len(),
                lay.min_fields,
                truncate(line)
            )));
        }
        let (t, fractional) = parse_time_us(f[lay.t], lay.unit).ok_or_else(|| {
            self.lines
                .err(format!("time `{}` is not a number", truncate(f[lay.t])))
        })?;
        if fractional && !lay.unit_stated {
            return Err(self.lines.err(format!(
                "trigger time `{}` has a fractional part but its unit is not stated; name the column `t_s`/`t_us`",
                f[lay.t]
            )));
        }
        let channel: u8 = f[lay.x].parse().map_err(|_| {
            self.lines
                .err(format!("trigger id `{}` is not 0..255", truncate(f[lay.x])))
        })?;
        let edge = match f[lay.p].to_ascii_lowercase().as_str() {
            "1" | "rising" | "true" | "r" => Edge::Rising,
            "0" | "falling" | "false" | "f" | "-1" => Edge::Falling,
            other => {
                return Err(self.lines.err(format!(
                    "trigger edge `{}` is not 1/0 or rising/falling",
                    truncate(other)
                )))
            }
        };
        Ok(Trigger { t, channel, edge })
    }

    fn next(&mut self) -> Result<Option<Trigger>> {
        if let Some(p) = self.peeked.take() {
            return Ok(Some(p));
        }
        if let Some(first) = self.pending_first.take() {
            return self.parse(&first).map(Some);
        }
        match self.lines.next_line()? {
            Some(l) => {
                let l = l.to_string();
                self.parse(&l).map(Some)
            }
            None => Ok(None),
        }
    }

    /// Move triggers with `t <= limit` (at most `max`) into `out`.
    fn take_until(&mut self, limit: i64, max: usize, out: &mut Vec<Trigger>) -> Result<()> {
        while out.len() < max {
            match self.next()? {
                Some(tr) if tr.t <= limit => out.push(tr),
                Some(tr) => {
                    self.peeked = Some(tr);
                    break;
                }
                None => break,
            }
        }
        Ok(())
    }
}

#[cfg(feature = "testkit")]
/// Read a whole trigger CSV (openeb `p,id,t`, or any order by header names
/// `t`, `id`, `p`). Time unit as for events; `unit` applies when the header
/// does not state one.
pub(crate) fn read_trigger_csv(
    path: impl AsRef<Path>,
    unit: Option<TimeUnit>,
) -> Result<Vec<Trigger>> {
    let path = path.as_ref();
    let mut out = Vec::new();
    if let Some(mut s) = TriggerStream::open(path, unit)? {
        while let Some(t) = s.next()? {
            out.push(t);
        }
    }
    Ok(out)
}

/// CSV event writer: `t,x,y,p` and a `<stem>_triggers.csv` sidecar.
#[ebptv_macros::testkit]
pub(crate) struct CsvWriter {
    events: AtomicFile,
    trigger_path: PathBuf,
    triggers: Option<AtomicFile>,
    buf: Vec<u8>,
}

impl CsvWriter {
    /// Creates a writer for `path`.
    #[ebptv_macros::testkit]
    pub(crate) fn create(path: &Path) -> Result<Self> {
        let mut events = AtomicFile::create(path)?;
        events
            .write_all(b"t,x,y,p\n")
            .map_err(|e| Error::io(path, e))?;
        Ok(CsvWriter {
            events,
            trigger_path: sidecar_path(path, "_triggers", "csv"),
            triggers: None,
            buf: Vec::with_capacity(1 << 16),
        })
    }
}

impl crate::EventWriter for CsvWriter {
    fn write_chunk(&mut self, chunk: &Chunk) -> Result<()> {
        let ev = &chunk.events;
        self.buf.clear();
        for i in 0..ev.len() {
            // Infallible: writing into a Vec.
            let _ = writeln!(self.buf, "{},{},{},{}", ev.t[i], ev.x[i], ev.y[i], ev.p[i]);
        }
        let target = self.events.target().to_path_buf();
        self.events
            .write_all(&self.buf)
            .map_err(|e| Error::io(&target, e))?;
        if !chunk.triggers.is_empty() {
            if self.triggers.is_none() {
                let mut f = AtomicFile::create(&self.trigger_path)?;
                f.write_all(b"t,id,p\n")
                    .map_err(|e| Error::io(&self.trigger_path, e))?;
                self.triggers = Some(f);
            }
            self.buf.clear();
            for tr in &chunk.triggers {
                let _ = writeln!(
                    self.buf,
                    "{},{},{}",
                    tr.t,
                    tr.channel,
                    (tr.edge == Edge::Rising) as u8
                );
            }
            let f = self.triggers.as_mut().expect("created above");
            f.write_all(&self.buf)
                .map_err(|e| Error::io(&self.trigger_path, e))?;
        }
        Ok(())
    }

    fn finish(self: Box<Self>) -> Result<()> {
        let this = *self;
        match this.triggers {
            Some(t) => t.commit()?,
            None => {
                if this.trigger_path.is_file() {
                    std::fs::remove_file(&this.trigger_path)
                        .map_err(|e| Error::io(&this.trigger_path, e))?;
                }
            }
        }
        this.events.commit()
    }
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;
    use crate::events::Event;
    use crate::EventWriter;

    fn read_all(
        path: &Path,
        chunk: usize,
        unit: Option<TimeUnit>,
    ) -> Result<(Vec<Event>, Vec<Trigger>, StreamInfo)> {
        let mut r = CsvReader::open(path, chunk, unit)?;
        let mut c = Chunk::default();
        let (mut ev, mut tr) = (Vec::new(), Vec::new());
        while r.next_chunk(&mut c)? {
            assert!(!c.is_empty());
            ev.extend(c.events.iter());
            tr.extend_from_slice(&c.triggers);
        }
        Ok((ev, tr, r.info().clone()))
    }

    fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
        let p = dir.join(name);
        std::fs::write(&p, text).unwrap();
        p
    }

    #[ebptv_macros::unit_test]
    fn time_parsing_is_exact() {
        assert_eq!(
            parse_time_us("123", TimeUnit::Microseconds),
            Some((123, false))
        );
        assert_eq!(
            parse_time_us("1.000001", TimeUnit::Seconds),
            Some((1_000_001, true))
        );
        assert_eq!(
            parse_time_us("0.0000015", TimeUnit::Seconds),
            Some((2, true))
        );
        assert_eq!(
            parse_time_us("-0.5", TimeUnit::Milliseconds),
            Some((-500, true))
        );
        assert_eq!(
            parse_time_us("1500", TimeUnit::Nanoseconds),
            Some((2, false))
        );
        assert_eq!(parse_time_us("1e-3", TimeUnit::Seconds), Some((1000, true)));
        assert_eq!(
            parse_time_us("12.5", TimeUnit::Microseconds),
            Some((13, true))
        );
        assert_eq!(parse_time_us("abc", TimeUnit::Microseconds), None);
        assert_eq!(parse_time_us("", TimeUnit::Microseconds), None);
        assert_eq!(parse_time_us(".", TimeUnit::Microseconds), None);
        assert_eq!(
            parse_time_us("99999999999999999999999", TimeUnit::Seconds),
            None
        );
        // 1722.123456 s exactly, which f64 * 1e6 would not give for all inputs.
        assert_eq!(
            parse_time_us("1722.123457", TimeUnit::Seconds),
            Some((1_722_123_457, true))
        );
    }

    #[ebptv_macros::unit_test]
    fn header_names_any_order_and_units() {
        let dir = tempfile::tempdir().unwrap();
        let expect = vec![
            Event {
                t: 1_500_000,
                x: 3,
                y: 4,
                p: 1,
            },
            Event {
                t: 2_000_001,
                x: 5,
                y: 6,
                p: 0,
            },
        ];
        let cases = [
            "t,x,y,p\n1500000,3,4,1\n2000001,5,6,0\n",
            "x,y,p,t\n3,4,1,1500000\n5,6,0,2000001\n",
            "timestamp_s,x,y,polarity\n1.5,3,4,1\n2.000001,5,6,-1\n",
            "# comment\n\nTimestamp [us] ; X ; Y ; On\n1500000;3;4;true\n2000001;5;6;false\n",
            "t(ms)\tx\ty\tp\textra\n1500\t3\t4\t1\t9\n2000.001\t5\t6\t0\t9\n",
            "\"t\",\"x\",\"y\",\"p\"\n1500000,3,4,1\n2000001,5,6,0\n",
        ];
        for (i, text) in cases.iter().enumerate() {
            let p = write(dir.path(), &format!("c{i}.csv"), text);
            let (ev, tr, _) = read_all(&p, 1, None).unwrap_or_else(|e| panic!("case {i}: {e}"));
            assert_eq!(ev, expect, "case {i}");
            assert!(tr.is_empty());
        }
        // Seconds requested by option for a plain `t` column.
        let p = write(dir.path(), "o.csv", "t,x,y,p\n1.5,3,4,1\n2.000001,5,6,0\n");
        assert_eq!(read_all(&p, 10, Some(TimeUnit::Seconds)).unwrap().0, expect);
        // ...and refused without it, naming the line.
        let e = read_all(&p, 10, None).unwrap_err().to_string();
        assert!(e.contains("line 2") && e.contains("fractional"), "{e}");
        // Conflicting unit.
        let p = write(dir.path(), "k.csv", "t_s,x,y,p\n1,3,4,1\n");
        assert!(read_all(&p, 10, Some(TimeUnit::Microseconds)).is_err());
    }

    #[ebptv_macros::unit_test]
    fn headerless_is_openeb_order_and_checked() {
        let dir = tempfile::tempdir().unwrap();
        let p = write(dir.path(), "h.csv", "3,4,1,1500000\n5,6,0,2000001\n");
        let (ev, _, info) = read_all(&p, 10, None).unwrap();
        assert_eq!(
            ev[1],
            Event {
                t: 2_000_001,
                x: 5,
                y: 6,
                p: 0
            }
        );
        let cols = info.header.iter().find(|(k, _)| k == "columns").unwrap();
        assert!(cols.1.contains("assumed"));
        // Numbers other than -1/0/1 are not polarities.
        for bad in ["7", "2", "0.5", "-3"] {
            assert_eq!(parse_polarity(bad), None, "{bad}");
        }
        for (ok, v) in [("1.0", ON), ("-1.0", OFF), ("0.0", OFF)] {
            assert_eq!(parse_polarity(ok), Some(v), "{ok}");
        }
        // A t,x,y,p file without header: the "polarity" column holds y values.
        let p = write(dir.path(), "h2.csv", "100,3,4,1\n200,5,66,0\n");
        let e = read_all(&p, 10, None).unwrap_err().to_string();
        assert!(
            e.contains("line 1") && e.contains("add a header line"),
            "{e}"
        );
    }

    #[ebptv_macros::unit_test]
    fn bad_rows_name_the_line() {
        let dir = tempfile::tempdir().unwrap();
        for (text, needle) in [
            ("t,x,y,p\n1,2,3,1\n2,2,3\n", "line 3"),
            ("t,x,y,p\n1,2,3,1\n2,-2,3,1\n", "line 3"),
            ("t,x,y,p\n1,2,3,1\nfoo,2,3,1\n", "line 3"),
            ("t,x,y,p\n1,2,3,maybe\n", "line 2"),
            ("a,b,c\n1,2,3\n", "lacks"),
            ("t,x,t,p\n1,2,3,4\n", "twice"),
        ] {
            let p = write(dir.path(), "bad.csv", text);
            let e = read_all(&p, 10, None).unwrap_err().to_string();
            assert!(e.contains(needle) && e.contains("bad.csv"), "{text:?}: {e}");
        }
        let p = write(dir.path(), "empty.csv", "");
        assert!(matches!(read_all(&p, 10, None), Err(Error::Empty { .. })));
        let p = write(dir.path(), "hdr.csv", "t,x,y,p\n");
        assert!(read_all(&p, 10, None).unwrap().0.is_empty());
        let p = dir.path().join("bin.csv");
        std::fs::write(&p, [0xffu8, 0xfe, 0x00, 0x81]).unwrap();
        assert!(read_all(&p, 10, None).is_err());
    }

    #[ebptv_macros::unit_test]
    fn writer_roundtrip_with_triggers_and_geometry_comment() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("out.csv");
        let mut w: Box<dyn EventWriter> = Box::new(CsvWriter::create(&path).unwrap());
        let mut c = Chunk::default();
        let mut events = Vec::new();
        let mut trig = Vec::new();
        for k in 0..5i64 {
            c.clear();
            for i in 0..100i64 {
                let e = Event {
                    t: k * 1000 + i * 10 - 7,
                    x: i as u16,
                    y: (2 * i) as u16,
                    p: (i % 2) as u8,
                };
                c.events.push(e.t, e.x, e.y, e.p);
                events.push(e);
            }
            let tr = Trigger {
                t: k * 1000 + 500,
                channel: 1,
                edge: if k % 2 == 0 {
                    Edge::Rising
                } else {
                    Edge::Falling
                },
            };
            c.triggers.push(tr);
            trig.push(tr);
            w.write_chunk(&c).unwrap();
        }
        w.finish().unwrap();
        for chunk in [1, 37, 1000] {
            let (ev, tr, info) = read_all(&path, chunk, None).unwrap();
            assert_eq!(ev, events);
            assert_eq!(tr, trig);
            assert!(info.header.iter().any(|(k, _)| k == "triggers_file"));
        }
        assert_eq!(
            read_trigger_csv(dir.path().join("out_triggers.csv"), None).unwrap(),
            trig
        );
        // openeb-style trigger file without header: p,id,t.
        let tp = write(dir.path(), "o_triggers.csv", "1,0,100\n0,0,150\n");
        assert_eq!(
            read_trigger_csv(&tp, None).unwrap(),
            vec![
                Trigger {
                    t: 100,
                    channel: 0,
                    edge: Edge::Rising
                },
                Trigger {
                    t: 150,
                    channel: 0,
                    edge: Edge::Falling
                }
            ]
        );
        // Rewriting without triggers removes the stale sidecar.
        let mut w: Box<dyn EventWriter> = Box::new(CsvWriter::create(&path).unwrap());
        c.triggers.clear();
        w.write_chunk(&c).unwrap();
        w.finish().unwrap();
        assert!(!dir.path().join("out_triggers.csv").exists());
        // Geometry from a comment.
        let p = write(
            dir.path(),
            "g.csv",
            "% geometry 1280x720\nt,x,y,p\n1,2,3,1\n",
        );
        assert_eq!(
            read_all(&p, 10, None).unwrap().2.geometry,
            Some(Geometry::new(1280, 720))
        );
    }
}
