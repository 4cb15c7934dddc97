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
//! - `threshold_mismatch`: C varies per pixel (fixed pattern: a Gaussian
//!   factor 1 + σ·g, factor ≥ 0.05), g drawn from a hash of (seed, pixel)
//!   when the pixel is used rather than from a stored table: a ROI-sized
//!   table missed the cache on nearly every lookup;
//! - `intensity_latency`: τ = tau_us·(reference/s)^exponent (bright pixels
//!   are faster, as in real photoreceptors whose bandwidth grows with
//!   photocurrent); off: τ = tau_us;
//! - `latency_jitter`: Gaussian spread added to each event time;
//! - `off_events`: when the pulse ends the signal decays with `tau_us` of
//!   the effect and crosses the OFF threshold floor(ΔL/C_off) times.
//! Refractory period, noise and readout live in `readout`.

use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Poisson};
use rand_pcg::Pcg64;

use super::light::{envelope, PulseShape};
use super::scenario::{Light, Roi, Scenario};
use super::seeding::Snapshot;
use super::{stream_key, stream_seed};

/// Threshold-mismatch deviates are clamped to ±this many σ …
const MISMATCH_CLAMP: f64 = 6.0;
/// … and the factor to at least this.
const MIN_MISMATCH_FACTOR: f64 = 0.05;
use ebptv_io::events::{OFF, ON};

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
    /// threshold_mismatch: (σ, hash key of the fixed pattern).
    mismatch: Option<(f64, u64)>,
    /// The smallest threshold any pixel can have (ON or OFF): signals
    /// below it cannot fire.
    c_floor: f64,
    /// [`f32_at_least`]`(c_floor)`: the same test on the f32 sums
    /// without converting each touched pixel's sum to f64.
    c_floor_f32: f32,
    intensity_latency: Option<(f64, f64)>,
    jitter_us: Option<f64>,
    off: Option<(f64, f64)>,
    streak_scale: Option<f64>,
    /// Streak positions per px/s of speed before rounding up:
    /// `end_us · 1e-6 · scale / 0.2` (0 without `pulse_streaks`).
    streak_per_speed: f64,
    /// [`Self::streak_table`] (empty without `pulse_streaks`).
    streak_nodes: Vec<Vec<(f64, f64)>>,
    background_rate: Option<f64>,
    hot: Vec<(u16, u16, f64)>,
    /// The fast path's tabulated pixel fractions (see [`FractionTable`]).
    table: FractionTable,
    /// Four-pixel windows of `table` for small images (σ < ½), see
    /// [`QuadTable`]; None for larger images.
    quad: Option<QuadTable>,
    /// The fast path's logarithm.
    ln: &'static LnTable,
    /// [`normal_quantiles`].
    quantiles: &'static [f64; 4097],
}

impl PixelModel {
    pub fn new(sc: &Scenario, seed: u64) -> PixelModel {
        let roi = sc.roi();
        let n = roi.width as usize * roi.height as usize;
        let mismatch = sc
            .pixel
            .threshold_mismatch
            .map(|m| (m.sigma, stream_key(seed, 2)));
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
        let streak_nodes = sc.light.pulse_streaks.map_or(Vec::new(), |p| {
            Self::streak_table(&sc.light, &shape, p.scale)
        });
        // The smallest mismatch factor: g never goes below the quantile
        // table's first node (−3.67), however wide the clamp.
        let c_floor = sc.pixel.contrast_threshold
            * sc.pixel.threshold_mismatch.map_or(1.0, |m| {
                let g_min = normal_quantiles()[0].max(-MISMATCH_CLAMP);
                MIN_MISMATCH_FACTOR.max(1.0 + g_min * m.sigma)
            });
        let c_floor = sc
            .pixel
            .off_events
            .map_or(c_floor, |o| c_floor.min(o.threshold));
        let table = FractionTable::new(sc.optics.particle_diameter_px / 4.0);
        let streak_per_speed = sc
            .light
            .pulse_streaks
            .map_or(0.0, |p| shape.end_us * 1e-6 * p.scale / 0.2);
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
            streak_per_speed,
            streak_nodes,
            background_rate: sc.noise.background_noise.map(|b| b.rate_hz),
            hot,
            c_floor,
            c_floor_f32: f32_at_least(c_floor),
            quad: QuadTable::new(&table),
            table,
            ln: ln_table(),
            quantiles: normal_quantiles(),
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
        let erf = erf_table();
        let s = self.sigma_img;
        let reach = 3.0 * s;
        let k = std::f64::consts::FRAC_1_SQRT_2 / s;
        let (rx0, ry0) = (self.roi.x as i64, self.roi.y as i64);
        let (rx1, ry1) = (
            rx0 + self.roi.width as i64 - 1,
            ry0 + self.roi.height as i64 - 1,
        );
        let i0 = round_i64(x - reach).max(rx0);
        let i1 = round_i64(x + reach).min(rx1);
        let j0 = round_i64(y - reach).max(ry0);
        let j1 = round_i64(y + reach).min(ry1);
        if i0 > i1 || j0 > j1 {
            return;
        }
        // Pixel-integrated Gaussian: differences of erf at the pixel edges,
        // each edge evaluated once.
        let nx = ((i1 - i0 + 1) as usize).min(31);
        let mut ex = [0.0f64; 32];
        for (a, e) in ex.iter_mut().enumerate().take(nx + 1) {
            *e = erf.eval((i0 as f64 + a as f64 - 0.5 - x) * k);
        }
        let mut ey_lo = erf.eval((j0 as f64 - 0.5 - y) * k);
        for j in j0..=j1 {
            let ey_hi = erf.eval((j as f64 + 0.5 - y) * k);
            let fy = 0.5 * (ey_hi - ey_lo);
            ey_lo = ey_hi;
            for a in 0..nx {
                f(
                    (i0 + a as i64) as u32,
                    j as u32,
                    0.5 * (ex[a + 1] - ex[a]) * fy,
                );
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

    /// The order particles are rendered in, with the row bounds of their
    /// images: `(key, row_lo, row_hi)` sorted by key, where `key` packs
    /// `row_lo` (the lowest sensor row any of the particle's streak
    /// positions can touch, a lower bound) above the snapshot index, and
    /// `row_hi` is the matching upper bound.
    ///
    /// Rendering by `row_lo` is what lets [`render_pulse`] finish (drain)
    /// every row below the current particle's `row_lo`: no later particle
    /// can reach it. `sorted_by_reference`: a comparison sort (the
    /// reference path) instead of the radix sort.
    fn render_order(&self, snaps: &[Snapshot], sorted_by_reference: bool) -> Vec<(u64, i64, i64)> {
        let reach = 3.0 * self.sigma_img;
        let streak_s = self
            .streak_scale
            .map_or(0.0, |scale| self.shape.end_us * 1e-6 * scale);
        let mut order: Vec<(u64, i64, i64)> = snaps
            .iter()
            .enumerate()
            .map(|(i, s)| {
                // Streak positions lie between y and y + v·t_end·scale.
                let dy = s.v * streak_s;
                let y_lo = s.y.min(s.y + dy).clamp(-1e6, 1e6);
                let y_hi = s.y.max(s.y + dy).clamp(-1e6, 1e6);
                // (1e-6 px of slack for rounding in the streak positions.)
                let lo = round_i64(y_lo - reach - 1e-6);
                let hi = round_i64(y_hi + reach + 1e-6);
                (((lo + (1 << 24)) as u64) << 32 | i as u64, lo, hi)
            })
            .collect();
        if sorted_by_reference {
            order.sort_unstable_by_key(|o| o.0);
            return order;
        }
        // Keys are (row_lo, index) and `order` is in index order: a stable
        // counting sort by row_lo gives the comparison sort's order.
        let lo_min = order.iter().map(|o| o.1).min().unwrap_or(0);
        let lo_max = order.iter().map(|o| o.1).max().unwrap_or(0);
        let range = (lo_max - lo_min) as usize + 1;
        if range > 4 * order.len() + 4096 {
            // Sparse rows (far-out streaks): the radix sort of the keys.
            let mut keys: Vec<u64> = order.iter().map(|o| o.0).collect();
            super::radix_sort(&mut keys, &mut Vec::new());
            return keys
                .iter()
                .map(|&k| order[(k & 0xFFFF_FFFF) as usize])
                .collect();
        }
        let mut start = vec![0u32; range + 1];
        for o in &order {
            start[(o.1 - lo_min) as usize + 1] += 1;
        }
        for r in 1..=range {
            start[r] += start[r - 1];
        }
        let mut sorted = vec![(0u64, 0i64, 0i64); order.len()];
        for o in &order {
            let slot = &mut start[(o.1 - lo_min) as usize];
            sorted[*slot as usize] = *o;
            *slot += 1;
        }
        sorted
    }

    /// Signal contributions of one particle's image: `f(ix, iy, signal)`
    /// (sensor pixel coordinates inside the ROI).
    #[inline]
    fn particle_contributions(
        &self,
        s: &Snapshot,
        pos: &mut Vec<(f64, f64, f64)>,
        mut f: impl FnMut(u32, u32, f64),
    ) {
        self.positions(s, pos);
        let amp = self.gain * s.brightness;
        for &(px, py, pw) in pos.iter() {
            let a = amp * pw;
            self.footprint(px, py, |ix, iy, frac| f(ix, iy, a * frac));
        }
    }

    /// Image positions of a particle during the pulse as offsets along its
    /// velocity: `(dt, weight)` per position for a streak of `m`
    /// positions (index m − 1), the same numbers [`positions`] computes
    /// per particle (weights depend on m only).
    fn streak_table(light: &Light, shape: &PulseShape, scale: f64) -> Vec<Vec<(f64, f64)>> {
        (1..=32usize)
            .map(|m| {
                let mut v: Vec<(f64, f64)> = (0..m)
                    .map(|j| {
                        let t = (j as f64 + 0.5) / m as f64 * shape.end_us;
                        (t * 1e-6 * scale, envelope(light, t))
                    })
                    .collect();
                let mut total = 0.0;
                for p in &v {
                    total += p.1;
                }
                for p in v.iter_mut() {
                    p.1 /= total;
                }
                v
            })
            .collect()
    }

    /// The fast path's image of one particle, as per-pixel signals:
    /// `f(ix, iy, signal)` (for tests; the renderer takes them row by row
    /// through [`Self::particle_rows`]).
    #[cfg(test)]
    fn particle_contributions_fast(&self, s: &Snapshot, mut f: impl FnMut(u32, u32, f64)) {
        struct Each<F>(F, u32);
        impl<F: FnMut(u32, u32, f64)> ContributionSink for Each<F> {
            #[inline]
            fn row(&mut self, iy: u32) {
                self.1 = iy;
            }
            #[inline]
            fn add_run(&mut self, ix0: u32, fractions: &[f32], scale: f32) {
                for (a, &fx) in fractions.iter().enumerate() {
                    (self.0)(ix0 + a as u32, self.1, (scale * fx) as f64)
                }
            }
            #[inline]
            fn add_window<const W: usize>(
                &mut self,
                wx: i64,
                window: &[f32; W],
                scale: f32,
                x0: i64,
                n: usize,
            ) {
                let a = (x0 - wx) as usize;
                self.add_run(x0 as u32, &window[a..a + n], scale);
            }
        }
        self.particle_rows(s, &mut Profiles::new(), &mut Each(&mut f, 0));
    }

    /// Streak positions of `s` as `(dt, weight)` offsets along its
    /// velocity (from [`Self::streak_table`]; one position at rest or
    /// without `pulse_streaks`).
    #[inline(always)]
    fn streak_nodes_of(&self, s: &Snapshot) -> &[(f64, f64)] {
        const SINGLE: &[(f64, f64)] = &[(0.0, 1.0)];
        match self.streak_scale {
            None => SINGLE,
            Some(scale) => {
                let count = |speed: f64| speed * self.shape.end_us * 1e-6 * scale / 0.2;
                let q = if s.v == 0.0 {
                    count(s.u.abs())
                } else if s.u == 0.0 {
                    count(s.v.abs())
                } else {
                    // libm's hypot was 2–5 % of the CPU of the unsteady
                    // presets. √(u² + v²) is within 2 ulp of it, and
                    // times the precomputed `streak_per_speed` (one
                    // multiplication for `count`'s three and a division,
                    // each step within ½ ulp) within ~1e-15 relative of
                    // `count(hypot)`: the two node counts ⌈q⌉ can differ
                    // only when q is within ~1e-15·q of an integer. There
                    // (within 1e-12·q, and for tiny, huge or non-finite
                    // q) hypot decides, so the count is hypot's exactly.
                    let q = (s.u * s.u + s.v * s.v).sqrt() * self.streak_per_speed;
                    if q > 1e-3 && q < 1e12 {
                        // SAFETY: 0 < q < 1e12: in i64's range.
                        let t = unsafe { q.to_int_unchecked::<i64>() };
                        let frac = q - t as f64;
                        if frac > 1e-12 * q && frac < 1.0 - 1e-12 * q {
                            // (q is not an integer: ⌈q⌉ = t + 1, ≥ 1.)
                            return &self.streak_nodes[(t as usize).min(31)];
                        }
                    }
                    Self::streak_count_hypot(s, count)
                };
                &self.streak_nodes[ceil_count(q, 32) - 1]
            }
        }
    }

    /// [`Self::streak_nodes_of`]'s rare exact case, out of line.
    #[cold]
    #[inline(never)]
    fn streak_count_hypot(s: &Snapshot, count: impl Fn(f64) -> f64) -> f64 {
        count(s.u.hypot(s.v))
    }

    /// The pixels [`Self::footprint`] covers along one axis for a centre
    /// at `c`, clipped to `[r0, r1]` and to at most `cap` pixels: (first
    /// pixel, count).
    #[inline]
    fn axis_range(&self, c: f64, r0: i64, r1: i64, cap: usize) -> (i64, usize) {
        let reach = 3.0 * self.sigma_img;
        let i0 = round_i64(c - reach).max(r0);
        let i1 = round_i64(c + reach).min(r1);
        if i0 > i1 {
            (i0, 0)
        } else {
            (i0, ((i1 - i0 + 1) as usize).min(cap))
        }
    }

    /// The fast path's image of one particle, row by row: `sink.row(iy)`,
    /// then `sink.add_run(ix0, fractions, scale)` adds `scale·fractions[a]`
    /// to pixel `ix0 + a` of row iy.
    ///
    /// The same model as [`Self::particle_contributions`] (tested within
    /// 1e-5 relative), computed differently: pixel fractions come from the
    /// [`FractionTable`] in f32 rather than from erf at every pixel edge,
    /// and a streak whose positions share a row coordinate (v = 0, the
    /// jet's case; or share a column, u = 0) is one separable image —
    /// the weighted sum of its positions' x profiles times the common y
    /// profile — added to the ring once instead of once per position.
    #[inline]
    fn particle_rows(&self, s: &Snapshot, prof: &mut Profiles, sink: &mut impl ContributionSink) {
        if let Some(q) = &self.quad {
            if self.particle_rows_quad(q, s, prof, sink) {
                return;
            }
        }
        let amp = self.gain * s.brightness;
        let nodes = self.streak_nodes_of(s);
        let (rx0, ry0) = (self.roi.x as i64, self.roi.y as i64);
        let (rx1, ry1) = (
            rx0 + self.roi.width as i64 - 1,
            ry0 + self.roi.height as i64 - 1,
        );
        // (The single position has dt = 0: the centre itself.)
        let at = |c: f64, dir: f64, dt: f64| c + dir * dt;
        let Profiles { fx, fy, one } = prof;
        if nodes.len() == 1 || s.v == 0.0 || s.u == 0.0 {
            // Separable: one profile along the shared axis, the other the
            // weighted sum over positions (union of their ranges).
            let shared_y = nodes.len() == 1 || s.v == 0.0;
            // (With one position the shared coordinate is that position's;
            // with several it is the same for all: v = 0 or u = 0.)
            let dt0 = nodes[0].0;
            let (c_shared, c_moving, v_moving) = if shared_y {
                (at(s.y, s.v, dt0), s.x, s.u)
            } else {
                (at(s.x, s.u, dt0), s.y, s.v)
            };
            let (s0, s1, m0, m1, s_cap, m_cap) = if shared_y {
                (ry0, ry1, rx0, rx1, AXIS_MAX, X_CAP)
            } else {
                (rx0, rx1, ry0, ry1, X_CAP, AXIS_MAX)
            };
            let (slo, sn) = self.axis_range(c_shared, s0, s1, s_cap);
            if sn == 0 {
                return;
            }
            let (mut lo, mut hi) = (i64::MAX, i64::MIN);
            for &(dt, _) in nodes {
                let (r0, rn) = self.axis_range(at(c_moving, v_moving, dt), m0, m1, m_cap);
                if rn > 0 {
                    lo = lo.min(r0);
                    hi = hi.max(r0 + rn as i64 - 1);
                }
            }
            if lo > hi {
                return;
            }
            let mn = (hi - lo + 1) as usize;
            if mn <= MERGE_MAX {
                let (shared, moving) = if shared_y {
                    (&mut *fy, &mut *fx)
                } else {
                    (&mut *fx, &mut *fy)
                };
                self.table.eval(c_shared, slo, &mut shared[..sn]);
                if nodes.len() == 1 {
                    self.table
                        .eval(at(c_moving, v_moving, dt0), lo, &mut moving[..mn]);
                } else {
                    moving[..mn].fill(0.0);
                    for &(dt, pw) in nodes {
                        let c = at(c_moving, v_moving, dt);
                        let (r0, rn) = self.axis_range(c, m0, m1, m_cap);
                        if rn == 0 {
                            continue;
                        }
                        self.table.eval(c, r0, &mut one[..rn]);
                        let dst = &mut moving[(r0 - lo) as usize..][..rn];
                        let w = pw as f32;
                        for (d, &o) in dst.iter_mut().zip(&one[..rn]) {
                            *d += w * o;
                        }
                    }
                }
                let (xlo, nx, ylo, ny) = if shared_y {
                    (lo, mn, slo, sn)
                } else {
                    (slo, sn, lo, mn)
                };
                emit_rows(sink, xlo, &fx[..nx], ylo, &fy[..ny], amp as f32);
                return;
            }
        }
        // General streak (or one too long to merge): position by position.
        for &(dt, pw) in nodes {
            let (px, py) = (at(s.x, s.u, dt), at(s.y, s.v, dt));
            let (xlo, nx) = self.axis_range(px, rx0, rx1, X_CAP);
            let (ylo, ny) = self.axis_range(py, ry0, ry1, AXIS_MAX);
            if nx == 0 || ny == 0 {
                continue;
            }
            self.table.eval(px, xlo, &mut fx[..nx]);
            self.table.eval(py, ylo, &mut fy[..ny]);
            emit_rows(sink, xlo, &fx[..nx], ylo, &fy[..ny], (amp * pw) as f32);
        }
    }

    /// The common case of [`Self::particle_rows`] straight into the ring
    /// (no [`ContributionSink`] calls): a small image ([`QuadTable`])
    /// whose positions share their row coordinate (one position, or
    /// v = 0), at most [`LEAN_NODES`] positions, every window from the
    /// table's fixed lanes and inside the ROI. The same numbers, added
    /// in the same order, as `particle_rows` (`lean_images_match_particle_rows`).
    /// General (diagonal) streaks of at most [`LEAN_NODES`] positions go
    /// to [`Self::particle_lean_diagonal`].
    /// Returns the box written, or None, having written nothing, when
    /// the particle is not such a case.
    #[inline(always)]
    fn particle_lean(
        &self,
        q: &QuadTable,
        s: &Snapshot,
        sig: &mut [f32],
        mask: usize,
        stride: usize,
    ) -> Option<ImageBox> {
        let nodes = self.streak_nodes_of(s);
        let m = nodes.len();
        if m > LEAN_NODES {
            return None;
        }
        if !(m == 1 || s.v == 0.0) {
            // (u = 0 is `particle_rows`' separable case: not lean.)
            if s.u == 0.0 {
                return None;
            }
            return self.particle_lean_diagonal(q, s, nodes, sig, mask, stride);
        }
        let (rx0, ry0) = (self.roi.x as i64, self.roi.y as i64);
        let (rx1, ry1) = (
            rx0 + self.roi.width as i64 - 1,
            ry0 + self.roi.height as i64 - 1,
        );
        let dt0 = nodes[0].0;
        let (sw, fy, ya, yb) = q.eval_axis_table(s.y + s.v * dt0, ry0, ry1)?;
        // The moving axis: the weighted sum of the positions' windows in
        // an eight-pixel window starting at `mw` (as `particle_rows_quad`).
        let mut moving = [0.0f32; 8];
        let (mw, lo, hi);
        if m == 1 {
            let (w, v, a, b) = q.eval_axis_table(s.x + s.u * dt0, rx0, rx1)?;
            moving[..4].copy_from_slice(&v);
            (mw, lo, hi) = (w, w + a as i64, w + b as i64 - 1);
        } else {
            let mut win = [(0i64, [0.0f32; 4], 0.0f32); LEAN_NODES];
            let (mut first, mut last) = (i64::MAX, i64::MIN);
            let (mut l, mut h) = (i64::MAX, i64::MIN);
            for (slot, &(dt, pw)) in win.iter_mut().zip(nodes) {
                let (w, v, a, b) = q.eval_axis_table(s.x + s.u * dt, rx0, rx1)?;
                *slot = (w, v, pw as f32);
                first = first.min(w);
                last = last.max(w);
                l = l.min(w + a as i64);
                h = h.max(w + b as i64 - 1);
            }
            if last + 4 - first > 8 {
                return None;
            }
            for (w, v, pw) in &win[..m] {
                let at = (w - first) as usize;
                for (d, &o) in moving[at..at + 4].iter_mut().zip(v) {
                    *d += pw * o;
                }
            }
            (mw, lo, hi) = (first, l, h);
        }
        let amp = (self.gain * s.brightness) as f32;
        let col = (mw - rx0) as usize + RING_PAD;
        let row0 = (sw + ya as i64 - ry0) as u32;
        for j in ya..yb {
            let r = row0 as usize + (j - ya);
            let at = (r & mask) * stride + col;
            let dst: &mut [f32; 8] = (&mut sig[at..at + 8]).try_into().expect("window");
            let scale = amp * fy[j];
            for (d, &f) in dst.iter_mut().zip(&moving) {
                *d += scale * f;
            }
        }
        Some(ImageBox {
            col0: (lo - rx0) as u32,
            col1: (hi - rx0 + 1) as u32,
            row0,
            row1: row0 + (yb - ya) as u32 - 1,
        })
    }

    /// [`Self::particle_lean`] for a general (diagonal) streak: u ≠ 0,
    /// v ≠ 0, 2 ..= [`LEAN_NODES`] positions, each position's windows from
    /// the table's fixed lanes and inside the ROI. `particle_rows` adds
    /// such a streak position by position (`particle_rows_quad`'s general
    /// streak): per position, per covered row, `(scale · fy) · fx` to the
    /// four pixels of its x window, through a sink call per row that also
    /// finds the ring slot and grows the box. This does the same
    /// additions in the same order straight into the ring, the box once
    /// per particle (the union of the positions' covered pixels, as
    /// `RingRows` grows it).
    /// (`lean_images_match_particle_rows`, `diagonal_streaks_match_particle_rows`.)
    #[inline(always)]
    fn particle_lean_diagonal(
        &self,
        q: &QuadTable,
        s: &Snapshot,
        nodes: &[(f64, f64)],
        sig: &mut [f32],
        mask: usize,
        stride: usize,
    ) -> Option<ImageBox> {
        debug_assert!(nodes.len() >= 2 && nodes.len() <= LEAN_NODES);
        let (rx0, ry0) = (self.roi.x as i64, self.roi.y as i64);
        let (rx1, ry1) = (
            rx0 + self.roi.width as i64 - 1,
            ry0 + self.roi.height as i64 - 1,
        );
        let amp = self.gain * s.brightness;
        let m = nodes.len();
        // Per position: x window start and fractions, y window start and
        // fractions, covered window rows, scale (as `particle_rows_quad`);
        // all of them before writing, so a declined streak writes nothing.
        let mut win = [(0i64, [0.0f32; 4], 0i64, [0.0f32; 4], 0usize, 0usize, 0.0f32); LEAN_NODES];
        // Covered pixels (inclusive).
        let (mut xlo, mut xhi, mut ylo, mut yhi) = (i64::MAX, i64::MIN, i64::MAX, i64::MIN);
        for (slot, &(dt, pw)) in win.iter_mut().zip(nodes) {
            let (wx, vx, xa, xb) = q.eval_axis_table(s.x + s.u * dt, rx0, rx1)?;
            let (wy, vy, ya, yb) = q.eval_axis_table(s.y + s.v * dt, ry0, ry1)?;
            *slot = (wx, vx, wy, vy, ya, yb, (amp * pw) as f32);
            xlo = xlo.min(wx + xa as i64);
            xhi = xhi.max(wx + xb as i64 - 1);
            ylo = ylo.min(wy + ya as i64);
            yhi = yhi.max(wy + yb as i64 - 1);
        }
        for &(wx, vx, wy, vy, ya, yb, sc) in &win[..m] {
            let col = (wx - rx0) as usize + RING_PAD;
            let row0 = (wy - ry0) as usize;
            for j in ya..yb {
                let at = ((row0 + j) & mask) * stride + col;
                let dst: &mut [f32; 4] = (&mut sig[at..at + 4]).try_into().expect("window");
                let f = sc * vy[j & 3];
                for (d, &x) in dst.iter_mut().zip(&vx) {
                    *d += f * x;
                }
            }
        }
        Some(ImageBox {
            col0: (xlo - rx0) as u32,
            col1: (xhi - rx0 + 1) as u32,
            row0: (ylo - ry0) as u32,
            row1: (yhi - ry0) as u32,
        })
    }

    /// [`Self::particle_rows`] for small images through the [`QuadTable`]:
    /// the same cases, numbers and operations, with each profile in a
    /// fixed four-pixel window (eight for a merged streak) instead of a
    /// slice. Returns false, having emitted nothing, when a profile does
    /// not fit its window (the caller then takes the general path).
    #[inline]
    fn particle_rows_quad(
        &self,
        q: &QuadTable,
        s: &Snapshot,
        prof: &mut Profiles,
        sink: &mut impl ContributionSink,
    ) -> bool {
        let amp = self.gain * s.brightness;
        let nodes = self.streak_nodes_of(s);
        let (rx0, ry0) = (self.roi.x as i64, self.roi.y as i64);
        let (rx1, ry1) = (
            rx0 + self.roi.width as i64 - 1,
            ry0 + self.roi.height as i64 - 1,
        );
        let at = |c: f64, dir: f64, dt: f64| c + dir * dt;
        if nodes.len() == 1 || s.v == 0.0 || s.u == 0.0 {
            let shared_y = nodes.len() == 1 || s.v == 0.0;
            let dt0 = nodes[0].0;
            let (c_shared, c_moving, v_moving) = if shared_y {
                (at(s.y, s.v, dt0), s.x, s.u)
            } else {
                (at(s.x, s.u, dt0), s.y, s.v)
            };
            let (s0, s1, m0, m1, s_cap, m_cap) = if shared_y {
                (ry0, ry1, rx0, rx1, AXIS_MAX, X_CAP)
            } else {
                (rx0, rx1, ry0, ry1, X_CAP, AXIS_MAX)
            };
            let (sw, shared, slo, sn) = match q.eval_axis(self, c_shared, s0, s1, s_cap) {
                QuadAxis::Window(w, v, lo, n) => (w, v, lo, n),
                QuadAxis::Empty => return true,
                QuadAxis::NoFit => return false,
            };
            // The moving axis: the weighted sum of the positions' windows
            // in an eight-pixel window starting at `mw`.
            let mut moving = [0.0f32; 8];
            let (mut lo, mut hi) = (i64::MAX, i64::MIN);
            let mw;
            if nodes.len() == 1 {
                let c = at(c_moving, v_moving, dt0);
                let (w, v, r0, rn) = match q.eval_axis(self, c, m0, m1, m_cap) {
                    QuadAxis::Window(w, v, lo, n) => (w, v, lo, n),
                    QuadAxis::Empty => return true,
                    QuadAxis::NoFit => return false,
                };
                moving[..4].copy_from_slice(&v);
                (mw, lo, hi) = (w, r0, r0 + rn as i64 - 1);
            } else {
                let mut win = [(0i64, [0.0f32; 4], 0.0f32); 32];
                let mut n = 0;
                for &(dt, pw) in nodes {
                    let c = at(c_moving, v_moving, dt);
                    let (w, v, r0, rn) = match q.eval_axis(self, c, m0, m1, m_cap) {
                        QuadAxis::Window(w, v, lo, n) => (w, v, lo, n),
                        QuadAxis::Empty => continue,
                        QuadAxis::NoFit => return false,
                    };
                    lo = lo.min(r0);
                    hi = hi.max(r0 + rn as i64 - 1);
                    win[n] = (w, v, pw as f32);
                    n += 1;
                }
                if n == 0 {
                    return true;
                }
                let first = win[..n].iter().map(|w| w.0).min().unwrap_or(0);
                let last = win[..n].iter().map(|w| w.0).max().unwrap_or(0);
                if last + 4 - first > 8 {
                    return false;
                }
                mw = first;
                for (w, v, pw) in &win[..n] {
                    let at = (w - first) as usize;
                    for (d, &o) in moving[at..at + 4].iter_mut().zip(v) {
                        *d += pw * o;
                    }
                }
            }
            let mn = (hi - lo + 1) as usize;
            let amp = amp as f32;
            if shared_y {
                for y in slo..slo + sn as i64 {
                    sink.row(y as u32);
                    sink.add_window(mw, &moving, amp * shared[(y - sw) as usize], lo, mn);
                }
            } else {
                for y in lo..=hi {
                    sink.row(y as u32);
                    sink.add_window(sw, &shared, amp * moving[(y - mw) as usize], slo, sn);
                }
            }
            return true;
        }
        // General streak: position by position.
        for &(dt, pw) in nodes {
            let (px, py) = (at(s.x, s.u, dt), at(s.y, s.v, dt));
            let (xlo, nx) = self.axis_range(px, rx0, rx1, X_CAP);
            let (ylo, ny) = self.axis_range(py, ry0, ry1, AXIS_MAX);
            if nx == 0 || ny == 0 {
                continue;
            }
            let scale = (amp * pw) as f32;
            match (q.eval_masked(px, xlo, nx), q.eval_masked(py, ylo, ny)) {
                (Some((wx, fx)), Some((wy, fy))) => {
                    for y in ylo..ylo + ny as i64 {
                        sink.row(y as u32);
                        sink.add_window(wx, &fx, scale * fy[(y - wy) as usize], xlo, nx);
                    }
                }
                _ => {
                    let Profiles { fx, fy, .. } = prof;
                    self.table.eval(px, xlo, &mut fx[..nx]);
                    self.table.eval(py, ylo, &mut fy[..ny]);
                    emit_rows(sink, xlo, &fx[..nx], ylo, &fy[..ny], scale);
                }
            }
        }
        true
    }

    /// Signal contributions of a pulse's particle images, particles taken
    /// in [`render_order`]: `f(roi_pixel_index, signal)`.
    fn contributions(&self, snaps: &[Snapshot], mut f: impl FnMut(u32, f64)) {
        let w = self.roi.width;
        let mut pos = Vec::with_capacity(32);
        for &(key, _, _) in &self.render_order(snaps, true) {
            let s = &snaps[(key & 0xFFFF_FFFF) as usize];
            self.particle_contributions(s, &mut pos, |ix, iy, sig| {
                f((iy - self.roi.y) * w + (ix - self.roi.x), sig)
            });
        }
    }

    /// Events of every lit pixel for one pulse starting at `t_pulse_us`:
    /// [`Self::render_signals`] hands over the pixels at or above the
    /// lowest threshold (`c_floor`; most pixels of an image, its rim, are
    /// below), then each pixel's response. The pixels come in the order
    /// their images are finished, not in ROI-index order: the random
    /// draws are keyed by pixel and crossing ([`crossing_draw_key`]), so
    /// the order changes only the order of the requests, which the
    /// readout sorts.
    pub fn render_pulse(
        &self,
        snaps: &[Snapshot],
        t_pulse_us: f64,
        pulse_seed: u64,
        out: &mut impl ArrivalSink,
    ) {
        thread_local! {
            static SCRATCH: std::cell::RefCell<(Vec<Hit>, Vec<Lit>)> =
                const { std::cell::RefCell::new((Vec::new(), Vec::new())) };
        }
        SCRATCH.with(|cell| {
            let (hits, lit) = &mut *cell.borrow_mut();
            hits.clear();
            // (`v >= c_floor_f32` ⇔ `v as f64 >= c_floor`.)
            self.render_signals(snaps, self.c_floor_f32, hits);
            // The response in two passes of their own (the same
            // arithmetic as [`Self::respond`]): inlined into the drain,
            // or into each other, their loops had no free registers.
            match (self.mismatch.is_some(), self.off.is_some()) {
                (true, false) => self.threshold_pass::<true, false>(hits, lit),
                (true, true) => self.threshold_pass::<true, true>(hits, lit),
                (false, false) => self.threshold_pass::<false, false>(hits, lit),
                (false, true) => self.threshold_pass::<false, true>(hits, lit),
            }
            match (self.jitter_us.is_some(), self.off.is_some()) {
                (true, false) => {
                    self.crossing_pass::<true, false>(lit, t_pulse_us, pulse_seed, out)
                }
                (true, true) => self.crossing_pass::<true, true>(lit, t_pulse_us, pulse_seed, out),
                (false, false) => {
                    self.crossing_pass::<false, false>(lit, t_pulse_us, pulse_seed, out)
                }
                (false, true) => {
                    self.crossing_pass::<false, true>(lit, t_pulse_us, pulse_seed, out)
                }
            }
        });
    }

    /// The first half of [`Self::respond`] for each of `hits` (which are
    /// at or above `c_floor`): the pixel's threshold, the test against
    /// it, ΔL and the ON crossing count; the pixels that can fire go to
    /// `lit`. `MISMATCH`, `OFF_EVENTS`: `threshold_mismatch` and `off_events`
    /// are on (hoisted out of the loop).
    #[inline(never)]
    fn threshold_pass<const MISMATCH: bool, const OFF_EVENTS: bool>(
        &self,
        hits: &[Hit],
        lit: &mut Vec<Lit>,
    ) {
        debug_assert_eq!(
            (MISMATCH, OFF_EVENTS),
            (self.mismatch.is_some(), self.off.is_some())
        );
        lit.clear();
        lit.reserve(hits.len());
        let out = lit.spare_capacity_mut()[..hits.len()].as_mut_ptr();
        let mut n = 0;
        let (sigma, key) = self.mismatch.unwrap_or((0.0, 0));
        let c_off = self.off.map_or(0.0, |o| o.0);
        let (threshold, max_events, q, ln) =
            (self.threshold, self.max_events, self.quantiles, self.ln);
        let (w, x0, y0) = (self.roi.width, self.roi.x, self.roi.y);
        for h in hits {
            let sig = h.v as f64;
            let (r, col) = h.row_col();
            let idx = r * w + col;
            let c = if MISMATCH {
                threshold * Self::mismatch_factor_in(q, sigma, key, idx)
            } else {
                threshold
            };
            // Whether the pixel can fire, as `respond`'s two early
            // returns, but without a branch: the entry is written either
            // way and kept by advancing `n` (the tests mispredicted often:
            // a hit is at or above the lowest threshold, not its own).
            // ΔL and the count are computed for every hit (finite for
            // the positive f32 sums; unused when not kept).
            let fires = !(sig < c && (!OFF_EVENTS || sig < c_off));
            let dl = ln.ln(1.0 + sig);
            // dl/c > 0: truncation is floor (without a libm call).
            let n_on = ((dl / c) as u32).min(max_events);
            let keep = fires & (OFF_EVENTS | (n_on != 0));
            // SAFETY: at most one entry per hit: n < hits.len().
            unsafe {
                (*out.add(n)).write(Lit {
                    idx,
                    x: (x0 + col) as u16,
                    y: (y0 + r) as u16,
                    n_on,
                    sig,
                    c,
                    dl,
                })
            };
            n += keep as usize;
        }
        // SAFETY: the first n entries were written.
        unsafe { lit.set_len(n) };
    }

    /// The second half of [`Self::respond`] for each of `lit`: the
    /// crossing times, jittered, to `out`. `JITTER`, `OFF_EVENTS`:
    /// `latency_jitter` and `off_events` are on.
    #[inline(never)]
    fn crossing_pass<const JITTER: bool, const OFF_EVENTS: bool>(
        &self,
        lit: &[Lit],
        t0: f64,
        pulse_key: u64,
        out: &mut impl ArrivalSink,
    ) {
        debug_assert_eq!(
            (JITTER, OFF_EVENTS),
            (self.jitter_us.is_some(), self.off.is_some())
        );
        let (ln, q) = (self.ln, self.quantiles);
        let j = self.jitter_us.unwrap_or(0.0);
        let (c_off, tau_off) = self.off.unwrap_or((1.0, 0.0));
        // (The same sums as `respond`: (t0 + latency) + τ·(−ln …).)
        let t_on = t0 + self.latency_us;
        let t_off = t0 + self.shape.end_us + self.latency_us;
        let jitter = |t: f64, pixel_key: u64, k: u32, p: u8| {
            if JITTER {
                let g = table_normal(q, crossing_draw_key(pixel_key, k, p));
                let t = t + j * g;
                if t < t0 {
                    t0
                } else {
                    t
                }
            } else {
                t
            }
        };
        let mut times = [0.0f64; 16];
        for p in lit {
            let (x, y) = (p.x, p.y);
            let tau = match self.intensity_latency {
                Some((e, r)) if e == 0.5 => self.tau_us * (r / p.sig).sqrt().min(100.0),
                Some((e, r)) => self.tau_us * (r / p.sig).powf(e).min(100.0),
                None => self.tau_us,
            };
            let pixel_key = pulse_key ^ ((p.idx as u64) << 8);
            let mut n = 0;
            let step_on = p.c / p.dl;
            for k in 1..=p.n_on {
                let frac = 0.95 * (k as f64 * step_on).min(1.0);
                times[n] = jitter(t_on + tau * -ln.ln(1.0 - frac), pixel_key, k, ON);
                n += 1;
                if n == times.len() {
                    out.arrive_pixel(x, y, ON, &times);
                    n = 0;
                }
            }
            if n > 0 {
                out.arrive_pixel(x, y, ON, &times[..n]);
                n = 0;
            }
            if OFF_EVENTS {
                let n_off = ((p.dl / c_off) as u32).min(self.max_events);
                let step_off = c_off / p.dl;
                for k in 1..=n_off {
                    let frac = 0.95 * (k as f64 * step_off).min(1.0);
                    times[n] = jitter(t_off + tau_off * -ln.ln(1.0 - frac), pixel_key, k, OFF);
                    n += 1;
                    if n == times.len() {
                        out.arrive_pixel(x, y, OFF, &times);
                        n = 0;
                    }
                }
                if n > 0 {
                    out.arrive_pixel(x, y, OFF, &times[..n]);
                }
            }
        }
    }

    /// The summed signal of every pixel the fast path gives a non-zero
    /// sum for one pulse, in ROI-index order: `(roi_index, signal)`
    /// (tests compare it with [`Self::pixel_signals_reference`]).
    pub fn pixel_signals(&self, snaps: &[Snapshot]) -> Vec<(u32, f32)> {
        let mut v = Vec::new();
        // (The least positive f32: every pixel with a non-zero sum.)
        self.render_signals(snaps, f32::from_bits(1), &mut v);
        let w = self.roi.width;
        let mut v: Vec<(u32, f32)> = v
            .iter()
            .map(|h| {
                let (r, c) = h.row_col();
                (r * w + c, h.v)
            })
            .collect();
        v.sort_unstable_by_key(|p| p.0);
        v
    }

    /// The summed signal of every pixel of the exact model
    /// ([`Self::contributions`], f64), in ROI-index order.
    pub fn pixel_signals_reference(&self, snaps: &[Snapshot]) -> Vec<(u32, f64)> {
        let mut list: Vec<(u32, f64)> = Vec::new();
        self.contributions(snaps, |idx, sig| list.push((idx, sig)));
        list.sort_by_key(|a| a.0);
        let mut out: Vec<(u32, f64)> = Vec::new();
        for (idx, sig) in list {
            match out.last_mut() {
                Some(last) if last.0 == idx => last.1 += sig,
                _ => out.push((idx, sig)),
            }
        }
        out
    }

    /// The fast path's images of a pulse, summed per pixel: calls
    /// `pixel(roi_index, x, y, signal)` once for every pixel whose
    /// summed signal is at least `floor` (> 0), in the order the images
    /// are finished (not ROI-index order).
    ///
    /// Overlapping images add up (f32) in a small per-thread ring of
    /// sensor rows (a few rows × ROI width: it stays in cache, where a
    /// dense ROI-sized buffer missed the cache on nearly every pixel).
    /// Particles come in order of the lowest row they can touch, so when
    /// a particle starts at row r every row below r is complete. Each
    /// rendered image leaves the box of ring pixels it wrote
    /// ([`ImageBox`]) in the list of its last row; when that row is
    /// complete the box is drained: eight pixels at a time compared with
    /// `floor` (SSE2 `cmpps` + `movmskps`) and cleared. Every pixel of a
    /// complete row holds its final sum, so a pixel that two boxes share
    /// (overlapping images, or an eight-pixel group reaching into a
    /// neighbour) is handed out by the first box drained and reads 0 in
    /// the second: each pixel once. This replaced a bit set of touched
    /// pixels per row scanned pixel by pixel (~13 instructions per
    /// touched pixel, ~10 touched per image, most below every threshold).
    #[inline(never)]
    fn render_signals(&self, snaps: &[Snapshot], floor: f32, hits: &mut Vec<Hit>) {
        debug_assert!(floor > 0.0);
        let order = self.render_order(snaps, false);
        let (rw, rh) = (self.roi.width as usize, self.roi.height as i64);
        let ry0 = self.roi.y as i64;
        // Rows alive at once: those a particle spans (bounds inclusive).
        let span = order
            .iter()
            .map(|o| (o.2 - o.1 + 1).clamp(1, rh))
            .max()
            .unwrap_or(1) as usize;
        RENDER_RING.with(|cell| {
            let mut ring = cell.borrow_mut();
            // Rows alive at once: a pending box's rows reach up to
            // span − 1 below the first incomplete row (its last row is
            // still incomplete), the next particles write up to span − 1
            // above it: 2·span − 1 rows. A power of two, so the slot is a
            // mask, not a division.
            ring.reset((2 * span).next_power_of_two(), rw);
            let mut next_row = 0i64; // first ROI row not yet complete
            let RowRing {
                rows,
                sig,
                boxes,
                profiles,
                ..
            } = &mut *ring;
            let mask = *rows - 1;
            let stride = rw + 2 * RING_PAD;
            for &(key, lo, _) in &order {
                let lo_rel = (lo - ry0).min(rh);
                while next_row < lo_rel {
                    let list = &mut boxes[next_row as usize & mask];
                    if !list.is_empty() {
                        self.drain_boxes(sig, stride, mask, list, floor, hits);
                        list.clear();
                    }
                    next_row += 1;
                }
                let s = &snaps[(key & 0xFFFF_FFFF) as usize];
                debug_assert!((lo - ry0).max(0) >= next_row.min(rh), "row drained early");
                if let Some(q) = &self.quad {
                    if let Some(bx) = self.particle_lean(q, s, sig, mask, stride) {
                        debug_assert!(
                            bx.row1 as i64 >= next_row && bx.row1 as i64 - next_row < *rows as i64
                        );
                        boxes[bx.row1 as usize & mask].push(bx);
                        continue;
                    }
                }
                let mut sink = RingRows {
                    sig: &mut sig[..],
                    mask,
                    stride,
                    roi_x: self.roi.x,
                    roi_y: self.roi.y,
                    sig_at: 0,
                    row: 0,
                    bx: ImageBox::EMPTY,
                };
                self.particle_rows(s, profiles, &mut sink);
                let bx = sink.bx;
                if bx.col0 < bx.col1 {
                    debug_assert!(
                        bx.row1 as i64 >= next_row && bx.row1 as i64 - next_row < *rows as i64
                    );
                    boxes[bx.row1 as usize & mask].push(bx);
                }
            }
            while next_row < rh {
                let list = &mut boxes[next_row as usize & mask];
                if !list.is_empty() {
                    self.drain_boxes(sig, stride, mask, list, floor, hits);
                    list.clear();
                }
                next_row += 1;
            }
        });
    }

    /// Append every pixel of the boxes of `list` (and of the rest of
    /// their eight-pixel groups) whose sum is at least `floor` to `hits`,
    /// and clear them all. The boxes' rows must be complete.
    ///
    /// (A call of its own, with `hits` reserved up front so that no
    /// call is left inside its loops: inlined into the particle loop, or
    /// with a growing push, its loops kept their state on the stack.)
    #[inline(never)]
    fn drain_boxes(
        &self,
        sig: &mut [f32],
        stride: usize,
        mask: usize,
        list: &[ImageBox],
        floor: f32,
        hits: &mut Vec<Hit>,
    ) {
        // At most eight hits per group of eight pixels.
        let most: usize = list
            .iter()
            .map(|b| {
                (b.row1 - b.row0 + 1) as usize * (b.col1 - b.col0).next_multiple_of(8) as usize
            })
            .sum();
        hits.reserve(most);
        let out = hits.spare_capacity_mut()[..most].as_mut_ptr();
        let mut n = 0;
        let w = self.roi.width;
        // (Columns + 8 and rows fit the 16 bits of `Hit::rc`.)
        assert!(w <= 4096 && self.roi.height <= 1 << 16);
        assert!(sig.len() >= (mask + 1) * stride && stride >= w as usize + 2 * RING_PAD);
        let ring = sig.as_mut_ptr();
        for b in list {
            let (c0, c1) = (b.col0 as usize, b.col1 as usize);
            // (What keeps the groups inside the ring: the box's columns
            // lie in the ROI, so the last group ends inside the row's
            // right padding; rows wrap by `mask`.)
            assert!(c0 < c1 && c1 <= w as usize);
            for r in b.row0..b.row1 + 1 {
                // SAFETY: slot·stride + RING_PAD + c + 8 ≤ (slot + 1)·stride
                // for every group start c < c1 ≤ width (asserted above).
                let row = unsafe { ring.add((r as usize & mask) * stride + RING_PAD) };
                let mut c = c0;
                loop {
                    // SAFETY: see `row`.
                    let lanes = unsafe { &mut *(row.add(c) as *mut [f32; 8]) };
                    // Only the box's own lanes (c..c1): the others belong
                    // to no box or to another one, which hands them out
                    // and clears them when it is drained.
                    let own = (c1 - c).min(8);
                    let m = at_least_mask8(lanes, floor) & ((1u32 << own) - 1);
                    // Every lane written, the count advanced by its bit:
                    // no branch on how many pixels of the group fire
                    // (the loop over the mask's bits mispredicted ~once
                    // per group).
                    // SAFETY: n counts the hits among the lanes before
                    // this group, of at most `most` lanes in all, and the
                    // group's eight lanes are among them: n + 8 ≤ most.
                    n = unsafe { write_hits8(out.add(n), lanes, r << 16 | c as u32, m) } + n;
                    clear_lanes8(lanes, own);
                    c += 8;
                    if c >= c1 {
                        break;
                    }
                }
            }
        }
        debug_assert!(n <= most);
        // SAFETY: the first n entries of the spare capacity were written.
        unsafe { hits.set_len(hits.len() + n) };
    }

    /// The exact model, plainly (the reference the fast
    /// [`Self::render_pulse`] is tested against): every contribution from
    /// erf at the pixel edges ([`Self::footprint`]), per-pixel sums in f64
    /// ([`Self::pixel_signals_reference`]), responses with libm's
    /// logarithms; pixels in ROI-index order, so the random draws pair up
    /// with the fast path's.
    pub fn render_pulse_reference(
        &self,
        snaps: &[Snapshot],
        t_pulse_us: f64,
        pulse_seed: u64,
        out: &mut impl ArrivalSink,
    ) {
        for (idx, sig) in self.pixel_signals_reference(snaps) {
            let x = (self.roi.x + idx % self.roi.width) as u16;
            let y = (self.roi.y + idx / self.roi.width) as u16;
            self.respond::<true>(idx, x, y, sig, t_pulse_us, pulse_seed, out);
        }
    }

    /// Threshold factor of ROI pixel `idx` under `threshold_mismatch`
    /// (σ, key): 1 + σ·g with g a standard normal deviate chosen by a hash
    /// of the pixel index, so the pattern is fixed for a seed. g is one of
    /// 4096 equiprobable bins of the normal quantile function (table
    /// lookup, no `ln`/`cos`), interpolated linearly within the bin: a
    /// Gaussian except that the tails stop at ±3.67σ (the 1/8192
    /// quantile), so a 1280×720 array lacks its ~225 most extreme pixels.
    #[inline]
    pub fn mismatch_factor(sigma: f64, key: u64, idx: u32) -> f64 {
        Self::mismatch_factor_in(normal_quantiles(), sigma, key, idx)
    }

    /// [`Self::mismatch_factor`] with the quantile table at hand (no
    /// once-lock check per pixel).
    #[inline(always)]
    fn mismatch_factor_in(q: &[f64; 4097], sigma: f64, key: u64, idx: u32) -> f64 {
        let g = table_normal(q, super::splitmix(key ^ idx as u64));
        (1.0 + sigma * g.clamp(-MISMATCH_CLAMP, MISMATCH_CLAMP)).max(MIN_MISMATCH_FACTOR)
    }

    /// The events of ROI pixel `idx` (sensor `x`, `y`) for a pulse signal
    /// `sig` starting at `t0`. `EXACT`: libm's logarithms (the reference);
    /// otherwise [`LnTable::ln`] (error < 1e-14, far below the 1 ns time
    /// resolution).
    #[allow(clippy::too_many_arguments)]
    #[inline]
    fn respond<const EXACT: bool>(
        &self,
        idx: u32,
        x: u16,
        y: u16,
        sig: f64,
        t0: f64,
        pulse_key: u64,
        out: &mut impl ArrivalSink,
    ) {
        let ln = |v: f64| if EXACT { v.ln() } else { self.ln.ln(v) };
        // ln(1 + s) ≤ s: a signal below every threshold cannot fire; most
        // pixels at the rim of an image are such (skips hash and log).
        if sig < self.c_floor {
            return;
        }
        let c = match self.mismatch {
            Some((sigma, key)) => {
                self.threshold * Self::mismatch_factor_in(self.quantiles, sigma, key, idx)
            }
            None => self.threshold,
        };
        // The same bound with this pixel's threshold.
        if sig < c && self.off.is_none_or(|(c_off, _)| sig < c_off) {
            return;
        }
        let dl = if EXACT {
            sig.ln_1p()
        } else {
            self.ln.ln(1.0 + sig)
        };
        // dl/c > 0: truncation is floor (without a libm call).
        let n_on = ((dl / c) as u32).min(self.max_events);
        if n_on == 0 && self.off.is_none() {
            return;
        }
        let tau = match self.intensity_latency {
            Some((e, r)) if e == 0.5 => self.tau_us * (r / sig).sqrt().min(100.0),
            Some((e, r)) => self.tau_us * (r / sig).powf(e).min(100.0),
            None => self.tau_us,
        };
        // Times go to the sink in batches of a pixel's events.
        let mut times = [0.0f64; 16];
        let mut n = 0;
        // The jitter of crossing k of polarity p: a keyed draw
        // ([`crossing_draw_key`]), so it does not depend on which other
        // pixels or crossings were computed before.
        let pixel_key = pulse_key ^ ((idx as u64) << 8);
        let jitter = |t: f64, k: u32, p: u8| match self.jitter_us {
            Some(j) => {
                let g = table_normal(self.quantiles, crossing_draw_key(pixel_key, k, p));
                // (`max` without its NaN handling: t is finite.)
                let t = t + j * g;
                if t < t0 {
                    t0
                } else {
                    t
                }
            }
            None => t,
        };
        // (One division per pixel, not per crossing.)
        let step_on = c / dl;
        for k in 1..=n_on {
            let frac = 0.95 * (k as f64 * step_on).min(1.0);
            times[n] = jitter(t0 + self.latency_us + tau * -ln(1.0 - frac), k, ON);
            n += 1;
            if n == times.len() {
                out.arrive_pixel(x, y, ON, &times);
                n = 0;
            }
        }
        if n > 0 {
            out.arrive_pixel(x, y, ON, &times[..n]);
            n = 0;
        }
        if let Some((c_off, tau_off)) = self.off {
            let n_off = ((dl / c_off) as u32).min(self.max_events);
            let step_off = c_off / dl;
            for k in 1..=n_off {
                let frac = 0.95 * (k as f64 * step_off).min(1.0);
                times[n] = jitter(
                    t0 + self.shape.end_us + self.latency_us + tau_off * -ln(1.0 - frac),
                    k,
                    OFF,
                );
                n += 1;
                if n == times.len() {
                    out.arrive_pixel(x, y, OFF, &times);
                    n = 0;
                }
            }
            if n > 0 {
                out.arrive_pixel(x, y, OFF, &times[..n]);
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

/// The hash whose bits give the jitter of threshold crossing `k` (1…64)
/// of polarity `p` of a pixel, `pixel_key` = pulse key ^ (ROI index << 8):
/// every (pixel, crossing, polarity) of a pulse has its own input, so the
/// draws are independent of each other and of the order they are taken
/// in (a keyed, counter-based stream instead of one sequential generator
/// per pulse).
#[inline(always)]
pub(crate) fn crossing_draw_key(pixel_key: u64, k: u32, p: u8) -> u64 {
    super::splitmix(pixel_key ^ ((k as u64) << 1 | p as u64))
}

/// A standard normal deviate from 64 random bits `h`: the top 12 bits
/// pick one of 4096 equiprobable bins of [`normal_quantiles`], the low 52
/// interpolate linearly within it (a table lookup and a multiply-add:
/// no `ln`, no rejection). So the distribution function is the normal one
/// at every inner bin edge and linear in between (|ΔF| < 2e-5, largest in
/// the outer bins; see `table_normal_moments_and_quantiles`); the tails
/// stop at ±3.67: the outermost bins (mass 1/4096 each) are squeezed to
/// [3.49, 3.67], where a true normal has 2.4e-4 of its mass beyond 3.67σ.
/// Mean 0, variance 0.99946, kurtosis 2.987 (a normal's: 1, 3).
#[inline(always)]
pub(crate) fn table_normal(q: &[f64; 4097], h: u64) -> f64 {
    let bin = (h >> 52) as usize; // 12 bits
                                  // (Through i64: the same value, one instruction instead of the
                                  // u64 → f64 sequence.)
    let frac = (h & 0xF_FFFF_FFFF_FFFF) as i64 as f64 * (1.0 / (1u64 << 52) as f64);
    q[bin] + (q[bin + 1] - q[bin]) * frac
}

/// Standard normal quantiles at the 4097 probabilities 0.5/4096,
/// 1/4096, …, 1 − 1/4096, 1 − 0.5/4096 (ends at half a bin, so the
/// interpolated deviate stays finite), by bisection on [`erf_series`].
/// Entries are independent, so they are computed in parallel (the same
/// values: ~50 M instructions, which held the start of every run ~15 ms
/// on one core).
fn normal_quantiles() -> &'static [f64; 4097] {
    use rayon::prelude::*;
    static TABLE: std::sync::OnceLock<Box<[f64; 4097]>> = std::sync::OnceLock::new();
    TABLE.get_or_init(|| {
        let mut t = Box::new([0.0; 4097]);
        t.par_iter_mut().enumerate().for_each(|(i, q)| {
            *q = normal_quantile_bisection(i, true);
        });
        t
    })
}

/// Entry `i` of [`normal_quantiles`]: 60 bisection steps on [−8, 8] for
/// the probability of node i, each deciding `cdf(mid) < p` with
/// [`erf_series`] in the cdf.
///
/// `screened`: the same decisions, but made with the erf table
/// ([`ErfTable`], within 1e-9 of the series) wherever the table's cdf is
/// more than 1e-7 from p, so the series' verdict cannot differ; only the
/// steps close to the quantile (about half) evaluate the slow series. The
/// result is the same number (`normal_quantiles_screening_is_exact`).
fn normal_quantile_bisection(i: usize, screened: bool) -> f64 {
    const MARGIN: f64 = 1e-7;
    let cdf = |g: f64| 0.5 * (1.0 + erf_series(g.abs() / std::f64::consts::SQRT_2).copysign(g));
    let erf = erf_table();
    let p = (i as f64 / 4096.0).clamp(0.5 / 4096.0, 1.0 - 0.5 / 4096.0);
    let (mut lo, mut hi) = (-8.0, 8.0);
    for _ in 0..60 {
        let mid = 0.5 * (lo + hi);
        let below = if screened {
            let f = 0.5 * (1.0 + erf.eval(mid / std::f64::consts::SQRT_2));
            if f < p - MARGIN {
                true
            } else if f > p + MARGIN {
                false
            } else {
                cdf(mid) < p
            }
        } else {
            cdf(mid) < p
        };
        if below {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    0.5 * (lo + hi)
}

/// The least f32 `f` with `f as f64 >= x` (x finite, positive), so that
/// `v >= f32_at_least(x)` ⇔ `v as f64 >= x` for every f32 `v` that is not
/// NaN.
pub(crate) fn f32_at_least(x: f64) -> f32 {
    let f = x as f32; // nearest
    if (f as f64) < x {
        f.next_up()
    } else {
        f
    }
}

/// `v.round() as i64` (half away from zero) without a libm call, for
/// |v| < 2^52.
#[inline]
pub(crate) fn round_i64(v: f64) -> i64 {
    let t = v as i64;
    let r = v - t as f64;
    // (Flags, not branches: the rounding direction is data-dependent.)
    t + (r >= 0.5) as i64 - (r <= -0.5) as i64
}

/// Where a pixel's events go: a list of arrivals (tests, the reference)
/// or the simulator's request keys.
pub trait ArrivalSink {
    fn arrive(&mut self, a: Arrival);
    /// Events of pixel (x, y), all of polarity `p`, at `times` (in this
    /// order): what [`PixelModel::respond`] hands over, so a sink can do
    /// its per-pixel work once.
    #[inline]
    fn arrive_pixel(&mut self, x: u16, y: u16, p: u8, times: &[f64]) {
        for &t in times {
            self.arrive(Arrival { t, x, y, p });
        }
    }
}

impl ArrivalSink for Vec<Arrival> {
    #[inline]
    fn arrive(&mut self, a: Arrival) {
        self.push(a);
    }
}

/// Receives a particle's contributions row by row.
trait ContributionSink {
    /// The following contributions are in sensor row `iy`.
    fn row(&mut self, iy: u32);
    /// Add `scale·fractions[a]` to sensor column `ix0 + a` of the current
    /// row.
    fn add_run(&mut self, ix0: u32, fractions: &[f32], scale: f32);
    /// Add `scale·window[a]` to sensor column `wx + a` of the current row
    /// for the pixels `x0 .. x0 + n` (inside the window and the ROI); the
    /// other lanes are 0 and may be added as such (the ring keeps
    /// [`RING_PAD`] columns either side for them) or skipped.
    fn add_window<const W: usize>(
        &mut self,
        wx: i64,
        window: &[f32; W],
        scale: f32,
        x0: i64,
        n: usize,
    );
}

/// Columns of padding either side of a ring row, for the zero lanes of a
/// window that reach past the ROI's edge.
const RING_PAD: usize = 8;

/// Longest axis profile of one image position: up to 31 pixels along x
/// (`footprint`'s cap) and along y (a valid scenario's images, ≤ 20 px
/// across, span at most 32 rows).
const AXIS_MAX: usize = 64;
/// `footprint`'s cap on the pixels along x.
const X_CAP: usize = 31;
/// Longest merged profile of a streak (positions' union); longer streaks
/// are rendered position by position.
const MERGE_MAX: usize = 128;

/// Most streak positions [`PixelModel::particle_lean`] takes.
const LEAN_NODES: usize = 4;

/// Add the separable image `scale·fx ⊗ fy` (pixels `xlo..`, rows `ylo..`).
#[inline]
fn emit_rows(
    sink: &mut impl ContributionSink,
    xlo: i64,
    fx: &[f32],
    ylo: i64,
    fy: &[f32],
    scale: f32,
) {
    for (j, &f) in fy.iter().enumerate() {
        sink.row((ylo + j as i64) as u32);
        sink.add_run(xlo as u32, fx, scale * f);
    }
}

/// A pixel at or above its threshold, between the two passes of
/// [`PixelModel::render_pulse`]'s response: ROI index, sensor
/// coordinates, ON crossing count, signal, threshold, ΔL.
#[derive(Debug, Clone, Copy)]
struct Lit {
    idx: u32,
    x: u16,
    y: u16,
    n_on: u32,
    sig: f64,
    c: f64,
    dl: f64,
}

/// A pixel handed out by [`PixelModel::render_signals`]: its ROI row and
/// column packed as `row << 16 | column` (ROIs are at most 4096 px
/// wide), and its summed signal. Eight bytes, `repr(C)`: the drain
/// writes one as a single u64 (`column key | signal bits << 32`).
#[derive(Debug, Clone, Copy)]
#[repr(C)]
struct Hit {
    rc: u32,
    v: f32,
}

impl Hit {
    /// ROI-relative (row, column).
    #[inline(always)]
    fn row_col(self) -> (u32, u32) {
        (self.rc >> 16, self.rc & 0xFFFF)
    }
}

/// The ring pixels one image wrote: ROI-relative columns `col0..col1`
/// of rows `row0..=row1` (empty when `col0 >= col1`).
#[derive(Debug, Clone, Copy)]
struct ImageBox {
    col0: u32,
    col1: u32,
    row0: u32,
    row1: u32,
}

impl ImageBox {
    const EMPTY: ImageBox = ImageBox {
        col0: u32::MAX,
        col1: 0,
        row0: u32::MAX,
        row1: 0,
    };
}

/// The row ring as a [`ContributionSink`]: the slot's offset is found
/// once per row; the box of the pixels written grows with each run.
struct RingRows<'a> {
    sig: &'a mut [f32],
    mask: usize,
    /// Ring row length: ROI width plus [`RING_PAD`] either side.
    stride: usize,
    roi_x: u32,
    roi_y: u32,
    sig_at: usize,
    /// Current row (ROI-relative).
    row: u32,
    bx: ImageBox,
}

impl ContributionSink for RingRows<'_> {
    #[inline]
    fn row(&mut self, iy: u32) {
        self.row = iy - self.roi_y;
        self.sig_at = (self.row as usize & self.mask) * self.stride;
    }

    #[inline]
    fn add_run(&mut self, ix0: u32, fractions: &[f32], scale: f32) {
        let x0 = (ix0 - self.roi_x) as usize;
        let n = fractions.len();
        for (d, &f) in self.sig[self.sig_at + RING_PAD + x0..][..n]
            .iter_mut()
            .zip(fractions)
        {
            *d += scale * f;
        }
        self.extend(x0 as u32, n as u32);
    }

    #[inline]
    fn add_window<const W: usize>(
        &mut self,
        wx: i64,
        window: &[f32; W],
        scale: f32,
        x0: i64,
        n: usize,
    ) {
        // (wx ≥ ROI x − RING_PAD: the window holds an ROI pixel.)
        let at = (self.sig_at as i64 + RING_PAD as i64 + wx - self.roi_x as i64) as usize;
        let dst: &mut [f32; W] = (&mut self.sig[at..at + W]).try_into().expect("window");
        for (d, &f) in dst.iter_mut().zip(window) {
            *d += scale * f;
        }
        self.extend((x0 - self.roi_x as i64) as u32, n as u32);
    }
}

impl RingRows<'_> {
    /// Grow the box by ROI columns x0 .. x0 + n of the current row.
    #[inline]
    fn extend(&mut self, x0: u32, n: u32) {
        let b = &mut self.bx;
        b.col0 = b.col0.min(x0);
        b.col1 = b.col1.max(x0 + n);
        b.row0 = b.row0.min(self.row);
        b.row1 = b.row1.max(self.row);
    }
}

/// Write the eight lanes of `v` as [`Hit`]s with keys `rc + j` to
/// consecutive slots from `out`, the j-th to the slot after the hits of
/// lanes below j whose bit is set in `m`: every lane written (a later one
/// overwrites a lane whose bit is clear), no branch on how many fire
/// (the loop over the mask's bits mispredicted ~once per group). Returns
/// the number of set bits.
///
/// # Safety
/// `out` must be valid for writes of eight `Hit`s.
#[inline(always)]
unsafe fn write_hits8(
    out: *mut std::mem::MaybeUninit<Hit>,
    v: &[f32; 8],
    rc: u32,
    m: u32,
) -> usize {
    // (`Hit` is `repr(C)` {rc: u32, v: f32}: one u64, key low.)
    let out = out as *mut u64;
    let mut n = 0;
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::*;
        // SAFETY: SSE2 is part of the x86_64 baseline; the loads read
        // the eight f32 of `v`; every store is to one of the eight slots
        // (n ≤ j for lane j).
        unsafe {
            let k0 = _mm_add_epi32(_mm_set1_epi32(rc as i32), _mm_setr_epi32(0, 1, 2, 3));
            let k1 = _mm_add_epi32(k0, _mm_set1_epi32(4));
            let v0 = _mm_castps_si128(_mm_loadu_ps(v.as_ptr()));
            let v1 = _mm_castps_si128(_mm_loadu_ps(v.as_ptr().add(4)));
            // Key and value interleaved: two hits per register.
            let pairs = [
                _mm_unpacklo_epi32(k0, v0),
                _mm_unpackhi_epi32(k0, v0),
                _mm_unpacklo_epi32(k1, v1),
                _mm_unpackhi_epi32(k1, v1),
            ];
            for (i, &p) in pairs.iter().enumerate() {
                _mm_storel_epi64(out.add(n) as *mut __m128i, p);
                n += (m >> (2 * i)) as usize & 1;
                _mm_storeh_pd(out.add(n) as *mut f64, _mm_castsi128_pd(p));
                n += (m >> (2 * i + 1)) as usize & 1;
            }
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    for (j, &x) in v.iter().enumerate() {
        // SAFETY: n ≤ j < 8.
        unsafe {
            out.add(n)
                .write_unaligned((x.to_bits() as u64) << 32 | (rc + j as u32) as u64)
        };
        n += (m >> j) as usize & 1;
    }
    n
}

/// Set lanes `0..n` (n ≤ 8) of `v` to +0.0, keep the others bit for bit.
#[inline(always)]
fn clear_lanes8(v: &mut [f32; 8], n: usize) {
    // KEEP[n]: all-ones for lanes n.., zero below.
    const KEEP: [[u32; 8]; 9] = {
        let mut t = [[0u32; 8]; 9];
        let mut n = 0;
        while n < 9 {
            let mut j = n;
            while j < 8 {
                t[n][j] = u32::MAX;
                j += 1;
            }
            n += 1;
        }
        t
    };
    let keep = &KEEP[n];
    for (x, &k) in v.iter_mut().zip(keep) {
        *x = f32::from_bits(x.to_bits() & k);
    }
}

/// Bit j set where `v[j] >= floor` (false for NaN, as `>=`).
#[inline(always)]
fn at_least_mask8(v: &[f32; 8], floor: f32) -> u32 {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_mm_cmpge_ps, _mm_loadu_ps, _mm_movemask_ps, _mm_set1_ps};
        // SAFETY: SSE2 is part of the x86_64 baseline; the loads read
        // the eight f32 of `v`.
        unsafe {
            let f = _mm_set1_ps(floor);
            let lo = _mm_cmpge_ps(_mm_loadu_ps(v.as_ptr()), f);
            let hi = _mm_cmpge_ps(_mm_loadu_ps(v.as_ptr().add(4)), f);
            (_mm_movemask_ps(lo) | _mm_movemask_ps(hi) << 4) as u32
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let mut m = 0;
        for (j, &x) in v.iter().enumerate() {
            m |= ((x >= floor) as u32) << j;
        }
        m
    }
}

/// Pixel fractions of a Gaussian particle image along one axis, tabulated
/// over the sub-pixel position of its centre: the fast path's replacement
/// for erf at every pixel edge.
///
/// For a centre `c = i + d` (i = round(c), d ∈ [−½, ½]) pixel `i + a`
/// receives `f_a(d) = ½[erf((a + ½ − d)k) − erf((a − ½ − d)k)]`,
/// k = 1/(σ√2), a smooth function of d. The table holds `f_a` and its
/// derivative at `steps + 1` nodes of d for every a in −r..=r, and
/// [`FractionTable::eval`] interpolates by cubic Hermite: the basis is
/// computed once per centre and each pixel costs four multiply-adds (in
/// f32). Nodes every σ/48 or finer keep the interpolation error below
/// ~1e-9 absolute (tested: relative 1e-5 of every covered pixel's
/// fraction, which are ≥ ~1e-3 by the ±3σ range), where f32 rounding
/// dominates.
struct FractionTable {
    steps: usize,
    /// 3σ: pixels within this of the centre are covered.
    reach: f64,
    r: i64,
    width: usize,
    /// Node i (d = −½ + i/steps), entry a + r: (f_a(d), f_a'(d)/steps).
    nodes: Vec<[f32; 2]>,
}

impl FractionTable {
    fn new(sigma: f64) -> FractionTable {
        let r = (3.0 * sigma).ceil() as i64 + 1;
        let width = (2 * r + 1) as usize;
        // (Even, so the middle node sits at d = 0: see [`QuadTable`].)
        let steps = ((48.0 / sigma).ceil() as usize)
            .clamp(64, 2048)
            .next_multiple_of(2);
        let h = 1.0 / steps as f64;
        let k = std::f64::consts::FRAC_1_SQRT_2 / sigma;
        let mut nodes = Vec::with_capacity((steps + 1) * width);
        for i in 0..=steps {
            let d = -0.5 + i as f64 * h;
            for a in -r..=r {
                let hi = (a as f64 + 0.5 - d) * k;
                let lo = (a as f64 - 0.5 - d) * k;
                let f = 0.5 * (erf_exact(hi) - erf_exact(lo));
                // Moving the centre by +d moves both edges by −d·k.
                let df = 0.5
                    * k
                    * std::f64::consts::FRAC_2_SQRT_PI
                    * ((-lo * lo).exp() - (-hi * hi).exp());
                nodes.push([f as f32, (df * h) as f32]);
            }
        }
        FractionTable {
            steps,
            reach: 3.0 * sigma,
            r,
            width,
            nodes,
        }
    }

    /// Fractions of pixels `lo .. lo + out.len()` for a centre at `c`
    /// (pixels within `r` of round(c): those of [`PixelModel::axis_range`]).
    #[inline]
    fn eval(&self, c: f64, lo: i64, out: &mut [f32]) {
        let base = round_i64(c);
        // Exact (the nearest integer is within a factor 2 of c, or 0).
        let d = c - base as f64;
        let u = (d + 0.5) * self.steps as f64;
        let i = (u as usize).min(self.steps - 1);
        let t = (u - i as f64) as f32;
        let t2 = t * t;
        let t3 = t2 * t;
        let (h00, h10) = (2.0 * t3 - 3.0 * t2 + 1.0, t3 - 2.0 * t2 + t);
        let (h01, h11) = (3.0 * t2 - 2.0 * t3, t3 - t2);
        let a0 = (lo - base + self.r) as usize;
        let n = out.len();
        let row0 = &self.nodes[i * self.width + a0..][..n];
        let row1 = &self.nodes[(i + 1) * self.width + a0..][..n];
        for ((o, p), q) in out.iter_mut().zip(row0).zip(row1) {
            *o = h00 * p[0] + h10 * p[1] + h01 * q[0] + h11 * q[1];
        }
    }
}

/// The [`FractionTable`] cut into four-pixel windows, for images narrow
/// enough (σ < ½: at most 4 pixels along an axis, the presets' 1.3–1.5 px
/// particles) that one window holds every pixel of an image position.
///
/// For a centre `c = base + d`, [`PixelModel::axis_range`]'s pixels lie
/// in `base − 2 ..= base + 1` when d < 0 and in `base − 1 ..= base + 2`
/// when d ≥ 0 (3σ < 1.5). A table interval lies on one side of d = 0
/// (the table's step count is even), so each interval stores its two
/// nodes' values and slopes for its window's four pixels side by side:
/// one 64-byte cell, four-lane arithmetic (the same f32 operations in the
/// same order as [`FractionTable::eval`], so the same numbers), no
/// slicing. Callers check that the pixels they need lie in the window
/// (they always do unless `d + ½` rounds across the middle node) and
/// take the general path otherwise.
struct QuadTable {
    steps: usize,
    /// `steps` as f64 (no integer conversion per call).
    steps_f: f64,
    /// Per interval: f and slope at its lower node, then at its upper
    /// node, for window pixels 0..4.
    cells: Vec<[[f32; 4]; 4]>,
    /// Per interval: the lanes of its window that
    /// [`PixelModel::axis_range`] covers for every centre in the interval
    /// (away from the ROI's edges), as `a | b << 4` for lanes `a..b`, or
    /// [`QuadTable::AMBIGUOUS`] when the range changes inside the
    /// interval (a rounding boundary of `c ± 3σ` lies in it or within
    /// 1e-9 px of it).
    lanes: Vec<u8>,
}

impl QuadTable {
    fn new(t: &FractionTable) -> Option<QuadTable> {
        // σ < ½ ⇔ 3σ < 1.5; the table's r is ceil(3σ) + 1 ≥ 2.
        if !(t.reach < 1.5) || t.r < 2 || t.steps % 2 != 0 {
            return None;
        }
        let cells = (0..t.steps)
            .map(|i| {
                let a0 = Self::window_offset(t.steps, i);
                let mut cell = [[0.0f32; 4]; 4];
                for j in 0..4 {
                    let a = (a0 + j as i64 + t.r) as usize;
                    let (lo, hi) = (t.nodes[i * t.width + a], t.nodes[(i + 1) * t.width + a]);
                    cell[0][j] = lo[0];
                    cell[1][j] = lo[1];
                    cell[2][j] = hi[0];
                    cell[3][j] = hi[1];
                }
                cell
            })
            .collect();
        let lanes = (0..t.steps)
            .map(|i| Self::interval_lanes(t.steps, t.reach, i))
            .collect();
        Some(QuadTable {
            steps: t.steps,
            steps_f: t.steps as f64,
            cells,
            lanes,
        })
    }

    /// Marks an interval whose lanes are not fixed.
    const AMBIGUOUS: u8 = 0xFF;

    /// The window lanes `a..b` (as `a | b << 4`) that
    /// [`PixelModel::axis_range`] gives for every centre `c = round(c) +
    /// d` with d in table interval `i`, unclipped, or
    /// [`Self::AMBIGUOUS`].
    ///
    /// Why this is exact: `axis_range` takes round(c ∓ 3σ). Away from a
    /// tie, round(c − 3σ) = round(c) + round(d − 3σ), and d − 3σ stays
    /// between the same two half-integers over the whole interval when
    /// both its ends (widened by 1e-9 px, far more than the rounding of
    /// `c − 3σ` or of the interval index for |c| < 2^20) round alike.
    fn interval_lanes(steps: usize, reach: f64, i: usize) -> u8 {
        const MARGIN: f64 = 1e-9;
        let d0 = -0.5 + i as f64 / steps as f64 - MARGIN;
        let d1 = -0.5 + (i + 1) as f64 / steps as f64 + MARGIN;
        let cell = |e: f64| (e + 0.5).floor() as i64;
        let (lo0, lo1) = (cell(d0 - reach), cell(d1 - reach));
        let (hi0, hi1) = (cell(d0 + reach), cell(d1 + reach));
        if lo0 != lo1 || hi0 != hi1 {
            return Self::AMBIGUOUS;
        }
        let off = Self::window_offset(steps, i);
        let (a, b) = (lo0 - off, hi0 - off + 1);
        if a < 0 || b > 4 || a >= b {
            return Self::AMBIGUOUS;
        }
        (a | b << 4) as u8
    }

    /// First window pixel relative to round(c) for table interval `i`.
    #[inline(always)]
    fn window_offset(steps: usize, i: usize) -> i64 {
        if 2 * i < steps {
            -2
        } else {
            -1
        }
    }

    /// Fractions of the window's four pixels for a centre at `c`: (first
    /// pixel of the window, fractions), as [`FractionTable::eval`]
    /// computes them.
    #[inline(always)]
    fn eval(&self, c: f64) -> (i64, [f32; 4]) {
        let base = round_i64(c);
        let d = c - base as f64;
        let u = (d + 0.5) * self.steps_f;
        // (0 ≤ u ≤ steps; through i64, the short conversions.)
        let i = (u as i64).min(self.steps as i64 - 1) as usize;
        (
            base + Self::window_offset(self.steps, i),
            self.eval_at(i, u),
        )
    }

    /// The window's fractions at table position `u` in interval `i`.
    #[inline(always)]
    fn eval_at(&self, i: usize, u: f64) -> [f32; 4] {
        let t = (u - i as i64 as f64) as f32;
        let t2 = t * t;
        let t3 = t2 * t;
        let (h00, h10) = (2.0 * t3 - 3.0 * t2 + 1.0, t3 - 2.0 * t2 + t);
        let (h01, h11) = (3.0 * t2 - 2.0 * t3, t3 - t2);
        let cell = &self.cells[i];
        let mut out = [0.0f32; 4];
        for j in 0..4 {
            out[j] = h00 * cell[0][j] + h10 * cell[1][j] + h01 * cell[2][j] + h11 * cell[3][j];
        }
        out
    }

    /// [`Self::eval`] with the lanes outside pixels `lo .. lo + n` set to
    /// 0 (window start, fractions), or None when those pixels are not
    /// all in the window.
    #[inline(always)]
    fn eval_masked(&self, c: f64, lo: i64, n: usize) -> Option<(i64, [f32; 4])> {
        let (w, mut v) = self.eval(c);
        let (a, b) = (lo - w, lo - w + n as i64);
        if a < 0 || b > 4 {
            return None;
        }
        // Lanes a..b kept bit for bit, the others +0.0: a bit mask (no
        // branch per lane; the per-lane tests were ~10 % of rendering).
        let keep = &QUAD_LANES[a as usize][b as usize];
        for (x, &m) in v.iter_mut().zip(keep) {
            *x = f32::from_bits(x.to_bits() & m);
        }
        Some((w, v))
    }
}

/// One axis of a small image ([`QuadTable::eval_axis`]).
enum QuadAxis {
    /// No pixel of the ROI is covered.
    Empty,
    /// The covered pixels do not fit the window: take the general path.
    NoFit,
    /// Window start, fractions (zero outside the covered pixels), first
    /// covered pixel and their count.
    Window(i64, [f32; 4], i64, usize),
}

impl QuadTable {
    /// [`PixelModel::axis_range`] of a centre `c` clipped to `[r0, r1]`,
    /// then [`Self::eval_masked`] of those pixels, in one: the same
    /// result. When the window lies inside `[r0, r1]` and its table
    /// interval has fixed lanes ([`Self::interval_lanes`]) the range comes
    /// from the table instead of two more roundings; otherwise (ROI edges,
    /// ~3 % of the intervals) through the two calls.
    #[inline(always)]
    fn eval_axis(&self, model: &PixelModel, c: f64, r0: i64, r1: i64, cap: usize) -> QuadAxis {
        if let Some((w, v, a, b)) = self.eval_axis_table(c, r0, r1) {
            return QuadAxis::Window(w, v, w + a as i64, b - a);
        }
        let (lo, n) = model.axis_range(c, r0, r1, cap);
        if n == 0 {
            return QuadAxis::Empty;
        }
        match self.eval_masked(c, lo, n) {
            Some((w, v)) => QuadAxis::Window(w, v, lo, n),
            None => QuadAxis::NoFit,
        }
    }
}

impl QuadTable {
    /// The table branch of [`Self::eval_axis`] alone: window start,
    /// fractions (zero outside the covered lanes) and the covered lanes
    /// `a..b` of a centre `c` whose window lies inside `[r0, r1]` in an
    /// interval with fixed lanes; None where `eval_axis` takes the two
    /// calls instead.
    #[inline(always)]
    fn eval_axis_table(&self, c: f64, r0: i64, r1: i64) -> Option<(i64, [f32; 4], usize, usize)> {
        if !(c.abs() < (1u64 << 20) as f64) {
            return None;
        }
        let base = round_small(c);
        let d = c - base as f64;
        let u = (d + 0.5) * self.steps_f;
        // (0 ≤ u ≤ steps, finite.)
        let i = (unsafe { u.to_int_unchecked::<i64>() }).min(self.steps as i64 - 1) as usize;
        let lanes = self.lanes[i];
        let w = base + Self::window_offset(self.steps, i);
        if lanes == Self::AMBIGUOUS || w < r0 || w + 3 > r1 {
            return None;
        }
        let (a, b) = ((lanes & 15) as usize, (lanes >> 4) as usize);
        let mut v = self.eval_at(i, u);
        let keep = &QUAD_LANES[a][b];
        for (x, &m) in v.iter_mut().zip(keep) {
            *x = f32::from_bits(x.to_bits() & m);
        }
        Some((w, v, a, b))
    }
}

/// `v.round() as i64` (half away from zero) for |v| < 2^52, like
/// [`round_i64`] but with the truncation unchecked.
#[inline(always)]
fn round_small(v: f64) -> i64 {
    debug_assert!(v.abs() < (1u64 << 52) as f64);
    // (Finite and in range: the caller checked |v|.)
    let t = unsafe { v.to_int_unchecked::<i64>() };
    let r = v - t as f64;
    t + (r >= 0.5) as i64 - (r <= -0.5) as i64
}

/// `QUAD_LANES[a][b]`: all-ones for the lanes a..b of a four-pixel
/// window, zero for the others ([`QuadTable::eval_masked`]).
const QUAD_LANES: [[[u32; 4]; 5]; 5] = {
    let mut t = [[[0u32; 4]; 5]; 5];
    let mut a = 0;
    while a < 5 {
        let mut b = 0;
        while b < 5 {
            let mut j = 0;
            while j < 4 {
                if j >= a && j < b {
                    t[a][b][j] = u32::MAX;
                }
                j += 1;
            }
            b += 1;
        }
        a += 1;
    }
    t
};

/// erf(x) for any x to ~1e-15 ([`erf_series`] with the sign; ±1 beyond 6.5).
fn erf_exact(x: f64) -> f64 {
    let a = x.abs();
    let v = if a > 6.5 { 1.0 } else { erf_series(a) };
    v.copysign(x)
}

/// ln(x) for positive normal x without a libm call or a division:
/// x = 2^e·m, m in [1, 2); the top 7 bits of m pick c = 1 + (i + ½)/128
/// from a table of (1/c, ln c), and ln m = ln c + ln(1 + r) with
/// r = m/c − 1, |r| < 2^-8, by its series to r^5 (truncation < 1e-15,
/// tested against libm to 2e-15 absolute on the response's range). The
/// response takes one per event and one per lit pixel: libm's
/// `log`/`log1p` were ~5 % of the simulator's instructions.
pub struct LnTable {
    /// (1/c_i, ln c_i).
    nodes: [(f64, f64); 128],
}

impl LnTable {
    fn new() -> LnTable {
        let mut nodes = [(0.0, 0.0); 128];
        for (i, n) in nodes.iter_mut().enumerate() {
            let c = 1.0 + (i as f64 + 0.5) / 128.0;
            *n = (1.0 / c, c.ln());
        }
        LnTable { nodes }
    }

    #[inline(always)]
    pub fn ln(&self, x: f64) -> f64 {
        let bits = x.to_bits();
        let e = ((bits >> 52) & 0x7FF) as i64 - 1023;
        let m = f64::from_bits((bits & 0x000F_FFFF_FFFF_FFFF) | 0x3FF0_0000_0000_0000);
        let (inv, ln_c) = self.nodes[((bits >> 45) & 127) as usize];
        let r = m * inv - 1.0;
        let p = r * (1.0 + r * (-0.5 + r * (1.0 / 3.0 + r * (-0.25 + r * 0.2))));
        (e as f64 * std::f64::consts::LN_2 + ln_c) + p
    }
}

/// The process-wide [`LnTable`].
pub fn ln_table() -> &'static LnTable {
    static TABLE: std::sync::OnceLock<LnTable> = std::sync::OnceLock::new();
    TABLE.get_or_init(LnTable::new)
}

/// [`LnTable::ln`] through the process-wide table.
pub fn ln_fast(x: f64) -> f64 {
    ln_table().ln(x)
}

/// `x.ceil() as usize` clamped to 1..=max (NaN → 1), without a libm call.
#[inline]
fn ceil_count(x: f64, max: usize) -> usize {
    if x > max as f64 {
        max
    } else if x > 0.0 {
        // (Through i64: 0 < x ≤ max, the short conversions.)
        let t = x as i64;
        (t + ((t as f64) < x) as i64).clamp(1, max as i64) as usize
    } else {
        1
    }
}

/// erf by cubic Hermite interpolation in a table of erf and its
/// derivative (step 1/64 on [0, 6]; erf = ±1 beyond, within 2e-17). The
/// interpolation error is below 1e-9, better than the rational
/// approximation (1.5e-7) it replaces, at a fraction of the cost (no
/// `exp`); nodes come from [`erf_series`].
pub struct ErfTable {
    /// (erf(x_i), h·erf'(x_i)) at x_i = i·h.
    nodes: Vec<(f64, f64)>,
}

const ERF_TABLE_STEPS_PER_UNIT: f64 = 64.0;
const ERF_TABLE_END: f64 = 6.0;

impl ErfTable {
    fn new() -> ErfTable {
        let h = 1.0 / ERF_TABLE_STEPS_PER_UNIT;
        let n = (ERF_TABLE_END * ERF_TABLE_STEPS_PER_UNIT) as usize;
        let nodes = (0..=n + 1)
            .map(|i| {
                let x = i as f64 * h;
                let d = std::f64::consts::FRAC_2_SQRT_PI * (-x * x).exp();
                (erf_series(x), h * d)
            })
            .collect();
        ErfTable { nodes }
    }

    #[inline(always)]
    pub fn eval(&self, x: f64) -> f64 {
        let ax = x.abs();
        if !(ax < ERF_TABLE_END) {
            return if x.is_nan() { x } else { x.signum() };
        }
        let u = ax * ERF_TABLE_STEPS_PER_UNIT;
        let i = u as usize;
        let t = u - i as f64;
        let (f0, d0) = self.nodes[i];
        let (f1, d1) = self.nodes[i + 1];
        // Cubic Hermite basis on [0, 1].
        let t2 = t * t;
        let t3 = t2 * t;
        let v = (2.0 * t3 - 3.0 * t2 + 1.0) * f0
            + (t3 - 2.0 * t2 + t) * d0
            + (3.0 * t2 - 2.0 * t3) * f1
            + (t3 - t2) * d1;
        v.copysign(x)
    }
}

/// The process-wide erf table (built once, 6 kB).
pub fn erf_table() -> &'static ErfTable {
    static TABLE: std::sync::OnceLock<ErfTable> = std::sync::OnceLock::new();
    TABLE.get_or_init(ErfTable::new)
}

/// erf(x) for 0 ≤ x ≤ 7 to ~1e-15 by the all-positive series
/// erf x = 2/√π · e^{−x²} · Σ 2ⁿ x^{2n+1} / (1·3·…·(2n+1)) (no
/// cancellation); slow, for building the table and testing.
pub fn erf_series(x: f64) -> f64 {
    let mut term = x;
    let mut sum = x;
    let mut n = 0.0;
    while term > 1e-17 * sum {
        n += 1.0;
        term *= 2.0 * x * x / (2.0 * n + 1.0);
        sum += term;
    }
    (std::f64::consts::FRAC_2_SQRT_PI * (-x * x).exp() * sum).min(1.0)
}

thread_local! {
    /// [`PixelModel::render_signals`]' ring (module level, so that tests
    /// can check that a pulse leaves it all-zero).
    static RENDER_RING: std::cell::RefCell<RowRing> =
        const { std::cell::RefCell::new(RowRing::new()) };
}

/// Per-thread accumulation buffer of [`PixelModel::render_pulse`]: `rows`
/// (a power of two) ROI rows, row r in slot r mod rows, and per slot the
/// boxes of the images whose last row it is (drained when the row is
/// complete).
struct RowRing {
    rows: usize,
    width: usize,
    sig: Vec<f32>,
    boxes: Vec<Vec<ImageBox>>,
    profiles: Profiles,
}

/// Scratch axis profiles of [`PixelModel::particle_rows`] (kept per
/// thread: zeroing them per particle was a memset call each).
struct Profiles {
    fx: [f32; MERGE_MAX],
    fy: [f32; MERGE_MAX],
    one: [f32; AXIS_MAX],
}

impl Profiles {
    const fn new() -> Profiles {
        Profiles {
            fx: [0.0; MERGE_MAX],
            fy: [0.0; MERGE_MAX],
            one: [0.0; AXIS_MAX],
        }
    }
}

impl RowRing {
    const fn new() -> RowRing {
        RowRing {
            rows: 1,
            width: 0,
            sig: Vec::new(),
            boxes: Vec::new(),
            profiles: Profiles::new(),
        }
    }

    /// Shape for `rows` × `width` (all-zero, no boxes; a finished pulse
    /// leaves it so).
    fn reset(&mut self, rows: usize, width: usize) {
        debug_assert!(rows.is_power_of_two());
        self.rows = rows;
        self.width = width;
        let stride = width + 2 * RING_PAD;
        if self.sig.len() < rows * stride {
            self.sig.resize(rows * stride, 0.0);
        }
        if self.boxes.len() < rows {
            self.boxes.resize_with(rows, Vec::new);
        }
        debug_assert!(self.boxes.iter().all(|b| b.is_empty()));
        debug_assert!(self.sig.iter().all(|&v| v == 0.0));
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
    use crate::flow::erf;
    use crate::scenario::*;

    /// Snapshots: dense, overlapping, some straddling the ROI edge; jet-
    /// like (v = 0), u = 0, at rest and general velocities.
    fn scene(n: usize, w: f64, h: f64, seed: u64) -> Vec<Snapshot> {
        let mut rng = Pcg64::seed_from_u64(seed);
        (0..n)
            .map(|i| {
                let (u, v) = match i % 4 {
                    0 => (rng.gen_range(-40_000.0..40_000.0), 0.0),
                    1 => (0.0, rng.gen_range(-40_000.0..40_000.0)),
                    2 => (0.0, 0.0),
                    _ => (
                        rng.gen_range(-40_000.0..40_000.0),
                        rng.gen_range(-40_000.0..40_000.0),
                    ),
                };
                Snapshot {
                    x: rng.gen_range(-5.0..w + 5.0),
                    y: rng.gen_range(-5.0..h + 5.0),
                    u,
                    v,
                    brightness: rng.gen_range(0.2..3.0),
                    id: i as u64,
                }
            })
            .collect()
    }

    /// The streak node count with √(u² + v²) and the hypot fallback is
    /// hypot's count exactly, also for speeds whose count ⌈q⌉ sits on an
    /// integer (every count's boundary, approached to the last bit, in
    /// many directions) and for tiny, axis-aligned and huge velocities.
    #[test]
    fn streak_count_is_hypots() {
        for (scale, width) in [(1.0, 10.0), (0.37, 10.0), (3.0, 5.0), (30.0, 7.3)] {
            streak_count_is_hypots_for(scale, width);
        }
    }

    fn streak_count_is_hypots_for(scale: f64, width: f64) {
        let mut sc = Scenario::default();
        sc.sensor = small_sensor();
        sc.light.pulse_width_us = width;
        sc.light.pulse_streaks = Some(PulseStreaks { scale });
        let model = PixelModel::new(&sc, 4);
        let scale = model.streak_scale.unwrap();
        let per_speed = model.shape.end_us * 1e-6 * scale / 0.2;
        let want = |u: f64, v: f64| {
            let len = u.hypot(v) * model.shape.end_us * 1e-6 * scale;
            &model.streak_nodes[ceil_count(len / 0.2, 32) - 1]
        };
        let mut speeds = vec![0.0, 1e-300, 1e-12, 1.0, 1e200, f64::MAX];
        for k in 1..=33 {
            let s = k as f64 / per_speed;
            let mut lo = s;
            let mut hi = s;
            for _ in 0..4 {
                speeds.extend([lo, hi]);
                lo = f64::from_bits(lo.to_bits() - 1);
                hi = f64::from_bits(hi.to_bits() + 1);
            }
            speeds.extend([s * (1.0 - 1e-13), s * (1.0 + 1e-13), s * 0.999, s * 1.001]);
        }
        let mut checked = 0;
        for &speed in &speeds {
            for a in 0..720 {
                let th = a as f64 * (std::f64::consts::TAU / 720.0) + 1e-3;
                let (u, v) = (speed * th.cos(), speed * th.sin());
                for (u, v) in [(u, v), (speed, 0.0), (0.0, -speed)] {
                    let snap = Snapshot {
                        x: 10.0,
                        y: 10.0,
                        u,
                        v,
                        brightness: 1.0,
                        id: 0,
                    };
                    assert!(
                        std::ptr::eq(model.streak_nodes_of(&snap), want(u, v).as_slice()),
                        "({u:e}, {v:e})"
                    );
                    checked += 1;
                }
            }
        }
        assert!(checked > 100_000);
    }

    fn small_sensor() -> Sensor {
        Sensor {
            width: 80,
            height: 60,
            roi: Some(Roi {
                x: 4,
                y: 3,
                width: 70,
                height: 50,
            }),
        }
    }

    #[test]
    fn fast_pixel_signals_match_exact_model() {
        // The fast path (tabulated f32 fractions, merged streaks, ring)
        // against the exact model (erf at every edge, f64 sums): every
        // pixel's summed signal within 1e-5 relative, the same pixels.
        for (streaks, diameter) in [
            (None, 1.3),
            (Some(1.0), 1.5),
            (Some(30.0), 2.5),
            (Some(1.0), 12.0),
            (Some(1.0), 0.3),
        ] {
            let mut sc = Scenario::default();
            sc.sensor = small_sensor();
            sc.optics.particle_diameter_px = diameter;
            sc.light.sawtooth_depth = 0.15;
            sc.light.pulse_streaks = streaks.map(|scale| PulseStreaks { scale });
            let model = PixelModel::new(&sc, 4);
            let snaps = scene(600, 80.0, 60.0, 2);
            let fast = model.pixel_signals(&snaps);
            let exact = model.pixel_signals_reference(&snaps);
            // A merged streak's profile may include a gap pixel no position
            // covers (added as 0): not a pixel of the model.
            let fast: Vec<(u32, f32)> = fast.into_iter().filter(|p| p.1 != 0.0).collect();
            assert_eq!(fast.len(), exact.len(), "{streaks:?} {diameter}");
            let mut worst = 0.0f64;
            for (f, e) in fast.iter().zip(&exact) {
                assert_eq!(f.0, e.0);
                worst = worst.max((f.1 as f64 - e.1).abs() / e.1);
            }
            assert!(
                worst < 1e-5,
                "{streaks:?} {diameter}: relative error {worst:e}"
            );
            // Per particle too (no overlap to hide a wrong pixel).
            for s in snaps.iter().take(100) {
                let mut f: Vec<(u32, u32, f64)> = Vec::new();
                model.particle_contributions_fast(s, |x, y, v| f.push((y, x, v)));
                let mut e: Vec<(u32, u32, f64)> = Vec::new();
                let mut pos = Vec::new();
                model.particle_contributions(s, &mut pos, |x, y, v| e.push((y, x, v)));
                let sum = |v: &mut Vec<(u32, u32, f64)>| {
                    v.sort_by(|a, b| (a.0, a.1).cmp(&(b.0, b.1)));
                    let mut out: Vec<(u32, u32, f64)> = Vec::new();
                    for &(y, x, s) in v.iter() {
                        match out.last_mut() {
                            Some(l) if (l.0, l.1) == (y, x) => l.2 += s,
                            _ => out.push((y, x, s)),
                        }
                    }
                    out.retain(|p| p.2 != 0.0);
                    out
                };
                let (f, e) = (sum(&mut f), sum(&mut e));
                assert_eq!(f.len(), e.len(), "{s:?}");
                for (a, b) in f.iter().zip(&e) {
                    assert_eq!((a.0, a.1), (b.0, b.1));
                    assert!((a.2 - b.2).abs() <= 1e-5 * b.2, "{s:?}: {a:?} vs {b:?}");
                }
            }
            assert_eq!(
                model.render_order(&snaps, false),
                model.render_order(&snaps, true)
            );
        }
        assert_eq!(ceil_count(f64::NAN, 32), 1);
        assert_eq!(ceil_count(-3.0, 32), 1);
        assert_eq!(ceil_count(f64::INFINITY, 32), 32);
        for i in 0..20_000 {
            let x = i as f64 * 0.0017;
            assert_eq!(ceil_count(x, 32), (x.ceil() as usize).clamp(1, 32), "{x}");
        }
    }

    /// A plain [`ContributionSink`]: a dense ROI-sized buffer, only the
    /// covered pixels of each run or window added to.
    struct DenseSink<'a> {
        sig: &'a mut [f32],
        roi: Roi,
        row: usize,
    }

    impl ContributionSink for DenseSink<'_> {
        fn row(&mut self, iy: u32) {
            self.row = (iy - self.roi.y) as usize;
        }
        fn add_run(&mut self, ix0: u32, fractions: &[f32], scale: f32) {
            for (a, &f) in fractions.iter().enumerate() {
                let x = (ix0 - self.roi.x) as usize + a;
                self.sig[self.row * self.roi.width as usize + x] += scale * f;
            }
        }
        fn add_window<const W: usize>(
            &mut self,
            wx: i64,
            window: &[f32; W],
            scale: f32,
            x0: i64,
            n: usize,
        ) {
            for x in x0..x0 + n as i64 {
                let at = self.row * self.roi.width as usize + (x - self.roi.x as i64) as usize;
                self.sig[at] += scale * window[(x - wx) as usize];
            }
        }
    }

    #[test]
    fn drained_hits_match_dense_sums() {
        // The drain (boxes, eight-pixel groups, branch-free hit writes,
        // each box clearing only its own columns) against a dense ROI
        // buffer given the same additions in the same order (particles in
        // render order through `particle_rows`, which the lean paths
        // match bit for bit): every pixel at or above the floor exactly
        // once, with the same f32 sum; and the ring all-zero after each
        // pulse (pulses in a row on one thread: a leftover would also
        // show in a later pulse's sums).
        for (streaks, diameter) in [
            (None, 1.3),
            (Some(1.0), 1.5),
            (Some(3.0), 1.0),
            (Some(30.0), 2.5),
            (Some(1.0), 12.0),
            (Some(1.0), 0.3),
        ] {
            let mut sc = Scenario::default();
            sc.sensor = small_sensor();
            sc.optics.particle_diameter_px = diameter;
            sc.light.pulse_streaks = streaks.map(|scale| PulseStreaks { scale });
            let model = PixelModel::new(&sc, 4);
            let roi = model.roi;
            let w = roi.width;
            for seed in 0..4 {
                // Dense scenes (overlapping images, shared groups) and
                // sparse ones.
                let n = if seed % 2 == 0 { 900 } else { 40 };
                let snaps = scene(n, 80.0, 60.0, 11 + seed);
                let mut dense = vec![0.0f32; (w * roi.height) as usize];
                let mut sink = DenseSink {
                    sig: &mut dense,
                    roi,
                    row: 0,
                };
                let mut prof = Profiles::new();
                for &(key, _, _) in &model.render_order(&snaps, false) {
                    let s = &snaps[(key & 0xFFFF_FFFF) as usize];
                    model.particle_rows(s, &mut prof, &mut sink);
                }
                for floor in [f32::from_bits(1), model.c_floor_f32, 0.05, 0.4] {
                    let mut hits = Vec::new();
                    model.render_signals(&snaps, floor, &mut hits);
                    let mut got: Vec<(u32, u32)> = hits
                        .iter()
                        .map(|h| {
                            let (r, c) = h.row_col();
                            assert!(r < roi.height && c < w, "{r} {c}");
                            (r * w + c, h.v.to_bits())
                        })
                        .collect();
                    got.sort_unstable();
                    let want: Vec<(u32, u32)> = dense
                        .iter()
                        .enumerate()
                        .filter(|(_, &v)| v >= floor)
                        .map(|(i, v)| (i as u32, v.to_bits()))
                        .collect();
                    assert!(
                        got == want,
                        "{streaks:?} {diameter} seed {seed} floor {floor}: {} hits vs {}",
                        got.len(),
                        want.len()
                    );
                    RENDER_RING.with(|cell| {
                        let ring = cell.borrow();
                        assert!(ring.sig.iter().all(|&v| v.to_bits() == 0));
                        assert!(ring.boxes.iter().all(|b| b.is_empty()));
                    });
                }
            }
        }
    }

    #[test]
    fn response_passes_match_respond() {
        // `render_pulse`'s two passes (branch-free threshold pass, then
        // the crossings) against `respond::<false>` (the same fast
        // arithmetic in one plain function) for each pixel the renderer
        // hands over: the same events, bit for bit, for every combination
        // of the switches the passes are specialised on.
        let mut sc = Scenario::default();
        sc.sensor = small_sensor();
        sc.light.pulse_streaks = Some(PulseStreaks { scale: 1.0 });
        for (mismatch, off, jitter, latency) in [
            (false, false, false, false),
            (true, false, false, false),
            (false, true, false, true),
            (true, true, true, true),
            (true, false, true, false),
            (false, true, true, false),
        ] {
            sc.pixel.threshold_mismatch = mismatch.then_some(ThresholdMismatch { sigma: 0.3 });
            sc.pixel.off_events = off.then_some(OffEvents {
                threshold: 0.3,
                tau_us: 15.0,
            });
            sc.pixel.latency_jitter = jitter.then_some(LatencyJitter { spread_us: 2.0 });
            sc.pixel.intensity_latency = latency.then_some(IntensityLatency {
                exponent: 0.5,
                reference: 2.0,
            });
            let model = PixelModel::new(&sc, 4);
            let mut total = 0;
            for pulse in 0..3 {
                let snaps = scene(900, 80.0, 60.0, 5 + pulse);
                let seed = stream_seed(9, 6, pulse);
                let mut fast: Vec<Arrival> = Vec::new();
                model.render_pulse(&snaps, 100.0, seed, &mut fast);
                let mut hits = Vec::new();
                model.render_signals(&snaps, model.c_floor_f32, &mut hits);
                let mut plain: Vec<Arrival> = Vec::new();
                for h in &hits {
                    let (r, c) = h.row_col();
                    let (x, y) = ((model.roi.x + c) as u16, (model.roi.y + r) as u16);
                    let idx = r * model.roi.width + c;
                    model.respond::<false>(idx, x, y, h.v as f64, 100.0, seed, &mut plain);
                }
                assert!(!plain.is_empty());
                assert!(
                    fast == plain,
                    "{mismatch} {off} {jitter} {latency} pulse {pulse}: {} vs {}",
                    fast.len(),
                    plain.len()
                );
                total += plain.len();
            }
            assert!(total > 1000, "{total}");
        }
    }

    #[test]
    fn fast_events_match_exact_model() {
        // Same pixels in the same order: every pixel's events agree
        // (count, and times within 1e-5 of the delay) except where a
        // signal sits within f32 rounding of a threshold crossing. The
        // jitter draws are keyed by (pulse, pixel, crossing, polarity),
        // so this holds with jitter on as well (with a sequential stream
        // a mismatched pixel shifted every later pixel's draws).
        let mut sc = Scenario::default();
        sc.sensor = Sensor {
            width: 400,
            height: 300,
            roi: Some(Roi {
                x: 3,
                y: 5,
                width: 390,
                height: 290,
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
        let compare = |sc: &Scenario, pulses: u64| {
            let model = PixelModel::new(sc, 4);
            let (mut fast, mut exact) = (Vec::new(), Vec::new());
            for pulse in 0..pulses {
                let snaps = scene(6000, 400.0, 300.0, 1 + 9 * pulse);
                let seed = stream_seed(9, 6, pulse);
                let (f0, e0) = (fast.len(), exact.len());
                model.render_pulse(&snaps, 100.0, seed, &mut fast);
                model.render_pulse_reference(&snaps, 100.0, seed, &mut exact);
                // The fast path hands pixels over in the order their
                // images finish: per pulse into pixel order (stable, so
                // a pixel's events keep theirs).
                let by_pixel = |a: &Arrival| (a.y, a.x, a.p);
                fast[f0..].sort_by_key(by_pixel);
                exact[e0..].sort_by_key(by_pixel);
            }
            assert!(exact.len() > 5000 * pulses as usize, "{}", exact.len());
            let key = |a: &Arrival| (a.y, a.x, a.p);
            let mut mismatched = 0;
            let (mut i, mut j) = (0, 0);
            while i < fast.len() && j < exact.len() {
                // Events of one pixel and polarity are consecutive in both.
                let k = key(&fast[i]).min(key(&exact[j]));
                let fi = fast[i..].iter().take_while(|a| key(a) == k).count();
                let ej = exact[j..].iter().take_while(|a| key(a) == k).count();
                if fi == ej {
                    for (a, b) in fast[i..i + fi].iter().zip(&exact[j..j + ej]) {
                        // (f32 signals: ~1e-7, amplified up to ~20× near the
                        // last crossing of a pixel, where ln(1 − 0.95·kC/ΔL)
                        // is steep.)
                        assert!(
                            (a.t - b.t).abs() < 1e-5 * (b.t - 100.0) + 1e-6,
                            "{a:?} vs {b:?}"
                        );
                    }
                } else {
                    mismatched += 1;
                }
                i += fi;
                j += ej;
            }
            assert!(i == fast.len() && j == exact.len());
            assert!(
                mismatched * 2000 <= exact.len(),
                "{mismatched} of {}",
                exact.len()
            );
            let d = fast.len().abs_diff(exact.len());
            assert!(d * 1000 <= exact.len(), "{} vs {}", fast.len(), exact.len());
            assert!(fast
                .iter()
                .all(|a| (3..393).contains(&a.x) && (5..295).contains(&a.y)));
            fast
        };
        let plain = compare(&sc, 1);
        // All effects: the jitter moves times, not which pixels fire.
        sc.pixel.latency_jitter = Some(LatencyJitter { spread_us: 2.0 });
        let jittered = compare(&sc, 3);
        assert!(jittered.len() > 2 * plain.len());
        let moved = jittered[..plain.len()]
            .iter()
            .zip(&plain)
            .filter(|(a, b)| a.t != b.t)
            .count();
        assert!(moved * 10 > plain.len() * 9, "jitter moved {moved}");
    }

    #[test]
    fn lean_images_match_particle_rows() {
        // The lean renderer writes the ring bit for bit as
        // `particle_rows` does through its sink, with the same box, for
        // every particle it takes (and takes most of them).
        for (streaks, diameter) in [
            (Some(1.0), 1.5),
            (None, 1.3),
            (Some(3.0), 1.0),
            (Some(1.0), 0.3),
            (Some(8.0), 1.99),
        ] {
            let mut sc = Scenario::default();
            sc.sensor = small_sensor();
            sc.optics.particle_diameter_px = diameter;
            sc.light.sawtooth_depth = 0.15;
            sc.light.pulse_streaks = streaks.map(|scale| PulseStreaks { scale });
            let model = PixelModel::new(&sc, 4);
            let q = model.quad.as_ref().expect("small images");
            let rw = model.roi.width as usize;
            let stride = rw + 2 * RING_PAD;
            let rows = (model.roi.height as usize).next_power_of_two();
            let mut taken = 0;
            let snaps = scene(3000, 80.0, 60.0, 7);
            for s in &snaps {
                let mut lean = vec![0.0f32; rows * stride];
                let Some(bx) = model.particle_lean(q, s, &mut lean, rows - 1, stride) else {
                    continue;
                };
                taken += 1;
                let mut plain = vec![0.0f32; rows * stride];
                let mut sink = RingRows {
                    sig: &mut plain,
                    mask: rows - 1,
                    stride,
                    roi_x: model.roi.x,
                    roi_y: model.roi.y,
                    sig_at: 0,
                    row: 0,
                    bx: ImageBox::EMPTY,
                };
                model.particle_rows(s, &mut Profiles::new(), &mut sink);
                let want = sink.bx;
                assert_eq!(
                    (bx.col0, bx.col1, bx.row0, bx.row1),
                    (want.col0, want.col1, want.row0, want.row1),
                    "{s:?}"
                );
                for (a, b) in lean.iter().zip(&plain) {
                    assert_eq!(a.to_bits(), b.to_bits(), "{s:?}");
                }
            }
            // (Half of the scene's particles move with v ≠ 0 and u ≠ 0,
            // some sit at the ROI's edge or streak over more than
            // LEAN_NODES positions: not lean. Enough to exercise it.)
            assert!(taken * 8 > snaps.len(), "{streaks:?} {diameter}: {taken}");
        }
    }

    /// The lean diagonal-streak kernel (`particle_lean_diagonal`)
    /// against `particle_rows` through its sink: diagonal streaks of
    /// every direction, 2 ..= LEAN_NODES positions (and longer ones,
    /// which it must decline), centres all over the sub-pixel range and
    /// along the ROI's edges, added onto a ring that already holds sums
    /// (so the order of the additions counts): the same ring bit for bit
    /// and the same box.
    #[test]
    fn diagonal_streaks_match_particle_rows() {
        for (scale, diameter) in [(1.0, 1.5), (1.0, 1.3), (2.5, 1.0), (1.0, 0.3), (4.0, 1.99)] {
            let mut sc = Scenario::default();
            sc.sensor = small_sensor();
            sc.optics.particle_diameter_px = diameter;
            sc.light.sawtooth_depth = 0.15;
            sc.light.pulse_streaks = Some(PulseStreaks { scale });
            let model = PixelModel::new(&sc, 4);
            let q = model.quad.as_ref().expect("small images");
            let rw = model.roi.width as usize;
            let stride = rw + 2 * RING_PAD;
            let rows = (model.roi.height as usize).next_power_of_two();
            // Speed of a streak of `k` positions (node count ⌈q⌉ = k).
            let per_speed = model.shape.end_us * 1e-6 * scale / 0.2;
            let (rx0, ry0) = (model.roi.x as f64, model.roi.y as f64);
            let (rx1, ry1) = (
                rx0 + model.roi.width as f64 - 1.0,
                ry0 + model.roi.height as f64 - 1.0,
            );
            let mut rng = Pcg64::seed_from_u64(diameter.to_bits() ^ scale.to_bits());
            let mut base = vec![0.0f32; rows * stride];
            for (i, v) in base.iter_mut().enumerate() {
                let col = i % stride;
                if (RING_PAD..RING_PAD + rw).contains(&col) {
                    *v = rng.gen_range(0.0..2.0);
                }
            }
            let (mut taken, mut interior, mut interior_taken, mut long_taken) = (0, 0, 0, 0);
            for n in 0..6000 {
                let k = 2 + n % (LEAN_NODES + 2);
                let q_count = k as f64 - rng.gen_range(0.0..1.0);
                let speed = q_count / per_speed;
                let th = rng.gen_range(0.0..std::f64::consts::TAU);
                let (u, v) = (speed * th.cos(), speed * th.sin());
                // Interior, or hugging one of the ROI's edges.
                let (x, y) = match n % 5 {
                    0 => (rx0 + rng.gen_range(-1.5..2.5), rng.gen_range(ry0..ry1)),
                    1 => (rx1 + rng.gen_range(-2.5..1.5), rng.gen_range(ry0..ry1)),
                    2 => (rng.gen_range(rx0..rx1), ry0 + rng.gen_range(-1.5..2.5)),
                    3 => (rng.gen_range(rx0..rx1), ry1 + rng.gen_range(-2.5..1.5)),
                    _ => (
                        rng.gen_range(rx0 + 3.0..rx1 - 3.0),
                        rng.gen_range(ry0 + 3.0..ry1 - 3.0),
                    ),
                };
                let s = Snapshot {
                    x,
                    y,
                    u,
                    v,
                    brightness: rng.gen_range(0.2..3.0),
                    id: n as u64,
                };
                if u == 0.0 || v == 0.0 {
                    continue;
                }
                let inside = n % 5 == 4 && k <= LEAN_NODES;
                interior += inside as usize;
                let mut lean = base.clone();
                let Some(bx) = model.particle_lean(q, &s, &mut lean, rows - 1, stride) else {
                    continue;
                };
                taken += 1;
                interior_taken += inside as usize;
                let m = model.streak_nodes_of(&s).len();
                assert!((2..=LEAN_NODES).contains(&m), "{s:?}: {m} positions");
                long_taken += (m == LEAN_NODES) as usize;
                let mut plain = base.clone();
                let mut sink = RingRows {
                    sig: &mut plain,
                    mask: rows - 1,
                    stride,
                    roi_x: model.roi.x,
                    roi_y: model.roi.y,
                    sig_at: 0,
                    row: 0,
                    bx: ImageBox::EMPTY,
                };
                model.particle_rows(&s, &mut Profiles::new(), &mut sink);
                let want = sink.bx;
                assert_eq!(
                    (bx.col0, bx.col1, bx.row0, bx.row1),
                    (want.col0, want.col1, want.row0, want.row1),
                    "{s:?}"
                );
                for (i, (a, b)) in lean.iter().zip(&plain).enumerate() {
                    assert_eq!(a.to_bits(), b.to_bits(), "{s:?} at {i}");
                }
                assert!(lean != base, "{s:?}: nothing written");
            }
            // Most interior streaks with up to LEAN_NODES positions are
            // taken (not those in an ambiguous interval); some at the
            // edges too.
            assert!(
                interior_taken * 10 > interior * 8,
                "{scale} {diameter}: {interior_taken} of {interior}"
            );
            assert!(
                taken > interior_taken && long_taken > 0,
                "{scale} {diameter}"
            );
        }
    }

    #[test]
    fn quad_path_matches_general_fast_path_exactly() {
        // The four-pixel windows give the general table's numbers bit for
        // bit (0 outside the image's pixels) ...
        for diameter in [0.3, 1.0, 1.3, 1.5, 1.99] {
            let sigma = diameter / 4.0;
            let table = FractionTable::new(sigma);
            let q = QuadTable::new(&table).expect("σ < ½");
            let mut rng = Pcg64::seed_from_u64(21);
            for _ in 0..20_000 {
                let c: f64 = rng.gen_range(-3.0..50.0);
                let (lo, hi) = (round_i64(c - 3.0 * sigma), round_i64(c + 3.0 * sigma));
                let n = (hi - lo + 1) as usize;
                let mut want = vec![0.0f32; n];
                table.eval(c, lo, &mut want);
                let (w, v) = q.eval_masked(c, lo, n).expect("the image fits the window");
                for (a, &f) in v.iter().enumerate() {
                    let px = w + a as i64;
                    if (lo..=hi).contains(&px) {
                        assert_eq!(f.to_bits(), want[(px - lo) as usize].to_bits(), "{c}");
                    } else {
                        assert_eq!(f, 0.0);
                    }
                }
            }
        }
        assert!(QuadTable::new(&FractionTable::new(0.5)).is_none());
        // ... so whole pulses (single images, merged streaks, general and
        // too-long streaks that fall back, ROI edges) give the same
        // per-pixel signals as the general fast path, bit for bit.
        for (streaks, diameter) in [
            (None, 1.3),
            (Some(1.0), 1.5),
            (Some(30.0), 1.5),
            (Some(1.0), 0.3),
            (Some(3.0), 1.99),
        ] {
            let mut sc = Scenario::default();
            sc.sensor = small_sensor();
            sc.optics.particle_diameter_px = diameter;
            sc.light.pulse_streaks = streaks.map(|scale| PulseStreaks { scale });
            let model = PixelModel::new(&sc, 4);
            assert!(model.quad.is_some());
            let mut general = PixelModel::new(&sc, 4);
            general.quad = None;
            let snaps = scene(600, 80.0, 60.0, 3);
            let (a, b) = (model.pixel_signals(&snaps), general.pixel_signals(&snaps));
            assert_eq!(a.len(), b.len(), "{streaks:?} {diameter}");
            for (x, y) in a.iter().zip(&b) {
                assert_eq!((x.0, x.1.to_bits()), (y.0, y.1.to_bits()));
            }
        }
    }

    /// `QuadTable::eval_axis` (lanes from the interval table) against
    /// `axis_range` + `eval_masked` (the two extra roundings): the same
    /// window, fractions (bit for bit), first pixel and count, for centres
    /// all over the sub-pixel range, at and next to every table node and
    /// rounding boundary of c ± 3σ, and at the ROI's edges.
    #[test]
    fn quad_axis_lanes_match_axis_range() {
        for diameter in [0.6, 1.0, 1.3, 1.5, 1.9] {
            let mut sc = Scenario::default();
            sc.sensor = small_sensor();
            sc.optics.particle_diameter_px = diameter;
            let model = PixelModel::new(&sc, 1);
            let q = model.quad.as_ref().expect("small images");
            let reach = 3.0 * model.sigma_img;
            let amb = q
                .lanes
                .iter()
                .filter(|&&l| l == QuadTable::AMBIGUOUS)
                .count();
            assert!(
                amb * 10 <= q.lanes.len(),
                "{amb} of {} ambiguous",
                q.lanes.len()
            );
            let mut centres = Vec::new();
            let mut rng = Pcg64::seed_from_u64(diameter.to_bits());
            for _ in 0..20_000 {
                centres.push(rng.gen_range(-3.0..70.0));
            }
            for base in [0.0f64, 1.0, 17.0, 30.0, 62.0, 63.0, 1000.0] {
                for i in 0..=q.steps {
                    let d = -0.5 + i as f64 / q.steps as f64;
                    for e in [-1e-12, 0.0, 1e-12] {
                        centres.push(base + d + e);
                    }
                }
                for k in [-2.0f64, -1.0, 0.0, 1.0, 2.0] {
                    for sign in [-1.0, 1.0] {
                        let c = base + k + 0.5 + sign * reach;
                        for e in [-1e-9, -1e-13, 0.0, 1e-13, 1e-9] {
                            centres.push(c + e);
                        }
                    }
                }
            }
            let (r0, r1) = (0i64, 63i64);
            for &c in &centres {
                let got = q.eval_axis(&model, c, r0, r1, X_CAP);
                let (lo, n) = model.axis_range(c, r0, r1, X_CAP);
                match (got, n) {
                    (QuadAxis::Empty, 0) => {}
                    (QuadAxis::Window(w, v, glo, gn), _) => {
                        let (ew, ev) = q.eval_masked(c, lo, n).expect("fits");
                        assert_eq!((w, glo, gn), (ew, lo, n), "c = {c}");
                        let bits = |a: [f32; 4]| a.map(f32::to_bits);
                        assert_eq!(bits(v), bits(ev), "c = {c}");
                    }
                    (QuadAxis::NoFit, _) => assert!(n > 0 && q.eval_masked(c, lo, n).is_none()),
                    (QuadAxis::Empty, _) => panic!("c = {c}: empty, expected {n} pixels"),
                }
            }
        }
    }

    /// The screened bisection of the quantile table gives the plain
    /// bisection's numbers, bit for bit, at every node.
    #[test]
    fn normal_quantiles_screening_is_exact() {
        let table = normal_quantiles();
        for i in 0..=4096 {
            let plain = normal_quantile_bisection(i, false);
            assert_eq!(table[i].to_bits(), plain.to_bits(), "node {i}");
        }
    }

    #[test]
    fn fraction_table_matches_erf() {
        for sigma in [0.025, 0.1, 0.325, 0.375, 1.0, 5.0] {
            let t = FractionTable::new(sigma);
            let k = std::f64::consts::FRAC_1_SQRT_2 / sigma;
            let mut rng = Pcg64::seed_from_u64(3);
            let mut worst = 0.0f64;
            for _ in 0..5000 {
                let c: f64 = rng.gen_range(-3.0..50.0);
                let reach = 3.0 * sigma;
                let (lo, hi) = (round_i64(c - reach), round_i64(c + reach));
                let n = (hi - lo + 1) as usize;
                let mut out = vec![0.0f32; n];
                t.eval(c, lo, &mut out);
                for (a, &f) in out.iter().enumerate() {
                    let i = (lo + a as i64) as f64;
                    let e = 0.5 * (erf_exact((i + 0.5 - c) * k) - erf_exact((i - 0.5 - c) * k));
                    worst = worst.max((f as f64 - e).abs() / e);
                }
            }
            assert!(worst < 1e-5, "sigma {sigma}: {worst:e}");
        }
    }

    #[test]
    fn ln_table_matches_libm() {
        let mut rng = Pcg64::seed_from_u64(5);
        for _ in 0..200_000 {
            let x: f64 = 10f64.powf(rng.gen_range(-3.0..3.0));
            let (f, e) = (ln_fast(x), x.ln());
            assert!((f - e).abs() <= 2e-15 * e.abs().max(1.0), "{x}: {f} vs {e}");
        }
        for x in [1.0, 2.0, 0.5, 1.0 - 1e-9, 1.0 + 1e-9, 0.05, 0.9999] {
            assert!((ln_fast(x) - x.ln()).abs() <= 2e-15, "{x}");
        }
    }

    #[test]
    fn erf_table_is_accurate_and_round_matches() {
        let t = erf_table();
        // Known values (Abramowitz & Stegun, table 7.1).
        for (x, e) in [
            (0.5, 0.520_499_877_813_046_5),
            (1.0, 0.842_700_792_949_714_9),
            (2.0, 0.995_322_265_018_952_7),
            (3.0, 0.999_977_909_503_001_4),
        ] {
            assert!((erf_series(x) - e).abs() < 1e-14, "series {x}");
            assert!((t.eval(x) - e).abs() < 1e-9, "table {x}");
            assert!((t.eval(-x) + e).abs() < 1e-9, "table {}", -x);
        }
        let mut worst = 0.0f64;
        let mut worst_as = 0.0f64;
        for i in 0..70_000 {
            let x = i as f64 * 1e-4 + 0.5e-4;
            worst = worst.max((t.eval(x) - erf_series(x)).abs());
            worst_as = worst_as.max((erf(x) - erf_series(x)).abs());
        }
        assert!(worst < 1e-9, "table error {worst:e}");
        // The table is far closer than the rational approximation it replaces.
        assert!(worst < worst_as / 50.0, "{worst:e} vs {worst_as:e}");
        assert_eq!(t.eval(0.0), 0.0);
        assert_eq!(t.eval(9.0), 1.0);
        assert_eq!(t.eval(-9.0), -1.0);
        for i in -40_000i64..40_000 {
            let v = i as f64 * 0.000_25 + [0.0, 1e-12, -1e-12][(i % 3).unsigned_abs() as usize];
            assert_eq!(round_i64(v), v.round() as i64, "{v}");
        }
        // Around ±2^52 (where the fraction test stops mattering), NaN.
        let big = 4_503_599_627_370_496.0f64; // 2^52
        for v in [
            big - 0.5,
            big - 1.5,
            big,
            big + 2.0,
            -big + 0.5,
            -big,
            -big - 2.0,
            1e17,
            -1e17,
        ] {
            assert_eq!(round_i64(v), v.round() as i64, "{v}");
        }
        assert_eq!(round_i64(f64::NAN), 0);
    }

    #[test]
    fn f32_floor_test_equals_f64_test() {
        let mut rng = Pcg64::seed_from_u64(17);
        let mut xs: Vec<f64> = (0..2000).map(|_| rng.gen_range(1e-3..5.0)).collect();
        // Values exactly representable in f32, and the presets' floors.
        xs.extend([0.25, 0.125, 1.0, 0.25 * 0.05, 0.25 * (1.0 - 3.668 * 0.1)]);
        for x in xs {
            let f = f32_at_least(x);
            let near = x as f32;
            for v in [
                near.next_down().next_down(),
                near.next_down(),
                near,
                near.next_up(),
                near.next_up().next_up(),
                0.0,
                f32::INFINITY,
            ] {
                assert_eq!(v >= f, v as f64 >= x, "x {x:e} v {v:e}");
            }
        }
    }

    #[test]
    fn table_normal_moments_and_quantiles() {
        // Exact moments of the table distribution: bin i is uniform on
        // [q_i, q_{i+1}] with mass 1/4096.
        let q = normal_quantiles();
        let (mut m1, mut m2, mut m4) = (0.0, 0.0, 0.0);
        for i in 0..4096 {
            let (a, b) = (q[i], q[i + 1]);
            let pow = |k: i32| (b.powi(k + 1) - a.powi(k + 1)) / ((k + 1) as f64 * (b - a));
            m1 += pow(1) / 4096.0;
            m2 += pow(2) / 4096.0;
            m4 += pow(4) / 4096.0;
        }
        let kurt = m4 / (m2 * m2);
        eprintln!("table normal: mean {m1:e} variance {m2:.5} kurtosis {kurt:.4}");
        assert!(m1.abs() < 1e-12, "{m1}");
        assert!((m2 - 0.99946).abs() < 1e-5, "{m2}");
        assert!((kurt - 2.9867).abs() < 1e-3, "{kurt}");
        // Distribution function: exact at the inner bin edges, and inside a
        // bin off the normal's by at most the curvature over one bin (the
        // largest in the outer bins, where the density changes fastest).
        let cdf = |g: f64| 0.5 * (1.0 + erf_series(g.abs() / std::f64::consts::SQRT_2).copysign(g));
        let mut worst: f64 = 0.0;
        for i in 1..4095 {
            assert!((cdf(q[i]) - i as f64 / 4096.0).abs() < 1e-12, "node {i}");
            let mid = 0.5 * (q[i] + q[i + 1]);
            worst = worst.max((cdf(mid) - (i as f64 + 0.5) / 4096.0).abs());
        }
        eprintln!("table normal: largest |ΔF| inside a bin {worst:e}");
        assert!(worst < 2e-5, "{worst}");
        // The bound the tails stop at.
        assert!((q[0] + 3.66833).abs() < 1e-5 && (q[4096] - 3.66833).abs() < 1e-5);
        // Keyed draws (crossings k of consecutive pixels, both
        // polarities, as the jitter takes them): sample moments and
        // quantiles. 2^20 draws: standard errors 1e-3 (mean), 1.4e-3
        // (variance), 2e-4 (P(|g| > 2)), 5e-5 (P(|g| > 3)).
        let key = stream_seed(11, 6, 3);
        let mut g = Vec::with_capacity(1 << 20);
        for idx in 0..(1u64 << 17) {
            for k in 1..=4 {
                for p in [ON, OFF] {
                    g.push(table_normal(q, crossing_draw_key(key ^ (idx << 8), k, p)));
                }
            }
        }
        let n = g.len() as f64;
        let mean = g.iter().sum::<f64>() / n;
        let var = g.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n;
        let beyond = |k: f64| g.iter().filter(|v| v.abs() > k).count() as f64 / n;
        eprintln!(
            "keyed draws: mean {mean:.5} var {var:.5} P(|g|>1) {:.5} P(|g|>2) {:.5} P(|g|>3) {:.6}",
            beyond(1.0),
            beyond(2.0),
            beyond(3.0)
        );
        assert!(mean.abs() < 5e-3, "{mean}");
        assert!((var - 0.99946).abs() < 7e-3, "{var}");
        assert!((beyond(1.0) - 0.31731).abs() < 2.5e-3, "{}", beyond(1.0));
        assert!((beyond(2.0) - 0.04550).abs() < 1e-3, "{}", beyond(2.0));
        assert!((beyond(3.0) - 0.00270).abs() < 2.5e-4, "{}", beyond(3.0));
        // Neighbouring crossings are uncorrelated.
        let lag: f64 = g.windows(2).map(|w| w[0] * w[1]).sum::<f64>() / n;
        assert!(lag.abs() < 5e-3, "lag-1 correlation {lag}");
    }

    #[test]
    fn mismatch_pattern_is_gaussian_fixed_and_seeded() {
        let (sigma, key) = (0.1, stream_key(7, 2));
        let f: Vec<f64> = (0..200_000u32)
            .map(|i| PixelModel::mismatch_factor(sigma, key, i))
            .collect();
        let n = f.len() as f64;
        let mean = f.iter().sum::<f64>() / n;
        let sd = (f.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n).sqrt();
        // Standard errors: 2.2e-4 (mean), 1.6e-4 (sd).
        assert!((mean - 1.0).abs() < 1e-3, "{mean}");
        assert!((sd - sigma).abs() < 1e-3, "{sd}");
        // Gaussian tails: P(|g| > 2) = 4.55 %, P(|g| > 3) = 0.27 %.
        // (Standard errors 0.05 % and 0.01 %.)
        let beyond = |k: f64| f.iter().filter(|v| (*v - 1.0).abs() > k * sigma).count() as f64 / n;
        assert!((beyond(2.0) - 0.0455).abs() < 0.002, "{}", beyond(2.0));
        assert!((beyond(3.0) - 0.0027).abs() < 0.0005, "{}", beyond(3.0));
        // Fixed per pixel, different for another seed.
        assert_eq!(PixelModel::mismatch_factor(sigma, key, 123), f[123]);
        let other = stream_key(8, 2);
        let same = (0..1000u32)
            .filter(|&i| PixelModel::mismatch_factor(sigma, other, i) == f[i as usize])
            .count();
        assert!(same < 5, "{same}");
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
