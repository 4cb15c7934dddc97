//! Writing a simulated recording to a directory: the event file, the truth,
//! the scenario actually used and a summary — each through `AtomicFile`, so
//! an interrupted run leaves no half-written file under a final name.
//!
//! Files (the contract of `ebptv simulate`):
//! - `recording.raw` (EVT 3.0 with trigger words; EVT 2.0 also `.raw`),
//!   `recording.csv` or `recording.npy`, depending on the format;
//! - `truth_particles.csv` (or another table: [`write_recording_with`]):
//!   `pulse,t_us,particle_id,x,y,u,v` — one row per
//!   lit particle per pulse with its image centre in the ROI (px, px/s;
//!   `t_us` the pulse start);
//! - `scenario.toml`: the scenario as simulated (after `--seconds`);
//! - `summary.json`: see [`RecordingSummary`].

use std::io::Write;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::{Scenario, SimStats, Simulator, TruthSample};
use ebptv_io::atomic::AtomicFile;
use ebptv_io::error::{Error, Result};
use ebptv_io::events::{Chunk, Geometry};
use ebptv_io::{EventSource, Format};

/// Streams truth rows to `truth_particles.csv`.
///
/// Rows are formatted in place into a large batch buffer (see
/// [`truth_row_rest`]). Two things rows share are formatted once: the
/// `pulse,t_us,` of a pulse ([`RowPrefix`]) and the `y,u,v` tail of a
/// particle ([`TailCache`]): in a steady parallel flow (jet, channel,
/// boundary layer, uniform) a particle keeps its y and velocity from pulse
/// to pulse while only x moves, so the tail's text is reused for as long
/// as the same three numbers come back; in other flows the cache misses,
/// and once a probe of its hit rate has found that out it is bypassed
/// for the tails ([`TailCache`]).
pub(crate) struct TruthWriter {
    file: AtomicFile,
    /// Rows formatted in place (`BATCH` bytes plus one row window), so a
    /// row costs no copy of its own; written out per `BATCH` bytes.
    buf: Vec<u8>,
    pos: usize,
    /// The formatted `pulse,t_us,` of the last row (rows of one pulse
    /// share it): formatted once per pulse, copied per row.
    prefix: RowPrefix,
    /// The formatted `y,u,v` tails of recent rows.
    tails: TailCache,
    /// Batches written since the last [`AtomicFile::start_writeback`].
    batches_since_writeback: u32,
}

/// The formatted `particle_id` and tail `y,u,v\n` of a particle's last
/// row, each keyed by the numbers it shows (so a hit is exact whatever
/// particle it came from).
#[derive(Clone, Copy)]
#[repr(C, align(16))]
struct TailText {
    /// Bits of y, u, v.
    key: [u64; 3],
    /// Bytes of `text` in use; 0: empty.
    len: u32,
    /// Digits of `id_text` in use; 0: empty.
    id_len: u32,
    id: u64,
    id_text: u64,
    text: [u64; TAIL_WORDS],
}

/// Longest cached tail (bytes): `719.9999,-19999.999,-19999.999\n` is 31.
/// Longer tails are formatted every time.
const TAIL_WORDS: usize = 4;

/// Direct-mapped cache of row tails, indexed by particle slot: the
/// simulator's particle ids are `slot + slots · generation` (a slot's new
/// particle gets a new id), so `id mod slots` gives every slot its own
/// entry. With another id scheme (or too many slots for the table) entries
/// are shared and simply miss more often: a hit needs the same key.
///
/// In an unsteady flow (a wake, a vortex, turbulence) the tail changes at
/// every pulse and the cache never hits; a miss costs the lookup and the
/// entry's store on top of formatting. So the cache measures its hit rate
/// over [`TAIL_PROBE_ROWS`] rows and, below 1 in [`TAIL_MIN_HIT_RATIO`],
/// formats the next [`TAIL_BYPASS_ROWS`] rows' tails without it (the ids
/// still through it: they repeat whatever the flow) before measuring
/// again. Only speed depends on it: a hit is exact.
struct TailCache {
    entries: Vec<TailText>,
    /// `entries.len()` and its [`fastmod_u32`] multiplier.
    n: u64,
    n_inv: u64,
    /// Rows looked up and tail hits in the current probe.
    probed: u32,
    hits: u32,
    /// Rows still to format without the cache.
    bypass: u32,
}

/// Rows per measurement of the tail cache's hit rate.
const TAIL_PROBE_ROWS: u32 = 1 << 12;
/// A probe with fewer hits than 1 in this many rows turns the cache off …
const TAIL_MIN_HIT_RATIO: u32 = 8;
/// … for this many rows (a probe then costs ~1.5 % of them a lookup).
const TAIL_BYPASS_ROWS: u32 = 1 << 18;

/// Largest tail table (entries of 80 bytes: 5 MiB).
const TAIL_TABLE_MAX: u64 = 1 << 16;

impl TailCache {
    fn new(slots: u64) -> TailCache {
        let n = slots.clamp(1, TAIL_TABLE_MAX);
        TailCache {
            entries: vec![
                TailText {
                    key: [0; 3],
                    len: 0,
                    id_len: 0,
                    id: 0,
                    id_text: 0,
                    text: [0; TAIL_WORDS],
                };
                n as usize
            ],
            n,
            n_inv: fastmod_u32_inverse(n as u32),
            probed: 0,
            hits: 0,
            bypass: 0,
        }
    }

    /// The index of particle `id`'s entry.
    #[inline(always)]
    fn index(&self, id: u64) -> usize {
        if id <= u32::MAX as u64 {
            fastmod_u32(id as u32, self.n_inv, self.n as u32) as usize
        } else {
            (id % self.n) as usize
        }
    }

    /// [`truth_row_rest`] of `r` from position `p` of `w`, through the
    /// cache ([`truth_row_cached`]; while bypassed, the id only).
    #[inline(always)]
    fn row(&mut self, w: &mut [u8; ROW_WINDOW], p: usize, r: &TruthSample) -> Option<usize> {
        if self.bypass > 0 {
            self.bypass -= 1;
            return truth_row_cached::<false>(w, p, r, self);
        }
        let row = truth_row_cached::<true>(w, p, r, self);
        self.probed += 1;
        if self.probed == TAIL_PROBE_ROWS {
            if self.hits * TAIL_MIN_HIT_RATIO < self.probed {
                self.bypass = TAIL_BYPASS_ROWS;
            }
            self.probed = 0;
            self.hits = 0;
        }
        row
    }
}

/// The multiplier of [`fastmod_u32`] for divisor `d` ≥ 1.
fn fastmod_u32_inverse(d: u32) -> u64 {
    (u64::MAX / d as u64).wrapping_add(1)
}

/// `a % d` by two multiplications (Lemire, Kaser and Kurz, "Faster
/// remainder by direct computation", 2019; exact for 32-bit `a` and `d`).
#[inline(always)]
fn fastmod_u32(a: u32, inverse: u64, d: u32) -> u32 {
    let low = inverse.wrapping_mul(a as u64);
    ((low as u128 * d as u128) >> 64) as u32
}

/// `pulse,t_us,` as formatted for one (pulse, t_us).
struct RowPrefix {
    key: Option<(i64, u64)>,
    len: usize,
    bytes: [u8; PREFIX_MAX],
}

/// Longest `pulse,t_us,`: a 20-byte pulse, a t_us below 1e15 with sign,
/// point and 3 decimals (≤ 20 bytes), two commas, in whole u64 words.
const PREFIX_MAX: usize = 48;

impl RowPrefix {
    /// The prefix of `r`'s pulse, or None when its `t_us` needs the
    /// exact formatter.
    #[inline]
    fn of(&mut self, r: &TruthSample) -> Option<&RowPrefix> {
        let key = (r.pulse, r.t_us.to_bits());
        if self.key != Some(key) {
            let mut w = [0u8; ROW_WINDOW];
            let mut p = 0;
            if r.pulse < 0 {
                p = put_byte(&mut w, p, b'-');
            }
            p = put_uint(&mut w, p, r.pulse.unsigned_abs());
            p = put_byte(&mut w, p, b',');
            p = put_fixed::<3>(&mut w, p, r.t_us)?;
            p = put_byte(&mut w, p, b',');
            debug_assert!(p <= PREFIX_MAX);
            self.bytes.copy_from_slice(&w[..PREFIX_MAX]);
            self.len = p;
            self.key = Some(key);
        }
        Some(self)
    }
}

/// Tail-cache entries when the slot count is not given.
const DEFAULT_SLOTS: u64 = 4096;

/// Bytes of formatted rows per `write_all`: the output's buffer size
/// (`AtomicFile`'s 1 MiB), so a batch goes to the file directly instead
/// of being copied into that buffer first.
const BATCH: usize = 1 << 20;

/// Batches between write-back requests (4 MiB): the full-frame truth is
/// ~200 MB, whose sync at the commit otherwise held the end of the run
/// for ~80 ms with every core idle.
const WRITEBACK_BATCHES: u32 = 4;

/// The window a row is formatted into. The longest row the fast path
/// writes is 152 bytes (numbers below 1e15 — ≤ 12 integer digits, sign,
/// point, ≤ 4 decimals — a 20-digit id, a 20-byte pulse, commas,
/// newline), plus 8 bytes of slack for the 8-byte digit stores; positions
/// are masked to 0..256 so the compiler drops the bounds checks.
const ROW_WINDOW: usize = 256 + 8;
const ROW_MASK: usize = 255;

impl TruthWriter {
    pub(crate) const HEADER: &'static str = "pulse,t_us,particle_id,x,y,u,v";

    pub(crate) fn create(path: impl AsRef<Path>) -> Result<TruthWriter> {
        let mut file = AtomicFile::create(path.as_ref())?;
        writeln!(file, "{}", Self::HEADER).map_err(|e| Error::io(path.as_ref(), e))?;
        Ok(TruthWriter {
            file,
            buf: vec![0; BATCH + ROW_WINDOW],
            pos: 0,
            prefix: RowPrefix {
                key: None,
                len: 0,
                bytes: [0; PREFIX_MAX],
            },
            tails: TailCache::new(DEFAULT_SLOTS),
            batches_since_writeback: 0,
        })
    }

    /// Tell the writer the simulator's number of particle slots (ids are
    /// `slot + slots · generation`), so each slot's row tail has its own
    /// cache entry. Only speed depends on it; any value gives the same
    /// file.
    pub(crate) fn set_particle_slots(&mut self, slots: u64) {
        self.tails = TailCache::new(slots);
    }

    fn flush_batch(&mut self) -> Result<()> {
        let n = std::mem::take(&mut self.pos);
        self.file
            .write_all(&self.buf[..n])
            .map_err(|e| Error::io(self.file.target(), e))?;
        if n >= BATCH {
            self.batches_since_writeback += 1;
            if self.batches_since_writeback == WRITEBACK_BATCHES {
                self.batches_since_writeback = 0;
                self.file.start_writeback();
            }
        }
        Ok(())
    }

    /// Append `rows`.
    pub(crate) fn write(&mut self, rows: &[TruthSample]) -> Result<()> {
        for r in rows {
            if self.pos >= BATCH {
                self.flush_batch()?;
            }
            let window: &mut [u8; ROW_WINDOW] = (&mut self.buf[self.pos..self.pos + ROW_WINDOW])
                .try_into()
                .expect("window size");
            let row = match self.prefix.of(r) {
                Some(prefix) => {
                    // Most prefixes (pulse < 10^6, t_us < 10^7) fit in 16
                    // bytes.
                    let words = if prefix.len <= 16 { 2 } else { PREFIX_MAX / 8 };
                    for k in 0..words {
                        let word = &prefix.bytes[8 * k..8 * k + 8];
                        put8(
                            window,
                            8 * k,
                            u64::from_le_bytes(word.try_into().expect("8")),
                        );
                    }
                    self.tails.row(window, prefix.len, r)
                }
                None => None,
            };
            match row {
                Some(n) => self.pos += n,
                None => {
                    // A value near a rounding tie, huge or not finite: the
                    // exact formatter (its row may be longer).
                    self.flush_batch()?;
                    let mut line = Vec::new();
                    truth_line_exact(&mut line, r);
                    self.file
                        .write_all(&line)
                        .map_err(|e| Error::io(self.file.target(), e))?;
                }
            }
        }
        self.flush_batch()
    }

    pub(crate) fn finish(self) -> Result<()> {
        self.file.commit()
    }
}

/// One CSV row of the truth (with newline), byte for byte what
/// [`truth_line_exact`] writes, without `core::fmt`'s exact float
/// formatting (which was 40 % of the CPU time of a full-frame
/// `ebptv simulate`); a row with a value near a rounding tie is written
/// by the reference instead.
#[cfg(feature = "testkit")]
pub(crate) fn truth_line(line: &mut Vec<u8>, r: &TruthSample) {
    let mut window = [0u8; ROW_WINDOW];
    match truth_row_fast(&mut window, r) {
        Some(n) => line.extend_from_slice(&window[..n]),
        None => truth_line_exact(line, r),
    }
}

/// Format `r` at the start of `w`: its length, or None when a value
/// needs the exact formatter.
#[inline]
#[cfg(feature = "testkit")]
fn truth_row_fast(w: &mut [u8; ROW_WINDOW], r: &TruthSample) -> Option<usize> {
    let mut p = 0;
    if r.pulse < 0 {
        p = put_byte(w, p, b'-');
    }
    p = put_uint(w, p, r.pulse.unsigned_abs());
    p = put_byte(w, p, b',');
    p = put_fixed::<3>(w, p, r.t_us)?;
    p = put_byte(w, p, b',');
    truth_row_rest(w, p, r)
}

/// The fields of `r` after `pulse,t_us,` from position `p` of `w` (see
/// [`truth_row_fast`]): the row's length, or None.
#[inline(always)]
#[cfg(feature = "testkit")]
fn truth_row_rest(w: &mut [u8; ROW_WINDOW], p: usize, r: &TruthSample) -> Option<usize> {
    let mut p = put_uint(w, p, r.particle_id);
    p = put_byte(w, p, b',');
    p = put_fixed::<4>(w, p, r.x)?;
    p = put_byte(w, p, b',');
    put_tail(w, p, r)
}

/// `y,u,v\n` of `r` from position `p`: the row's length, or None.
#[inline(always)]
fn put_tail(w: &mut [u8; ROW_WINDOW], p: usize, r: &TruthSample) -> Option<usize> {
    let mut p = put_fixed::<4>(w, p, r.y)?;
    p = put_byte(w, p, b',');
    p = put_fixed::<3>(w, p, r.u)?;
    p = put_byte(w, p, b',');
    p = put_fixed::<3>(w, p, r.v)?;
    Some(put_byte(w, p, b'\n'))
}

/// [`truth_row_rest`] with the id and (`TAIL`) the tail from (or into)
/// `tails`.
#[inline(always)]
fn truth_row_cached<const TAIL: bool>(
    w: &mut [u8; ROW_WINDOW],
    p: usize,
    r: &TruthSample,
    tails: &mut TailCache,
) -> Option<usize> {
    let i = tails.index(r.particle_id);
    // (i < n by construction; the index check stays cheap.)
    let entry = &mut tails.entries[i];
    let mut p = if entry.id_len != 0 && entry.id == r.particle_id {
        put8(w, p, entry.id_text);
        p + entry.id_len as usize
    } else {
        let end = put_uint(w, p, r.particle_id);
        if end - p <= 8 {
            entry.id = r.particle_id;
            entry.id_text = get8(w, p);
            entry.id_len = (end - p) as u32;
        }
        end
    };
    p = put_byte(w, p, b',');
    p = put_fixed::<4>(w, p, r.x)?;
    p = put_byte(w, p, b',');
    if !TAIL {
        return put_tail(w, p, r);
    }
    let key = [r.y.to_bits(), r.u.to_bits(), r.v.to_bits()];
    if entry.len != 0 && entry.key == key {
        for (k, &word) in entry.text.iter().enumerate() {
            put8(w, p + 8 * k, word);
        }
        let end = p + entry.len as usize;
        tails.hits += 1;
        return Some(end);
    }
    let end = put_tail(w, p, r)?;
    if end - p <= 8 * TAIL_WORDS {
        entry.key = key;
        entry.len = (end - p) as u32;
        for (k, word) in entry.text.iter_mut().enumerate() {
            *word = get8(w, p + 8 * k);
        }
    }
    Some(end)
}

/// Eight decimal digits of `n` (< 10^8, leading zeros included) as the
/// bytes of a little-endian u64, most significant digit in the lowest
/// byte, values 0–9 (not yet ASCII): SWAR — split 4+4 digits into the two
/// 32-bit halves, then 2+2 into 16-bit lanes, then 1+1 into bytes, each
/// split a multiply-shift on all lanes at once.
#[inline(always)]
fn digits8(n: u64) -> u64 {
    debug_assert!(n < 100_000_000);
    let x = (n / 10_000) | ((n % 10_000) << 32);
    // v / 100 for v < 10^4 per 32-bit lane (10486 / 2^20 ≈ 1/100).
    let h = ((x * 10_486) >> 20) & 0x0000_007F_0000_007F;
    let x = h | ((x - h * 100) << 16);
    // v / 10 for v < 100 per 16-bit lane (103 / 2^10 ≈ 1/10).
    let t = ((x * 103) >> 10) & 0x000F_000F_000F_000F;
    t | ((x - t * 10) << 8)
}

/// Eight ASCII '0's.
const ZEROS: u64 = 0x3030_3030_3030_3030;

// Decimal text written forward into a row window: each function takes
// the position and returns the next (kept in a register, masked into the
// window). Integers go through [`digits8`] with leading zeros shifted
// out; fixed-point values are the digits of the integer |v|·10^D with
// the point inserted.

#[inline(always)]
fn put_byte(w: &mut [u8; ROW_WINDOW], p: usize, b: u8) -> usize {
    w[p & ROW_MASK] = b;
    p + 1
}

/// Store 8 bytes at `p` (the position does not advance).
#[inline(always)]
fn put8(w: &mut [u8; ROW_WINDOW], p: usize, v: u64) {
    let at = p & ROW_MASK;
    w[at..at + 8].copy_from_slice(&v.to_le_bytes());
}

/// The 8 bytes at `p`.
#[inline(always)]
fn get8(w: &[u8; ROW_WINDOW], p: usize) -> u64 {
    let at = p & ROW_MASK;
    u64::from_le_bytes(w[at..at + 8].try_into().expect("8"))
}

/// `n` < 10^8 without leading zeros (one digit at least).
#[inline(always)]
fn put_uint8(w: &mut [u8; ROW_WINDOW], p: usize, n: u64) -> usize {
    let d = digits8(n);
    let lz = ((d.trailing_zeros() / 8) as usize).min(7);
    put8(w, p, (d >> (8 * lz)) | ZEROS);
    p + 8 - lz
}

#[inline(always)]
fn put_uint(w: &mut [u8; ROW_WINDOW], p: usize, n: u64) -> usize {
    const E8: u64 = 100_000_000;
    if n < E8 {
        return put_uint8(w, p, n);
    }
    let p = if n < E8 * E8 {
        put_uint8(w, p, n / E8)
    } else {
        let p = put_uint8(w, p, n / (E8 * E8));
        put8(w, p, digits8(n / E8 % E8) | ZEROS);
        p + 8
    };
    put8(w, p, digits8(n % E8) | ZEROS);
    p + 8
}

/// `v` with `D` (3 or 4) decimals as `format!("{v:.D$}")` writes it,
/// when rounding `|v|·10^D` to an integer is unambiguous (not within a
/// few ulps of a tie) and it is below 1e15; else None.
#[inline(always)]
fn put_fixed<const D: usize>(w: &mut [u8; ROW_WINDOW], p: usize, v: f64) -> Option<usize> {
    const E8: u64 = 100_000_000;
    let scale = if D == 3 { 1e3 } else { 1e4 };
    let a = v.abs() * scale;
    if !(a < 1e15) {
        return None;
    }
    // Truncation (floor for 0 ≤ a); through i64, one instruction each way.
    // SAFETY: 0 ≤ a < 1e15 here (NaN fails the test above), inside i64's
    // range, so the conversion needs none of `as`'s saturation checks.
    let whole = unsafe { a.to_int_unchecked::<i64>() };
    let frac = a - whole as f64;
    // The product is within half an ulp of the exact one; stay well away.
    if (frac - 0.5).abs() <= a * (4.0 * f64::EPSILON) {
        return None;
    }
    let n = whole as u64 + (frac > 0.5) as u64;
    // The sign without a branch (velocities take either at random): a
    // '-' always written, kept or overwritten.
    put_byte(w, p, b'-');
    let mut p = p + v.is_sign_negative() as usize;
    // The last 8 digits hold the D decimals and 8 − D integer digits;
    // higher digits (n ≥ 10^8, rare: |v| ≥ 10^4 or 10^5) go first,
    // without leading zeros; the division only on that branch.
    let (d, lz) = if n < E8 {
        let d = digits8(n);
        // Keep the units digit.
        (d, ((d.trailing_zeros() / 8) as usize).min(7 - D))
    } else {
        p = put_uint(w, p, n / E8);
        (digits8(n % E8), 0)
    };
    put8(w, p, (d >> (8 * lz)) | ZEROS);
    p = put_byte(w, p + 8 - D - lz, b'.');
    put8(w, p, (d >> (8 * (8 - D))) | ZEROS);
    Some(p + D)
}

/// The plain definition of a truth row.
pub(crate) fn truth_line_exact(line: &mut Vec<u8>, r: &TruthSample) {
    use std::io::Write as _;
    let _ = writeln!(
        line,
        "{},{:.3},{},{:.4},{:.4},{:.3},{:.3}",
        r.pulse, r.t_us, r.particle_id, r.x, r.y, r.u, r.v
    );
}

/// `summary.json`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RecordingSummary {
    /// The scenario's name.
    pub scenario: String,
    /// The seed of the run.
    pub seed: u64,
    /// The recording written.
    pub recording: PathBuf,
    /// Its encoding.
    pub format: Format,
    /// The run's counters, as top-level keys of the JSON.
    #[serde(flatten)]
    pub stats: SimStats,
    /// Mean event rate (events/s).
    pub event_rate_ev_s: f64,
    /// Mean events per lit particle and pulse.
    pub events_per_particle_per_pulse: f64,
}

impl RecordingSummary {
    fn new(sc: &Scenario, seed: u64, recording: PathBuf, format: Format, st: &SimStats) -> Self {
        RecordingSummary {
            scenario: sc.name.clone(),
            seed,
            recording,
            format,
            stats: st.clone(),
            event_rate_ev_s: st.event_rate_ev_s(),
            events_per_particle_per_pulse: st.events_per_particle_per_pulse(),
        }
    }
}

/// File name of the recording for `format`.
pub(crate) fn recording_name(format: Format) -> Result<&'static str> {
    Ok(match format {
        Format::Evt3 | Format::Evt2 => "recording.raw",
        Format::Csv => "recording.csv",
        Format::Npy => "recording.npy",
        other => {
            return Err(Error::param(
                "format",
                format!(
                    "simulate cannot write {}; use evt3, evt2, csv or npy",
                    other.name()
                ),
            ))
        }
    })
}

/// Simulate `sc` and write the recording and its truth into `dir`.
/// `progress(pulses_done, pulses_total)` is called after every block.
///
/// Simulation and writing overlap: the simulator runs on the calling
/// thread (itself parallel through rayon, in the caller's pool) while two
/// more threads, one or two blocks behind, encode the events and format
/// the truth (the truth is the larger job: ~200 MB of text at full
/// frame). Separate threads rather than one writer give the OS two
/// independent jobs to fill a core with whenever the simulator's own
/// threads wait (a block's sequential readout, the start, the end).
/// Blocks are written in order, so the files do not depend on this. Each
/// writer commits its file only after the last block; on any error
/// nothing appears under a final name (a writer that failed closes its
/// channel, the simulator stops, the other writer sees its channel close
/// without the end message and drops its file uncommitted).
pub fn write_recording(
    sc: &Scenario,
    seed: u64,
    dir: &Path,
    format: Format,
    progress: impl FnMut(u64, u64),
) -> Result<RecordingSummary> {
    write_recording_with(sc, seed, dir, format, None, progress)
}

/// A writer of the truth table other than `truth_particles.csv` (e.g.
/// Parquet): rows in blocks, in order, then committed.
pub trait TruthTable: Send {
    /// Appends `rows`.
    fn write(&mut self, rows: &[TruthSample]) -> Result<()>;
    /// Writes the end and gives the file its final name. A writer dropped
    /// without it leaves no file.
    fn finish(self: Box<Self>) -> Result<()>;
}

/// Makes the [`TruthTable`] of a recording's folder.
pub type TruthTableMaker<'a> = &'a (dyn Fn(&Path) -> Result<Box<dyn TruthTable>> + Sync);

impl TruthTable for TruthWriter {
    fn write(&mut self, rows: &[TruthSample]) -> Result<()> {
        TruthWriter::write(self, rows)
    }
    fn finish(self: Box<Self>) -> Result<()> {
        TruthWriter::finish(*self)
    }
}

/// [`write_recording`] with the truth written by `truth` (made from
/// `dir`) instead of `truth_particles.csv` when given.
pub fn write_recording_with(
    sc: &Scenario,
    seed: u64,
    dir: &Path,
    format: Format,
    truth: Option<TruthTableMaker<'_>>,
    mut progress: impl FnMut(u64, u64),
) -> Result<RecordingSummary> {
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let mut sim = Simulator::new(sc, seed)?;
    let name = recording_name(format)?;
    let geometry = Geometry::new(sc.sensor.width as u16, sc.sensor.height as u16);
    let particle_slots = sim.stats().particles;
    /// A writer thread's input: the next block, or (after the last) the
    /// order to commit.
    enum Msg<T> {
        Block(T),
        End,
    }
    let stats = std::thread::scope(|scope| -> Result<SimStats> {
        // Two blocks in flight per writer: the simulator waits only if a
        // writer is the slower side.
        let (events_tx, events_rx) = std::sync::mpsc::sync_channel::<Msg<Chunk>>(2);
        let (truth_tx, truth_rx) = std::sync::mpsc::sync_channel::<Msg<Vec<TruthSample>>>(2);
        // Written chunks and truth lists go back to the simulator for reuse.
        let (back_tx, back_rx) = std::sync::mpsc::channel::<Chunk>();
        let (truth_back_tx, truth_back_rx) = std::sync::mpsc::channel::<Vec<TruthSample>>();
        let events_thread = scope.spawn(move || -> Result<()> {
            let mut writer = ebptv_io::create(dir.join(name), Some(format), geometry)?;
            for msg in events_rx.iter() {
                match msg {
                    Msg::Block(chunk) => {
                        if !chunk.is_empty() {
                            writer.write_chunk(&chunk)?;
                        }
                        let _ = back_tx.send(chunk);
                    }
                    Msg::End => return writer.finish(),
                }
            }
            // The simulator stopped early: drop the file uncommitted.
            Ok(())
        });
        let truth_thread = scope.spawn(move || -> Result<()> {
            let mut truth: Box<dyn TruthTable> = match truth {
                Some(make) => make(dir)?,
                None => {
                    let mut w = TruthWriter::create(dir.join("truth_particles.csv"))?;
                    w.set_particle_slots(particle_slots);
                    Box::new(w)
                }
            };
            for msg in truth_rx.iter() {
                match msg {
                    Msg::Block(rows) => {
                        truth.write(&rows)?;
                        let _ = truth_back_tx.send(rows);
                    }
                    Msg::End => return truth.finish(),
                }
            }
            Ok(())
        });
        let mut sent_all = false;
        let mut sim_result = Ok(());
        loop {
            let mut chunk = back_rx.try_recv().unwrap_or_default();
            while let Ok(rows) = truth_back_rx.try_recv() {
                sim.recycle_truth(rows);
            }
            let more = match sim.next_chunk(&mut chunk) {
                Ok(m) => m,
                Err(e) => {
                    sim_result = Err(e);
                    break;
                }
            };
            let (done, total) = sim.progress();
            // A closed channel means that writer failed: its error is below.
            if truth_tx.send(Msg::Block(sim.take_truth())).is_err()
                || events_tx.send(Msg::Block(chunk)).is_err()
            {
                break;
            }
            progress(done, total);
            if !more {
                sent_all = events_tx.send(Msg::End).is_ok() && truth_tx.send(Msg::End).is_ok();
                break;
            }
        }
        drop(events_tx);
        drop(truth_tx);
        let panicked = || Error::analysis("recording writer thread panicked");
        let events_written = events_thread.join().map_err(|_| panicked())?;
        let truth_written = truth_thread.join().map_err(|_| panicked())?;
        sim_result?;
        events_written?;
        truth_written?;
        if !sent_all {
            return Err(Error::analysis("recording writer stopped early (bug)"));
        }
        Ok(sim.stats().clone())
    })?;
    let summary = RecordingSummary::new(sc, seed, PathBuf::from(name), format, &stats);
    let toml = sc.to_toml_string()?;
    let json = serde_json::to_string_pretty(&summary)
        .map_err(|e| Error::analysis(format!("summary: {e}")))?;
    // The big files are committed; the small ones last mark completion.
    AtomicFile::write_all_to(dir.join("scenario.toml"), toml.as_bytes())?;
    AtomicFile::write_all_to(dir.join("summary.json"), json.as_bytes())?;
    Ok(summary)
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    #[ebptv_macros::unit_test]
    fn truth_line_matches_reference() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(4);
        let (mut a, mut b) = (Vec::new(), Vec::new());
        for _ in 0..10_000 {
            let r = TruthSample {
                pulse: rng.gen_range(-5_000_000..1_000_000),
                t_us: rng.gen_range(0.0..1e7),
                particle_id: rng.gen(),
                x: rng.gen_range(-10.0..1300.0),
                y: rng.gen_range(-10.0..730.0),
                u: rng.gen_range(-5e4..5e4),
                v: rng.gen_range(-5e4..5e4),
            };
            a.clear();
            b.clear();
            truth_line(&mut a, &r);
            truth_line_exact(&mut b, &r);
            assert_eq!(a, b);
        }
        // Every magnitude from 1e-5 to 1e12 (the digit-chunk boundaries
        // at 10^8 and 10^16 of the scaled value), both signs, every field,
        // and integers at every length.
        for i in 0..40_000 {
            let mag = 10f64.powi(rng.gen_range(-5..13));
            let v = rng.gen_range(-1.0..1.0) * mag;
            let int = rng.gen::<u64>() >> rng.gen_range(0..64);
            let r = TruthSample {
                pulse: if i % 2 == 0 {
                    int as i64
                } else {
                    -((int >> 1) as i64)
                },
                t_us: v,
                particle_id: int,
                x: -v * 0.37,
                y: v * 1.9,
                u: v * 11.0,
                v: -v * 0.013,
            };
            a.clear();
            b.clear();
            truth_line(&mut a, &r);
            truth_line_exact(&mut b, &r);
            assert_eq!(a, b, "{r:?}");
        }
        // Values at rounding ties (the row falls back to the reference),
        // negative zero, huge and non-finite values, in every field.
        let odd = [
            0.00005,
            0.0625,
            -0.0,
            2.5e-4,
            1.0005,
            1e16,
            f64::NAN,
            -f64::INFINITY,
        ];
        for (i, &v) in odd.iter().enumerate() {
            for field in 0..5 {
                let mut r = TruthSample {
                    pulse: -(i as i64),
                    t_us: 12.5,
                    particle_id: u64::MAX - i as u64,
                    x: 3.25,
                    y: -7.125,
                    u: 1e4,
                    v: -2e4,
                };
                match field {
                    0 => r.t_us = v,
                    1 => r.x = v,
                    2 => r.y = v,
                    3 => r.u = v,
                    _ => r.v = v,
                }
                a.clear();
                b.clear();
                truth_line(&mut a, &r);
                truth_line_exact(&mut b, &r);
                assert_eq!(a, b, "{v} in field {field}");
            }
        }
    }

    #[ebptv_macros::unit_test]
    fn truth_writer_file_matches_reference_rows() {
        // Enough rows for several batches, with fallback rows (ties, huge,
        // non-finite values) in between: same bytes, same order.
        let mut rng = rand_pcg::Pcg64::seed_from_u64(9);
        let odd = [0.0625, 1e300, f64::NAN, -0.0, 2.5e-4];
        let rows: Vec<TruthSample> = (0..5000)
            .map(|i| TruthSample {
                pulse: i / 3,
                t_us: i as f64 * 200.0 + 37.0,
                particle_id: rng.gen_range(0..1u64 << 40),
                x: if i % 997 == 5 {
                    odd[(i / 997) as usize % odd.len()]
                } else {
                    rng.gen_range(-5.0..1285.0)
                },
                y: rng.gen_range(-5.0..725.0),
                u: rng.gen_range(-3e4..3e4),
                v: rng.gen_range(-3e4..3e4),
            })
            .collect();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("truth.csv");
        let mut w = TruthWriter::create(&path).unwrap();
        w.write(&rows[..1234]).unwrap();
        w.write(&[]).unwrap();
        w.write(&rows[1234..]).unwrap();
        w.finish().unwrap();
        let mut want = format!("{}\n", TruthWriter::HEADER).into_bytes();
        for r in &rows {
            truth_line_exact(&mut want, r);
        }
        assert_eq!(std::fs::read(&path).unwrap(), want);
    }

    #[ebptv_macros::unit_test]
    fn truth_writer_over_many_batches_with_writeback_matches_reference() {
        // ~10 MB: several write-back requests (every WRITEBACK_BATCHES
        // full batches) between batches; the file is unchanged by them.
        let mut rng = rand_pcg::Pcg64::seed_from_u64(13);
        let rows: Vec<TruthSample> = (0..140_000)
            .map(|i| TruthSample {
                pulse: i / 2900,
                t_us: (i / 2900) as f64 * 200.0 + 11.0,
                particle_id: rng.gen_range(0..1u64 << 40),
                x: rng.gen_range(-5.0..1285.0),
                y: rng.gen_range(-5.0..725.0),
                u: rng.gen_range(-3e4..3e4),
                v: rng.gen_range(-3e4..3e4),
            })
            .collect();
        let mut want = format!("{}\n", TruthWriter::HEADER).into_bytes();
        for r in &rows {
            truth_line_exact(&mut want, r);
        }
        assert!(want.len() > 2 * WRITEBACK_BATCHES as usize * BATCH);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("truth.csv");
        let mut w = TruthWriter::create(&path).unwrap();
        for part in rows.chunks(7777) {
            w.write(part).unwrap();
        }
        w.finish().unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), want);
    }

    #[ebptv_macros::unit_test]
    fn fastmod_equals_remainder() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(21);
        for d in [1u32, 2, 3, 7, 4096, 4801, 65_536, u32::MAX - 1, u32::MAX] {
            let inv = fastmod_u32_inverse(d);
            for a in [0u32, 1, d - 1, d, d.wrapping_add(1), u32::MAX, u32::MAX - 1]
                .into_iter()
                .chain((0..20_000).map(|_| rng.gen::<u32>()))
            {
                assert_eq!(fastmod_u32(a, inv, d), a % d, "{a} % {d}");
            }
        }
    }

    /// Rows as the simulator writes them in a steady parallel flow: per
    /// pulse the lit particles in slot order, each keeping its y, u, v
    /// (only x moves) until its slot gets a new particle (new id). Some
    /// particles change only v or only the id, some tails are too long to
    /// cache, some ids too long for the id cache or above 2^32, some
    /// values sit at a rounding tie (the whole row through the reference,
    /// again at the next pulse): the file equals the reference rows, with
    /// the right slot count, a wrong one (entries shared) and the default.
    #[ebptv_macros::unit_test]
    fn truth_writer_tail_cache_matches_reference() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(17);
        let slots = 300u64;
        #[derive(Clone, Copy)]
        struct P {
            id: u64,
            x: f64,
            y: f64,
            u: f64,
            v: f64,
        }
        let fresh = |rng: &mut rand_pcg::Pcg64, id: u64| {
            let kind = rng.gen_range(0..40);
            P {
                id: match kind {
                    0 => id + (1 << 40),      // above 2^32
                    1 => id + 12_345_678_900, // 11 digits
                    _ => id,
                },
                x: rng.gen_range(-5.0..1285.0),
                y: if kind == 2 {
                    0.00005
                } else {
                    rng.gen_range(-5.0..725.0)
                },
                u: match kind {
                    3 => -1.234_567_8e9, // tail longer than the cache holds
                    _ => rng.gen_range(-3e4..3e4),
                },
                v: if kind < 20 {
                    0.0
                } else {
                    rng.gen_range(-3e4..3e4)
                },
            }
        };
        let mut ps: Vec<(P, u64)> = (0..slots).map(|s| (fresh(&mut rng, s), 0)).collect();
        let mut rows = Vec::new();
        for pulse in 0..60i64 {
            for (s, (p, generation)) in ps.iter_mut().enumerate() {
                match rng.gen_range(0..100) {
                    0..=3 => {
                        *generation += 1;
                        *p = fresh(&mut rng, s as u64 + slots * *generation);
                    }
                    4 => p.v = rng.gen_range(-3e4..3e4),
                    5 => p.id += slots, // same tail, new id
                    _ => {}
                }
                p.x += p.u * 2e-4;
                if rng.gen_bool(0.3) {
                    continue; // not lit or outside the ROI at this pulse
                }
                rows.push(TruthSample {
                    pulse,
                    t_us: 37.0 + 200.0 * pulse as f64,
                    particle_id: p.id,
                    x: p.x,
                    y: p.y,
                    u: p.u,
                    v: p.v,
                });
            }
        }
        let mut want = format!("{}\n", TruthWriter::HEADER).into_bytes();
        for r in &rows {
            truth_line_exact(&mut want, r);
        }
        let dir = tempfile::tempdir().unwrap();
        for given in [Some(slots), Some(7), Some(1), Some(1 << 40), None] {
            let path = dir.path().join("truth.csv");
            let mut w = TruthWriter::create(&path).unwrap();
            if let Some(n) = given {
                w.set_particle_slots(n);
            }
            for part in rows.chunks(997) {
                w.write(part).unwrap();
            }
            w.finish().unwrap();
            assert!(std::fs::read(&path).unwrap() == want, "slots {given:?}");
        }
    }

    /// The tail cache's bypass: unsteady rows (every tail new) turn the
    /// cache off after a probe, steady rows (tails repeat) turn it back
    /// on at the next probe, and rows through the reference (ties) and
    /// long ids or tails come in every phase: the file equals the
    /// reference rows throughout.
    #[ebptv_macros::unit_test]
    fn truth_writer_tail_cache_bypass_matches_reference() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(23);
        let slots = 1000u64;
        let steady: Vec<(f64, f64, f64)> = (0..slots)
            .map(|_| {
                (
                    rng.gen_range(-5.0..725.0),
                    rng.gen_range(-3e4..3e4),
                    rng.gen_range(-3e4..3e4),
                )
            })
            .collect();
        let mut pulse = 0i64;
        let mut phase = |rng: &mut rand_pcg::Pcg64, pulses: usize, unsteady: bool| {
            let mut rows = Vec::new();
            for _ in 0..pulses {
                for s in 0..slots {
                    let (mut y, mut u, mut v) = steady[s as usize];
                    if unsteady {
                        (y, u, v) = (
                            rng.gen_range(-5.0..725.0),
                            rng.gen_range(-3e4..3e4),
                            rng.gen_range(-3e4..3e4),
                        );
                    }
                    match rng.gen_range(0..500) {
                        0 => y = 0.00005,        // a tie: the reference
                        1 => u = -1.234_567_8e9, // too long to cache
                        _ => {}
                    }
                    let id = match rng.gen_range(0..200) {
                        0 => s + (1 << 40),
                        1 => s + 12_345_678_900,
                        _ => s,
                    };
                    rows.push(TruthSample {
                        pulse,
                        t_us: 37.0 + 200.0 * pulse as f64,
                        particle_id: id,
                        x: rng.gen_range(-5.0..1285.0),
                        y,
                        u,
                        v,
                    });
                }
                pulse += 1;
            }
            rows
        };
        let unsteady = phase(
            &mut rng,
            2 + (TAIL_PROBE_ROWS as usize) / slots as usize,
            true,
        );
        let steady_rows = (TAIL_BYPASS_ROWS + 2 * TAIL_PROBE_ROWS) as usize / slots as usize;
        let steady = phase(&mut rng, steady_rows, false);
        let unsteady_again = phase(&mut rng, 7, true);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("truth.csv");
        let mut w = TruthWriter::create(&path).unwrap();
        w.set_particle_slots(slots);
        let mut want = format!("{}\n", TruthWriter::HEADER).into_bytes();
        for (rows, bypassed) in [(&unsteady, true), (&steady, false), (&unsteady_again, true)] {
            for part in rows.chunks(1999) {
                w.write(part).unwrap();
            }
            for r in rows.iter() {
                truth_line_exact(&mut want, r);
            }
            assert_eq!(w.tails.bypass > 0, bypassed);
        }
        w.finish().unwrap();
        assert!(std::fs::read(&path).unwrap() == want);
    }

    #[ebptv_macros::unit_test]
    fn truth_writer_reuses_the_pulse_prefix_correctly() {
        // Rows in runs sharing (pulse, t_us), as the simulator writes
        // them: the prefix is formatted once per run and copied. Runs
        // with the longest pulses and times, negative ones, a t_us at a
        // rounding tie (the whole row through the reference) and runs
        // that differ in only one of pulse and t_us.
        let mut rng = rand_pcg::Pcg64::seed_from_u64(10);
        let runs: Vec<(i64, f64)> = vec![
            (0, 37.0),
            (1, 237.0),
            (1, 237.5),
            (2, 237.5),
            (i64::MIN, -999_999_999_999.999),
            (i64::MAX, 999_999_999_999.999),
            (-7, 0.0625),
            (-7, 1e300),
            (12_345_678, 2_469_135_637.0),
        ];
        let mut rows = Vec::new();
        for (k, &(pulse, t_us)) in runs.iter().enumerate() {
            for _ in 0..(50 + 40 * k) {
                rows.push(TruthSample {
                    pulse,
                    t_us,
                    particle_id: rng.gen_range(0..1u64 << 40),
                    x: rng.gen_range(-5.0..1285.0),
                    y: rng.gen_range(-5.0..725.0),
                    u: rng.gen_range(-3e4..3e4),
                    v: rng.gen_range(-3e4..3e4),
                });
            }
        }
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("truth.csv");
        let mut w = TruthWriter::create(&path).unwrap();
        // Split inside runs too.
        w.write(&rows[..77]).unwrap();
        w.write(&rows[77..]).unwrap();
        w.finish().unwrap();
        let mut want = format!("{}\n", TruthWriter::HEADER).into_bytes();
        for r in &rows {
            truth_line_exact(&mut want, r);
        }
        assert_eq!(std::fs::read(&path).unwrap(), want);
    }
}
