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
//! | `off_burst_pixel_count` | histogram of visits (pulses) per pixel with events outside the burst window, over pixels with any | hot-pixel rate (far tail) vs background and latency tails (ones) |
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
//! | `burst_repeat_share` | scalar, log10 of the share of pixels (with two events or more) that fired twice within half a pulse period | refractory period (no pixel fires twice in a burst) |
//! | `events_per_cluster` | histogram (needs particles) | brightness, threshold |
//! | `latency_vs_brightness` | profile: mean first latency per events-per-cluster bin | intensity-dependent latency |
//! | `latency_vs_yield` | profile: mean folded latency of a visit's first event per events in the visit (1, 2, 3, 4+), less the mean over all visits | intensity-dependent latency (a brighter pixel fires more events, and earlier) |
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
//! independently (their product alone is what `off_burst_rate` sees). The
//! counts are of visits (pulses with off-burst events), not of events: a
//! pixel whose whole visit comes late (the tail of the latency) fires its
//! few events of that pulse together, a hot pixel fires at every pulse. Both
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
//! Busy windows: the same relation summed over `BUSY_WINDOW_TICKS`
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

#[cfg(feature = "testkit")]
pub(crate) mod reference;

use serde::{Deserialize, Serialize};

use crate::cluster::Particle;
use crate::error::{Error, Result};
use crate::events::{EventChunk, Geometry, ON};
use crate::pulses::PulseTiming;
use crate::track::Track;

mod accumulator;

pub(crate) use accumulator::*;

/// How a histogram's bins are placed on the line when measuring distances
/// between distributions (see [`super::distance`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub(crate) enum BinScale {
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
pub(crate) struct Histogram {
    /// Bin edges, `counts.len() + 1` of them, finite and increasing.
    pub edges: Vec<f64>,
    /// Count (or summed weight) per bin.
    pub counts: Vec<f64>,
    /// Where the bins sit for distance computations.
    pub scale: BinScale,
}

impl Histogram {
    /// `edges`: at least two, finite, strictly increasing.
    pub(crate) fn new(edges: Vec<f64>, scale: BinScale) -> Result<Self> {
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

    /// Number of bins.
    pub(crate) fn n_bins(&self) -> usize {
        self.counts.len()
    }

    /// Bin of `v` (clamped to the first / last bin), `None` for NaN.
    #[inline]
    pub(crate) fn bin_of(&self, v: f64) -> Option<usize> {
        if v.is_nan() {
            return None;
        }
        let k = self.edges.partition_point(|e| *e <= v);
        Some(k.saturating_sub(1).min(self.counts.len() - 1))
    }

    #[inline]
    pub(crate) fn add(&mut self, v: f64) {
        self.add_weighted(v, 1.0);
    }

    #[inline]
    pub(crate) fn add_weighted(&mut self, v: f64, w: f64) {
        if let Some(k) = self.bin_of(v) {
            self.counts[k] += w;
        }
    }

    /// Sum of the counts.
    pub(crate) fn total(&self) -> f64 {
        self.counts.iter().sum()
    }

    /// Where each bin sits on the line for distance computations.
    pub(crate) fn positions(&self) -> Vec<f64> {
        match self.scale {
            BinScale::Linear => self.edges.windows(2).map(|w| 0.5 * (w[0] + w[1])).collect(),
            BinScale::Index => (0..self.counts.len()).map(|k| k as f64).collect(),
        }
    }

    #[cfg(feature = "testkit")]
    /// Centre of the bin holding `v` (`v` itself for NaN).
    pub(crate) fn bin_centre(&self, v: f64) -> f64 {
        match self.bin_of(v) {
            Some(k) => 0.5 * (self.edges[k] + self.edges[k + 1]),
            None => v,
        }
    }

    /// Same bins (edges and scale)?
    pub(crate) fn same_bins(&self, other: &Histogram) -> bool {
        self.scale == other.scale && self.edges == other.edges
    }
}

/// Mean of a quantity per bin of another (e.g. latency per brightness).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(crate) struct Profile {
    /// Bin edges of the conditioning quantity, `mean.len() + 1` of them.
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

/// The value of one signature.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "lowercase")]
pub(crate) enum SignatureValue {
    /// A distribution on fixed bins.
    Histogram(Histogram),
    /// A mean per bin of another quantity.
    Profile(Profile),
    /// A single number.
    Scalar {
        /// The number, in the unit the signature's description gives.
        value: f64,
    },
}

/// One named statistic of a recording, compared between measurement and simulation.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(crate) struct Signature {
    /// Name of the signature (the key in tables and figures).
    pub name: String,
    /// What is counted and in which unit (for tables and figure labels).
    pub description: String,
    /// The statistic itself.
    pub value: SignatureValue,
}

/// All signatures of one recording, in a fixed order.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(crate) struct Signatures {
    /// The signatures, each name once.
    pub items: Vec<Signature>,
    /// Events inside the geometry that entered the signatures.
    pub n_events: u64,
    /// Events outside the configured geometry (ignored).
    pub n_outside: u64,
    /// Time span covered (µs): last − first event time.
    pub duration_us: f64,
}

impl Signatures {
    /// The signature called `name`.
    pub(crate) fn get(&self, name: &str) -> Option<&Signature> {
        self.items.iter().find(|s| s.name == name)
    }
    /// The value of the scalar signature `name` (`None` if absent or not a scalar).
    pub(crate) fn scalar(&self, name: &str) -> Option<f64> {
        match self.get(name)?.value {
            SignatureValue::Scalar { value } => Some(value),
            _ => None,
        }
    }
    /// The histogram signature `name` (`None` if absent or not a histogram).
    pub(crate) fn histogram(&self, name: &str) -> Option<&Histogram> {
        match &self.get(name)?.value {
            SignatureValue::Histogram(h) => Some(h),
            _ => None,
        }
    }
    #[cfg(feature = "testkit")]
    /// The profile signature `name` (`None` if absent or not a profile).
    pub(crate) fn profile(&self, name: &str) -> Option<&Profile> {
        match &self.get(name)?.value {
            SignatureValue::Profile(p) => Some(p),
            _ => None,
        }
    }
}

/// Binning and windows shared by the measured and every simulated data set.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(crate) struct SignatureConfig {
    /// Sensor geometry; events outside it are ignored.
    pub geometry: Geometry,
    /// The pulse train the events are folded on.
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
    pub(crate) fn new(geometry: Geometry, timing: PulseTiming) -> Self {
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
pub(crate) fn count_edges(max: f64) -> Vec<f64> {
    let mut e: Vec<f64> = (0..=16).map(|k| k as f64).collect();
    let mut x = 16.0f64;
    while x < max {
        x = (x * 2f64.powf(0.25)).round();
        e.push(x);
    }
    e
}

/// `burst_repeat_share`: log10 of the share of pixels, among those with an
/// inter-event interval, whose shortest interval is under half the pulse
/// period: pixels that fired twice in one burst. Add-one smoothing keeps
/// it finite (a sensor whose pixels never repeat within a burst reads
/// about −log10 of its pixel count).
///
/// A refractory period longer than the burst leaves no such pixel; a
/// well-behaved sensor at any bias setting has some (a lit pixel's second
/// threshold crossing follows its first by microseconds). On a log scale
/// the difference between "some" and "none" is what counts: the Wasserstein
/// distance of `min_iei` weighs it as one shift of mass among others, of a
/// size a higher contrast threshold also makes.
pub(crate) fn burst_repeat_share(min_intervals: impl Iterator<Item = f64>, period_us: f64) -> f64 {
    let (mut short, mut all) = (0u64, 0u64);
    for d in min_intervals {
        all += 1;
        short += (d < 0.5 * period_us) as u64;
    }
    ((short as f64 + 1.0) / (all as f64 + 1.0)).log10()
}

/// A folded latency (µs, ≥ 0) in quarter microseconds, as `latency_vs_yield`
/// keeps it per pixel: rounded down, saturating at `u16::MAX` (16 ms, a
/// pulse rate of 61 Hz). Sums of quarter microseconds are exact.
pub(crate) fn quarter_us(folded_us: f64) -> u16 {
    // `as` saturates (and maps NaN to 0).
    (folded_us * 4.0) as u16
}

/// Bin edges of `latency_vs_yield`: visits of 1, 2, 3 and 4 or more events.
pub(crate) const LATENCY_YIELD_EDGES: [f64; 5] = [1.0, 2.0, 3.0, 4.0, 17.0];

/// `latency_vs_yield` from the sums of its visits' first-event latencies
/// (µs) and the visits per bin: each bin's mean less the mean over all
/// visits. The level of the latency (its median is matched in every
/// simulation, its shape is the `latency` histogram's) drops out; what is
/// left is how the latency depends on the events a pixel fires.
pub(crate) fn latency_yield_profile(sums: &[f64], counts: &[f64]) -> Profile {
    let n: f64 = counts.iter().sum();
    let all = sums.iter().sum::<f64>() / n;
    Profile {
        edges: LATENCY_YIELD_EDGES.to_vec(),
        mean: sums
            .iter()
            .zip(counts)
            .map(|(s, c)| if *c > 0.0 { s / c - all } else { f64::NAN })
            .collect(),
        count: counts.to_vec(),
    }
}

/// Edges for intervals (µs): [0, 1), then 4 bins per decade up to 10 s.
pub(crate) fn interval_edges() -> Vec<f64> {
    let mut e = vec![0.0];
    for k in 0..=28 {
        e.push(10f64.powf(k as f64 / 4.0));
    }
    e
}

/// Smallest circular window around the peak of a folded latency histogram
/// holding at least `fraction` of the events: grown bin by bin towards the
/// fuller neighbour. Returns `[start, end)` µs (end may exceed the period).
pub(crate) fn burst_window(latency: &Histogram, fraction: f64) -> Result<(f64, f64)> {
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
pub(crate) fn quiet_complement(latency: &Histogram, quiet_fraction: f64) -> Result<(f64, f64)> {
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

#[cfg(feature = "testkit")]
/// Pearson correlation; 0 when either side has no variance.
fn pearson(a: &[u32], b: &[u32]) -> f64 {
    let as_f64 = |v: &[u32]| v.iter().map(|&x| x as f64).collect::<Vec<f64>>();
    pearson_f64(&as_f64(a), &as_f64(b))
}

#[cfg(feature = "testkit")]
/// Convenience: signatures of one in-memory event set.
pub(crate) fn compute(
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
pub(crate) const DRIFT_BLOCKS: usize = 8;

/// Name of the clock-drift signature.
pub(crate) const LATENCY_DRIFT: &str = "latency_drift";

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
pub(crate) fn latency_drift(cfg: &SignatureConfig, events: &EventChunk) -> Result<Signature> {
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

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::{floor_i64, interquartile_mean};

    #[ebptv_macros::unit_test]
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

    #[ebptv_macros::unit_test]
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
