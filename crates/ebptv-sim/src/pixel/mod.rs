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
//! - `latency_jitter`: a Gaussian delay per visit (one pixel's crossings of
//!   one polarity at one pulse): every crossing of the visit is shifted by
//!   the same draw, so a pixel's events keep the photoreceptor's order and
//!   spacing. A pixel's latency varies with the state of its
//!   photoreceptor and comparator at the pulse, which all its crossings
//!   of that pulse share; independent draws per event would make a pixel
//!   that fires more events fire its first one earlier by order
//!   statistics alone (the first of k draws), a brightness dependence of
//!   the latency that the pixel does not have;
//! - `off_events`: when the pulse ends the signal decays with `tau_us` of
//!   the effect and crosses the OFF threshold floor(ΔL/C_off) times.
//!
//! Refractory period, noise and readout live in `readout`.

use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Poisson};
use rand_pcg::Pcg64;

use crate::light::{envelope, PulseShape};
use crate::scenario::{Light, Roi, Scenario};
use crate::seeding::Snapshot;
use crate::{stream_key, stream_seed};

/// Threshold-mismatch deviates are clamped to ±this many σ …
const MISMATCH_CLAMP: f64 = 6.0;
/// … and the factor to at least this.
const MIN_MISMATCH_FACTOR: f64 = 0.05;
use ebptv_io::events::{OFF, ON};

/// An event as it leaves the pixel (before the readout timestamps it).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Arrival {
    /// Time the pixel requests readout (µs, fractional).
    pub t: f64,
    /// Column (px).
    pub x: u16,
    /// Row (px).
    pub y: u16,
    /// Polarity (`ON` or `OFF`).
    pub p: u8,
}

/// The event pixels of a scenario: turns particle images at each pulse into pixel events.
pub(crate) struct PixelModel {
    roi: Roi,
    /// The light sheet (the exact model of the tests reads its envelope).
    #[cfg(feature = "testkit")]
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
    #[cfg(feature = "testkit")]
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
    /// The pixel model of scenario `sc`; `seed` fixes the fixed-pattern and per-event draws.
    pub(crate) fn new(sc: &Scenario, seed: u64) -> PixelModel {
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
            #[cfg(feature = "testkit")]
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
            #[cfg(feature = "testkit")]
            c_floor,
            c_floor_f32: f32_at_least(c_floor),
            quad: QuadTable::new(&table),
            table,
            ln: ln_table(),
            quantiles: normal_quantiles(),
        }
    }

    /// Hot pixels (x, y, rate Hz), for tests and diagnostics.
    pub(crate) fn hot_pixels(&self) -> &[(u16, u16, f64)] {
        &self.hot
    }
}

impl PixelModel {
    /// Events of every lit pixel for one pulse starting at `t_pulse_us`:
    /// [`Self::render_signals`] hands over the pixels at or above the
    /// lowest threshold (`c_floor`; most pixels of an image, its rim, are
    /// below), then each pixel's response. The pixels come in the order
    /// their images are finished, not in ROI-index order: the random
    /// draws are keyed by pixel and polarity ([`visit_draw_key`]), so
    /// the order changes only the order of the requests, which the
    /// readout sorts.
    pub(crate) fn render_pulse(
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
        // One delay per visit and polarity ([`visit_draw_key`]): every
        // crossing of the visit is shifted by it.
        let delay = |pixel_key: u64, p: u8| {
            if JITTER {
                j * table_normal(q, visit_draw_key(pixel_key, p))
            } else {
                0.0
            }
        };
        let jitter = |t: f64, d: f64| {
            if JITTER {
                let t = t + d;
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
                Some((0.5, r)) => self.tau_us * (r / p.sig).sqrt().min(100.0),
                Some((e, r)) => self.tau_us * (r / p.sig).powf(e).min(100.0),
                None => self.tau_us,
            };
            let pixel_key = pulse_key ^ ((p.idx as u64) << 8);
            let mut n = 0;
            let step_on = p.c / p.dl;
            let d_on = delay(pixel_key, ON);
            for k in 1..=p.n_on {
                let frac = 0.95 * (k as f64 * step_on).min(1.0);
                times[n] = jitter(t_on + tau * -ln.ln(1.0 - frac), d_on);
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
                let d_off = delay(pixel_key, OFF);
                for k in 1..=n_off {
                    let frac = 0.95 * (k as f64 * step_off).min(1.0);
                    times[n] = jitter(t_off + tau_off * -ln.ln(1.0 - frac), d_off);
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
    /// (tests compare it with `pixel_signals_reference` (in the tests)).
    #[cfg(feature = "testkit")]
    pub(crate) fn pixel_signals(&self, snaps: &[Snapshot]) -> Vec<(u32, f32)> {
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
    #[cfg(feature = "testkit")]
    pub(crate) fn pixel_signals_reference(&self, snaps: &[Snapshot]) -> Vec<(u32, f64)> {
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
                self.draw_particle(s, profiles, &mut sink);
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
    #[cfg(feature = "testkit")]
    pub(crate) fn render_pulse_reference(
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

    #[cfg(feature = "testkit")]
    /// Threshold factor of ROI pixel `idx` under `threshold_mismatch`
    /// (σ, key): 1 + σ·g with g a standard normal deviate chosen by a hash
    /// of the pixel index, so the pattern is fixed for a seed. g is one of
    /// 4096 equiprobable bins of the normal quantile function (table
    /// lookup, no `ln`/`cos`), interpolated linearly within the bin: a
    /// Gaussian except that the tails stop at ±3.67σ (the 1/8192
    /// quantile), so a 1280×720 array lacks its ~225 most extreme pixels.
    #[inline]
    pub(crate) fn mismatch_factor(sigma: f64, key: u64, idx: u32) -> f64 {
        Self::mismatch_factor_in(normal_quantiles(), sigma, key, idx)
    }

    /// [`Self::mismatch_factor`] with the quantile table at hand (no
    /// once-lock check per pixel).
    #[inline(always)]
    fn mismatch_factor_in(q: &[f64; 4097], sigma: f64, key: u64, idx: u32) -> f64 {
        let g = table_normal(q, crate::splitmix(key ^ idx as u64));
        (1.0 + sigma * g.clamp(-MISMATCH_CLAMP, MISMATCH_CLAMP)).max(MIN_MISMATCH_FACTOR)
    }

    /// The events of ROI pixel `idx` (sensor `x`, `y`) for a pulse signal
    /// `sig` starting at `t0`. `EXACT`: libm's logarithms (the reference);
    /// otherwise [`LnTable::ln`] (error < 1e-14, far below the 1 ns time
    /// resolution).
    #[allow(clippy::too_many_arguments)]
    #[inline]
    #[cfg(feature = "testkit")]
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
            Some((0.5, r)) => self.tau_us * (r / sig).sqrt().min(100.0),
            Some((e, r)) => self.tau_us * (r / sig).powf(e).min(100.0),
            None => self.tau_us,
        };
        // Times go to the sink in batches of a pixel's events.
        let mut times = [0.0f64; 16];
        let mut n = 0;
        // The delay of the visit's crossings of polarity p: a keyed draw
        // ([`visit_draw_key`]), so it does not depend on which other
        // pixels were computed before.
        let pixel_key = pulse_key ^ ((idx as u64) << 8);
        let jitter = |t: f64, p: u8| match self.jitter_us {
            Some(j) => {
                let g = table_normal(self.quantiles, visit_draw_key(pixel_key, p));
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
            times[n] = jitter(t0 + self.latency_us + tau * -ln(1.0 - frac), ON);
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
    pub(crate) fn noise(&self, t0: f64, t1: f64, block_seed: u64, out: &mut Vec<Arrival>) {
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

/// The hash whose bits give the latency jitter of a visit: the crossings
/// of polarity `p` of one pixel at one pulse, `pixel_key` = pulse key ^
/// (ROI index << 8). Every (pixel, polarity) of a pulse has its own input,
/// so the draws are independent of each other and of the order they are
/// taken in (a keyed, counter-based stream instead of one sequential
/// generator per pulse).
#[inline(always)]
pub(crate) fn visit_draw_key(pixel_key: u64, p: u8) -> u64 {
    crate::splitmix(pixel_key ^ (2 | p as u64))
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
pub(crate) trait ArrivalSink {
    /// Receives one event.
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

fn poisson(rng: &mut Pcg64, mean: f64) -> u64 {
    if mean <= 0.0 {
        return 0;
    }
    Poisson::new(mean)
        .map(|d| d.sample(rng) as u64)
        .unwrap_or(0)
}

pub(crate) mod drain;
mod render;
mod tables;

use drain::*;
use render::*;
pub(crate) use tables::*;

#[cfg(feature = "testkit")]
pub(crate) mod tests;
