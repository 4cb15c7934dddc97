//! The event pixel, event-driven: only pixels under particle images (and
//! noise pixels) are ever touched.
//!
//! Model (in the spirit of v2e / IEBCS, reduced to what a µs-short pulse on a
//! slow photoreceptor needs). A pulse adds a signal `s` (relative to the
//! pixel's background) to each pixel under a particle image: `s = energy ·
//! mean pulse level · brightness · (pixel-integrated Gaussian image)`,
//! summed over overlapping particles. The log-intensity step is
//! `ΔL = ln(1 + s)`. The photoreceptor follows it as a first-order low-pass
//! with time constant τ, so the k-th ON threshold crossing (`k·C ≤ ΔL`)
//! happens `τ·(−ln(1 − 0.95·k·C/ΔL))` after the pulse (0.95: the
//! step is approached, never reached), and the event leaves the pixel after
//! a fixed `latency_us` more. Switchable parts:
//! - `threshold_mismatch`: C varies per pixel (fixed pattern, log-normal-free
//!   Gaussian, relative σ);
//! - `intensity_latency`: τ = tau_us·(reference/s)^exponent (bright pixels
//!   are faster, as in real photoreceptors whose bandwidth grows with
//!   photocurrent); off: τ = tau_us;
//! - `latency_jitter`: Gaussian spread added to each event time;
//! - `off_events`: when the pulse ends the signal decays with `tau_us` of
//!   the effect and crosses the OFF threshold floor(ΔL/C_off) times.
//! Refractory period, noise and readout live in `readout`.

use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Poisson, StandardNormal};
use rand_pcg::Pcg64;

use super::flow::erf;
use super::light::{envelope, PulseShape};
use super::scenario::{Light, Roi, Scenario};
use super::seeding::Snapshot;
use super::stream_seed;
use crate::events::{OFF, ON};

/// An event as it leaves the pixel (before the readout timestamps it).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Arrival {
    /// Time the pixel requests readout (µs, fractional).
    pub t: f64,
    pub x: u16,
    pub y: u16,
    pub p: u8,
}

pub struct PixelModel {
    roi: Roi,
    light: Light,
    shape: PulseShape,
    sigma_img: f64,
    /// energy · mean pulse level: the signal of a unit-brightness particle
    /// fully on one pixel.
    gain: f64,
    threshold: f64,
    latency_us: f64,
    tau_us: f64,
    max_events: u32,
    /// Per-ROI-pixel threshold factor (threshold_mismatch), row-major.
    mismatch: Option<Vec<f32>>,
    intensity_latency: Option<(f64, f64)>,
    jitter_us: Option<f64>,
    off: Option<(f64, f64)>,
    streak_scale: Option<f64>,
    background_rate: Option<f64>,
    hot: Vec<(u16, u16, f64)>,
}

impl PixelModel {
    pub fn new(sc: &Scenario, seed: u64) -> PixelModel {
        let roi = sc.roi();
        let n = roi.width as usize * roi.height as usize;
        let mismatch = sc.pixel.threshold_mismatch.map(|m| {
            let mut rng = Pcg64::seed_from_u64(stream_seed(seed, 2, 0));
            (0..n)
                .map(|_| {
                    let g: f64 = StandardNormal.sample(&mut rng);
                    (1.0 + m.sigma * g).max(0.05) as f32
                })
                .collect()
        });
        let hot = match sc.noise.hot_pixels {
            Some(h) if h.count > 0 => {
                let mut rng = Pcg64::seed_from_u64(stream_seed(seed, 3, 0));
                let idx = rand::seq::index::sample(&mut rng, n, h.count as usize);
                let mut v: Vec<(u16, u16, f64)> = idx
                    .iter()
                    .map(|i| {
                        (
                            (roi.x as usize + i % roi.width as usize) as u16,
                            (roi.y as usize + i / roi.width as usize) as u16,
                            h.rate_hz,
                        )
                    })
                    .collect();
                v.sort_by_key(|h| (h.1, h.0));
                v
            }
            _ => Vec::new(),
        };
        let shape = PulseShape::new(&sc.light);
        PixelModel {
            roi,
            light: sc.light,
            sigma_img: sc.optics.particle_diameter_px / 4.0,
            gain: sc.light.energy * shape.mean_level,
            shape,
            threshold: sc.pixel.contrast_threshold,
            latency_us: sc.pixel.latency_us,
            tau_us: sc.pixel.tau_us,
            max_events: sc.pixel.max_events_per_pulse,
            mismatch,
            intensity_latency: sc
                .pixel
                .intensity_latency
                .map(|i| (i.exponent, i.reference)),
            jitter_us: sc.pixel.latency_jitter.map(|j| j.spread_us),
            off: sc.pixel.off_events.map(|o| (o.threshold, o.tau_us)),
            streak_scale: sc.light.pulse_streaks.map(|p| p.scale),
            background_rate: sc.noise.background_noise.map(|b| b.rate_hz),
            hot,
        }
    }

    /// Hot pixels (x, y, rate Hz), for tests and diagnostics.
    pub fn hot_pixels(&self) -> &[(u16, u16, f64)] {
        &self.hot
    }

    /// Pixel-integrated Gaussian image of a particle at (x, y): calls
    /// `f(ix, iy, fraction)` for each ROI pixel it covers.
    #[inline]
    fn footprint(&self, x: f64, y: f64, mut f: impl FnMut(u32, u32, f64)) {
        let s = self.sigma_img;
        let reach = 3.0 * s;
        let k = std::f64::consts::FRAC_1_SQRT_2 / s;
        let (rx0, ry0) = (self.roi.x as i64, self.roi.y as i64);
        let (rx1, ry1) = (
            rx0 + self.roi.width as i64 - 1,
            ry0 + self.roi.height as i64 - 1,
        );
        let i0 = ((x - reach).round() as i64).max(rx0);
        let i1 = ((x + reach).round() as i64).min(rx1);
        let j0 = ((y - reach).round() as i64).max(ry0);
        let j1 = ((y + reach).round() as i64).min(ry1);
        if i0 > i1 || j0 > j1 {
            return;
        }
        let mut fx = [0.0f64; 32];
        let nx = ((i1 - i0 + 1) as usize).min(32);
        for (a, fxa) in fx.iter_mut().enumerate().take(nx) {
            let i = (i0 + a as i64) as f64;
            *fxa = 0.5 * (erf((i + 0.5 - x) * k) - erf((i - 0.5 - x) * k));
        }
        for j in j0..=j1 {
            let jf = j as f64;
            let fy = 0.5 * (erf((jf + 0.5 - y) * k) - erf((jf - 0.5 - y) * k));
            if fy < 1e-6 {
                continue;
            }
            for (a, fxa) in fx.iter().enumerate().take(nx) {
                let w = fxa * fy;
                if w > 1e-6 {
                    f((i0 + a as i64) as u32, j as u32, w);
                }
            }
        }
    }

    /// Image positions of a particle during the pulse and their weights.
    fn positions(&self, s: &Snapshot, out: &mut Vec<(f64, f64, f64)>) {
        out.clear();
        match self.streak_scale {
            None => out.push((s.x, s.y, 1.0)),
            Some(scale) => {
                let len = (s.u.hypot(s.v)) * self.shape.end_us * 1e-6 * scale;
                let m = ((len / 0.2).ceil() as usize).clamp(1, 32);
                let mut total = 0.0;
                for j in 0..m {
                    let t = (j as f64 + 0.5) / m as f64 * self.shape.end_us;
                    let w = envelope(&self.light, t);
                    let dt = t * 1e-6 * scale;
                    out.push((s.x + s.u * dt, s.y + s.v * dt, w));
                    total += w;
                }
                for p in out.iter_mut() {
                    p.2 /= total;
                }
            }
        }
    }

    /// Events of every lit pixel for one pulse starting at `t_pulse_us`.
    /// `scratch` is reused between calls.
    pub fn render_pulse(
        &self,
        snaps: &[Snapshot],
        t_pulse_us: f64,
        pulse_seed: u64,
        scratch: &mut Vec<(u32, f32)>,
        out: &mut Vec<Arrival>,
    ) {
        scratch.clear();
        let w = self.roi.width;
        let mut pos = Vec::with_capacity(32);
        for s in snaps {
            self.positions(s, &mut pos);
            let amp = self.gain * s.brightness;
            for &(px, py, pw) in &pos {
                self.footprint(px, py, |ix, iy, frac| {
                    let idx = (iy - self.roi.y) * w + (ix - self.roi.x);
                    scratch.push((idx, (amp * pw * frac) as f32));
                });
            }
        }
        scratch.sort_unstable_by_key(|a| a.0);
        let mut rng = Pcg64::seed_from_u64(pulse_seed);
        let mut i = 0;
        while i < scratch.len() {
            let idx = scratch[i].0;
            let mut sig = 0.0f64;
            while i < scratch.len() && scratch[i].0 == idx {
                sig += scratch[i].1 as f64;
                i += 1;
            }
            self.pixel_response(idx, sig, t_pulse_us, &mut rng, out);
        }
    }

    #[inline]
    fn pixel_response(&self, idx: u32, sig: f64, t0: f64, rng: &mut Pcg64, out: &mut Vec<Arrival>) {
        let dl = sig.ln_1p();
        let c = match &self.mismatch {
            Some(m) => self.threshold * m[idx as usize] as f64,
            None => self.threshold,
        };
        let x = (self.roi.x + idx % self.roi.width) as u16;
        let y = (self.roi.y + idx / self.roi.width) as u16;
        let n_on = ((dl / c).floor() as u32).min(self.max_events);
        let tau = match self.intensity_latency {
            Some((e, r)) => self.tau_us * (r / sig).powf(e).min(100.0),
            None => self.tau_us,
        };
        for k in 1..=n_on {
            let frac = 0.95 * (k as f64 * c / dl).min(1.0);
            let mut t = t0 + self.latency_us + tau * -(1.0 - frac).ln();
            if let Some(j) = self.jitter_us {
                let g: f64 = StandardNormal.sample(rng);
                t = (t + j * g).max(t0);
            }
            out.push(Arrival { t, x, y, p: ON });
        }
        if let Some((c_off, tau_off)) = self.off {
            let n_off = ((dl / c_off).floor() as u32).min(self.max_events);
            for k in 1..=n_off {
                let frac = 0.95 * (k as f64 * c_off / dl).min(1.0);
                let mut t = t0 + self.shape.end_us + self.latency_us + tau_off * -(1.0 - frac).ln();
                if let Some(j) = self.jitter_us {
                    let g: f64 = StandardNormal.sample(rng);
                    t = (t + j * g).max(t0);
                }
                out.push(Arrival { t, x, y, p: OFF });
            }
        }
    }

    /// Background activity and hot-pixel events in [t0, t1) µs.
    pub fn noise(&self, t0: f64, t1: f64, block_seed: u64, out: &mut Vec<Arrival>) {
        let dt = t1 - t0;
        if dt <= 0.0 {
            return;
        }
        if let Some(rate) = self.background_rate {
            let mut rng = Pcg64::seed_from_u64(stream_seed(block_seed, 4, 0));
            let npix = self.roi.width as f64 * self.roi.height as f64;
            let mean = rate * npix * dt * 1e-6;
            let n = poisson(&mut rng, mean);
            for _ in 0..n {
                let t = rng.gen_range(t0..t1);
                let x = (self.roi.x + rng.gen_range(0..self.roi.width)) as u16;
                let y = (self.roi.y + rng.gen_range(0..self.roi.height)) as u16;
                let p = if rng.gen_bool(0.5) { ON } else { OFF };
                out.push(Arrival { t, x, y, p });
            }
        }
        if !self.hot.is_empty() {
            let mut rng = Pcg64::seed_from_u64(stream_seed(block_seed, 5, 0));
            for &(x, y, rate) in &self.hot {
                let n = poisson(&mut rng, rate * dt * 1e-6);
                for _ in 0..n {
                    out.push(Arrival {
                        t: rng.gen_range(t0..t1),
                        x,
                        y,
                        p: ON,
                    });
                }
            }
        }
    }
}

fn poisson(rng: &mut Pcg64, mean: f64) -> u64 {
    if mean <= 0.0 {
        return 0;
    }
    Poisson::new(mean)
        .map(|d| d.sample(rng) as u64)
        .unwrap_or(0)
}
