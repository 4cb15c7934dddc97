//! # ebptv-sim — simulator of pulsed event-based imaging with ground truth
//!
//! A particle-seeded flow, lit by a pulsed laser sheet, seen by an event
//! camera: the simulator streams the camera's events and trigger edges
//! and records the truth (position and velocity of every lit particle at
//! every pulse). A preset is a complete [`Scenario`]; [`simulate`] runs
//! it into memory, `Simulator` streams it as an
//! [`EventSource`]:
//!
//! ```
//! use ebptv_sim::{presets, simulate};
//!
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! let mut scenario = presets::preset("demo")?;
//! scenario.duration_s = 0.002; // ten pulses at 5 kHz
//! let out = simulate(&scenario, 1)?;
//! let pulses = out.pulse_starts_us.len();
//! assert!(pulses >= 9);
//! assert!(out.events.len() > 1000);
//! // Truth: every lit particle inside the ROI at every pulse.
//! assert!(out.truth.len() > 100 * pulses);
//! assert!(out.truth.iter().all(|s| s.pulse >= 0 && s.u.is_finite()));
//! # Ok(())
//! # }
//! ```
//!
//! The chain: [`flow`] (exact u(x, y, t)) → `seeding` (particles in a
//! light-sheet slab, RK4 pathlines, recycling) → [`light`] (pulse envelope,
//! saw-tooth modulation) → `pixel` (log-contrast pixel, latency, OFF,
//! noise) → `readout` (refractory, row arbiter, timestamps, rate limiter)
//! → events + triggers, with the truth (`TruthSample`: position and velocity
//! of every lit particle at every pulse).
//!
//! ## Why event-driven
//! A pulse lights only the pixels under particle images: at 0.01 ppp with
//! 1.3 px images that is a few percent of the array, for a few µs out of a
//! 200 µs period. So the simulator never steps pixels through time: per
//! pulse it renders the particle images into a sparse list of lit pixels,
//! computes each pixel's response to that pulse in closed form (threshold
//! crossings of a first-order photoreceptor), and adds noise events as
//! Poisson processes. Only the readout (a queue) is sequential.
//!
//! ## Streaming and determinism
//! `Simulator` is an [`EventSource`]: it works in blocks of pulses (about
//! 2 ms), so memory is bounded by a block whatever the duration, and the
//! truth of the pulses produced so far is taken with
//! `Simulator::take_truth`. Particle advection is parallel over particles,
//! rendering parallel over pulses (rayon), and the sequential readout of a
//! block (request sort, refractory, arbiter) runs while the next block is
//! being rendered (see `Simulator`); every random draw comes from a
//! stream derived from the user's seed and the item's index (particle slot,
//! pulse, block), so the output does not depend on the thread count.
//! [`simulate`] drains a `Simulator` into memory (tests, small scenes);
//! [`simulate_with`] does the same with a [`MotionCache`], which replays
//! the particle motion of a scene and seed simulated before (many
//! simulations of one scene with only the sensor changed, as a model
//! check runs: the same output, without advecting again).
//!
//! ## Effects
//! Each sensor/readout effect (and the laser's `clock_drift` against the
//! camera clock, which moves pulses, triggers and truth together) is an
//! `Option` in the [`Scenario`]; `None`
//! means exactly absent (no random draws are taken for it either, so
//! switching one effect does not reshuffle the others). See
//! [`scenario`] for the table of names and parameters.

#![warn(missing_docs)]

use serde::{Deserialize, Serialize};

pub(crate) mod fastmath;
pub mod flow;
pub mod light;
pub(crate) mod motion;
pub(crate) mod pixel;
pub mod presets;
pub(crate) mod readout;
pub(crate) mod record;
pub mod scenario;
pub(crate) mod seeding;
pub mod simd;

#[ebptv_macros::testkit]
pub(crate) use flow::Flow;
pub use motion::MotionCache;
pub use record::{
    write_recording, write_recording_with, RecordingSummary, TruthTable, TruthTableMaker,
};
pub use scenario::{Scenario, EFFECT_NAMES};

use ebptv_io::error::{Error, Result};
use ebptv_io::events::{Chunk, Edge, EventChunk, Geometry, Trigger};
use ebptv_io::{EventSource, Format, StreamInfo};

/// Ground truth of one particle at one pulse (`truth_particles.csv`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TruthSample {
    /// Pulse index.
    pub pulse: i64,
    /// Pulse start time (µs).
    pub t_us: f64,
    /// Particle id (stable while the particle lives).
    pub particle_id: u64,
    /// Particle-image centre at the pulse (px).
    pub x: f64,
    /// Particle-image centre y at the pulse (px).
    pub y: f64,
    /// True velocity (px/s).
    pub u: f64,
    /// True y velocity (px/s).
    pub v: f64,
}

/// A whole simulated recording in memory (tests, small scenes). Long
/// recordings stream through `Simulator` (an `EventSource`) instead.
#[derive(Debug, Clone, Default)]
pub struct SimOutput {
    /// Geometry of the recording.
    pub geometry: Option<Geometry>,
    /// Events in readout order (time-ordered).
    pub events: EventChunk,
    /// Trigger events (laser TTL), time-ordered.
    pub triggers: Vec<Trigger>,
    /// Ground truth, one row per lit particle and pulse.
    pub truth: Vec<TruthSample>,
    /// True start time of every light pulse (µs).
    pub pulse_starts_us: Vec<f64>,
}

/// Counters of a simulation run (`summary.json`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct SimStats {
    /// Contrast events written.
    pub events: u64,
    /// ON events written.
    pub on_events: u64,
    /// OFF events written.
    pub off_events: u64,
    /// Trigger events written.
    pub triggers: u64,
    /// Light pulses simulated.
    pub pulses: u64,
    /// Particle slots in the slab (lit or not, ROI plus margin).
    pub particles: u64,
    /// Truth rows: lit particles inside the ROI, summed over pulses.
    pub truth_samples: u64,
    /// Requests lost in the readout (pixel still blocked).
    pub lost_in_readout: u64,
    /// Simulated time (s).
    pub duration_s: f64,
}

impl SimStats {
    /// Mean event rate over the simulated time (events/s).
    pub(crate) fn event_rate_ev_s(&self) -> f64 {
        self.events as f64 / self.duration_s
    }
    /// Events per lit particle per pulse (noise included).
    pub(crate) fn events_per_particle_per_pulse(&self) -> f64 {
        if self.truth_samples == 0 {
            0.0
        } else {
            self.events as f64 / self.truth_samples as f64
        }
    }
}

/// SplitMix64's finaliser: a bijective 64-bit mix.
#[inline]
pub(crate) fn splitmix(mut z: u64) -> u64 {
    z = z.wrapping_add(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// The part of [`stream_seed`] that does not depend on the index.
#[inline]
pub(crate) fn stream_key(seed: u64, stream: u64) -> u64 {
    splitmix(splitmix(seed) ^ stream.wrapping_mul(0xA24B_AED4_963E_E407))
}

/// A seed for an independent random stream (SplitMix64 mixing).
pub(crate) fn stream_seed(seed: u64, stream: u64, index: u64) -> u64 {
    splitmix(stream_key(seed, stream) ^ index)
}

/// Target time span of one block (µs).
pub(crate) const BLOCK_US: f64 = 2000.0;

/// How a request packs into one u64 sort key: time at 1 ns resolution
/// relative to the block's `t_begin` (ample for 1 µs timestamps; 2^39 ns
/// = 9 min of carry-over, 2^38 for a 4096×4096 ROI), then y, x (relative
/// to the ROI, in as few bits as its size needs), the group flag
/// ([`GROUP_FLAG`]) and polarity. Requests are ordered by (time, y),
/// equal ones in input order, as `sort_requests_reference` (in the tests) defines: a
/// stable sort of the keys on the bits above x ([`Self::x_shift`]) — in
/// practice a radix sort on the time field (2 passes of 11 bits for a
/// 2 ms block) and an insertion pass for rows within a nanosecond, see
/// [`sort_request_keys`] (x and p need not be sorted on: same-row
/// requests at the same nanosecond are rare, and a pulse's pixels come
/// in x order anyway). Times come back rounded to the nanosecond.
#[derive(Debug, Clone, Copy)]
struct KeyLayout {
    x0: u16,
    y0: u16,
    x_bits: u32,
    time_shift: u32,
    /// The largest time field (ns).
    ns_max: u64,
    /// Mask of the y field (after shifting it down).
    y_mask: u64,
}

/// Key bit (below x, so the sort carries it without comparing it) marking
/// the head of a refractory group: the request has later requests of the
/// same pixel and pulse kept aside in the block's tail list, each less
/// than the refractory period after it (see [`Back::block`]).
const GROUP_FLAG: u64 = 2;

impl KeyLayout {
    fn new(roi: scenario::Roi) -> KeyLayout {
        let bits = |n: u32| 32 - n.saturating_sub(1).leading_zeros();
        let x_bits = bits(roi.width);
        let time_shift = 2 + x_bits + bits(roi.height);
        KeyLayout {
            x0: roi.x as u16,
            y0: roi.y as u16,
            x_bits,
            time_shift,
            ns_max: (1u64 << (64 - time_shift).min(39)) - 1,
            y_mask: (1u64 << bits(roi.height)) - 1,
        }
    }

    /// The key bits below y (x, group flag and p), which the sort does not
    /// compare.
    fn x_shift(&self) -> u32 {
        2 + self.x_bits
    }

    #[inline]
    fn key(&self, a: &pixel::Arrival, t_begin: f64) -> u64 {
        debug_assert!(a.x >= self.x0 && a.y >= self.y0, "request outside the ROI");
        let ns = (pixel::round_i64((a.t - t_begin) * 1000.0).max(0) as u64).min(self.ns_max);
        (ns << self.time_shift)
            | (((a.y - self.y0) as u64) << (2 + self.x_bits))
            | (((a.x - self.x0) as u64) << 2)
            | a.p as u64
    }

    #[inline]
    fn arrival(&self, k: u64, t_begin: f64) -> pixel::Arrival {
        pixel::Arrival {
            t: self.time(k, t_begin),
            y: self.y0 + ((k >> (2 + self.x_bits)) & self.y_mask) as u16,
            x: self.x0 + ((k >> 2) & ((1u64 << self.x_bits) - 1)) as u16,
            p: (k & 1) as u8,
        }
    }

    /// The pixel of key `k` relative to the ROI's corner (x, y).
    #[inline(always)]
    fn pixel_offsets(&self, k: u64) -> (usize, usize) {
        (
            ((k >> 2) & ((1u64 << self.x_bits) - 1)) as usize,
            ((k >> (2 + self.x_bits)) & self.y_mask) as usize,
        )
    }

    /// The key bits of pixel (x, y) (for [`Self::key_at`]).
    #[inline]
    fn pixel_bits(&self, x: u16, y: u16) -> u64 {
        debug_assert!(x >= self.x0 && y >= self.y0, "request outside the ROI");
        (((y - self.y0) as u64) << (2 + self.x_bits)) | (((x - self.x0) as u64) << 2)
    }

    /// [`Self::key`] from the pixel's [`Self::pixel_bits`], the time and
    /// the polarity.
    #[inline]
    fn key_at(&self, pixel_bits: u64, t: f64, p: u8, t_begin: f64) -> u64 {
        let ns = pixel::round_i64((t - t_begin) * 1000.0).clamp(0, self.ns_max as i64) as u64;
        (ns << self.time_shift) | pixel_bits | p as u64
    }

    /// The request time of key `k` (µs).
    #[inline]
    fn time(&self, k: u64, t_begin: f64) -> f64 {
        // (< 2^39 ns: through i64, the same value without the u64 → f64
        // sequence.)
        t_begin + (k >> self.time_shift) as i64 as f64 * 1e-3
    }
}

/// Pixel events straight into request keys (no intermediate list).
struct KeySink {
    layout: KeyLayout,
    t_begin: f64,
    keys: Vec<u64>,
    /// Refractory grouping: a pixel's later requests of this pulse less
    /// than this many ns after its earliest go to `tails` instead of
    /// `keys` (0: no grouping, the refractory filter is off).
    group_ns: u64,
    /// (head key with [`GROUP_FLAG`], member key) of every group.
    tails: Vec<(u64, u64)>,
}

impl pixel::ArrivalSink for KeySink {
    #[inline]
    fn arrive(&mut self, a: pixel::Arrival) {
        self.keys.push(self.layout.key(&a, self.t_begin));
    }

    #[inline(always)]
    fn arrive_pixel(&mut self, x: u16, y: u16, p: u8, times: &[f64]) {
        // The layout in locals: the pushes would make the compiler
        // reload it per event.
        let (layout, t_begin) = (self.layout, self.t_begin);
        let bits = layout.pixel_bits(x, y);
        if times.len() < 2 || self.group_ns == 0 {
            self.keys.reserve(times.len());
            for &t in times {
                self.keys.push(layout.key_at(bits, t, p, t_begin));
            }
            return;
        }
        // The pixel's earliest request heads a group of those less than
        // `group_ns` after it: the readout looks at them only if the head
        // is dropped (see `Back::block`); the rest are plain requests.
        // (Keys grow with the time: the earliest time has the least key.)
        let n = times.len();
        let mut h = 0;
        for i in 1..n {
            if times[i] < times[h] {
                h = i;
            }
        }
        let head = layout.key_at(bits, times[h], p, t_begin);
        let limit = (head >> layout.time_shift) + self.group_ns;
        let (keys, tails) = (&mut self.keys, &mut self.tails);
        keys.reserve(n);
        tails.reserve(n);
        let mut flag = 0;
        for (i, &t) in times.iter().enumerate() {
            if i != h {
                let k = layout.key_at(bits, t, p, t_begin);
                if k >> layout.time_shift < limit {
                    tails.push((head | GROUP_FLAG, k));
                    flag = GROUP_FLAG;
                } else {
                    keys.push(k);
                }
            }
        }
        keys.push(head | flag);
    }
}

/// The plain definition of the request order (test reference): keys,
/// stable comparison sort by (time in ns, y), decode.
#[cfg(feature = "testkit")]
pub(crate) fn sort_requests_reference(reqs: &mut [pixel::Arrival], t_begin: f64) {
    let mut keys: Vec<u64> = reqs
        .iter()
        .map(|a| {
            let ns = (((a.t - t_begin) * 1000.0).round().max(0.0) as u64).min((1 << 39) - 1);
            (ns << 25) | ((a.y as u64) << 13) | ((a.x as u64) << 1) | a.p as u64
        })
        .collect();
    keys.sort_by_key(|k| k >> 13);
    for (a, k) in reqs.iter_mut().zip(keys) {
        *a = pixel::Arrival {
            t: t_begin + (k >> 25) as f64 * 1e-3,
            y: ((k >> 13) & 0xFFF) as u16,
            x: ((k >> 1) & 0xFFF) as u16,
            p: (k & 1) as u8,
        };
    }
}

/// The simulator's request sort ([`KeyLayout`] keys through
/// [`radix_sort_above`]) for requests inside `roi` (for tests).
#[cfg(feature = "testkit")]
pub(crate) fn sort_requests(reqs: &mut [pixel::Arrival], t_begin: f64, roi: scenario::Roi) {
    let layout = KeyLayout::new(roi);
    let mut keys: Vec<u64> = reqs.iter().map(|a| layout.key(a, t_begin)).collect();
    sort_request_keys(&mut keys, &mut Vec::new(), layout);
    for (a, k) in reqs.iter_mut().zip(keys) {
        *a = layout.arrival(k, t_begin);
    }
}

/// Sort request keys stably by (time, y) ([`KeyLayout`]): a radix sort on
/// the time field only (2 passes of 11 bits for a 2 ms block, where
/// sorting on y as well took 3), then an insertion pass that orders the
/// rows among requests of the same nanosecond — after the time sort an
/// out-of-order y can only follow a request of equal time, and those runs
/// are short, so the pass is linear. Same order as
/// `radix_sort_above(keys, scratch, layout.x_shift())`
/// (`request_sort_matches_reference`).
fn sort_request_keys(keys: &mut Vec<u64>, scratch: &mut Vec<u64>, layout: KeyLayout) {
    radix_sort_above(keys, scratch, layout.time_shift);
    if !order_rows_within_times(keys, layout.x_shift()) {
        // Long runs of one nanosecond (not seen in simulations): the
        // full radix sort instead of a quadratic insertion sort. Stable
        // sorts both, so the partly ordered keys sort as the original.
        radix_sort_above(keys, scratch, layout.x_shift());
    }
}

/// Stable insertion sort of `keys` by `key >> x_shift`, linear for input
/// already sorted by a prefix of those bits (the time field) with short
/// runs of equal prefix; false (and the keys partly sorted) if it would
/// move more than ~4 keys per key.
fn order_rows_within_times(keys: &mut [u64], x_shift: u32) -> bool {
    let mut budget = 4 * keys.len() + 1024;
    let Some(&first) = keys.first() else {
        return true;
    };
    // The sort bits of the largest key so far (after an insertion still
    // the key before the next one).
    let mut prev = first >> x_shift;
    for i in 1..keys.len() {
        let k = keys[i];
        if prev <= k >> x_shift {
            prev = k >> x_shift;
            continue;
        }
        let mut j = i;
        while j > 0 && keys[j - 1] >> x_shift > k >> x_shift {
            keys[j] = keys[j - 1];
            j -= 1;
        }
        keys[j] = k;
        budget = match budget.checked_sub(i - j) {
            Some(b) => b,
            None => return false,
        };
    }
    true
}

/// Sort `keys` ascending: LSD radix sort over the bits any key uses, in
/// digits of at most 11 bits (a 16 kB histogram stays in L1), skipping
/// digits all keys share. Same result as `sort_unstable` (keys are plain
/// integers), in a few linear passes instead of ~log2(n) comparisons per
/// key: the request sort was ~10 % of the simulator's instructions.
pub(crate) fn radix_sort(keys: &mut Vec<u64>, scratch: &mut Vec<u64>) {
    radix_sort_above(keys, scratch, 0);
}

/// Sort `keys` stably by `key >> low_bits` (the low bits are carried,
/// not compared: equal high parts keep their input order), by
/// [`radix_sort`]'s passes.
pub(crate) fn radix_sort_above(keys: &mut Vec<u64>, scratch: &mut Vec<u64>, low_bits: u32) {
    let n = keys.len();
    if n < 512 {
        if low_bits == 0 {
            keys.sort_unstable();
        } else {
            keys.sort_by_key(|&k| k >> low_bits);
        }
        return;
    }
    let used = keys.iter().fold(0u64, |m, &k| m | k) >> low_bits;
    let bits = 64 - used.leading_zeros();
    let passes = bits.div_ceil(11).max(1);
    let digit = bits.div_ceil(passes);
    let radix = 1usize << digit;
    let mask = radix as u64 - 1;
    let mut counts = vec![0usize; radix * passes as usize];
    if passes == 2 {
        // (The usual case, the time field of a block's request keys:
        // unrolled.)
        let (c0, c1) = counts.split_at_mut(radix);
        for &k in keys.iter() {
            let k = k >> low_bits;
            c0[(k & mask) as usize] += 1;
            c1[((k >> digit) & mask) as usize] += 1;
        }
    } else if passes == 3 {
        let (c0, rest) = counts.split_at_mut(radix);
        let (c1, c2) = rest.split_at_mut(radix);
        for &k in keys.iter() {
            let k = k >> low_bits;
            c0[(k & mask) as usize] += 1;
            c1[((k >> digit) & mask) as usize] += 1;
            c2[((k >> (2 * digit)) & mask) as usize] += 1;
        }
    } else {
        for &k in keys.iter() {
            let k = k >> low_bits;
            for p in 0..passes as usize {
                counts[p * radix + ((k >> (p as u32 * digit)) & mask) as usize] += 1;
            }
        }
    }
    // (Its old contents are overwritten: no clearing.)
    if scratch.len() < n {
        scratch.resize(n, 0);
    }
    scratch.truncate(n);
    let mut src_is_keys = true;
    for p in 0..passes as usize {
        let c = &mut counts[p * radix..(p + 1) * radix];
        if c.contains(&n) {
            continue; // every key has the same digit here
        }
        let mut sum = 0;
        for v in c.iter_mut() {
            let here = *v;
            *v = sum;
            sum += here;
        }
        let shift = low_bits + p as u32 * digit;
        let (src, dst) = if src_is_keys {
            (&keys[..], &mut scratch[..])
        } else {
            (&scratch[..], &mut keys[..])
        };
        for &k in src {
            let d = ((k >> shift) & mask) as usize;
            dst[c[d]] = k;
            c[d] += 1;
        }
        src_is_keys = !src_is_keys;
    }
    if !src_is_keys {
        std::mem::swap(keys, scratch);
    }
}

/// One block as the front stage (particles → pulses → requests) hands it
/// to the back stage (readout).
struct BlockRequests {
    block: u64,
    /// Camera-time start of each pulse of the block (µs).
    starts: Vec<f64>,
    t_begin: f64,
    t_end: f64,
    last: bool,
    /// The block's own requests (not the carry-over) as keys relative to
    /// `t_begin` ([`KeyLayout`]), not yet sorted.
    keys: Vec<u64>,
    /// Refractory groups: (head key, member key), see [`KeySink`]; one
    /// list per pulse (concatenated only if a lookup needs them sorted).
    tails: Vec<Vec<(u64, u64)>>,
    truth: Vec<TruthSample>,
}

/// Vectors the stages hand back for reuse. Freed and allocated anew every
/// pulse and block, the request lists made the allocator return their
/// pages to the OS and fault them in again (~0.1 s of system time in a
/// 0.25 s full-frame run, measured with the allocator's trimming off).
#[derive(Default)]
struct Buffers {
    pulse_keys: std::sync::Mutex<Vec<Vec<u64>>>,
    block_keys: std::sync::Mutex<Vec<Vec<u64>>>,
    tails: std::sync::Mutex<Vec<Vec<(u64, u64)>>>,
}

impl Buffers {
    /// An empty vector with room for `n`, reused if one is waiting.
    fn take<T>(pool: &std::sync::Mutex<Vec<Vec<T>>>, n: usize) -> Vec<T> {
        let mut v = pool
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .pop()
            .unwrap_or_default();
        v.clear();
        v.reserve(n);
        v
    }

    /// Hand `v` back (dropped if `max` are already waiting).
    fn give<T>(pool: &std::sync::Mutex<Vec<Vec<T>>>, v: Vec<T>, max: usize) {
        if v.capacity() > 0 {
            let mut p = pool.lock().unwrap_or_else(|e| e.into_inner());
            if p.len() < max {
                p.push(v);
            }
        }
    }
}

/// Requests between a prefetch of a pixel's refractory state and its use:
/// enough work (~20 ns each) to cover a load from memory.
const PREFETCH_AHEAD: usize = 16;

/// Per-pulse vectors kept for reuse (two blocks of pulses are in flight).
const POOLED_PULSE_MAX: usize = 48;
/// Per-block vectors kept for reuse.
const POOLED_BLOCK_MAX: usize = 3;

/// Particles, flow and pixel: everything up to the sorted requests.
struct Front {
    sc: Scenario,
    seed: u64,
    flow: Flow,
    particles: seeding::Particles,
    pixel: pixel::PixelModel,
    n_pulses: u64,
    pulses_per_block: u64,
    n_blocks: u64,
    /// Particle time (s).
    t_particles: f64,
    layout: KeyLayout,
    /// The snapshot lists of the last block, reused (their pages stay
    /// mapped).
    snaps: Vec<Vec<seeding::Snapshot>>,
    /// Truth lists given back by [`Simulator::recycle_truth`].
    truth_pool: Vec<Vec<TruthSample>>,
    /// [`KeySink::group_ns`].
    group_ns: u64,
    buffers: std::sync::Arc<Buffers>,
    /// The motion replayed instead of advecting (found in a
    /// [`MotionCache`]).
    replay: Option<std::sync::Arc<motion::Motion>>,
    /// Where this run's motion goes once its last block is made (not
    /// found in the cache): the cache, the key and the blocks so far.
    record: Option<(
        std::sync::Arc<MotionCache>,
        motion::MotionKey,
        Vec<motion::BlockSnapshots>,
    )>,
}

/// Readout state carried from block to block.
struct Back {
    refractory: Option<readout::Refractory>,
    arbiter: Option<readout::Arbiter>,
    limiter: Option<readout::RateLimiter>,
    /// Requests at or after the current block's end.
    carry: Vec<pixel::Arrival>,
    /// Refractory groups carried over: (index in `carry` of the head,
    /// member), in head order.
    carry_tails: Vec<(usize, pixel::Arrival)>,
    /// Groups whose head the refractory filter dropped, so that their
    /// members were looked at (counted for tests).
    pub(crate) groups_expanded: u64,
    lost_in_readout: u64,
    layout: KeyLayout,
    /// The radix sort's reused buffer.
    scratch: Vec<u64>,
    /// Decoded requests that passed the refractory filter.
    reqs: Vec<pixel::Arrival>,
    buffers: std::sync::Arc<Buffers>,
}

/// The streaming simulator.
///
/// Two stages per block: the front (advection, truth, rendering, noise;
/// itself parallel) and the back (request sort with the carry-over,
/// refractory, arbiter, limiter: sequential, a queue). The back of block k runs
/// concurrently with the front of block k + 1 (`rayon::join`), so the
/// sequential part does not leave a core idle; neither stage depends on
/// the other's output of those blocks, so the result is the same as
/// running them one after the other, for any thread count.
#[ebptv_macros::testkit]
pub(crate) struct Simulator {
    front: Front,
    back: Back,
    /// Block `block`'s front, computed while the previous block's back ran.
    ahead: Option<BlockRequests>,
    info: StreamInfo,
    block: u64,
    truth: Vec<TruthSample>,
    pulse_starts_us: Vec<f64>,
    stats: SimStats,
}

impl Simulator {
    /// A simulator of scenario `sc`; `seed` fixes every random draw.
    #[ebptv_macros::testkit]
    pub(crate) fn new(sc: &Scenario, seed: u64) -> Result<Simulator> {
        Simulator::build(sc, seed, None)
    }

    /// [`Simulator::new`], its particle motion replayed from `cache` when
    /// it holds this scene's and seed's, else simulated and kept there
    /// (see [`MotionCache`]).
    fn build(
        sc: &Scenario,
        seed: u64,
        cache: Option<&std::sync::Arc<MotionCache>>,
    ) -> Result<Simulator> {
        sc.validate()?;
        let flow = Flow::build(&sc.flow)?;
        let (mut replay, mut record) = (None, None);
        if let Some(cache) = cache {
            let key = motion::MotionKey::of(sc, seed);
            match cache.get(&key) {
                Some(m) => replay = Some(m),
                None => record = Some((cache.clone(), key, Vec::new())),
            }
        }
        let particles = match &replay {
            // Nothing to advect: the particle count is all that is used.
            Some(_) => seeding::Particles::empty(),
            None => seeding::Particles::seed(sc, &flow, seed),
        };
        let n_particles = replay.as_ref().map_or(particles.len(), |m| m.particles);
        let pixel = pixel::PixelModel::new(sc, seed);
        let roi = sc.roi();
        let n_pulses = sc.pulse_count();
        let pulses_per_block = ((BLOCK_US / sc.period_us()).round() as u64).max(1);
        let n_blocks = n_pulses.div_ceil(pulses_per_block).max(1);
        let geometry = Geometry::new(sc.sensor.width as u16, sc.sensor.height as u16);
        let info = StreamInfo {
            path: format!("<simulation {}>", sc.name).into(),
            // What `ebptv simulate` writes by default; no file is read.
            format: Format::Evt3,
            geometry: Some(geometry),
            header: vec![
                ("generator".into(), "ebptv simulate".into()),
                ("seed".into(), seed.to_string()),
            ],
            payload_offset: 0,
            file_size: None,
        };
        let buffers = std::sync::Arc::new(Buffers::default());
        let stats = SimStats {
            particles: n_particles as u64,
            duration_s: sc.duration_s,
            ..Default::default()
        };
        Ok(Simulator {
            back: Back {
                refractory: sc
                    .pixel
                    .refractory
                    .map(|r| readout::Refractory::new(r.period_us, roi)),
                arbiter: sc
                    .readout
                    .arbiter_saturation
                    .map(|a| readout::Arbiter::new(a, roi)),
                limiter: sc
                    .readout
                    .rate_limiter
                    .map(|r| readout::RateLimiter::new(r.max_rate_ev_s, r.window_us)),
                carry: Vec::new(),
                carry_tails: Vec::new(),
                groups_expanded: 0,
                lost_in_readout: 0,
                layout: KeyLayout::new(roi),
                scratch: Vec::new(),
                reqs: Vec::new(),
                buffers: buffers.clone(),
            },
            front: Front {
                sc: sc.clone(),
                seed,
                flow,
                particles,
                pixel,
                n_pulses,
                pulses_per_block,
                n_blocks,
                t_particles: 0.0,
                layout: KeyLayout::new(roi),
                snaps: Vec::new(),
                truth_pool: Vec::new(),
                group_ns: sc.pixel.refractory.map_or(0, |r| group_ns(r.period_us)),
                buffers,
                replay,
                record,
            },
            ahead: None,
            info,
            block: 0,
            truth: Vec::new(),
            pulse_starts_us: Vec::new(),
            stats,
        })
    }

    /// Every request through the sort and the refractory filter, no
    /// refractory groups (the plain definition the tests compare with).
    #[cfg(feature = "testkit")]
    fn without_refractory_groups(mut self) -> Simulator {
        self.front.group_ns = 0;
        self
    }

    /// The velocity field the particles follow.
    #[ebptv_macros::testkit]
    pub(crate) fn flow(&self) -> &Flow {
        &self.front.flow
    }

    /// Truth of the pulses simulated so far (and not taken before).
    #[ebptv_macros::testkit]
    pub(crate) fn take_truth(&mut self) -> Vec<TruthSample> {
        std::mem::take(&mut self.truth)
    }

    /// Give back a list from [`Simulator::take_truth`] once its rows are
    /// used: later blocks fill it instead of fresh memory (the truth of a
    /// full-frame block is ~2 MB, whose new pages cost system time).
    pub(crate) fn recycle_truth(&mut self, rows: Vec<TruthSample>) {
        if self.front.truth_pool.len() < 4 && rows.capacity() > 0 {
            self.front.truth_pool.push(rows);
        }
    }

    /// Start times of all pulses simulated so far (µs).
    #[ebptv_macros::testkit]
    pub(crate) fn pulse_starts_us(&self) -> &[f64] {
        &self.pulse_starts_us
    }

    /// The counters so far.
    #[ebptv_macros::testkit]
    pub(crate) fn stats(&self) -> &SimStats {
        &self.stats
    }

    /// (pulses done, pulses in total), for progress bars.
    pub(crate) fn progress(&self) -> (u64, u64) {
        (
            (self.block * self.front.pulses_per_block).min(self.front.n_pulses),
            self.front.n_pulses,
        )
    }

    /// Hot pixels (x, y, rate) of this run.
    #[ebptv_macros::testkit]
    pub(crate) fn hot_pixels(&self) -> &[(u16, u16, f64)] {
        self.front.pixel.hot_pixels()
    }

    /// Simulate the next block into `chunk` (cleared first), running the
    /// front of the block after it at the same time.
    fn run_block(&mut self, chunk: &mut Chunk) {
        chunk.clear();
        let b = self.block;
        let mut req = match self.ahead.take() {
            Some(r) => r,
            None => self.front.block(b),
        };
        debug_assert_eq!(req.block, b);
        let duration_us = self.front.sc.duration_s * 1e6;
        if b + 1 < self.front.n_blocks {
            let (front, back) = (&mut self.front, &mut self.back);
            let ((), next) = rayon::join(
                || back.block(&mut req, duration_us, &mut chunk.events),
                || front.block(b + 1),
            );
            self.ahead = Some(next);
        } else {
            self.back.block(&mut req, duration_us, &mut chunk.events);
        }
        let sc = &self.front.sc;
        if sc.triggers.enabled {
            let ch = sc.triggers.channel;
            for &s in &req.starts {
                for (t, edge) in [
                    (s, Edge::Rising),
                    (s + sc.light.pulse_width_us, Edge::Falling),
                ] {
                    if t < duration_us {
                        chunk.triggers.push(Trigger {
                            t: t.floor() as i64,
                            channel: ch,
                            edge,
                        });
                    }
                }
            }
        }
        self.stats.truth_samples += req.truth.len() as u64;
        if self.truth.is_empty() {
            self.truth = req.truth;
        } else {
            self.truth.extend_from_slice(&req.truth);
        }
        self.pulse_starts_us.extend_from_slice(&req.starts);
        self.stats.lost_in_readout = self.back.lost_in_readout;
        self.stats.pulses += req.starts.len() as u64;
        self.stats.events += chunk.events.len() as u64;
        let on = chunk
            .events
            .p
            .iter()
            .filter(|&&p| p == ebptv_io::events::ON)
            .count() as u64;
        self.stats.on_events += on;
        self.stats.off_events += chunk.events.len() as u64 - on;
        self.stats.triggers += chunk.triggers.len() as u64;
        self.block += 1;
    }
}

impl Front {
    /// Advance the particles through block `b`'s pulses and turn them into
    /// the block's sorted requests and truth.
    fn block(&mut self, b: u64) -> BlockRequests {
        use rayon::prelude::*;
        let sc = &self.sc;
        let duration_us = sc.duration_s * 1e6;
        let k0 = b * self.pulses_per_block;
        let k1 = ((b + 1) * self.pulses_per_block).min(self.n_pulses);
        let last = b + 1 == self.n_blocks;
        let t_begin = if b == 0 { 0.0 } else { sc.pulse_start_us(k0) };
        let t_end = if last {
            duration_us
        } else {
            sc.pulse_start_us(k1)
        };
        let starts: Vec<f64> = (k0..k1).map(|k| sc.pulse_start_us(k)).collect();
        let times_s: Vec<f64> = starts.iter().map(|t| t * 1e-6).collect();
        let snaps: motion::BlockSnapshots = match &self.replay {
            Some(m) => m.blocks[b as usize].clone(),
            None => {
                let mut snaps = if self.record.is_some() {
                    // Kept by the cache: fresh lists.
                    Vec::new()
                } else {
                    std::mem::take(&mut self.snaps)
                };
                self.particles.advance_and_snapshot_into(
                    &self.flow,
                    self.t_particles,
                    &times_s,
                    &mut snaps,
                );
                std::sync::Arc::new(snaps)
            }
        };
        if let Some(&t) = times_s.last() {
            self.t_particles = t;
        }
        // Truth: lit particles whose image centre is in the ROI.
        let roi = sc.roi();
        let (rx0, ry0) = (roi.x as f64 - 0.5, roi.y as f64 - 0.5);
        let (rx1, ry1) = (rx0 + roi.width as f64, ry0 + roi.height as f64);
        let mut truth = self.truth_pool.pop().unwrap_or_default();
        truth.clear();
        truth.reserve(snaps.iter().map(|s| s.len()).sum());
        for (i, s) in snaps.iter().enumerate() {
            for p in s {
                if p.x >= rx0 && p.x < rx1 && p.y >= ry0 && p.y < ry1 {
                    truth.push(TruthSample {
                        pulse: (k0 + i as u64) as i64,
                        t_us: starts[i],
                        particle_id: p.id,
                        x: p.x,
                        y: p.y,
                        u: p.u,
                        v: p.v,
                    });
                }
            }
        }
        // Pixel responses, parallel over pulses, as request keys.
        let pixel = &self.pixel;
        let seed = self.seed;
        let layout = self.layout;
        let group_ns = self.group_ns;
        let buffers = &*self.buffers;
        #[allow(clippy::type_complexity)]
        let per_pulse: Vec<(Vec<u64>, Vec<(u64, u64)>)> = snaps
            .par_iter()
            .enumerate()
            .map(|(i, s)| {
                let mut sink = KeySink {
                    layout,
                    t_begin,
                    // ~2 events per lit particle: no regrowth.
                    keys: Buffers::take(&buffers.pulse_keys, 3 * s.len() + 64),
                    group_ns,
                    // ~1 group per lit particle.
                    tails: if group_ns > 0 {
                        Buffers::take(&buffers.tails, s.len() + 64)
                    } else {
                        Vec::new()
                    },
                };
                pixel.render_pulse(s, starts[i], stream_seed(seed, 6, k0 + i as u64), &mut sink);
                (sink.keys, sink.tails)
            })
            .collect();
        let mut noise = Vec::new();
        pixel.noise(t_begin, t_end, stream_seed(seed, 7, b), &mut noise);
        let n = per_pulse.iter().map(|v| v.0.len()).sum::<usize>() + noise.len();
        let mut keys = Buffers::take(&buffers.block_keys, n);
        let mut tails = Vec::with_capacity(per_pulse.len());
        for (k, t) in per_pulse {
            keys.extend_from_slice(&k);
            Buffers::give(&buffers.pulse_keys, k, POOLED_PULSE_MAX);
            tails.push(t);
        }
        keys.extend(noise.iter().map(|a| layout.key(a, t_begin)));
        match self.record.take() {
            Some((cache, key, mut blocks)) => {
                blocks.push(snaps);
                if last {
                    let n = self.particles.len();
                    cache.insert(motion::Motion::new(key, n, blocks));
                } else {
                    self.record = Some((cache, key, blocks));
                }
            }
            None if self.replay.is_none() => {
                // Its lists are reused by the next block.
                if let Ok(v) = std::sync::Arc::try_unwrap(snaps) {
                    self.snaps = v;
                }
            }
            None => {}
        }
        BlockRequests {
            block: b,
            starts,
            t_begin,
            t_end,
            last,
            keys,
            tails,
            truth,
        }
    }
}

impl Back {
    /// Read out block `r`'s requests (with those carried over from the
    /// block before) into `events`. Takes `r.keys` and `r.tails`.
    ///
    /// **Refractory groups.** Most requests the refractory filter drops
    /// are a pixel's 2nd…k-th threshold crossings of one pulse, less than
    /// the period after its first. The front keys only a pixel's earliest
    /// request of a pulse (flagged [`GROUP_FLAG`]) and keeps those later
    /// ones aside in `tails`; they never enter the sort. When the head
    /// passes the filter, every member is less than the period after it,
    /// so the filter would drop them all: nothing more to do. When the
    /// head is dropped (an earlier request of the pixel less than the
    /// period before it), the first member that passes the filter *now*
    /// is merged into the request stream at its own time (a small heap),
    /// carrying the rest of the group; members before it would be
    /// dropped whatever happens in between (the pixel's last kept time
    /// only grows). So the result is the same as filtering every request
    /// in order (`refractory_groups_match_plain_filtering`).
    fn block(&mut self, r: &mut BlockRequests, duration_us: f64, events: &mut EventChunk) {
        use std::cmp::Reverse;
        let layout = self.layout;
        let t_begin = r.t_begin;
        // The block's keys with the carry-over keyed like them (its groups
        // too), then one sort of the union (here, in the sequential stage,
        // which runs while the next block's front keeps the other core
        // busy).
        let mut keys = std::mem::take(&mut r.keys);
        let mut tails = TailIndex {
            parts: std::mem::take(&mut r.tails),
            pairs: Vec::new(),
            sorted: false,
            lookups: 0,
            last_head: None,
        };
        let mut ct = 0;
        let mut carried = Vec::new();
        for (i, a) in self.carry.iter().enumerate() {
            let head = layout.key(a, t_begin);
            let mut flag = 0;
            while ct < self.carry_tails.len() && self.carry_tails[ct].0 == i {
                let m = layout.key(&self.carry_tails[ct].1, t_begin);
                carried.push((head | GROUP_FLAG, m));
                flag = GROUP_FLAG;
                ct += 1;
            }
            keys.push(head | flag);
        }
        tails.parts.push(carried);
        sort_request_keys(&mut keys, &mut self.scratch, layout);
        // Requests from the block's end on wait for the next block.
        let split = keys.partition_point(|&k| layout.time(k, t_begin) < r.t_end);
        self.carry.clear();
        self.carry_tails.clear();
        // Decoded, through the refractory filter and into the arbiter in
        // one pass (no list of requests in between); without an arbiter
        // into `reqs`, stamped below.
        let reqs = &mut self.reqs;
        reqs.clear();
        // At most one event per request (plus a few pending ones): grow
        // the chunk once, not by doubling.
        let n = split + 1024;
        events.t.reserve(n);
        events.x.reserve(n);
        events.y.reserve(n);
        events.p.reserve(n);
        let t_end = r.t_end;
        let mut arbiter = self.arbiter.as_mut();
        if arbiter.is_none() {
            reqs.reserve(split);
        }
        // Request `k` (decoded: time `t`, pixel (`dx`, `dy`) from the ROI's
        // corner) into the arbiter, or into `reqs` without one. (A macro,
        // not a closure: the prefetches below read the arbiter between
        // calls.)
        macro_rules! take {
            ($k:expr, $t:expr, $dx:expr, $dy:expr) => {
                match &mut arbiter {
                    Some(arb) => arb.offer_at($t, $dx, $dy, ($k & 1) as u8, t_end, events),
                    None => reqs.push(layout.arrival($k, t_begin)),
                }
            };
        }
        match &mut self.refractory {
            Some(rf) => {
                let xs = layout.x_shift();
                // Deferred group members: (sort bits, sequence, slot).
                let mut heap: std::collections::BinaryHeap<Reverse<(u64, u64, usize)>> =
                    Default::default();
                let mut slots: Vec<(u64, Vec<u64>)> = Vec::new();
                // A group whose head was dropped: its first member that
                // passes the filter now goes into the heap with the rest.
                macro_rules! expand {
                    ($members:expr) => {{
                        let members: Vec<u64> = $members;
                        if !members.is_empty() {
                            self.groups_expanded += 1;
                            if let Some(m) = members
                                .iter()
                                .position(|&m| rf.would_keep(&layout.arrival(m, t_begin)))
                            {
                                heap.push(Reverse((
                                    members[m] >> xs,
                                    slots.len() as u64,
                                    slots.len(),
                                )));
                                slots.push((members[m], members[m + 1..].to_vec()));
                            }
                        }
                    }};
                }
                let mut i = 0;
                loop {
                    // The sort bits of the first deferred member due in
                    // this block: keys up to them go first.
                    let due = match heap.peek() {
                        Some(&Reverse((sk, _, j)))
                            if layout.time(slots[j].0, t_begin) < r.t_end =>
                        {
                            Some(sk)
                        }
                        _ => None,
                    };
                    let bound = due.unwrap_or(u64::MAX);
                    // The requests in key order up to the bound (nearly all
                    // of them), each decoded once; stops early when a group
                    // is expanded (the heap changed).
                    let mut heap_changed = false;
                    while i < split && keys[i] >> xs <= bound {
                        if let Some(&ahead) = keys.get(i + PREFETCH_AHEAD) {
                            let (dx, dy) = layout.pixel_offsets(ahead);
                            rf.prefetch(dx, dy);
                            if let Some(arb) = &arbiter {
                                arb.prefetch(dx, dy);
                            }
                        }
                        let k = keys[i];
                        i += 1;
                        let t = layout.time(k, t_begin);
                        let (dx, dy) = layout.pixel_offsets(k);
                        if rf.keep_at(dx, dy, t) {
                            take!(k, t, dx, dy);
                        } else if k & GROUP_FLAG != 0 {
                            let before = heap.len();
                            expand!(tails.members(k));
                            if heap.len() != before {
                                heap_changed = true;
                                break;
                            }
                        }
                    }
                    if heap_changed {
                        continue; // a new bound
                    }
                    if due.is_none() {
                        break; // keys done, nothing due in the heap
                    }
                    // The deferred member is next.
                    let Reverse((_, _, j)) = heap.pop().expect("peeked");
                    let k = slots[j].0;
                    let t = layout.time(k, t_begin);
                    let (dx, dy) = layout.pixel_offsets(k);
                    if rf.keep_at(dx, dy, t) {
                        take!(k, t, dx, dy);
                    } else {
                        expand!(std::mem::take(&mut slots[j].1));
                    }
                }
                if !r.last {
                    for &k in &keys[split..] {
                        let members = if k & GROUP_FLAG != 0 {
                            tails.members(k)
                        } else {
                            Vec::new()
                        };
                        carry_push(
                            &mut self.carry,
                            &mut self.carry_tails,
                            (layout, t_begin),
                            k,
                            &members,
                        );
                    }
                    while let Some(Reverse((_, _, j))) = heap.pop() {
                        let (k, members) = std::mem::take(&mut slots[j]);
                        carry_push(
                            &mut self.carry,
                            &mut self.carry_tails,
                            (layout, t_begin),
                            k,
                            &members,
                        );
                    }
                }
            }
            None => {
                for (i, &k) in keys[..split].iter().enumerate() {
                    if let (Some(&ahead), Some(arb)) = (keys.get(i + PREFETCH_AHEAD), &arbiter) {
                        let (dx, dy) = layout.pixel_offsets(ahead);
                        arb.prefetch(dx, dy);
                    }
                    let (dx, dy) = layout.pixel_offsets(k);
                    take!(k, layout.time(k, t_begin), dx, dy);
                }
                if !r.last {
                    self.carry
                        .extend(keys[split..].iter().map(|&k| layout.arrival(k, t_begin)));
                }
            }
        }
        Buffers::give(&self.buffers.block_keys, keys, POOLED_BLOCK_MAX);
        for t in tails.parts {
            Buffers::give(&self.buffers.tails, t, POOLED_PULSE_MAX);
        }
        match &mut self.arbiter {
            Some(a) => {
                a.finish(t_end, events);
                self.lost_in_readout = a.lost;
            }
            None => readout::stamp_ideal(&self.reqs, events),
        }
        if r.last {
            events.retain(|t, _, _, _| (t as f64) < duration_us);
        }
        if let Some(l) = &mut self.limiter {
            l.apply(events);
        }
    }
}

/// Carry request `k` over to the next block, with its group's members
/// (`Back::carry`, `Back::carry_tails`).
fn carry_push(
    carry: &mut Vec<pixel::Arrival>,
    carry_tails: &mut Vec<(usize, pixel::Arrival)>,
    (layout, t_begin): (KeyLayout, f64),
    k: u64,
    members: &[u64],
) {
    let i = carry.len();
    carry.push(layout.arrival(k, t_begin));
    carry_tails.extend(members.iter().map(|&m| (i, layout.arrival(m, t_begin))));
}

/// A block's refractory groups, looked up by head only when a head is
/// dropped or carried over (at the pulse rates of the presets: a few per
/// block): the first lookups scan the list, later ones sort it once (by
/// head, then member) and search.
struct TailIndex {
    /// The block's lists of (head, member), as the pulses made them.
    parts: Vec<Vec<(u64, u64)>>,
    /// `parts` concatenated and sorted, once lookups are many.
    pairs: Vec<(u64, u64)>,
    sorted: bool,
    /// Lookups so far (by scanning while few).
    lookups: u32,
    /// The head last looked up: identical heads (same pixel, polarity and
    /// nanosecond, from two pulses) are adjacent in the sorted requests
    /// and share one list of members, handed out once.
    last_head: Option<u64>,
}

impl TailIndex {
    /// The members of head `k` in time order (empty if already handed out).
    fn members(&mut self, k: u64) -> Vec<u64> {
        if self.last_head == Some(k) {
            return Vec::new();
        }
        self.last_head = Some(k);
        self.lookups += 1;
        if !self.sorted && self.lookups <= 16 {
            // A scan is ~n instructions, the sort ~n·log n.
            let mut m: Vec<u64> = self
                .parts
                .iter()
                .flatten()
                .filter(|p| p.0 == k)
                .map(|p| p.1)
                .collect();
            m.sort_unstable();
            return m;
        }
        if !self.sorted {
            self.pairs = self.parts.concat();
            self.pairs.sort_unstable();
            self.sorted = true;
        }
        let lo = self.pairs.partition_point(|p| p.0 < k);
        let hi = self.pairs.partition_point(|p| p.0 <= k);
        self.pairs[lo..hi].iter().map(|p| p.1).collect()
    }
}

/// [`KeySink::group_ns`] for a refractory period: a few ns short of it,
/// so a member stays less than the period after its head whatever the
/// rounding to ns and the re-keying of carried requests (±1 ns each).
fn group_ns(period_us: f64) -> u64 {
    ((period_us * 1000.0).floor() as i64 - 3).max(0) as u64
}

impl EventSource for Simulator {
    fn info(&self) -> &StreamInfo {
        &self.info
    }

    fn next_chunk(&mut self, chunk: &mut Chunk) -> Result<bool> {
        while self.block < self.front.n_blocks {
            self.run_block(chunk);
            if !chunk.is_empty() {
                return Ok(true);
            }
        }
        chunk.clear();
        Ok(false)
    }
}

/// Simulate a whole recording in memory.
pub fn simulate(sc: &Scenario, seed: u64) -> Result<SimOutput> {
    drain(Simulator::new(sc, seed)?)
}

/// [`simulate`], the particle motion replayed from `cache` when it holds
/// this scene's and seed's (else simulated and kept there): for many
/// simulations of one scene that differ only in the sensor, as a model
/// check runs. The output is the same as [`simulate`]'s.
pub fn simulate_with(
    sc: &Scenario,
    seed: u64,
    cache: &std::sync::Arc<MotionCache>,
) -> Result<SimOutput> {
    drain(Simulator::build(sc, seed, Some(cache))?)
}

/// Run `sim` to its end into memory.
fn drain(mut sim: Simulator) -> Result<SimOutput> {
    let mut out = SimOutput {
        geometry: sim.info().geometry,
        ..Default::default()
    };
    let mut chunk = Chunk::default();
    while sim.next_chunk(&mut chunk)? {
        out.events.extend_from(&chunk.events);
        out.triggers.extend_from_slice(&chunk.triggers);
    }
    out.truth = sim.take_truth();
    out.pulse_starts_us = sim.pulse_starts_us.clone();
    if out.events.t.windows(2).any(|w| w[0] > w[1]) {
        return Err(Error::analysis(
            "simulator produced out-of-order events (bug)",
        ));
    }
    Ok(out)
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    #[ebptv_macros::unit_test]
    fn radix_sort_matches_comparison_sort() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(11);
        let mut scratch = Vec::new();
        // Sizes around the small-input cut-off, key widths from a few bits
        // (many ties, constant digits skipped) to all 64.
        for (n, bits) in [
            (0, 8),
            (1, 64),
            (511, 20),
            (512, 20),
            (5000, 3),
            (20_000, 47),
            (20_000, 64),
            (3000, 57),
        ] {
            let mut keys: Vec<u64> = (0..n)
                .map(|_| {
                    let k: u64 = rng.gen();
                    if bits == 64 {
                        k
                    } else {
                        k & ((1u64 << bits) - 1)
                    }
                })
                .collect();
            // Some constant high bits, as request keys have.
            if bits == 57 {
                keys.iter_mut().for_each(|k| *k |= 1 << 56);
            }
            // Stable on the high part only: equal high parts keep their
            // input order (the low bits are carried, not compared).
            for low in [1, 12, 40] {
                let mut above = keys.clone();
                let mut expect = keys.clone();
                expect.sort_by_key(|k| k >> low);
                radix_sort_above(&mut above, &mut scratch, low);
                assert_eq!(above, expect, "n {n}, bits {bits}, low {low}");
            }
            let mut expect = keys.clone();
            expect.sort_unstable();
            radix_sort(&mut keys, &mut scratch);
            assert_eq!(keys, expect, "n {n}, bits {bits}");
        }
    }

    #[ebptv_macros::unit_test]
    fn refractory_groups_match_plain_filtering() {
        // Scenes where group heads are often dropped (a refractory period
        // longer than the pulse period, dense noise), groups are carried
        // over block ends (latency beyond the block) and OFF events join:
        // the same events as sorting and filtering every request.
        let mut cases = Vec::new();
        for (period, latency, off, noise) in [
            (30.0, 12.0, false, 0.0),
            (150.0, 12.0, true, 2000.0),
            (400.0, 2500.0, false, 500.0),
            (60.0, 1900.0, true, 20_000.0),
        ] {
            let mut sc = presets::preset("water_jet_10khz").expect("preset");
            sc.duration_s = 0.012;
            sc.sensor.roi = Some(scenario::Roi {
                x: 100,
                y: 300,
                width: 300,
                height: 60,
            });
            sc.pixel.max_events_per_pulse = 8;
            sc.pixel.latency_us = latency;
            sc.pixel.refractory = Some(scenario::Refractory { period_us: period });
            if off {
                sc.pixel.off_events = Some(scenario::OffEvents {
                    threshold: 0.2,
                    tau_us: 20.0,
                });
            }
            if noise > 0.0 {
                sc.noise.background_noise = Some(scenario::BackgroundNoise { rate_hz: noise });
            }
            cases.push(sc);
        }
        for sc in &cases {
            let run = |grouped: bool| {
                let mut sim = Simulator::new(sc, 3).expect("valid scenario");
                if !grouped {
                    sim = sim.without_refractory_groups();
                }
                let mut ev = EventChunk::default();
                let mut chunk = Chunk::default();
                while sim.next_chunk(&mut chunk).expect("runs") {
                    ev.extend_from(&chunk.events);
                }
                (ev, sim.back.groups_expanded, sim.stats.lost_in_readout)
            };
            let (grouped, expanded, lost) = run(true);
            let (plain, none, plain_lost) = run(false);
            assert_eq!(none, 0);
            assert!(plain.len() > 10_000, "{}", plain.len());
            assert_eq!(grouped, plain, "{:?}", sc.pixel);
            assert_eq!(lost, plain_lost);
            // The lazy path is exercised where heads get dropped.
            if sc.pixel.refractory.expect("on").period_us > 100.0 {
                assert!(expanded > 100, "{expanded}");
            }
        }
    }

    #[ebptv_macros::unit_test]
    fn time_sort_with_row_ties_matches_full_radix_sort() {
        // Keys as a block makes them (2 and 3 radix passes on the time),
        // with runs of equal nanoseconds of every length up to one run
        // of all keys (the insertion pass gives up and sorts fully).
        let mut rng = rand_pcg::Pcg64::seed_from_u64(13);
        let roi = scenario::Roi {
            x: 0,
            y: 0,
            width: 1280,
            height: 720,
        };
        let layout = KeyLayout::new(roi);
        let mut scratch = Vec::new();
        for (n, span_ns, same) in [
            (100, 1000u64, 0.0),
            (5000, 2_300_000, 0.0),
            (50_000, 2_300_000, 0.05),
            (50_000, 50_000, 0.0),
            (50_000, 9_000_000, 0.01),
            (20_000, 1, 0.0),
            (20_000, 3_000_000, 0.5),
        ] {
            let keys: Vec<u64> = (0..n)
                .map(|_| {
                    let ns = if rng.gen_bool(same) {
                        777
                    } else {
                        rng.gen_range(0..span_ns)
                    };
                    (ns << layout.time_shift)
                        | layout.pixel_bits(rng.gen_range(0..1280), rng.gen_range(0..720))
                        | rng.gen_range(0..4)
                })
                .collect();
            let mut expect = keys.clone();
            radix_sort_above(&mut expect, &mut scratch, layout.x_shift());
            let mut got = keys;
            sort_request_keys(&mut got, &mut scratch, layout);
            assert_eq!(got, expect, "n {n}, span {span_ns}, same {same}");
        }
    }

    #[ebptv_macros::unit_test]
    fn request_sort_matches_reference() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(12);
        let t_begin = 123_456.789;
        for (x, y, width, height) in [
            (0, 0, 1280, 720),
            (17, 23, 333, 100),
            (5, 9, 1, 1),
            (0, 0, 4096, 4096),
        ] {
            let roi = scenario::Roi {
                x,
                y,
                width,
                height,
            };
            let reqs: Vec<pixel::Arrival> = (0..30_000)
                .map(|_| pixel::Arrival {
                    // Some before t_begin (clamped), many sharing a time.
                    t: t_begin
                        + rng.gen_range(-5.0..2500.0_f64)
                            * if rng.gen_bool(0.3) { 1.0 } else { 0.0 },
                    x: rng.gen_range(x..x + width) as u16,
                    y: rng.gen_range(y..y + height) as u16,
                    p: rng.gen_range(0..2),
                })
                .collect();
            let mut fast = reqs.clone();
            let mut slow = reqs;
            sort_requests(&mut fast, t_begin, roi);
            sort_requests_reference(&mut slow, t_begin);
            assert_eq!(fast, slow);
            assert!(fast.windows(2).all(|w| w[0].t <= w[1].t));
        }
    }
}

// The unit tests, indexed for tests/unit.rs (`unit_tests`; build.rs,
// `ebptv-testgen`); test kit only.
#[cfg(feature = "testkit")]
include!(concat!(env!("OUT_DIR"), "/unit_index.rs"));
