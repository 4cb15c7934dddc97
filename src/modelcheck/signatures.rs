//! Signatures: summaries of an event recording computed *identically* on
//! measured and simulated data, so that a difference between the two points
//! at a missing effect rather than at a difference in processing.
//!
//! Every signature is a histogram with a fixed binning (set by
//! [`SignatureConfig`], never by the data being summarised), a profile (the
//! mean of one quantity per bin of another), or a scalar. The binning of each
//! is chosen so that a known sensor or physics effect moves it:
//!
//! | name | kind | moved by |
//! |---|---|---|
//! | `latency` | histogram of (t − first pulse) mod period, µs | latency jitter, intensity latency, saturation (flattens) |
//! | `event_rate` | scalar, events/s | everything that adds or removes events |
//! | `on_fraction` | scalar, ON / all | OFF events, polarity noise |
//! | `pixel_count` | histogram of events per pixel (all pixels) | hot pixels (long tail), seeding |
//! | `split_half_min` | histogram of min(even-block, odd-block) count per pixel | fixed-pattern activity (hot pixels) |
//! | `split_half_correlation` | scalar, Pearson r of even- vs odd-block counts | fixed pattern vs chance |
//! | `off_burst_rate` | scalar, events/(pixel·s) outside the burst window | background noise |
//! | `off_burst_pixels` | scalar, fraction of pixels with an event outside the burst window | hot pixels (few) vs background (many) |
//! | `off_burst_pixel_count` | histogram of events per pixel outside the burst window, over pixels with any | hot-pixel rate (far tail) vs background (ones) |
//! | `shared_fraction` | scalar, fraction of events sharing (row, timestamp) | arbiter saturation |
//! | `group_size` | histogram of (row, timestamp) group sizes | arbiter saturation |
//! | `tick_events_vs_rows` | profile: events per timestamp tick per bin of distinct rows in the tick | arbiter row time vs event time |
//! | `busy_window_slope` | scalar: slope of events on groups over windows of 8 busy ticks | arbiter row time / event time |
//! | `off_latency` | histogram of the folded time of OFF events | OFF events (their decay time) |
//! | `events_per_pulse` | histogram of events per pulse period | rate limiter (a ceiling), everything that adds or removes events |
//! | `visit_yield` | histogram of events per (pixel, pulse) visit | threshold mismatch (a spread of yields), refractory |
//! | `yield_split_correlation` | scalar, Pearson r of per-pixel events per visit, even vs odd blocks | threshold mismatch (a fixed pattern of yields) |
//! | `extent_x`, `extent_y` | histograms of particle bounding-box extents (needs particles) | pulse streaks (elongation along the flow) |
//! | `elongation` | histogram of extent_x − extent_y per particle (needs particles) | pulse streaks, independent of brightness |
//! | `min_iei` | histogram of per-pixel minimum inter-event interval, µs | refractory period |
//! | `events_per_cluster` | histogram (needs particles) | brightness, threshold |
//! | `latency_vs_brightness` | profile: mean first latency per events-per-cluster bin | intensity-dependent latency |
//! | `elongation_vs_speed` | profile: extent along motion − across, per speed bin (needs tracks) | pulse streaks |
//! | `track_length` | histogram of points per track (needs tracks) | everything that breaks tracks |
//!
//! Split-half consistency: pulses are grouped in blocks of
//! [`SignatureConfig::block_pulses`]; each pixel's events are counted in even
//! and odd blocks separately. Activity driven by moving particles is chance:
//! the two halves are nearly independent (r ≈ 0). A fixed pattern (a hot
//! pixel) fires in both halves: r → 1 and `split_half_min` grows a tail.
//!
//! (Row, timestamp) groups: events with the same timestamp in the same row.
//! When the arbiters saturate, pending events of a row are read out together
//! with one timestamp; an unsaturated sensor gives groups of one (apart from
//! coincidences). Groups are formed over runs of equal timestamps in stream
//! order (readers never reorder time), across chunk boundaries.
//!
//! Yield per visit: a visit is a (pixel, pulse) with events. How many
//! events a visit gives depends on the particle image over the pixel
//! (chance) and on the pixel's contrast threshold (a fixed pattern under
//! threshold mismatch). The even- and odd-block mean yields of a pixel
//! share only the fixed part, so their correlation over pixels is ≈ 0 by
//! chance and grows with the pattern's share of the yield variance. It
//! needs particles whose paths change over the recording (out-of-plane
//! motion, a flow that is not a whole number of pixels per pulse): a
//! uniform flow whose lit particles stay in the sheet sends the same
//! particles at the same sub-pixel phase over the same pixels again and
//! again, a fixed pattern of its own.
//!
//! Elongation: the bounding box of a particle image grows along the motion
//! under pulse streaks. Brightness grows both extents alike, so the
//! difference extent_x − extent_y isolates the streak from the (chancy)
//! brightness of the few hundred particles of a short recording, which
//! swamps `extent_x` alone. Signed: a flow with a dominant direction shifts
//! it (x: up, y: down); mixed directions widen it.
//!
//! Off-burst pixels: background activity spreads a few events over many
//! pixels, hot pixels many events over few. The fraction of pixels with any
//! event outside the burst window and the distribution of those pixels'
//! off-burst counts separate the two and pin a hot pixel's count and rate
//! independently (their product alone is what `off_burst_rate` sees). Both
//! need a fixed [`SignatureConfig::burst_window_us`] (the per-pixel counts
//! are taken while streaming); without one they are left out.
//!
//! Timestamp ticks: a saturated row arbiter spends `row_time` per granted
//! row and `event_time` per event, so in a busy tick R·row_time +
//! E·event_time ≈ one tick: the mean events per tick E falls along a line
//! in the distinct rows per tick R whose slope is −row_time/event_time. The
//! latency histogram sees only the total service time; this profile tells
//! the two times apart. Only ticks whose neighbours both have events count
//! (inside a busy period), so the edges of a burst, where the server idles
//! part of a tick, do not blur the line.
//!
//! Busy windows: the same relation summed over [`BUSY_WINDOW_TICKS`]
//! consecutive busy ticks, G·row_time + E·event_time ≈ 8 µs for the G
//! (row, timestamp) groups (one per grant) and E events in them. A single
//! tick holds only one to three grants of a few hundred ns, so which tick
//! a grant falls in blurs the per-tick line; over eight ticks the edges
//! cut about one grant each and the line (slope −row_time/event_time)
//! stands out. Its least-squares slope over all windows is the signature
//! (a profile's per-bin means spread the few hundred windows of a short
//! recording too thin). This is what tells the row time from the event time when
//! the event time dominates the readout of a burst (the latency histogram
//! then pins only their weighted sum).
//!
//! Everything streams: [`SignatureAccumulator::add_events`] takes chunks in
//! order; per-pixel state is a few arrays of the sensor size.

use std::collections::HashMap;

pub mod reference;

use serde::{Deserialize, Serialize};

use crate::cluster::Particle;
use crate::error::{Error, Result};
use crate::events::{EventChunk, Geometry, ON};
use crate::pulses::PulseTiming;
use crate::track::Track;

/// How a histogram's bins are placed on the line when measuring distances
/// between distributions (see [`super::distance`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum BinScale {
    /// Bin centres in the quantity's own unit (µs for latency).
    Linear,
    /// Bin index: for roughly geometric binnings (counts, intervals), so a
    /// distance is in "bins", i.e. roughly in log units, and a tail of huge
    /// values does not swamp everything else.
    Index,
}

/// Counts on fixed bins. Values below the first edge are counted in the
/// first bin, values at or beyond the last edge in the last bin (so the
/// last bin is "≥ its left edge"), NaN is dropped.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Histogram {
    pub edges: Vec<f64>,
    pub counts: Vec<f64>,
    pub scale: BinScale,
}

impl Histogram {
    /// `edges`: at least two, finite, strictly increasing.
    pub fn new(edges: Vec<f64>, scale: BinScale) -> Result<Self> {
        if edges.len() < 2 {
            return Err(Error::param("histogram edges", "need at least two edges"));
        }
        if edges.iter().any(|e| !e.is_finite())
            || edges
                .windows(2)
                .any(|w| w[1].partial_cmp(&w[0]) != Some(std::cmp::Ordering::Greater))
        {
            return Err(Error::param(
                "histogram edges",
                "must be finite and strictly increasing",
            ));
        }
        let n = edges.len() - 1;
        Ok(Histogram {
            edges,
            counts: vec![0.0; n],
            scale,
        })
    }

    pub fn n_bins(&self) -> usize {
        self.counts.len()
    }

    /// Bin of `v` (clamped to the first / last bin), `None` for NaN.
    #[inline]
    pub fn bin_of(&self, v: f64) -> Option<usize> {
        if v.is_nan() {
            return None;
        }
        let k = self.edges.partition_point(|e| *e <= v);
        Some(k.saturating_sub(1).min(self.counts.len() - 1))
    }

    #[inline]
    pub fn add(&mut self, v: f64) {
        self.add_weighted(v, 1.0);
    }

    #[inline]
    pub fn add_weighted(&mut self, v: f64, w: f64) {
        if let Some(k) = self.bin_of(v) {
            self.counts[k] += w;
        }
    }

    pub fn total(&self) -> f64 {
        self.counts.iter().sum()
    }

    /// Where each bin sits on the line for distance computations.
    pub fn positions(&self) -> Vec<f64> {
        match self.scale {
            BinScale::Linear => self.edges.windows(2).map(|w| 0.5 * (w[0] + w[1])).collect(),
            BinScale::Index => (0..self.counts.len()).map(|k| k as f64).collect(),
        }
    }

    /// Centre of the bin holding `v` (`v` itself for NaN).
    pub fn bin_centre(&self, v: f64) -> f64 {
        match self.bin_of(v) {
            Some(k) => 0.5 * (self.edges[k] + self.edges[k + 1]),
            None => v,
        }
    }

    /// Same bins (edges and scale)?
    pub fn same_bins(&self, other: &Histogram) -> bool {
        self.scale == other.scale && self.edges == other.edges
    }
}

/// Mean of a quantity per bin of another (e.g. latency per brightness).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Profile {
    pub edges: Vec<f64>,
    /// Mean per bin (NaN where the bin is empty).
    pub mean: Vec<f64>,
    /// Samples per bin.
    pub count: Vec<f64>,
}

/// Accumulates a [`Profile`].
#[derive(Debug, Clone)]
struct ProfileAcc {
    bins: Histogram,
    sum: Vec<f64>,
}

impl ProfileAcc {
    fn new(edges: Vec<f64>) -> Result<Self> {
        let bins = Histogram::new(edges, BinScale::Index)?;
        let n = bins.n_bins();
        Ok(ProfileAcc {
            bins,
            sum: vec![0.0; n],
        })
    }
    fn add(&mut self, x: f64, v: f64) {
        if !v.is_finite() {
            return;
        }
        if let Some(k) = self.bins.bin_of(x) {
            self.bins.counts[k] += 1.0;
            self.sum[k] += v;
        }
    }
    fn finish(&self) -> Profile {
        Profile {
            edges: self.bins.edges.clone(),
            mean: self
                .sum
                .iter()
                .zip(&self.bins.counts)
                .map(|(s, c)| if *c > 0.0 { s / c } else { f64::NAN })
                .collect(),
            count: self.bins.counts.clone(),
        }
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub enum SignatureValue {
    Histogram(Histogram),
    Profile(Profile),
    Scalar { value: f64 },
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Signature {
    pub name: String,
    /// What is counted and in which unit (for tables and figure labels).
    pub description: String,
    pub value: SignatureValue,
}

/// All signatures of one recording, in a fixed order.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Signatures {
    pub items: Vec<Signature>,
    /// Events inside the geometry that entered the signatures.
    pub n_events: u64,
    /// Events outside the configured geometry (ignored).
    pub n_outside: u64,
    /// Time span covered (µs): last − first event time.
    pub duration_us: f64,
}

impl Signatures {
    pub fn get(&self, name: &str) -> Option<&Signature> {
        self.items.iter().find(|s| s.name == name)
    }
    pub fn scalar(&self, name: &str) -> Option<f64> {
        match self.get(name)?.value {
            SignatureValue::Scalar { value } => Some(value),
            _ => None,
        }
    }
    pub fn histogram(&self, name: &str) -> Option<&Histogram> {
        match &self.get(name)?.value {
            SignatureValue::Histogram(h) => Some(h),
            _ => None,
        }
    }
    pub fn profile(&self, name: &str) -> Option<&Profile> {
        match &self.get(name)?.value {
            SignatureValue::Profile(p) => Some(p),
            _ => None,
        }
    }
}

/// Binning and windows shared by the measured and every simulated data set.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SignatureConfig {
    pub geometry: Geometry,
    pub timing: PulseTiming,
    /// Bin width of the folded latency histogram (µs).
    pub latency_bin_us: f64,
    /// Burst window in folded time, `[start, end)` µs after the pulse start;
    /// `end` may exceed the period (the window wraps). `None`: derived from
    /// the data's own latency histogram (quick looks only — a comparison
    /// must fix it, e.g. from the measurement with [`burst_window`]).
    pub burst_window_us: Option<(f64, f64)>,
    /// Pulses per block for the split-half consistency.
    pub block_pulses: u64,
    /// Speed bin edges (px/s) for `elongation_vs_speed`.
    pub speed_edges: Vec<f64>,
}

impl SignatureConfig {
    /// Defaults: ~1 µs latency bins (at most 400 bins), blocks of 50 pulses,
    /// speed bins 0–20 000 px/s in steps of 2000.
    pub fn new(geometry: Geometry, timing: PulseTiming) -> Self {
        let latency_bin_us = (timing.period_us / 400.0).max(1.0);
        SignatureConfig {
            geometry,
            timing,
            latency_bin_us,
            burst_window_us: None,
            block_pulses: 50,
            speed_edges: (0..=10).map(|k| k as f64 * 2000.0).collect(),
        }
    }

    fn validate(&self) -> Result<()> {
        if self.geometry.pixels() == 0 {
            return Err(Error::param("geometry", "has no pixels"));
        }
        let p = self.timing.period_us;
        if !(p.is_finite() && p > 0.0) {
            return Err(Error::param("period_us", format!("{p} must be > 0")));
        }
        if !self.timing.first_pulse_us.is_finite() {
            return Err(Error::param("first_pulse_us", "must be finite"));
        }
        let b = self.latency_bin_us;
        if !(b.is_finite() && b > 0.0 && b <= p) {
            return Err(Error::param(
                "latency_bin_us",
                format!("{b} must be in (0, period = {p}]"),
            ));
        }
        if self.block_pulses == 0 {
            return Err(Error::param("block_pulses", "must be ≥ 1"));
        }
        if let Some((a, e)) = self.burst_window_us {
            if !(a.is_finite() && e.is_finite() && e > a && e - a <= p) {
                return Err(Error::param(
                    "burst_window_us",
                    format!("({a}, {e}) must be finite, start < end, at most one period long"),
                ));
            }
        }
        Ok(())
    }

    fn latency_edges(&self) -> Vec<f64> {
        let p = self.timing.period_us;
        let n = (p / self.latency_bin_us).ceil().max(1.0) as usize;
        let w = p / n as f64;
        (0..=n).map(|k| k as f64 * w).collect()
    }
}

/// Edges for counts spanning orders of magnitude: 0..16 exactly, then
/// geometric with ratio 2^(1/4) (about 19 % wide bins: fine enough to place
/// a tail of hot pixels, coarse enough to stay populated).
pub fn count_edges(max: f64) -> Vec<f64> {
    let mut e: Vec<f64> = (0..=16).map(|k| k as f64).collect();
    let mut x = 16.0f64;
    while x < max {
        x = (x * 2f64.powf(0.25)).round();
        e.push(x);
    }
    e
}

/// Edges for intervals (µs): [0, 1), then 4 bins per decade up to 10 s.
pub fn interval_edges() -> Vec<f64> {
    let mut e = vec![0.0];
    for k in 0..=28 {
        e.push(10f64.powf(k as f64 / 4.0));
    }
    e
}

/// Smallest circular window around the peak of a folded latency histogram
/// holding at least `fraction` of the events: grown bin by bin towards the
/// fuller neighbour. Returns `[start, end)` µs (end may exceed the period).
pub fn burst_window(latency: &Histogram, fraction: f64) -> Result<(f64, f64)> {
    let total = latency.total();
    if total <= 0.0 {
        return Err(Error::analysis(
            "no events in the latency histogram: cannot locate the burst",
        ));
    }
    if !(fraction > 0.0 && fraction <= 1.0) {
        return Err(Error::param(
            "burst fraction",
            format!("{fraction} must be in (0, 1]"),
        ));
    }
    let n = latency.n_bins();
    let c = &latency.counts;
    let peak = (0..n)
        .max_by(|&a, &b| c[a].total_cmp(&c[b]).then(b.cmp(&a)))
        .unwrap_or(0);
    let (mut lo, mut hi) = (peak as i64, peak as i64); // inclusive, circular
    let mut mass = c[peak];
    let at = |k: i64| c[k.rem_euclid(n as i64) as usize];
    while mass < fraction * total && ((hi - lo + 1) as usize) < n {
        let (left, right) = (at(lo - 1), at(hi + 1));
        if right >= left {
            hi += 1;
            mass += right;
        } else {
            lo -= 1;
            mass += left;
        }
    }
    let w = latency.edges[1] - latency.edges[0];
    let start = latency.edges[0] + lo as f64 * w;
    let end = latency.edges[0] + (hi + 1) as f64 * w;
    let period = latency.edges[n] - latency.edges[0];
    let shift = (start.div_euclid(period)) * period;
    Ok((start - shift, end - shift))
}

/// The burst window as the complement of the quietest part of the period:
/// the circular run of bins holding `quiet_fraction` of the period with
/// the fewest events is "off-burst", the rest is the burst. Returns
/// `[start, end)` µs (end may exceed the period), as [`burst_window`].
///
/// Unlike [`burst_window`]'s share of the events, this window does not
/// reach into the tails of the latency distribution: events there are the
/// floor of the folded histogram (background activity, hot pixels), not
/// the latency model's tails, whose shape differs from one sensor model to
/// another.
pub fn quiet_complement(latency: &Histogram, quiet_fraction: f64) -> Result<(f64, f64)> {
    if latency.total() <= 0.0 {
        return Err(Error::analysis(
            "no events in the latency histogram: cannot locate the burst",
        ));
    }
    if !(quiet_fraction > 0.0 && quiet_fraction < 1.0) {
        return Err(Error::param(
            "quiet fraction",
            format!("{quiet_fraction} must be in (0, 1)"),
        ));
    }
    let n = latency.n_bins();
    let k = ((quiet_fraction * n as f64).round() as usize).clamp(1, n - 1);
    let c = &latency.counts;
    let sum_at = |a: usize| (0..k).map(|j| c[(a + j) % n]).sum::<f64>();
    let best = (0..n)
        .min_by(|&a, &b| sum_at(a).total_cmp(&sum_at(b)).then(a.cmp(&b)))
        .unwrap_or(0);
    let w = latency.edges[1] - latency.edges[0];
    let period = latency.edges[n] - latency.edges[0];
    // Burst: from the end of the quiet run round to its start.
    let start = latency.edges[0] + ((best + k) % n) as f64 * w;
    Ok((start, start + period - k as f64 * w))
}

/// Streaming computation of [`Signatures`].
///
/// Fast path ([`reference::ReferenceAccumulator`] is the plain
/// version the tests compare it with, signature for signature): the
/// per-pixel state is one 32-byte record per pixel ([`PixelState`]), so
/// an event touches one cache line instead of eight arrays of the sensor
/// size (a 640x360 sensor's state does not fit in cache, and the events of
/// a burst land all over it); every histogram fed per event or per pixel
/// counts integers per bin and bins through a lookup table or the uniform
/// spacing ([`IntBins`], [`UniformBins`]) instead of a binary search per
/// value. Counts are exact integers either way, so the signatures are
/// identical, not just close.
pub struct SignatureAccumulator {
    cfg: SignatureConfig,
    latency: UniformBins,
    latency_counts: Vec<u64>,
    /// Per latency bin: is its centre outside the burst window (only with
    /// a fixed window)?
    latency_outside: Option<Vec<bool>>,
    /// Folded time of OFF events (same bins as `latency`).
    off_latency_counts: Vec<u64>,
    /// Events per pulse: the pulse being counted and its count so far.
    pulse_now: i64,
    pulse_count: u64,
    pulse_counts: Vec<u64>,
    /// The pulse the even/odd flag was taken for, and whether it lies in
    /// an even block.
    block_pulse: i64,
    block_even: bool,
    pix: Vec<PixelState>,
    /// Visits per number of events (index: events, saturating at 16 and
    /// above, which share the last bin).
    visit_yield: Vec<u64>,
    n_events: u64,
    n_on: u64,
    n_outside: u64,
    t_min: i64,
    t_max: i64,
    // (row, timestamp) grouping over runs of equal timestamps.
    run_t: i64,
    run_rows: Vec<u16>,
    /// Groups per size (index: size).
    group_sizes: Vec<u64>,
    shared_events: u64,
    tick_events: ProfileAcc,
    /// The last tick seen: (timestamp, distinct rows, events, whether the
    /// tick before it had events too).
    last_tick: Option<(i64, usize, usize, bool)>,
    /// The last busy tick and the (groups, events) of the busy ticks up to
    /// it (at most a window's worth, all consecutive).
    busy_last: i64,
    busy_ticks: std::collections::VecDeque<(usize, usize)>,
    /// Σ over busy windows of (1, G, E, G², G·E).
    window_sums: [f64; 5],
    /// Events per pixel outside the burst window (only with a fixed window;
    /// apart from [`PixelState`]: it is touched only by the few events
    /// outside the burst).
    count_off_burst: Option<Vec<u32>>,
    /// (events, first latency, extent x, extent y) per particle.
    particles: Vec<(u32, f32, f32, f32)>,
    elongation: Option<ProfileAcc>,
    track_lengths: Vec<u32>,
}

/// Everything the accumulator keeps per pixel, in one record.
///
/// The pixel's current visit (the pulse of its last event) is not stored:
/// it is the pulse of `last_t`, recomputed (a division costs less than the
/// cache line another 8 bytes per pixel would spill into).
#[derive(Debug, Clone, Copy)]
#[repr(C, align(32))]
struct PixelState {
    /// Time of the last event (`NO_TIME`: none yet).
    last_t: i64,
    /// Smallest interval between two events, µs, capped at
    /// `u32::MAX - 1` (far inside the last `min_iei` bin, which starts at
    /// 10⁷ µs); `u32::MAX`: no interval yet.
    min_dt: u32,
    count_even: u32,
    count_odd: u32,
    visits_even: u32,
    visits_odd: u32,
    /// Events in the current visit (saturating).
    visit_events: u16,
}

const NO_INTERVAL: u32 = u32::MAX;

impl PixelState {
    const EMPTY: PixelState = PixelState {
        last_t: NO_TIME,
        min_dt: NO_INTERVAL,
        count_even: 0,
        count_odd: 0,
        visits_even: 0,
        visits_odd: 0,
        visit_events: 0,
    };
}

/// Binning of a histogram with uniformly spaced edges (the folded latency):
/// the bin from the spacing, corrected against the edges so that it is the
/// bin [`Histogram::bin_of`] finds.
#[derive(Debug, Clone)]
struct UniformBins {
    hist: Histogram,
    inv_width: f64,
}

impl UniformBins {
    fn new(hist: Histogram) -> Self {
        let n = hist.n_bins();
        let inv_width = n as f64 / (hist.edges[n] - hist.edges[0]);
        UniformBins { hist, inv_width }
    }

    /// Same as `self.hist.bin_of(v)`.
    #[inline]
    fn bin_of(&self, v: f64) -> Option<usize> {
        if v.is_nan() {
            return None;
        }
        let e = &self.hist.edges;
        let n = e.len() - 1;
        let guess = (v - e[0]) * self.inv_width;
        // `as usize` saturates (and maps a negative guess to 0).
        let mut k = (guess as usize).min(n - 1);
        while k > 0 && e[k] > v {
            k -= 1;
        }
        while k + 1 < n && e[k + 1] <= v {
            k += 1;
        }
        Some(k)
    }

    /// The histogram with `counts` in its bins.
    fn with_counts(&self, counts: &[u64]) -> Histogram {
        let mut h = self.hist.clone();
        for (c, &n) in h.counts.iter_mut().zip(counts) {
            *c = n as f64;
        }
        h
    }
}

/// Binning of non-negative integers (counts, intervals in µs) on any
/// edges: a table of [`Histogram::bin_of`] for the small values, which
/// are nearly all of them, the binary search beyond.
#[derive(Debug, Clone)]
struct IntBins {
    hist: Histogram,
    table: Vec<u16>,
    counts: Vec<u64>,
}

/// Values binned by table in [`IntBins`].
const INT_TABLE: usize = 4096;

impl IntBins {
    fn new(hist: Histogram) -> Self {
        let table = (0..INT_TABLE)
            .map(|v| hist.bin_of(v as f64).expect("not NaN") as u16)
            .collect();
        let counts = vec![0; hist.n_bins()];
        IntBins {
            hist,
            table,
            counts,
        }
    }

    #[inline]
    fn add(&mut self, v: u64) {
        let k = match self.table.get(v as usize) {
            Some(&k) => k as usize,
            None => self.hist.bin_of(v as f64).expect("not NaN"),
        };
        self.counts[k] += 1;
    }

    fn finish(mut self) -> Histogram {
        for (c, &n) in self.hist.counts.iter_mut().zip(&self.counts) {
            *c = n as f64;
        }
        self.hist
    }
}

/// Events ahead whose pixel record [`SignatureAccumulator::add_events`]
/// prefetches: enough to cover a memory latency with the work of the
/// events between.
const PREFETCH_AHEAD: usize = 12;

/// Hint the cache to fetch `*r` (no effect on results; a no-op off x86-64).
#[inline(always)]
fn prefetch<T>(r: &T) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        // SAFETY: a prefetch never faults, and the address is a live reference.
        unsafe { _mm_prefetch::<_MM_HINT_T0>(r as *const T as *const i8) };
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = r;
}

/// `x.floor() as i64` without the libm call (the baseline x86-64 target
/// has no rounding instruction): truncation, one down for negative
/// non-integers; saturating as `as` does, 0 for NaN.
#[inline(always)]
fn floor_i64(x: f64) -> i64 {
    let q = x as i64;
    if (q as f64) > x {
        q.saturating_sub(1)
    } else {
        q
    }
}

const NO_TIME: i64 = i64::MIN;

/// Ticks per busy window of `busy_window_slope`: long enough
/// that the grants cut by the window's edges (about one per edge) are a
/// small part of it, short enough for a few windows per burst.
pub const BUSY_WINDOW_TICKS: usize = 8;

/// Upper end of the per-pixel count binning (the last bin is "≥ this").
/// Fixed, never taken from the data, so every data set shares the bins.
const MAX_COUNT_EDGE: f64 = (1u64 << 24) as f64;

/// Bins of `visit_yield` and `events_per_cluster`: 1, 2, …, 16 and more.
fn yield_edges() -> Vec<f64> {
    (1..=17).map(|k| k as f64).collect()
}

impl SignatureAccumulator {
    pub fn new(cfg: SignatureConfig) -> Result<Self> {
        cfg.validate()?;
        let latency = UniformBins::new(Histogram::new(cfg.latency_edges(), BinScale::Linear)?);
        let n_lat = latency.hist.n_bins();
        let period = cfg.timing.period_us;
        let latency_outside = cfg.burst_window_us.map(|w| {
            latency
                .hist
                .edges
                .windows(2)
                .map(|e| outside_window(0.5 * (e[0] + e[1]), w, period))
                .collect()
        });
        let n = cfg.geometry.pixels();
        Ok(SignatureAccumulator {
            latency,
            latency_counts: vec![0; n_lat],
            latency_outside,
            off_latency_counts: vec![0; n_lat],
            pulse_now: NO_TIME,
            pulse_count: 0,
            pulse_counts: Vec::new(),
            block_pulse: NO_TIME,
            block_even: true,
            pix: vec![PixelState::EMPTY; n],
            visit_yield: vec![0; 17],
            n_events: 0,
            n_on: 0,
            n_outside: 0,
            t_min: i64::MAX,
            t_max: i64::MIN,
            run_t: NO_TIME,
            run_rows: Vec::new(),
            group_sizes: Vec::new(),
            shared_events: 0,
            tick_events: ProfileAcc::new(count_edges(65536.0)[1..].to_vec())?,
            last_tick: None,
            busy_last: NO_TIME,
            busy_ticks: Default::default(),
            window_sums: [0.0; 5],
            count_off_burst: cfg.burst_window_us.map(|_| vec![0; n]),
            particles: Vec::new(),
            elongation: None,
            track_lengths: Vec::new(),
            cfg,
        })
    }

    pub fn config(&self) -> &SignatureConfig {
        &self.cfg
    }

    /// Add a chunk of events (chunks in stream order).
    pub fn add_events(&mut self, ev: &EventChunk) {
        let g = self.cfg.geometry;
        let width = g.width as usize;
        let period = self.cfg.timing.period_us;
        let first = self.cfg.timing.first_pulse_us;
        let block = self.cfg.block_pulses as i64;
        for i in 0..ev.len() {
            // The events of a burst land all over the sensor: ask for the
            // pixel record of an event a few ahead while this one is done.
            if let Some(j) = i.checked_add(PREFETCH_AHEAD).filter(|&j| j < ev.len()) {
                if g.contains(ev.x[j], ev.y[j]) {
                    prefetch(&self.pix[ev.y[j] as usize * width + ev.x[j] as usize]);
                }
            }
            let (t, x, y, p) = (ev.t[i], ev.x[i], ev.y[i], ev.p[i]);
            if !g.contains(x, y) {
                self.n_outside += 1;
                continue;
            }
            self.n_events += 1;
            self.n_on += (p == ON) as u64;
            self.t_min = self.t_min.min(t);
            self.t_max = self.t_max.max(t);

            let rel = t as f64 - first;
            let folded = rel.rem_euclid(period);
            let lat_bin = self.latency.bin_of(folded);
            if let Some(k) = lat_bin {
                self.latency_counts[k] += 1;
                if p != ON {
                    self.off_latency_counts[k] += 1;
                }
            }
            let pulse = floor_i64(rel / period);
            if pulse != self.pulse_now {
                if self.pulse_count > 0 {
                    self.pulse_counts.push(self.pulse_count);
                }
                self.pulse_now = pulse;
                self.pulse_count = 0;
            }
            self.pulse_count += 1;
            if pulse != self.block_pulse {
                self.block_pulse = pulse;
                self.block_even = pulse.div_euclid(block) % 2 == 0;
            }
            let pix = y as usize * width + x as usize;
            let s = &mut self.pix[pix];
            let last = s.last_t;
            // A new visit unless the pixel's last event is in this pulse
            // (its pulse computed exactly as this event's).
            if last == NO_TIME || floor_i64((last as f64 - first) / period) != pulse {
                if last != NO_TIME {
                    self.visit_yield[(s.visit_events as usize).min(16)] += 1;
                }
                s.visit_events = 0;
                if self.block_even {
                    s.visits_even += 1;
                } else {
                    s.visits_odd += 1;
                }
            }
            s.visit_events = s.visit_events.saturating_add(1);
            if self.block_even {
                s.count_even += 1;
            } else {
                s.count_odd += 1;
            }
            if last != NO_TIME {
                // Readers never reorder time; a backwards step is data, and
                // its size is still an interval between two events.
                let dt = (t - last).unsigned_abs().min(NO_INTERVAL as u64 - 1) as u32;
                s.min_dt = s.min_dt.min(dt);
            }
            s.last_t = t;
            if let (Some(out), Some(c), Some(k)) = (
                self.latency_outside.as_ref(),
                self.count_off_burst.as_mut(),
                lat_bin,
            ) {
                // Folded time, binned as the latency histogram bins it, so
                // the per-pixel counts agree with `off_burst_rate`.
                if out[k] {
                    c[pix] += 1;
                }
            }

            if t != self.run_t {
                self.flush_run();
                self.run_t = t;
            }
            self.run_rows.push(y);
        }
    }

    fn flush_run(&mut self) {
        if self.run_rows.is_empty() {
            return;
        }
        self.run_rows.sort_unstable();
        let rows = std::mem::take(&mut self.run_rows);
        let distinct = rows.chunk_by(|a, b| a == b).count();
        // Only ticks inside a busy period (the ticks before and after have
        // events too): there the server never idles, and R·row_time +
        // E·event_time fills the tick.
        let t = self.run_t;
        let mut after_busy = false;
        if let Some((pt, r, e, before)) = self.last_tick {
            after_busy = pt == t - 1;
            if before && after_busy {
                self.tick_events.add(r as f64, e as f64);
                self.add_busy_tick(pt, r, e);
            }
        }
        self.last_tick = Some((t, distinct, rows.len(), after_busy));
        for group in rows.chunk_by(|a, b| a == b) {
            let s = group.len() as u32;
            let s = s as usize;
            if self.group_sizes.len() <= s {
                self.group_sizes.resize(s + 1, 0);
            }
            self.group_sizes[s] += 1;
            if s >= 2 {
                self.shared_events += s as u64;
            }
        }
        self.run_rows = rows;
        self.run_rows.clear();
    }

    /// A tick inside a busy period extends the current run of busy ticks
    /// (or starts one when it does not follow the last); every window of
    /// [`BUSY_WINDOW_TICKS`] consecutive busy ticks (sliding: overlapping
    /// windows use every phase of the grants against the tick grid) adds
    /// its (groups, events) point to the regression sums.
    fn add_busy_tick(&mut self, t: i64, groups: usize, events: usize) {
        if self.busy_last != NO_TIME && t != self.busy_last + 1 {
            self.busy_ticks.clear();
        }
        self.busy_last = t;
        self.busy_ticks.push_back((groups, events));
        if self.busy_ticks.len() > BUSY_WINDOW_TICKS {
            self.busy_ticks.pop_front();
        }
        if self.busy_ticks.len() == BUSY_WINDOW_TICKS {
            let (g, e) = self
                .busy_ticks
                .iter()
                .fold((0usize, 0usize), |a, b| (a.0 + b.0, a.1 + b.1));
            let (g, e) = (g as f64, e as f64);
            for (s, v) in self.window_sums.iter_mut().zip([1.0, g, e, g * g, g * e]) {
                *s += v;
            }
        }
    }

    /// Add clustered particles (any order).
    pub fn add_particles(&mut self, particles: &[Particle]) {
        self.particles.extend(
            particles
                .iter()
                .map(|p| (p.n_events, p.first_latency_us, p.extent_x, p.extent_y)),
        );
    }

    /// Add tracks, with the particles they were built from (for the
    /// elongation of each tracked particle image). A particle is matched to
    /// the track point at the same pulse nearest to it, within 2 px.
    pub fn add_tracks(&mut self, tracks: &[Track], particles: &[Particle]) -> Result<()> {
        if self.elongation.is_none() {
            self.elongation =
                Some(ProfileAcc::new(self.cfg.speed_edges.clone()).map_err(|_| {
                    Error::param(
                        "speed_edges",
                        "need ≥ 2 finite, strictly increasing edges (px/s)",
                    )
                })?);
        }
        self.track_lengths
            .extend(tracks.iter().map(|t| t.points.len() as u32));
        let mut by_pulse: HashMap<i64, Vec<(f64, f64, f64, f64)>> = HashMap::new();
        for tr in tracks {
            for pt in &tr.points {
                if !pt.interpolated {
                    by_pulse
                        .entry(pt.pulse)
                        .or_default()
                        .push((pt.x, pt.y, pt.u, pt.v));
                }
            }
        }
        let acc = self.elongation.as_mut().expect("set above");
        for p in particles {
            let Some(cands) = by_pulse.get(&p.pulse) else {
                continue;
            };
            let best = cands
                .iter()
                .map(|c| ((c.0 - p.x).powi(2) + (c.1 - p.y).powi(2), c))
                .min_by(|a, b| a.0.total_cmp(&b.0));
            if let Some((d2, &(_, _, u, v))) = best {
                if d2 <= 4.0 {
                    let (ex, ey) = (p.extent_x as f64, p.extent_y as f64);
                    let along_minus_across = if u.abs() >= v.abs() { ex - ey } else { ey - ex };
                    acc.add(u.hypot(v), along_minus_across);
                }
            }
        }
        Ok(())
    }

    /// Finish: all signatures. Errors when no event fell inside the sensor.
    pub fn finish(mut self) -> Result<Signatures> {
        self.flush_run();
        if self.n_events == 0 {
            return Err(Error::analysis(
                "no events inside the sensor geometry: no signatures",
            ));
        }
        let duration_us = (self.t_max - self.t_min) as f64;
        let seconds = (duration_us.max(self.cfg.timing.period_us)) * 1e-6;
        let n_pix = self.cfg.geometry.pixels() as f64;
        let mut items = Vec::new();
        let mut push = |name: &str, description: &str, value: SignatureValue| {
            items.push(Signature {
                name: name.into(),
                description: description.into(),
                value,
            })
        };

        let latency = self.latency.with_counts(&self.latency_counts);
        push(
            "latency",
            "events per folded time bin, (t - first pulse) mod period (us)",
            SignatureValue::Histogram(latency.clone()),
        );
        push(
            "event_rate",
            "events per second",
            SignatureValue::Scalar {
                value: self.n_events as f64 / seconds,
            },
        );
        push(
            "on_fraction",
            "fraction of ON events",
            SignatureValue::Scalar {
                value: self.n_on as f64 / self.n_events as f64,
            },
        );

        // One pass over the pixels for every per-pixel histogram; the
        // yields of pixels visited in both halves in pixel order (the
        // correlation sums in that order, as the reference does).
        let edges = count_edges(MAX_COUNT_EDGE);
        let mut pixel_count = IntBins::new(Histogram::new(edges.clone(), BinScale::Index)?);
        let mut split_min = IntBins::new(Histogram::new(edges, BinScale::Index)?);
        let mut iei = IntBins::new(Histogram::new(interval_edges(), BinScale::Index)?);
        let mut visit_yield = self.visit_yield.clone();
        let (mut ye, mut yo) = (Vec::new(), Vec::new());
        let (mut sum_even, mut sum_odd) = (0u64, 0u64);
        for s in &self.pix {
            let (a, b) = (s.count_even, s.count_odd);
            pixel_count.add((a + b) as u64);
            split_min.add(a.min(b) as u64);
            sum_even += a as u64;
            sum_odd += b as u64;
            if s.min_dt != NO_INTERVAL {
                iei.add(s.min_dt as u64);
            }
            if s.last_t != NO_TIME {
                visit_yield[(s.visit_events as usize).min(16)] += 1;
            }
            let (ve, vo) = (s.visits_even, s.visits_odd);
            if ve > 0 && vo > 0 {
                ye.push(a as f64 / ve as f64);
                yo.push(b as f64 / vo as f64);
            }
        }
        push(
            "pixel_count",
            "pixels per bin of events per pixel",
            SignatureValue::Histogram(pixel_count.finish()),
        );
        push(
            "split_half_min",
            "pixels per bin of min(even-block, odd-block) event count",
            SignatureValue::Histogram(split_min.finish()),
        );
        push(
            "split_half_correlation",
            "Pearson r of per-pixel counts in even vs odd pulse blocks",
            SignatureValue::Scalar {
                value: pixel_pearson(&self.pix, sum_even, sum_odd),
            },
        );

        let window = match self.cfg.burst_window_us {
            Some(w) => w,
            None => burst_window(&latency, 0.95)?,
        };
        let period = self.cfg.timing.period_us;
        let off: f64 = latency
            .positions()
            .iter()
            .zip(&latency.counts)
            .filter(|(c, _)| outside_window(**c, window, period))
            .map(|(_, n)| n)
            .sum();
        push(
            "off_burst_rate",
            "events per pixel per second outside the burst window",
            SignatureValue::Scalar {
                value: off / n_pix / seconds,
            },
        );

        if let Some(c) = &self.count_off_burst {
            let mut hist = IntBins::new(Histogram::new(
                count_edges(MAX_COUNT_EDGE)[1..].to_vec(),
                BinScale::Index,
            )?);
            let mut active = 0usize;
            for &k in c.iter().filter(|&&k| k > 0) {
                hist.add(k as u64);
                active += 1;
            }
            push(
                "off_burst_pixels",
                "fraction of pixels with an event outside the burst window",
                SignatureValue::Scalar {
                    value: active as f64 / n_pix,
                },
            );
            push(
                "off_burst_pixel_count",
                "pixels per bin of their events outside the burst window (pixels with any)",
                SignatureValue::Histogram(hist.finish()),
            );
        }

        push(
            "shared_fraction",
            "fraction of events sharing (row, timestamp) with another event",
            SignatureValue::Scalar {
                value: self.shared_events as f64 / self.n_events as f64,
            },
        );
        let mut groups = Histogram::new(count_edges(65536.0)[1..].to_vec(), BinScale::Index)?;
        for (s, &n) in self.group_sizes.iter().enumerate() {
            if n > 0 {
                groups.add_weighted(s as f64, n as f64);
            }
        }
        push(
            "group_size",
            "(row, timestamp) groups per bin of group size",
            SignatureValue::Histogram(groups),
        );

        push(
            "tick_events_vs_rows",
            "mean events per timestamp tick per bin of distinct rows in the tick",
            SignatureValue::Profile(self.tick_events.finish()),
        );

        push(
            "busy_window_slope",
            "least-squares slope of events on (row, timestamp) groups over windows of 8 busy ticks",
            SignatureValue::Scalar {
                value: regression_slope(&self.window_sums),
            },
        );

        push(
            "min_iei",
            "pixels per bin of their minimum inter-event interval (us)",
            SignatureValue::Histogram(iei.finish()),
        );

        push(
            "off_latency",
            "OFF events per folded time bin (us)",
            SignatureValue::Histogram(self.latency.with_counts(&self.off_latency_counts)),
        );
        if self.pulse_count > 0 {
            self.pulse_counts.push(self.pulse_count);
        }
        let mut per_pulse = IntBins::new(Histogram::new(
            count_edges(MAX_COUNT_EDGE)[1..].to_vec(),
            BinScale::Index,
        )?);
        for &c in &self.pulse_counts {
            per_pulse.add(c);
        }
        push(
            "events_per_pulse",
            "pulse periods per bin of their events (periods with any)",
            SignatureValue::Histogram(per_pulse.finish()),
        );
        let mut yields = Histogram::new(yield_edges(), BinScale::Index)?;
        for (v, &n) in visit_yield.iter().enumerate() {
            if n > 0 {
                yields.add_weighted(v as f64, n as f64);
            }
        }
        push(
            "visit_yield",
            "(pixel, pulse) visits per number of events in them",
            SignatureValue::Histogram(yields),
        );
        push(
            "yield_split_correlation",
            "Pearson r of per-pixel events per visit in even vs odd pulse blocks (pixels visited in both)",
            SignatureValue::Scalar {
                value: pearson_f64(&ye, &yo),
            },
        );

        if !self.particles.is_empty() {
            let mut epc = Histogram::new((1..=17).map(|k| k as f64).collect(), BinScale::Index)?;
            let mut lat = ProfileAcc::new(vec![1.0, 2.0, 3.0, 4.0, 5.0, 7.0, 10.0, 16.0])?;
            let extent_edges: Vec<f64> = (1..=13).map(|k| k as f64).collect();
            let mut ext_x = Histogram::new(extent_edges.clone(), BinScale::Index)?;
            let mut ext_y = Histogram::new(extent_edges, BinScale::Index)?;
            // Integer differences at the bin centres, ±6 px and beyond in
            // the end bins.
            let mut elongation =
                Histogram::new((-6..=7).map(|k| k as f64 - 0.5).collect(), BinScale::Linear)?;
            for &(n, l, ex, ey) in &self.particles {
                epc.add(n as f64);
                lat.add(n as f64, l as f64);
                ext_x.add(ex as f64);
                ext_y.add(ey as f64);
                elongation.add(ex as f64 - ey as f64);
            }
            push(
                "extent_x",
                "particles per bounding-box extent along x (px)",
                SignatureValue::Histogram(ext_x),
            );
            push(
                "extent_y",
                "particles per bounding-box extent along y (px)",
                SignatureValue::Histogram(ext_y),
            );
            push(
                "elongation",
                "particles per bounding-box extent x minus extent y (px)",
                SignatureValue::Histogram(elongation),
            );
            push(
                "events_per_cluster",
                "particles per number of events",
                SignatureValue::Histogram(epc),
            );
            push(
                "latency_vs_brightness",
                "mean first-event latency (us) per events-per-cluster bin",
                SignatureValue::Profile(lat.finish()),
            );
        }
        if let Some(el) = &self.elongation {
            push(
                "elongation_vs_speed",
                "mean extent along minus across the motion (px) per speed bin (px/s)",
                SignatureValue::Profile(el.finish()),
            );
            let mut tl = Histogram::new(
                vec![
                    1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0, 15.0, 20.0, 30.0, 50.0, 100.0, 200.0,
                ],
                BinScale::Index,
            )?;
            for &n in &self.track_lengths {
                tl.add(n as f64);
            }
            push(
                "track_length",
                "tracks per number of points",
                SignatureValue::Histogram(tl),
            );
        }

        Ok(Signatures {
            items,
            n_events: self.n_events,
            n_outside: self.n_outside,
            duration_us,
        })
    }
}

/// [`pearson`] of the per-pixel even- and odd-block counts, straight from
/// the pixel records (`sum_even`, `sum_odd`: the counts' sums). The same
/// arithmetic in the same order as `pearson(count_even, count_odd)`: the
/// means from exact integer sums, the products summed in pixel order.
fn pixel_pearson(pix: &[PixelState], sum_even: u64, sum_odd: u64) -> f64 {
    let n = pix.len() as f64;
    if n < 2.0 {
        return 0.0;
    }
    let (ma, mb) = (sum_even as f64 / n, sum_odd as f64 / n);
    let (mut cov, mut va, mut vb) = (0.0, 0.0, 0.0);
    for s in pix {
        let (dx, dy) = (s.count_even as f64 - ma, s.count_odd as f64 - mb);
        cov += dx * dy;
        va += dx * dx;
        vb += dy * dy;
    }
    if va <= 0.0 || vb <= 0.0 {
        0.0
    } else {
        cov / (va * vb).sqrt()
    }
}
/// Is folded time `c` outside the circular window `[w.0, w.1)`?
fn outside_window(c: f64, w: (f64, f64), period: f64) -> bool {
    (c - w.0).rem_euclid(period) >= w.1 - w.0
}

/// Slope of the least-squares line through points given by their sums
/// [n, Σx, Σy, Σx², Σxy]; NaN with fewer than three points or no spread
/// in x (then the signature is not compared).
fn regression_slope(s: &[f64; 5]) -> f64 {
    let [n, sx, sy, sxx, sxy] = *s;
    let var = n * sxx - sx * sx;
    if n < 3.0 || var <= 1e-9 * n * sxx.max(1.0) {
        return f64::NAN;
    }
    (n * sxy - sx * sy) / var
}

/// [`pearson`] on floats.
fn pearson_f64(a: &[f64], b: &[f64]) -> f64 {
    let n = a.len() as f64;
    if n < 2.0 {
        return 0.0;
    }
    let (ma, mb) = (a.iter().sum::<f64>() / n, b.iter().sum::<f64>() / n);
    let (mut cov, mut va, mut vb) = (0.0, 0.0, 0.0);
    for (&x, &y) in a.iter().zip(b) {
        let (dx, dy) = (x - ma, y - mb);
        cov += dx * dy;
        va += dx * dx;
        vb += dy * dy;
    }
    if va <= 0.0 || vb <= 0.0 {
        0.0
    } else {
        cov / (va * vb).sqrt()
    }
}

/// Pearson correlation; 0 when either side has no variance.
fn pearson(a: &[u32], b: &[u32]) -> f64 {
    let as_f64 = |v: &[u32]| v.iter().map(|&x| x as f64).collect::<Vec<f64>>();
    pearson_f64(&as_f64(a), &as_f64(b))
}

/// Convenience: signatures of one in-memory event set.
pub fn compute(
    cfg: &SignatureConfig,
    events: &EventChunk,
    particles: &[Particle],
    tracks: Option<&[Track]>,
) -> Result<Signatures> {
    let mut acc = SignatureAccumulator::new(cfg.clone())?;
    acc.add_events(events);
    acc.add_particles(particles);
    if let Some(t) = tracks {
        acc.add_tracks(t, particles)?;
    }
    acc.finish()
}

// ---------------------------------------------------------------------------
// Clock drift (its own block; computed by
// `workflow::signatures_of` next to the accumulator's signatures).

/// Time blocks of [`latency_drift`]: enough points for a slope, each block
/// still holding thousands of events on a 100-pulse recording.
pub const DRIFT_BLOCKS: usize = 8;

/// Name of the clock-drift signature.
pub const LATENCY_DRIFT: &str = "latency_drift";

/// `latency_drift`: the slope of the burst's latency over the recording,
/// in ppm (µs of latency per s of recording).
///
/// When the camera's clock and the laser's run at different rates, the
/// pulses drift through the folding period `cfg.timing` assumes: the folded
/// latency of every event moves by `ppm · 10⁻⁶` µs per µs of recording. The
/// latency histogram only smears (a few µs over a 100-pulse block at
/// 100 ppm, inside its own width); the slope shows the drift directly, with
/// its sign.
///
/// How: ON events (OFF events decay after the pulse and follow other
/// physics) are folded with the configured timing and unwrapped around the
/// burst window's centre (the configured window, or the data's own 95 %
/// window when none is set), so a burst near the period's edge does not
/// wrap. The pulses spanned by the events are cut into [`DRIFT_BLOCKS`]
/// equal blocks; each block's latency is the interquartile mean of its
/// events (robust against the flat floor of noise events, and finer than
/// the 1 µs timestamp grid, which a median would snap to). The signature is
/// the least-squares slope of block latency on block centre time; NaN (not
/// compared) with fewer than three populated blocks.
pub fn latency_drift(cfg: &SignatureConfig, events: &EventChunk) -> Result<Signature> {
    cfg.validate()?;
    let period = cfg.timing.period_us;
    let first = cfg.timing.first_pulse_us;
    let g = cfg.geometry;
    let on: Vec<usize> = (0..events.len())
        .filter(|&i| events.p[i] == ON && g.contains(events.x[i], events.y[i]))
        .collect();
    let value = if on.is_empty() {
        f64::NAN
    } else {
        let window = match cfg.burst_window_us {
            Some(w) => w,
            None => {
                let mut h = Histogram::new(cfg.latency_edges(), BinScale::Linear)?;
                for &i in &on {
                    h.add((events.t[i] as f64 - first).rem_euclid(period));
                }
                burst_window(&h, 0.95)?
            }
        };
        let centre = 0.5 * (window.0 + window.1);
        let pulse_of = |t: i64| ((t as f64 - first) / period).floor() as i64;
        let (k_lo, k_hi) = on.iter().fold((i64::MAX, i64::MIN), |(lo, hi), &i| {
            let k = pulse_of(events.t[i]);
            (lo.min(k), hi.max(k))
        });
        let span = (k_hi - k_lo + 1) as f64;
        let mut blocks: Vec<Vec<f64>> = vec![Vec::new(); DRIFT_BLOCKS];
        for &i in &on {
            let rel = events.t[i] as f64 - first;
            let k = (rel / period).floor();
            // Folded, then unwrapped into [centre − P/2, centre + P/2).
            let unwrapped = (rel - k * period - centre + 0.5 * period).rem_euclid(period) + centre
                - 0.5 * period;
            let b = (((k - k_lo as f64) / span) * DRIFT_BLOCKS as f64) as usize;
            blocks[b.min(DRIFT_BLOCKS - 1)].push(unwrapped);
        }
        let mut points: Vec<(f64, f64)> = Vec::with_capacity(DRIFT_BLOCKS);
        for (b, lat) in blocks.iter_mut().enumerate() {
            if lat.len() < 8 {
                continue;
            }
            let iqm = interquartile_mean(lat);
            let t_centre = (k_lo as f64 + (b as f64 + 0.5) * span / DRIFT_BLOCKS as f64) * period;
            points.push((t_centre, iqm));
        }
        line_slope(&points) * 1e6
    };
    Ok(Signature {
        name: LATENCY_DRIFT.into(),
        description: "slope of the burst's latency over the recording (ppm: us per s)".into(),
        value: SignatureValue::Scalar { value },
    })
}

/// Mean of the middle half of `v` (ranks len/4 .. len − len/4), summed in
/// sorted order; reorders `v`. Partitions at both quartiles and sorts only
/// what lies between: the same sum as after a full sort (tested).
fn interquartile_mean(v: &mut [f64]) -> f64 {
    let (q1, q3) = (v.len() / 4, v.len() - v.len() / 4);
    if q3 <= q1 {
        return f64::NAN;
    }
    if q1 < v.len() {
        v.select_nth_unstable_by(q1, f64::total_cmp);
    }
    let upper = &mut v[q1..];
    if q3 - q1 < upper.len() {
        upper.select_nth_unstable_by(q3 - q1, f64::total_cmp);
    }
    v[q1..q3].sort_unstable_by(f64::total_cmp);
    v[q1..q3].iter().sum::<f64>() / (q3 - q1) as f64
}

/// Least-squares slope of y on x, centred (no cancellation for large x);
/// NaN with fewer than three points or no spread in x.
fn line_slope(points: &[(f64, f64)]) -> f64 {
    let n = points.len() as f64;
    if n < 3.0 {
        return f64::NAN;
    }
    let mx = points.iter().map(|p| p.0).sum::<f64>() / n;
    let my = points.iter().map(|p| p.1).sum::<f64>() / n;
    let (mut cov, mut var) = (0.0, 0.0);
    for &(x, y) in points {
        cov += (x - mx) * (y - my);
        var += (x - mx) * (x - mx);
    }
    if var <= 0.0 {
        f64::NAN
    } else {
        cov / var
    }
}

#[cfg(test)]
mod tests {
    use super::{floor_i64, interquartile_mean};

    #[test]
    fn interquartile_mean_equals_full_sort() {
        let mut state = 12345u64;
        let mut next = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        for n in [1usize, 3, 4, 5, 8, 9, 31, 100, 1001, 5000] {
            // Few distinct values too: ties across the quartile cuts.
            for distinct in [3.0, 1e9] {
                let v: Vec<f64> = (0..n)
                    .map(|_| (next() * distinct).floor() * 0.37 - 11.1)
                    .collect();
                let mut full = v.clone();
                full.sort_unstable_by(f64::total_cmp);
                let (q1, q3) = (n / 4, n - n / 4);
                let want = full[q1..q3].iter().sum::<f64>() / (q3 - q1) as f64;
                let mut w = v.clone();
                assert_eq!(
                    interquartile_mean(&mut w).to_bits(),
                    want.to_bits(),
                    "n = {n}"
                );
            }
        }
    }

    #[test]
    fn floor_i64_is_floor_as_i64() {
        let mut xs = vec![
            0.0,
            -0.0,
            0.5,
            -0.5,
            1.0,
            -1.0,
            -1e-300,
            2.5e15 + 0.5,
            -2.5e15 - 0.5,
            9.3e18,
            -9.3e18,
            1e300,
            -1e300,
            f64::NAN,
            f64::INFINITY,
            f64::NEG_INFINITY,
            (1u64 << 53) as f64,
            -((1u64 << 53) as f64) - 2.0,
        ];
        for k in -3000..3000 {
            xs.push(k as f64 * 0.37 + 1e-9 * k as f64);
            xs.push((k as f64 - 13.3) / 199.7);
        }
        for x in xs {
            assert_eq!(floor_i64(x), x.floor() as i64, "x = {x}");
        }
    }
}
