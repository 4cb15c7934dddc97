//! The local flow seen by the tracker's established tracks, and the ghost
//! test of short tracks against it.
//!
//! # Why
//! A track of four or five detections cannot prove on its own that it is
//! one particle: in a seeding of 0.01 particles per pixel, four images of
//! *different* particles line up within the predictor's gate now and then
//! ("ghost" tracks; without the ghost test: 29 of 288 four-detection tracks of the
//! paper-like synthetic scene, holding 64 % of the squared velocity error
//! once such tracks are kept). A ghost chain's velocity, though, is that of
//! a random pair of particles up to `max_disp` apart, while a real short
//! track moves with the flow that its long-lived neighbours show: on that
//! scene 193 of 213 clean four-detection tracks are within 1 px/pulse of
//! their neighbours' mean velocity, 26 of 29 ghosts are further than
//! 1.5 px/pulse (`benches/examples/ptv_ghost.rs`).
//!
//! # How
//! Every link made by a track that already holds
//! `TrackParams::flow_min_detections` detections adds its displacement
//! (px per pulse) to a grid of `cell` px cells at the link's midpoint:
//! per cell an exponentially forgetting sum (time constant `memory`
//! pulses) of the displacement, its square and the weight, decayed lazily
//! at each touch. [`LocalFlow::at`] gives the mean over the 3 × 3 cells
//! around a point, the spread of the single displacements and the weight.
//! A short track is a ghost ([`flow_consistent`]) when its least-squares
//! velocity differs from the local mean by more than `k` standard
//! deviations of the difference: the true variation of the flow in the
//! neighbourhood (the spread minus the displacement noise 2σ² per axis),
//! the noise of the track's slope (σ²/Σ(τ − τ̄)²) and of the mean.
//! Updates are O(1) per link and the test O(9) per short track, so the
//! cost is a few percent of linking at most; everything is a pure
//! function of the links in pulse order (deterministic).

/// Weight below which a neighbourhood's flow counts as unknown.
pub(crate) const MIN_FLOW_WEIGHT: f64 = 3.0;

/// Largest grid (cells per axis): positions beyond it contribute nothing
/// and see no flow (a short track there is judged by `min_length` alone).
const MAX_CELLS: usize = 4096;

/// A growing `nx × ny` grid of square `cell` px cells from the origin (up
/// to [`MAX_CELLS`] per axis), the storage of [`LocalFlow`].
#[derive(Debug, Clone)]
struct CellGrid<C> {
    cell: f64,
    nx: usize,
    ny: usize,
    cells: Vec<C>,
}

impl<C: Copy + Default> CellGrid<C> {
    fn new(cell: f64) -> Self {
        CellGrid {
            cell,
            nx: 0,
            ny: 0,
            cells: Vec::new(),
        }
    }

    /// The cell holding `(x, y)`; `None` left of or above the origin and
    /// beyond the largest grid.
    fn index(&self, x: f64, y: f64) -> Option<(usize, usize)> {
        let (fx, fy) = (x / self.cell, y / self.cell);
        if !(fx >= 0.0 && fy >= 0.0 && fx < MAX_CELLS as f64 && fy < MAX_CELLS as f64) {
            return None;
        }
        Some((fx as usize, fy as usize))
    }

    /// Cell `(ix, iy)`, growing the grid to hold it.
    fn cell_mut(&mut self, ix: usize, iy: usize) -> &mut C {
        if ix >= self.nx || iy >= self.ny {
            let (nx, ny) = ((ix + 1).max(self.nx), (iy + 1).max(self.ny));
            let mut cells = vec![C::default(); nx * ny];
            for y in 0..self.ny {
                for x in 0..self.nx {
                    cells[y * nx + x] = self.cells[y * self.nx + x];
                }
            }
            self.cells = cells;
            self.nx = nx;
            self.ny = ny;
        }
        &mut self.cells[iy * self.nx + ix]
    }

    /// The existing cells of the 3 × 3 block around `(ix, iy)`, with their
    /// indices.
    fn neighbours(&self, ix: usize, iy: usize) -> impl Iterator<Item = (usize, usize, &C)> + '_ {
        let xs = ix.saturating_sub(1)..(ix + 2).min(self.nx);
        (iy.saturating_sub(1)..(iy + 2).min(self.ny)).flat_map(move |cy| {
            xs.clone()
                .map(move |cx| (cx, cy, &self.cells[cy * self.nx + cx]))
        })
    }
}

#[derive(Debug, Clone, Copy, Default)]
struct FlowCell {
    /// Pulse the sums are decayed to.
    pulse: i64,
    w: f64,
    su: f64,
    sv: f64,
    /// Σ w (u² + v²).
    sq: f64,
}

/// Mean local velocity (px per pulse) with its spread and support.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct FlowEstimate {
    pub u: f64,
    pub v: f64,
    /// Variance per axis of the single displacements around the mean.
    pub spread2: f64,
    /// Sum of the (decayed) weights: about the number of recent links.
    pub weight: f64,
}

/// One link's displacement `(u, v)` (px per pulse) at `(x, y)` and
/// `pulse`, as added to a [`LocalFlow`]. The tracker keeps the samples it
/// adds so that the finaliser, on another thread, can replay them into its
/// own copy of the flow in the same order and see the same flow.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct FlowSample {
    pub pulse: i64,
    pub x: f64,
    pub y: f64,
    pub u: f64,
    pub v: f64,
}

/// Exponentially forgetting grid of link displacements (see module docs).
#[derive(Debug, Clone)]
pub(crate) struct LocalFlow {
    grid: CellGrid<FlowCell>,
    decay: f64,
    /// `decay.powi(k)` for the recent `k` (a table lookup instead of the
    /// call, the same numbers).
    decay_pow: [f64; DECAY_TABLE],
}

/// Ages (pulses) whose decay factor is tabulated.
const DECAY_TABLE: usize = 64;

impl LocalFlow {
    /// A grid of `cell` px cells forgetting with a time constant of
    /// `memory` pulses.
    pub(crate) fn new(cell: f64, memory: f64) -> Self {
        let decay = (-1.0 / memory).exp();
        LocalFlow {
            grid: CellGrid::new(cell),
            decay,
            // `black_box`: the runtime `powi` the lookup replaces, not a
            // constant-folded expansion that may round differently.
            decay_pow: std::array::from_fn(|k| decay.powi(std::hint::black_box(k as i32))),
        }
    }

    /// [`LocalFlow::add`] of one [`FlowSample`].
    pub(crate) fn add_sample(&mut self, s: FlowSample) {
        self.add(s.pulse, s.x, s.y, s.u, s.v)
    }

    /// Add a displacement `(u, v)` px per pulse seen at `(x, y)` at `pulse`.
    pub(crate) fn add(&mut self, pulse: i64, x: f64, y: f64, u: f64, v: f64) {
        let Some((ix, iy)) = self.grid.index(x, y) else {
            return;
        };
        let (decay, pow) = (self.decay, &self.decay_pow);
        let c = self.grid.cell_mut(ix, iy);
        if c.pulse != pulse {
            let f = decay_factor(decay, pow, pulse - c.pulse);
            c.w *= f;
            c.su *= f;
            c.sv *= f;
            c.sq *= f;
            c.pulse = pulse;
        }
        c.w += 1.0;
        c.su += u;
        c.sv += v;
        c.sq += u * u + v * v;
    }

    /// The flow around `(x, y)` as of `pulse`: the 3 × 3 cells around the
    /// point's, their sums decayed to `pulse`; `None` without any support.
    pub(crate) fn at(&self, pulse: i64, x: f64, y: f64) -> Option<FlowEstimate> {
        let (ix, iy) = self.grid.index(x, y)?;
        let (mut w, mut su, mut sv, mut sq) = (0.0, 0.0, 0.0, 0.0);
        for (_, _, c) in self.grid.neighbours(ix, iy) {
            if c.w == 0.0 {
                continue;
            }
            let f = decay_factor(self.decay, &self.decay_pow, pulse - c.pulse);
            w += f * c.w;
            su += f * c.su;
            sv += f * c.sv;
            sq += f * c.sq;
        }
        if w <= 0.0 {
            return None;
        }
        let (u, v) = (su / w, sv / w);
        Some(FlowEstimate {
            u,
            v,
            spread2: ((sq / w - u * u - v * v) / 2.0).max(0.0),
            weight: w,
        })
    }
}

/// `decay` to the power of the age (clamped to 0..=10 000 pulses), from
/// the table `pow` where it holds the age.
#[inline]
fn decay_factor(decay: f64, pow: &[f64; DECAY_TABLE], age: i64) -> f64 {
    let k = age.clamp(0, 10_000) as usize;
    match pow.get(k) {
        Some(&f) => f,
        None => decay.powi(k as i32),
    }
}

/// Least-squares velocity (px per pulse, τ = pulse index) and mean
/// position of detections `(pulse, x, y)`, with Σ(τ − τ̄)².
pub(crate) fn line_fit(dets: &[(i64, f64, f64)]) -> Option<([f64; 2], [f64; 2], f64, f64)> {
    let n = dets.len() as f64;
    if dets.len() < 2 {
        return None;
    }
    let t0 = dets[0].0;
    let tm = dets.iter().map(|d| (d.0 - t0) as f64).sum::<f64>() / n;
    let xm = dets.iter().map(|d| d.1).sum::<f64>() / n;
    let ym = dets.iter().map(|d| d.2).sum::<f64>() / n;
    let (mut stt, mut stx, mut sty) = (0.0, 0.0, 0.0);
    for d in dets {
        let t = (d.0 - t0) as f64 - tm;
        stt += t * t;
        stx += t * (d.1 - xm);
        sty += t * (d.2 - ym);
    }
    if stt <= 0.0 {
        return None;
    }
    Some(([stx / stt, sty / stt], [xm, ym], t0 as f64 + tm, stt))
}

/// Outcome of the ghost test of a short track.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum FlowCheck {
    /// Its velocity agrees with the local flow.
    Consistent,
    /// It disagrees: a ghost.
    Ghost,
    /// The neighbourhood has too little support to tell.
    Unknown,
}

/// Is a short track with detections `dets` (`(pulse, x, y)`) consistent
/// with the local flow `flow` (position noise `sigma` px per axis, `k`
/// standard deviations)? See the module docs.
pub(crate) fn flow_consistent(
    dets: &[(i64, f64, f64)],
    flow: &LocalFlow,
    sigma: f64,
    k: f64,
) -> FlowCheck {
    let Some((vel, mean, t_mid, stt)) = line_fit(dets) else {
        return FlowCheck::Unknown;
    };
    let Some(f) = flow.at(t_mid.round() as i64, mean[0], mean[1]) else {
        return FlowCheck::Unknown;
    };
    if f.weight < MIN_FLOW_WEIGHT {
        return FlowCheck::Unknown;
    }
    let s2 = sigma * sigma;
    let variation = (f.spread2 - 2.0 * s2).max(0.0);
    let var = variation + s2 / stt + f.spread2 / f.weight;
    let d2 = (vel[0] - f.u).powi(2) + (vel[1] - f.v).powi(2);
    if d2 <= k * k * var {
        FlowCheck::Consistent
    } else {
        FlowCheck::Ghost
    }
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;

    /// A uniform flow (3, −1) px/pulse seen by many links with ±0.3 px
    /// noise (deterministic pattern).
    fn uniform_flow() -> LocalFlow {
        let mut f = LocalFlow::new(16.0, 8.0);
        for pulse in 0..20 {
            for i in 0..40 {
                let (x, y) = (40.0 + (i % 8) as f64 * 4.0, 40.0 + (i / 8) as f64 * 6.0);
                let e = 0.3 * if (i + pulse) % 2 == 0 { 1.0 } else { -1.0 };
                f.add(pulse, x, y, 3.0 + e, -1.0 - e);
            }
        }
        f
    }

    #[ebptv_macros::unit_test]
    fn tabulated_decay_is_the_power_bit_for_bit() {
        for memory in [8.0, 3.0, 1e-3, 1e6] {
            let f = LocalFlow::new(16.0, memory);
            for age in -3..300i64 {
                let want = f
                    .decay
                    .powi(std::hint::black_box(age.clamp(0, 10_000) as i32));
                let got = decay_factor(f.decay, &f.decay_pow, age);
                assert_eq!(got.to_bits(), want.to_bits(), "memory {memory}, age {age}");
            }
        }
    }

    #[ebptv_macros::unit_test]
    fn mean_spread_and_decay() {
        let f = uniform_flow();
        let e = f.at(19, 50.0, 50.0).unwrap();
        assert!(
            (e.u - 3.0).abs() < 0.02 && (e.v + 1.0).abs() < 0.02,
            "{e:?}"
        );
        assert!((e.spread2 - 0.09).abs() < 0.01, "{e:?}");
        // Sum of 40·Σ e^{−k/8} over the 20 pulses of the cells in reach.
        assert!(e.weight > 40.0 * 5.0, "{e:?}");
        // Long after the last link the support fades.
        let late = f.at(19 + 80, 50.0, 50.0).unwrap();
        assert!(late.weight < MIN_FLOW_WEIGHT, "{late:?}");
        // Far away: nothing; negative coordinates: nothing.
        assert!(f.at(19, 300.0, 300.0).is_none());
        assert!(f.at(19, -5.0, 50.0).is_none());
    }

    #[ebptv_macros::unit_test]
    fn ghost_test_separates_off_flow_tracks() {
        let f = uniform_flow();
        let sigma = 0.4;
        let track = |u: f64, v: f64, wobble: f64| -> Vec<(i64, f64, f64)> {
            (0..4)
                .map(|k| {
                    let w = if k % 2 == 0 { wobble } else { -wobble };
                    (16 + k, 50.0 + u * k as f64 + w, 50.0 + v * k as f64 - w)
                })
                .collect()
        };
        // With the flow, noisy: kept.
        assert_eq!(
            flow_consistent(&track(3.2, -0.8, 0.3), &f, sigma, 3.0),
            FlowCheck::Consistent
        );
        // Across the flow at the same speed: a ghost.
        assert_eq!(
            flow_consistent(&track(1.0, 3.0, 0.0), &f, sigma, 3.0),
            FlowCheck::Ghost
        );
        // 2 px/pulse off along the flow: a ghost too.
        assert_eq!(
            flow_consistent(&track(5.0, -1.0, 0.0), &f, sigma, 3.0),
            FlowCheck::Ghost
        );
        // Where no link was seen: unknown.
        let far: Vec<(i64, f64, f64)> = track(3.0, -1.0, 0.0)
            .into_iter()
            .map(|(p, x, y)| (p, x + 400.0, y + 400.0))
            .collect();
        assert_eq!(flow_consistent(&far, &f, sigma, 3.0), FlowCheck::Unknown);
    }

    #[ebptv_macros::unit_test]
    fn line_fit_is_exact_on_a_line() {
        let d: Vec<(i64, f64, f64)> = [5, 6, 8, 9]
            .iter()
            .map(|&p| (p, 1.0 + 2.0 * p as f64, 3.0 - 0.5 * p as f64))
            .collect();
        let (v, m, t, stt) = line_fit(&d).unwrap();
        assert!((v[0] - 2.0).abs() < 1e-12 && (v[1] + 0.5).abs() < 1e-12);
        assert!((t - 7.0).abs() < 1e-12);
        assert!((m[0] - 15.0).abs() < 1e-12 && (m[1] + 0.5).abs() < 1e-12);
        assert!((stt - 10.0).abs() < 1e-12);
        assert!(line_fit(&d[..1]).is_none());
    }
}
