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
    /// Signal contributions below this are dropped: 1 % of the smallest
    /// signal that can cross any pixel's threshold.
    negligible: f64,
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
            negligible: {
                let c_min = sc.pixel.contrast_threshold
                    * 0.05f64.max(1.0 - 6.0 * sc.pixel.threshold_mismatch.map_or(0.0, |m| m.sigma));
                let c_min = sc
                    .pixel
                    .off_events
                    .map_or(c_min, |o| c_min.min(o.threshold));
                0.01 * c_min.exp_m1()
            },
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
        // Pixel-integrated Gaussian: differences of erf at the pixel edges,
        // each edge evaluated once.
        let nx = ((i1 - i0 + 1) as usize).min(31);
        let mut ex = [0.0f64; 32];
        for (a, e) in ex.iter_mut().enumerate().take(nx + 1) {
            *e = erf((i0 as f64 + a as f64 - 0.5 - x) * k);
        }
        let mut ey_lo = erf((j0 as f64 - 0.5 - y) * k);
        for j in j0..=j1 {
            let ey_hi = erf((j as f64 + 0.5 - y) * k);
            let fy = 0.5 * (ey_hi - ey_lo);
            ey_lo = ey_hi;
            if fy < 1e-6 {
                continue;
            }
            for a in 0..nx {
                let w = 0.5 * (ex[a + 1] - ex[a]) * fy;
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

    /// Signal contributions of a pulse's particle images, particles taken
    /// by image row then input order: `f(roi_pixel_index, signal)`.
    fn contributions(&self, snaps: &[Snapshot], mut f: impl FnMut(u32, f64)) {
        let w = self.roi.width;
        let mut pos = Vec::with_capacity(32);
        // Visit particles row by row: consecutive images then touch the same
        // few sensor rows, which keeps the accumulation buffer in cache.
        let mut order: Vec<u64> = snaps
            .iter()
            .enumerate()
            .map(|(i, s)| ((s.y.clamp(-1e6, 1e6) + 1e6) as u64) << 32 | i as u64)
            .collect();
        order.sort_unstable();
        for &o in &order {
            let s = &snaps[(o & 0xFFFF_FFFF) as usize];
            self.positions(s, &mut pos);
            let amp = self.gain * s.brightness;
            for &(px, py, pw) in &pos {
                let a = amp * pw;
                self.footprint(px, py, |ix, iy, frac| {
                    let sig = a * frac;
                    if sig >= self.negligible {
                        f((iy - self.roi.y) * w + (ix - self.roi.x), sig);
                    }
                });
            }
        }
    }

    /// Events of every lit pixel for one pulse starting at `t_pulse_us`.
    ///
    /// Overlapping images add up in a dense per-thread ROI buffer; pixels
    /// are visited in order of first touch (row-sorted particles), so no sort is
    /// needed and the result is deterministic.
    pub fn render_pulse(
        &self,
        snaps: &[Snapshot],
        t_pulse_us: f64,
        pulse_seed: u64,
        out: &mut Vec<Arrival>,
    ) {
        thread_local! {
            static DENSE: std::cell::RefCell<(Vec<f32>, Vec<u32>)> = const { std::cell::RefCell::new((Vec::new(), Vec::new())) };
        }
        DENSE.with(|cell| {
            let mut guard = cell.borrow_mut();
            let (dense, touched) = &mut *guard;
            let n = self.roi.width as usize * self.roi.height as usize;
            if dense.len() < n {
                dense.resize(n, 0.0);
            }
            touched.clear();
            self.contributions(snaps, |idx, sig| {
                let d = &mut dense[idx as usize];
                if *d == 0.0 {
                    touched.push(idx);
                }
                *d += sig as f32;
            });
            let mut rng = Pcg64::seed_from_u64(pulse_seed);
            for &idx in touched.iter() {
                let sig = std::mem::replace(&mut dense[idx as usize], 0.0) as f64;
                self.pixel_response(idx, sig, t_pulse_us, &mut rng, out);
            }
        });
    }

    /// Plain reference for [`render_pulse`]: collect, stable-sort by pixel,
    /// sum, respond (pixels in index order).
    pub fn render_pulse_reference(
        &self,
        snaps: &[Snapshot],
        t_pulse_us: f64,
        pulse_seed: u64,
        out: &mut Vec<Arrival>,
    ) {
        let mut list: Vec<(u32, f64)> = Vec::new();
        self.contributions(snaps, |idx, sig| list.push((idx, sig)));
        list.sort_by_key(|a| a.0);
        let mut rng = Pcg64::seed_from_u64(pulse_seed);
        let mut i = 0;
        while i < list.len() {
            let idx = list[i].0;
            // Summed in f32 in input order, as the fast path does.
            let mut sig = 0.0f32;
            while i < list.len() && list[i].0 == idx {
                sig += list[i].1 as f32;
                i += 1;
            }
            self.pixel_response(idx, sig as f64, t_pulse_us, &mut rng, out);
        }
    }

    #[inline]
    fn pixel_response(&self, idx: u32, sig: f64, t0: f64, rng: &mut Pcg64, out: &mut Vec<Arrival>) {
        let c = match &self.mismatch {
            Some(m) => self.threshold * m[idx as usize] as f64,
            None => self.threshold,
        };
        let dl = sig.ln_1p();
        let x = (self.roi.x + idx % self.roi.width) as u16;
        let y = (self.roi.y + idx / self.roi.width) as u16;
        let n_on = ((dl / c).floor() as u32).min(self.max_events);
        if n_on == 0 && self.off.is_none() {
            return;
        }
        let tau = match self.intensity_latency {
            Some((e, r)) if e == 0.5 => self.tau_us * (r / sig).sqrt().min(100.0),
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sim::scenario::*;

    #[test]
    fn dense_render_matches_sorted_reference() {
        let mut sc = Scenario::default();
        sc.sensor = Sensor {
            width: 64,
            height: 48,
            roi: Some(Roi {
                x: 3,
                y: 5,
                width: 50,
                height: 40,
            }),
        };
        sc.pixel.threshold_mismatch = Some(ThresholdMismatch { sigma: 0.15 });
        sc.pixel.intensity_latency = Some(IntensityLatency {
            exponent: 0.7,
            reference: 2.0,
        });
        sc.pixel.off_events = Some(OffEvents {
            threshold: 0.3,
            tau_us: 15.0,
        });
        sc.light.pulse_streaks = Some(PulseStreaks { scale: 1.0 });
        let model = PixelModel::new(&sc, 4);
        let mut rng = Pcg64::seed_from_u64(1);
        // Dense, overlapping particles, some straddling the ROI edge.
        let snaps: Vec<Snapshot> = (0..400)
            .map(|i| Snapshot {
                x: rng.gen_range(0.0..56.0),
                y: rng.gen_range(2.0..48.0),
                u: rng.gen_range(-30_000.0..30_000.0),
                v: rng.gen_range(-30_000.0..30_000.0),
                brightness: rng.gen_range(0.2..3.0),
                id: i,
            })
            .collect();
        let key = |a: &Arrival| (a.t.to_bits(), a.x, a.y, a.p);
        let mut fast = Vec::new();
        let mut slow = Vec::new();
        model.render_pulse(&snaps, 100.0, 9, &mut fast);
        model.render_pulse_reference(&snaps, 100.0, 9, &mut slow);
        assert!(fast.len() > 300);
        fast.sort_by_key(key);
        slow.sort_by_key(key);
        assert_eq!(fast, slow);
        // Every event lies in the ROI.
        assert!(fast
            .iter()
            .all(|a| (3..53).contains(&a.x) && (5..45).contains(&a.y)));
    }

    #[test]
    fn events_per_pixel_follow_the_log_contrast() {
        // One bright particle centred on a pixel, no effects: the centre
        // pixel fires floor(ln(1 + s)/C) events, capped.
        let mut sc = Scenario::default();
        sc.sensor = Sensor {
            width: 16,
            height: 16,
            roi: None,
        };
        sc.pixel.max_events_per_pulse = 64;
        sc.light.rise_us = 0.0;
        sc.light.fall_us = 0.0;
        let model = PixelModel::new(&sc, 0);
        let snap = Snapshot {
            x: 8.0,
            y: 8.0,
            u: 0.0,
            v: 0.0,
            brightness: 4.0,
            id: 0,
        };
        let mut out = Vec::new();
        model.render_pulse(&[snap], 0.0, 0, &mut out);
        let centre = out.iter().filter(|a| a.x == 8 && a.y == 8).count();
        let k = std::f64::consts::FRAC_1_SQRT_2 / (sc.optics.particle_diameter_px / 4.0);
        let frac = erf(0.5 * k).powi(2);
        let s = sc.light.energy * 4.0 * frac;
        assert_eq!(
            centre,
            (s.ln_1p() / sc.pixel.contrast_threshold).floor() as usize
        );
        // Crossing times increase and start after the fixed latency.
        let mut t: Vec<f64> = out
            .iter()
            .filter(|a| a.x == 8 && a.y == 8)
            .map(|a| a.t)
            .collect();
        t.sort_by(f64::total_cmp);
        assert!(t[0] >= sc.pixel.latency_us);
        assert!(t.windows(2).all(|w| w[0] < w[1]));
    }
}
