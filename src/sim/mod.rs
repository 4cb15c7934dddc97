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
//! rendering parallel over pulses (rayon); every random draw comes from a
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

/// Sort requests by time at 1 ns resolution relative to `t_begin` (ample
/// for 1 µs timestamps; 2^39 ns = 9 min of carry-over), ties by pixel and
/// polarity. Each request packs into one u64 key (time, y, x, p), so the
/// sort moves plain integers; times come back rounded to the nanosecond.
fn sort_requests(reqs: &mut [pixel::Arrival], t_begin: f64) {
    use rayon::prelude::*;
    let mut keys: Vec<u64> = reqs
        .iter()
        .map(|a| {
            let ns = (((a.t - t_begin) * 1000.0).round().max(0.0) as u64).min((1 << 39) - 1);
            (ns << 25) | ((a.y as u64) << 13) | ((a.x as u64) << 1) | a.p as u64
        })
        .collect();
    keys.par_sort_unstable();
    for (a, k) in reqs.iter_mut().zip(keys) {
        *a = pixel::Arrival {
            t: t_begin + (k >> 25) as f64 * 1e-3,
            y: ((k >> 13) & 0xFFF) as u16,
            x: ((k >> 1) & 0xFFF) as u16,
            p: (k & 1) as u8,
        };
    }
}

/// The streaming simulator.
pub struct Simulator {
    sc: Scenario,
    seed: u64,
    flow: Flow,
    particles: seeding::Particles,
    pixel: pixel::PixelModel,
    refractory: Option<readout::Refractory>,
    arbiter: Option<readout::Arbiter>,
    limiter: Option<readout::RateLimiter>,
    info: StreamInfo,
    n_pulses: u64,
    pulses_per_block: u64,
    n_blocks: u64,
    block: u64,
    /// Particle time (s).
    t_particles: f64,
    /// Requests at or after the current block's end.
    carry: Vec<pixel::Arrival>,
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
            sc: sc.clone(),
            seed,
            flow,
            particles,
            pixel,
            info,
            n_pulses,
            pulses_per_block,
            n_blocks,
            block: 0,
            t_particles: 0.0,
            carry: Vec::new(),
            truth: Vec::new(),
            pulse_starts_us: Vec::new(),
            stats,
        })
    }

    pub fn scenario(&self) -> &Scenario {
        &self.sc
    }

    pub fn flow(&self) -> &Flow {
        &self.flow
    }

    /// Truth of the pulses simulated so far (and not taken before).
    pub fn take_truth(&mut self) -> Vec<TruthSample> {
        std::mem::take(&mut self.truth)
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
            (self.block * self.pulses_per_block).min(self.n_pulses),
            self.n_pulses,
        )
    }

    /// Hot pixels (x, y, rate) of this run.
    pub fn hot_pixels(&self) -> &[(u16, u16, f64)] {
        self.pixel.hot_pixels()
    }

    /// Camera-time start of pulse `k` (µs; `clock_drift` included).
    fn pulse_start_us(&self, k: u64) -> f64 {
        self.sc.pulse_start_us(k)
    }

    /// Simulate the next block into `chunk` (cleared first).
    fn run_block(&mut self, chunk: &mut Chunk) {
        use rayon::prelude::*;
        chunk.clear();
        let b = self.block;
        let duration_us = self.sc.duration_s * 1e6;
        let k0 = b * self.pulses_per_block;
        let k1 = ((b + 1) * self.pulses_per_block).min(self.n_pulses);
        let last = b + 1 == self.n_blocks;
        let t_begin = if b == 0 { 0.0 } else { self.pulse_start_us(k0) };
        let t_end = if last {
            duration_us
        } else {
            self.pulse_start_us(k1)
        };
        let starts: Vec<f64> = (k0..k1).map(|k| self.pulse_start_us(k)).collect();
        let times_s: Vec<f64> = starts.iter().map(|t| t * 1e-6).collect();
        let snaps = self
            .particles
            .advance_and_snapshot(&self.flow, self.t_particles, &times_s);
        if let Some(&t) = times_s.last() {
            self.t_particles = t;
        }
        // Truth: lit particles whose image centre is in the ROI.
        let roi = self.sc.roi();
        let (rx0, ry0) = (roi.x as f64 - 0.5, roi.y as f64 - 0.5);
        let (rx1, ry1) = (rx0 + roi.width as f64, ry0 + roi.height as f64);
        for (i, s) in snaps.iter().enumerate() {
            for p in s {
                if p.x >= rx0 && p.x < rx1 && p.y >= ry0 && p.y < ry1 {
                    self.truth.push(TruthSample {
                        pulse: (k0 + i as u64) as i64,
                        t_us: starts[i],
                        particle_id: p.id,
                        x: p.x,
                        y: p.y,
                        u: p.u,
                        v: p.v,
                    });
                    self.stats.truth_samples += 1;
                }
            }
        }
        // Pixel responses, parallel over pulses.
        let pixel = &self.pixel;
        let seed = self.seed;
        let per_pulse: Vec<Vec<pixel::Arrival>> = snaps
            .par_iter()
            .enumerate()
            .map(|(i, s)| {
                let mut out = Vec::new();
                pixel.render_pulse(s, starts[i], stream_seed(seed, 6, k0 + i as u64), &mut out);
                out
            })
            .collect();
        let mut reqs = std::mem::take(&mut self.carry);
        for v in per_pulse {
            reqs.extend(v);
        }
        self.pixel
            .noise(t_begin, t_end, stream_seed(seed, 7, b), &mut reqs);
        sort_requests(&mut reqs, t_begin);
        let split = reqs.partition_point(|a| a.t < t_end);
        self.carry = if last {
            Vec::new()
        } else {
            reqs.split_off(split)
        };
        reqs.truncate(split);
        if let Some(r) = &mut self.refractory {
            r.apply(&mut reqs);
        }
        match &mut self.arbiter {
            Some(a) => {
                a.run(&reqs, t_end, &mut chunk.events);
                self.stats.lost_in_readout = a.lost;
            }
            None => readout::stamp_ideal(&reqs, &mut chunk.events),
        }
        if last {
            let d = duration_us;
            chunk.events.retain(|t, _, _, _| (t as f64) < d);
        }
        if let Some(l) = &mut self.limiter {
            l.apply(&mut chunk.events);
        }
        if self.sc.triggers.enabled {
            let ch = self.sc.triggers.channel;
            for &s in &starts {
                for (t, edge) in [
                    (s, Edge::Rising),
                    (s + self.sc.light.pulse_width_us, Edge::Falling),
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
        self.pulse_starts_us.extend_from_slice(&starts);
        self.stats.pulses += starts.len() as u64;
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

impl EventSource for Simulator {
    fn info(&self) -> &StreamInfo {
        &self.info
    }

    fn next_chunk(&mut self, chunk: &mut Chunk) -> Result<bool> {
        while self.block < self.n_blocks {
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
