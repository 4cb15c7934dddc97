//! A second event generator, written apart from `ebptv::sim` and different
//! from it on purpose, so that the model check is tested on recordings its
//! own simulator did not make:
//!
//! - flow: a shear layer u(y) = U₀ + ΔU·tanh((y − H/2)/δ) (px/pulse), wrapping
//!   around in x;
//! - particle image: a Gaussian spot (σ = 0.55 px) of log-normal brightness;
//!   a pixel fires ⌊2.2·I + ξ⌋ events (ξ uniform), at most three — no
//!   photoreceptor, no contrast threshold;
//! - latency: 45 µs + a gamma-distributed delay (shape 3, scale 8 µs), each
//!   further event of a pixel 3–9 µs after the previous one (not the
//!   simulator's fixed part + exponential response);
//! - background activity: uniform in time and space, either polarity, 0.3 %
//!   of the events;
//! - triggers on channel 0 (rising at the pulse, falling 2 µs later).
//!
//! Departures (one at a time): `latency_jitter` adds a Laplace-distributed
//! delay (scale `strength` µs, kept ≥ 0 overall), `off_events` makes a lit
//! pixel fire an OFF event with probability `strength` some 150 µs later,
//! `refractory` drops every event of a pixel that comes less than
//! `period_us` after the pixel's last event that was kept (a dead time).

#![allow(dead_code)]

use std::path::Path;

use ebptv::events::{Chunk, Edge, EventChunk, Geometry, Trigger};
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Gamma, LogNormal};
use rand_pcg::Pcg64;

#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Departure {
    None,
    LatencyJitter { scale_us: f64 },
    OffEvents { probability: f64 },
    Refractory { period_us: f64 },
}

pub struct Recording {
    pub width: u16,
    pub height: u16,
    pub pulses: usize,
    pub period_us: f64,
    pub ppp: f64,
    pub departure: Departure,
    pub seed: u64,
    /// Write the trigger channel (a recording without one needs the pulse
    /// frequency to be checked).
    pub triggers: bool,
}

impl Recording {
    pub fn new(departure: Departure, seed: u64) -> Self {
        Recording {
            width: 320,
            height: 180,
            pulses: 200,
            period_us: 200.0,
            ppp: 0.01,
            departure,
            seed,
            triggers: true,
        }
    }

    /// Write the recording as EVT 3.0 with triggers on channel 0 (unless
    /// `triggers` is off).
    pub fn write(&self, path: &Path) {
        let mut rng = Pcg64::seed_from_u64(self.seed);
        let (w, h) = (self.width as f64, self.height as f64);
        let n = (self.ppp * w * h).round() as usize;
        let bright = LogNormal::new(0.0, 0.5).unwrap();
        let delay = Gamma::new(3.0, 8.0).unwrap();
        let mut parts: Vec<(f64, f64, f64)> = (0..n)
            .map(|_| {
                (
                    rng.gen::<f64>() * w,
                    rng.gen::<f64>() * h,
                    bright.sample(&mut rng),
                )
            })
            .collect();
        let u = |y: f64| 2.0 + 1.5 * ((y - h / 2.0) / 25.0).tanh();
        let t0 = 37.0;
        let mut ev: Vec<(i64, u16, u16, u8)> = Vec::new();
        let mut trig = Vec::new();
        let sigma = 0.55f64;
        for k in 0..self.pulses {
            let tp = t0 + k as f64 * self.period_us;
            trig.push(Trigger {
                t: tp.round() as i64,
                channel: 0,
                edge: Edge::Rising,
            });
            trig.push(Trigger {
                t: tp.round() as i64 + 2,
                channel: 0,
                edge: Edge::Falling,
            });
            for p in parts.iter_mut() {
                let (x0, y0, b) = *p;
                let (xi, yi) = (x0.round() as i64, y0.round() as i64);
                for yy in yi - 2..=yi + 2 {
                    for xx in xi - 2..=xi + 2 {
                        if xx < 0 || yy < 0 || xx >= w as i64 || yy >= h as i64 {
                            continue;
                        }
                        let r2 = (xx as f64 - x0).powi(2) + (yy as f64 - y0).powi(2);
                        let i = b * (-r2 / (2.0 * sigma * sigma)).exp();
                        let m = ((2.2 * i + rng.gen::<f64>()).floor() as usize).min(3);
                        let mut lat = 45.0 + delay.sample(&mut rng);
                        if let Departure::LatencyJitter { scale_us } = self.departure {
                            let e: f64 = rng.gen::<f64>() - 0.5;
                            lat =
                                (lat - scale_us * e.signum() * (1.0 - 2.0 * e.abs()).ln()).max(1.0);
                        }
                        for j in 0..m {
                            if j > 0 {
                                lat += 3.0 + 6.0 * rng.gen::<f64>();
                            }
                            ev.push(((tp + lat).round() as i64, xx as u16, yy as u16, 1));
                        }
                        if let Departure::OffEvents { probability } = self.departure {
                            if m > 0 && rng.gen::<f64>() < probability {
                                let t = tp + 150.0 + 40.0 * rng.gen::<f64>();
                                ev.push((t.round() as i64, xx as u16, yy as u16, 0));
                            }
                        }
                    }
                }
                // Advect; wrap around in x, and re-seed 5 % per pulse
                // (out-of-sheet motion).
                p.0 = (x0 + u(y0)).rem_euclid(w);
                if rng.gen::<f64>() < 0.05 {
                    *p = (
                        rng.gen::<f64>() * w,
                        rng.gen::<f64>() * h,
                        bright.sample(&mut rng),
                    );
                }
            }
        }
        if let Departure::Refractory { period_us } = self.departure {
            ev.sort_by_key(|e| e.0);
            let mut last = vec![i64::MIN / 2; self.width as usize * self.height as usize];
            ev.retain(|&(t, x, y, _)| {
                let l = &mut last[y as usize * self.width as usize + x as usize];
                let keep = (t - *l) as f64 >= period_us;
                if keep {
                    *l = t;
                }
                keep
            });
        }
        let signal = ev.len();
        let noise = (signal as f64 * 0.003).round() as usize;
        let span = self.pulses as f64 * self.period_us;
        for _ in 0..noise {
            ev.push((
                (t0 + rng.gen::<f64>() * span).round() as i64,
                rng.gen_range(0..self.width),
                rng.gen_range(0..self.height),
                rng.gen_range(0..2u8),
            ));
        }
        ev.sort_by_key(|e| e.0);
        let mut events = EventChunk::default();
        for (t, x, y, p) in ev {
            events.push(t, x, y, p);
        }
        let mut w =
            ebptv::io::create(path, None, Geometry::new(self.width, self.height)).expect("writer");
        if !self.triggers {
            trig.clear();
        }
        w.write_chunk(&Chunk {
            events,
            triggers: trig,
        })
        .expect("write");
        w.finish().expect("finish");
    }
}
