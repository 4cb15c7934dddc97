//! Simulator of pulsed event-based imaging with ground truth.
//!
//! The chain: [`flow`] (exact u(x, y, t)) → [`seeding`] (particles in a
//! light-sheet slab, RK4 pathlines, recycling) → [`light`] (pulse envelope,
//! saw-tooth modulation) → [`pixel`] (log-contrast pixel, latency, OFF,
//! noise) → [`readout`] (refractory, row arbiter, timestamps, rate limiter)
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
//! [`Simulator`] is an [`EventSource`]: it works in blocks of pulses (about
//! 2 ms), so memory is bounded by a block whatever the duration, and the
//! truth of the pulses produced so far is taken with
//! [`Simulator::take_truth`]. Particle advection is parallel over particles,
//! rendering parallel over pulses (rayon), and the sequential readout of a
//! block (request sort, refractory, arbiter) runs while the next block is
//! being rendered (see [`Simulator`]); every random draw comes from a
//! stream derived from the user's seed and the item's index (particle slot,
//! pulse, block), so the output does not depend on the thread count.
//! [`simulate`] drains a `Simulator` into memory (tests, small scenes).
//!
//! ## Effects
//! Each sensor/readout effect (and the laser's `clock_drift` against the
//! camera clock, which moves pulses, triggers and truth together) is an
//! `Option` in the [`Scenario`]; `None`
//! means exactly absent (no random draws are taken for it either, so
//! switching one effect does not reshuffle the others). See
//! [`scenario`] for the table of names and parameters.

use serde::{Deserialize, Serialize};

pub mod flow;
pub mod light;
pub mod pixel;
pub mod presets;
pub mod readout;
pub mod record;
pub mod scenario;
pub mod seeding;

pub use flow::Flow;
pub use record::{write_recording, RecordingSummary, TruthWriter};
pub use scenario::{Scenario, EFFECT_NAMES};

use crate::error::{Error, Result};
use crate::events::{Chunk, Edge, EventChunk, Geometry, Trigger};
use crate::io::{EventSource, Format, StreamInfo};

/// Ground truth of one particle at one pulse (`truth_particles.csv`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TruthSample {
    pub pulse: i64,
    /// Pulse start time (µs).
    pub t_us: f64,
    pub particle_id: u64,
    /// Particle-image centre at the pulse (px).
    pub x: f64,
    pub y: f64,
    /// True velocity (px/s).
    pub u: f64,
    pub v: f64,
}

/// A whole simulated recording in memory (tests, small scenes). Long
/// recordings stream through `Simulator` (an `EventSource`) instead.
#[derive(Debug, Clone, Default)]
pub struct SimOutput {
    pub geometry: Option<Geometry>,
    /// Events in readout order (time-ordered).
    pub events: EventChunk,
    pub triggers: Vec<Trigger>,
    pub truth: Vec<TruthSample>,
    /// True start time of every light pulse (µs).
    pub pulse_starts_us: Vec<f64>,
}

/// Counters of a simulation run (`summary.json`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct SimStats {
    pub events: u64,
    pub on_events: u64,
    pub off_events: u64,
    pub triggers: u64,
    pub pulses: u64,
    /// Particle slots in the slab (lit or not, ROI plus margin).
    pub particles: u64,
    /// Truth rows: lit particles inside the ROI, summed over pulses.
    pub truth_samples: u64,
    /// Requests lost in the readout (pixel still blocked).
    pub lost_in_readout: u64,
    pub duration_s: f64,
}

impl SimStats {
    pub fn event_rate_ev_s(&self) -> f64 {
        self.events as f64 / self.duration_s
    }
    /// Events per lit particle per pulse (noise included).
    pub fn events_per_particle_per_pulse(&self) -> f64 {
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
const BLOCK_US: f64 = 2000.0;

/// How a request packs into one u64 sort key: time at 1 ns resolution
/// relative to the block's `t_begin` (ample for 1 µs timestamps; 2^39 ns
/// = 9 min of carry-over), then y, x (relative to the ROI, in as few bits
/// as its size needs) and polarity. Requests are ordered by (time, y),
/// equal ones in input order, as [`sort_requests_reference`] defines: a
/// stable radix sort of the keys on the bits above x ([`Self::x_shift`]),
/// 3 passes of 11 bits at full frame (x and p need not be sorted on:
/// same-row requests at the same nanosecond are rare, and a pulse's
/// pixels come in x order anyway). Times come back rounded to the
/// nanosecond.
#[derive(Debug, Clone, Copy)]
struct KeyLayout {
    x0: u16,
    y0: u16,
    x_bits: u32,
    time_shift: u32,
}

impl KeyLayout {
    fn new(roi: scenario::Roi) -> KeyLayout {
        let bits = |n: u32| 32 - n.saturating_sub(1).leading_zeros();
        let x_bits = bits(roi.width);
        KeyLayout {
            x0: roi.x as u16,
            y0: roi.y as u16,
            x_bits,
            time_shift: 1 + x_bits + bits(roi.height),
        }
    }

    /// The key bits below y (x and p), which the sort does not compare.
    fn x_shift(&self) -> u32 {
        1 + self.x_bits
    }

    #[inline]
    fn key(&self, a: &pixel::Arrival, t_begin: f64) -> u64 {
        debug_assert!(a.x >= self.x0 && a.y >= self.y0, "request outside the ROI");
        let ns = (pixel::round_i64((a.t - t_begin) * 1000.0).max(0) as u64).min((1 << 39) - 1);
        (ns << self.time_shift)
            | (((a.y - self.y0) as u64) << (1 + self.x_bits))
            | (((a.x - self.x0) as u64) << 1)
            | a.p as u64
    }

    #[inline]
    fn arrival(&self, k: u64, t_begin: f64) -> pixel::Arrival {
        let y_mask = (1u64 << (self.time_shift - 1 - self.x_bits)) - 1;
        pixel::Arrival {
            t: self.time(k, t_begin),
            y: self.y0 + ((k >> (1 + self.x_bits)) & y_mask) as u16,
            x: self.x0 + ((k >> 1) & ((1u64 << self.x_bits) - 1)) as u16,
            p: (k & 1) as u8,
        }
    }

    /// The key bits of pixel (x, y) (for [`Self::key_at`]).
    #[inline]
    fn pixel_bits(&self, x: u16, y: u16) -> u64 {
        debug_assert!(x >= self.x0 && y >= self.y0, "request outside the ROI");
        (((y - self.y0) as u64) << (1 + self.x_bits)) | (((x - self.x0) as u64) << 1)
    }

    /// [`Self::key`] from the pixel's [`Self::pixel_bits`], the time and
    /// the polarity.
    #[inline]
    fn key_at(&self, pixel_bits: u64, t: f64, p: u8, t_begin: f64) -> u64 {
        let ns = pixel::round_i64((t - t_begin) * 1000.0).clamp(0, (1 << 39) - 1) as u64;
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
}

impl pixel::ArrivalSink for KeySink {
    #[inline]
    fn arrive(&mut self, a: pixel::Arrival) {
        self.keys.push(self.layout.key(&a, self.t_begin));
    }

    #[inline]
    fn arrive_pixel(&mut self, x: u16, y: u16, p: u8, times: &[f64]) {
        // The layout in locals: the pushes would make the compiler
        // reload it per event.
        let (layout, t_begin) = (self.layout, self.t_begin);
        let bits = layout.pixel_bits(x, y);
        self.keys.reserve(times.len());
        for &t in times {
            self.keys.push(layout.key_at(bits, t, p, t_begin));
        }
    }
}

/// The plain definition of the request order (test reference): keys,
/// stable comparison sort by (time in ns, y), decode.
pub fn sort_requests_reference(reqs: &mut [pixel::Arrival], t_begin: f64) {
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
pub fn sort_requests(reqs: &mut [pixel::Arrival], t_begin: f64, roi: scenario::Roi) {
    let layout = KeyLayout::new(roi);
    let mut keys: Vec<u64> = reqs.iter().map(|a| layout.key(a, t_begin)).collect();
    radix_sort_above(&mut keys, &mut Vec::new(), layout.x_shift());
    for (a, k) in reqs.iter_mut().zip(keys) {
        *a = layout.arrival(k, t_begin);
    }
}

/// Sort `keys` ascending: LSD radix sort over the bits any key uses, in
/// digits of at most 11 bits (a 16 kB histogram stays in L1), skipping
/// digits all keys share. Same result as `sort_unstable` (keys are plain
/// integers), in a few linear passes instead of ~log2(n) comparisons per
/// key: the request sort was ~10 % of the simulator's instructions.
pub fn radix_sort(keys: &mut Vec<u64>, scratch: &mut Vec<u64>) {
    radix_sort_above(keys, scratch, 0);
}

/// Sort `keys` stably by `key >> low_bits` (the low bits are carried,
/// not compared: equal high parts keep their input order), by
/// [`radix_sort`]'s passes.
pub fn radix_sort_above(keys: &mut Vec<u64>, scratch: &mut Vec<u64>, low_bits: u32) {
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
    for &k in keys.iter() {
        let k = k >> low_bits;
        for p in 0..passes as usize {
            counts[p * radix + ((k >> (p as u32 * digit)) & mask) as usize] += 1;
        }
    }
    scratch.clear();
    scratch.resize(n, 0);
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
    truth: Vec<TruthSample>,
}

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
}

/// Readout state carried from block to block.
struct Back {
    refractory: Option<readout::Refractory>,
    arbiter: Option<readout::Arbiter>,
    limiter: Option<readout::RateLimiter>,
    /// Requests at or after the current block's end.
    carry: Vec<pixel::Arrival>,
    lost_in_readout: u64,
    layout: KeyLayout,
    /// The radix sort's reused buffer.
    scratch: Vec<u64>,
    /// Decoded requests that passed the refractory filter.
    reqs: Vec<pixel::Arrival>,
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
pub struct Simulator {
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
    pub fn new(sc: &Scenario, seed: u64) -> Result<Simulator> {
        sc.validate()?;
        let flow = Flow::build(&sc.flow)?;
        let particles = seeding::Particles::seed(sc, &flow, seed);
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
        let stats = SimStats {
            particles: particles.len() as u64,
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
                lost_in_readout: 0,
                layout: KeyLayout::new(roi),
                scratch: Vec::new(),
                reqs: Vec::new(),
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
            },
            ahead: None,
            info,
            block: 0,
            truth: Vec::new(),
            pulse_starts_us: Vec::new(),
            stats,
        })
    }

    pub fn scenario(&self) -> &Scenario {
        &self.front.sc
    }

    pub fn flow(&self) -> &Flow {
        &self.front.flow
    }

    /// Truth of the pulses simulated so far (and not taken before).
    pub fn take_truth(&mut self) -> Vec<TruthSample> {
        std::mem::take(&mut self.truth)
    }

    /// Give back a list from [`Simulator::take_truth`] once its rows are
    /// used: later blocks fill it instead of fresh memory (the truth of a
    /// full-frame block is ~2 MB, whose new pages cost system time).
    pub fn recycle_truth(&mut self, rows: Vec<TruthSample>) {
        if self.front.truth_pool.len() < 4 && rows.capacity() > 0 {
            self.front.truth_pool.push(rows);
        }
    }

    /// Start times of all pulses simulated so far (µs).
    pub fn pulse_starts_us(&self) -> &[f64] {
        &self.pulse_starts_us
    }

    pub fn stats(&self) -> &SimStats {
        &self.stats
    }

    /// (pulses done, pulses in total), for progress bars.
    pub fn progress(&self) -> (u64, u64) {
        (
            (self.block * self.front.pulses_per_block).min(self.front.n_pulses),
            self.front.n_pulses,
        )
    }

    /// Hot pixels (x, y, rate) of this run.
    pub fn hot_pixels(&self) -> &[(u16, u16, f64)] {
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
            .filter(|&&p| p == crate::events::ON)
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
        let mut snaps = std::mem::take(&mut self.snaps);
        self.particles.advance_and_snapshot_into(
            &self.flow,
            self.t_particles,
            &times_s,
            &mut snaps,
        );
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
        let per_pulse: Vec<Vec<u64>> = snaps
            .par_iter()
            .enumerate()
            .map(|(i, s)| {
                let mut sink = KeySink {
                    layout,
                    t_begin,
                    // ~2 events per lit particle: one allocation, no regrowth.
                    keys: Vec::with_capacity(3 * s.len() + 64),
                };
                pixel.render_pulse(s, starts[i], stream_seed(seed, 6, k0 + i as u64), &mut sink);
                sink.keys
            })
            .collect();
        let mut noise = Vec::new();
        pixel.noise(t_begin, t_end, stream_seed(seed, 7, b), &mut noise);
        let n = per_pulse.iter().map(|v| v.len()).sum::<usize>() + noise.len();
        let mut keys = Vec::with_capacity(n);
        for v in &per_pulse {
            keys.extend_from_slice(v);
        }
        keys.extend(noise.iter().map(|a| layout.key(a, t_begin)));
        self.snaps = snaps;
        BlockRequests {
            block: b,
            starts,
            t_begin,
            t_end,
            last,
            keys,
            truth,
        }
    }
}

impl Back {
    /// Read out block `r`'s requests (with those carried over from the
    /// block before) into `events`. Takes `r.keys`.
    fn block(&mut self, r: &mut BlockRequests, duration_us: f64, events: &mut EventChunk) {
        // The block's keys with the carry-over keyed like them, then one
        // sort of the union (here, in the sequential stage, which runs
        // while the next block's front keeps the other core busy).
        let mut keys = std::mem::take(&mut r.keys);
        keys.extend(self.carry.iter().map(|a| self.layout.key(a, r.t_begin)));
        radix_sort_above(&mut keys, &mut self.scratch, self.layout.x_shift());
        let layout = self.layout;
        let t_begin = r.t_begin;
        // Requests from the block's end on wait for the next block.
        let split = keys.partition_point(|&k| layout.time(k, t_begin) < r.t_end);
        self.carry.clear();
        if !r.last {
            self.carry
                .extend(keys[split..].iter().map(|&k| layout.arrival(k, t_begin)));
        }
        // Decoded and through the refractory filter in one pass.
        let reqs = &mut self.reqs;
        reqs.clear();
        reqs.reserve(split);
        match &mut self.refractory {
            Some(rf) => {
                for &k in &keys[..split] {
                    let a = layout.arrival(k, t_begin);
                    if rf.keep(&a) {
                        reqs.push(a);
                    }
                }
            }
            None => reqs.extend(keys[..split].iter().map(|&k| layout.arrival(k, t_begin))),
        }
        // At most one event per request (plus a few pending ones): grow
        // the chunk once, not by doubling.
        let n = reqs.len() + 1024;
        events.t.reserve(n);
        events.x.reserve(n);
        events.y.reserve(n);
        events.p.reserve(n);
        match &mut self.arbiter {
            Some(a) => {
                a.run(reqs, r.t_end, events);
                self.lost_in_readout = a.lost;
            }
            None => readout::stamp_ideal(reqs, events),
        }
        if r.last {
            events.retain(|t, _, _, _| (t as f64) < duration_us);
        }
        if let Some(l) = &mut self.limiter {
            l.apply(events);
        }
    }
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
    let mut sim = Simulator::new(sc, seed)?;
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

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    #[test]
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

    #[test]
    fn request_sort_matches_reference() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(12);
        let t_begin = 123_456.789;
        for (x, y, width, height) in [(0, 0, 1280, 720), (17, 23, 333, 100), (5, 9, 1, 1)] {
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
