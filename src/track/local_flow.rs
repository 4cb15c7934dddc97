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
//! 1.5 px/pulse (`tests/ptv_ghost.rs`).
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
pub const MIN_FLOW_WEIGHT: f64 = 3.0;

/// Largest grid (cells per axis): positions beyond it contribute nothing
/// and see no flow (a short track there is judged by `min_length` alone).
const MAX_CELLS: usize = 4096;

/// A growing `nx × ny` grid of square `cell` px cells from the origin (up
/// to [`MAX_CELLS`] per axis), shared by [`LocalFlow`] and [`LinearFlow`],
/// which differ only in what a cell sums.
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

    /// Centre of cell `(ix, iy)`.
    fn centre(&self, ix: usize, iy: usize) -> (f64, f64) {
        ((ix as f64 + 0.5) * self.cell, (iy as f64 + 0.5) * self.cell)
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
pub struct FlowEstimate {
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
pub struct FlowSample {
    pub pulse: i64,
    pub x: f64,
    pub y: f64,
    pub u: f64,
    pub v: f64,
}

/// Exponentially forgetting grid of link displacements (see module docs).
#[derive(Debug, Clone)]
pub struct LocalFlow {
    grid: CellGrid<FlowCell>,
    decay: f64,
}

impl LocalFlow {
    /// A grid of `cell` px cells forgetting with a time constant of
    /// `memory` pulses.
    pub fn new(cell: f64, memory: f64) -> Self {
        LocalFlow {
            grid: CellGrid::new(cell),
            decay: (-1.0 / memory).exp(),
        }
    }

    /// [`LocalFlow::add`] of one [`FlowSample`].
    pub fn add_sample(&mut self, s: FlowSample) {
        self.add(s.pulse, s.x, s.y, s.u, s.v)
    }

    /// Add a displacement `(u, v)` px per pulse seen at `(x, y)` at `pulse`.
    pub fn add(&mut self, pulse: i64, x: f64, y: f64, u: f64, v: f64) {
        let Some((ix, iy)) = self.grid.index(x, y) else {
            return;
        };
        let decay = self.decay;
        let c = self.grid.cell_mut(ix, iy);
        if c.pulse != pulse {
            let f = decay.powi((pulse - c.pulse).clamp(0, 10_000) as i32);
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
    pub fn at(&self, pulse: i64, x: f64, y: f64) -> Option<FlowEstimate> {
        let (ix, iy) = self.grid.index(x, y)?;
        let (mut w, mut su, mut sv, mut sq) = (0.0, 0.0, 0.0, 0.0);
        for (_, _, c) in self.grid.neighbours(ix, iy) {
            if c.w == 0.0 {
                continue;
            }
            let f = self.decay.powi((pulse - c.pulse).clamp(0, 10_000) as i32);
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

/// `decay^|dt|`: [`LinearFlow`] forgets symmetrically in time.
fn factor(decay: f64, dt: i64) -> f64 {
    decay.powi(dt.unsigned_abs().min(10_000) as i32)
}

/// Moments of one cell of a [`LinearFlow`]: positions relative to the
/// cell's centre (conditioning), decayed to `pulse`.
#[derive(Debug, Clone, Copy, Default)]
struct GradientCell {
    pulse: i64,
    /// w, Σx, Σy, Σx², Σxy, Σy², Σu, Σv, Σxu, Σyu, Σxv, Σyv, Σ(u² + v²).
    m: [f64; 13],
}

/// Fewest (decayed) links in a neighbourhood for a [`LinearFlow`]
/// estimate: the plane takes three per component, and a residual spread
/// from fewer than a handful more is itself too noisy to weigh by.
pub const MIN_PRIOR_WEIGHT: f64 = 8.0;

/// The local flow as a velocity prior for one point: the estimate (px per
/// pulse) and its error variance per axis against the true velocity there.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VelocityPrior {
    pub u: f64,
    pub v: f64,
    /// Expected squared error per axis: the flow's variation about the
    /// local plane (links' residual spread less their noise) plus the
    /// plane's own uncertainty at the point.
    pub variance: f64,
}

/// The link displacements of [`LocalFlow`] with position moments, so that
/// a neighbourhood gives a local *linear* flow `u = c₀ + c₁Δx + c₂Δy`
/// (per component) rather than a mean: the output fit's velocity prior
/// ([`LinearFlow::prior`]). A mean over the 48 px neighbourhood carries
/// the whole gradient across it as spread (paper-like scene: ~0.5 px/pulse,
/// more than a one-sided fit's own noise), the plane only its curvature.
/// Forgetting as [`LocalFlow`] (time constant `memory` pulses), but
/// symmetric in time: a query before a cell's last update decays its sums
/// by the same factor as one after it, so the prior of an early point of
/// a long track (the grid is as of the track's end) counts fewer links
/// and weakens by itself.
#[derive(Debug, Clone)]
pub struct LinearFlow {
    grid: CellGrid<GradientCell>,
    decay: f64,
}

impl LinearFlow {
    /// A grid of `cell` px cells forgetting with a time constant of
    /// `memory` pulses.
    pub fn new(cell: f64, memory: f64) -> Self {
        LinearFlow {
            grid: CellGrid::new(cell),
            decay: (-1.0 / memory).exp(),
        }
    }

    fn factor(&self, dt: i64) -> f64 {
        factor(self.decay, dt)
    }

    /// Add one link's displacement (as [`LocalFlow::add_sample`]).
    pub fn add_sample(&mut self, s: FlowSample) {
        let Some((ix, iy)) = self.grid.index(s.x, s.y) else {
            return;
        };
        let (cx, cy) = self.grid.centre(ix, iy);
        let (x, y) = (s.x - cx, s.y - cy);
        let decay = self.decay;
        let c = self.grid.cell_mut(ix, iy);
        if c.pulse != s.pulse {
            let f = factor(decay, s.pulse - c.pulse);
            if f != 1.0 {
                c.m.iter_mut().for_each(|m| *m *= f);
            }
        }
        c.pulse = s.pulse;
        let (u, v) = (s.u, s.v);
        let add = [
            1.0,
            x,
            y,
            x * x,
            x * y,
            y * y,
            u,
            v,
            x * u,
            y * u,
            x * v,
            y * v,
            u * u + v * v,
        ];
        for (m, a) in c.m.iter_mut().zip(add) {
            *m += a;
        }
    }

    /// The weighted moments of the 3 × 3 cells around `(x, y)` decayed to
    /// `pulse`, positions relative to `(x, y)`.
    fn moments(&self, pulse: i64, x: f64, y: f64) -> Option<[f64; 13]> {
        let (ix, iy) = self.grid.index(x, y)?;
        let mut t = [0.0f64; 13];
        for (cx, cy, c) in self.grid.neighbours(ix, iy) {
            {
                if c.m[0] == 0.0 {
                    continue;
                }
                let f = self.factor(pulse - c.pulse);
                // Shift the cell's moments from its centre to the point.
                let (a, b) = self.grid.centre(cx, cy);
                let (a, b) = (a - x, b - y);
                let m = &c.m;
                let shifted = [
                    m[0],
                    m[1] + a * m[0],
                    m[2] + b * m[0],
                    m[3] + 2.0 * a * m[1] + a * a * m[0],
                    m[4] + b * m[1] + a * m[2] + a * b * m[0],
                    m[5] + 2.0 * b * m[2] + b * b * m[0],
                    m[6],
                    m[7],
                    m[8] + a * m[6],
                    m[9] + b * m[6],
                    m[10] + a * m[7],
                    m[11] + b * m[7],
                    m[12],
                ];
                for (t, s) in t.iter_mut().zip(shifted) {
                    *t += f * s;
                }
            }
        }
        (t[0] > 0.0).then_some(t)
    }

    /// The local linear flow at `(x, y)` as of `pulse` as a velocity prior
    /// for position noise `sigma` (px per axis): the weighted least-squares
    /// plane of the links' displacements in the 3 × 3 cells around the
    /// point, evaluated there; its variance is the links' residual spread
    /// about the plane less their noise 2σ² (the flow's own variation:
    /// turbulence, unsteadiness within the memory, curvature of the
    /// field), plus the spread times the plane's variance factor at the
    /// point. `None` below [`MIN_PRIOR_WEIGHT`] or for a degenerate
    /// neighbourhood (links on one line).
    pub fn prior(&self, pulse: i64, x: f64, y: f64, sigma: f64) -> Option<VelocityPrior> {
        let m = self.moments(pulse, x, y)?;
        let w = m[0];
        if w < MIN_PRIOR_WEIGHT {
            return None;
        }
        let a = [[m[0], m[1], m[2]], [m[1], m[3], m[4]], [m[2], m[4], m[5]]];
        let inv = invert3(&a)?;
        let bu = [m[6], m[8], m[9]];
        let bv = [m[7], m[10], m[11]];
        let dot = |r: &[f64; 3], b: &[f64; 3]| r[0] * b[0] + r[1] * b[1] + r[2] * b[2];
        let cu = [dot(&inv[0], &bu), dot(&inv[1], &bu), dot(&inv[2], &bu)];
        let cv = [dot(&inv[0], &bv), dot(&inv[1], &bv), dot(&inv[2], &bv)];
        let ssr = (m[12] - dot(&cu, &bu) - dot(&cv, &bv)).max(0.0);
        let spread2 = ssr / (2.0 * (w - 3.0));
        let variation = (spread2 - 2.0 * sigma * sigma).max(0.0);
        // Var(ĉ₀) = spread²·(AᵀWA)⁻¹₀₀ for unit weights; decayed weights
        // (≤ 1) make the true variance smaller: conservative.
        let variance = variation + spread2 * inv[0][0];
        (variance.is_finite() && cu[0].is_finite() && cv[0].is_finite()).then_some(VelocityPrior {
            u: cu[0],
            v: cv[0],
            variance,
        })
    }
}

/// A [`LinearFlow`] with its recent past: a copy of the grid every
/// `block` pulses, the last `keep` of them. The finaliser fits a track
/// when it ends, but the one-sided fit at its *start* needs the flow of
/// that moment, long forgotten by a grid of 8 pulses' memory when the
/// track is long: [`FlowHistory::prior`] asks the first copy taken after
/// the point's pulse (within a block of it, the symmetric decay covering
/// the rest). A pure function of the samples in order: deterministic.
#[derive(Debug, Clone)]
pub struct FlowHistory {
    current: LinearFlow,
    /// `(boundary, grid)`: the grid with every sample of a pulse before
    /// `boundary`, oldest first.
    snapshots: std::collections::VecDeque<(i64, LinearFlow)>,
    block: i64,
    keep: usize,
    next_boundary: Option<i64>,
}

impl FlowHistory {
    /// A [`LinearFlow::new`]`(cell, memory)` with a copy every `block`
    /// pulses, the last `keep` kept.
    pub fn new(cell: f64, memory: f64, block: i64, keep: usize) -> Self {
        FlowHistory {
            current: LinearFlow::new(cell, memory),
            snapshots: Default::default(),
            block: block.max(1),
            keep: keep.max(1),
            next_boundary: None,
        }
    }

    /// Add one link's displacement; samples must come in pulse order.
    pub fn add_sample(&mut self, s: FlowSample) {
        let next = *self
            .next_boundary
            .get_or_insert((s.pulse.div_euclid(self.block) + 1) * self.block);
        if s.pulse >= next {
            // A long pause: the copies in between would all be the same
            // grid, and only the last `keep` could be kept anyway.
            let skip = ((s.pulse - next) / self.block - self.keep as i64).max(0);
            let mut b = next + skip * self.block;
            while s.pulse >= b {
                let mut grid = if self.snapshots.len() >= self.keep {
                    self.snapshots.pop_front().map(|(_, g)| g)
                } else {
                    None
                }
                .unwrap_or_else(|| self.current.clone());
                grid.clone_from(&self.current);
                self.snapshots.push_back((b, grid));
                b += self.block;
            }
            self.next_boundary = Some(b);
        }
        self.current.add_sample(s);
    }

    /// [`LinearFlow::prior`] from the first copy holding every link of
    /// `pulse` (the current grid when none does).
    pub fn prior(&self, pulse: i64, x: f64, y: f64, sigma: f64) -> Option<VelocityPrior> {
        let k = self.snapshots.partition_point(|(b, _)| *b <= pulse);
        self.snapshots
            .get(k)
            .map_or(&self.current, |(_, g)| g)
            .prior(pulse, x, y, sigma)
    }
}

/// One point of a first-pass track as a sample of the whole run's flow
/// ([`WholeRunFlow`]): its fitted velocity (px per pulse) and noise
/// variance per axis, and the serial of its detection (so that a track's
/// own points can be left out of its prior).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RunSample {
    pub pulse: i64,
    pub x: f64,
    pub y: f64,
    pub u: f64,
    pub v: f64,
    pub fit_var: f64,
    pub serial: u64,
}

/// Unknowns of [`WholeRunFlow`]'s local model per component: 1, Δx, Δy,
/// Δτ, Δx², ΔxΔy, Δy².
const RUN_TERMS: usize = 7;

/// Fewest samples for [`WholeRunFlow::prior`]: the quadratic takes seven
/// per component, and a residual spread needs a few more.
pub const MIN_RUN_SAMPLES: usize = 16;

/// The flow of a whole run from the fitted velocities of its first-pass
/// tracks, for the second pass's velocity prior
/// (`TrackParams::velocity_prior_two_pass`). The one-pass prior
/// ([`FlowHistory`]) only knows the links made so far — nothing in the
/// recording's first pulses — and fits a plane to noisy link
/// displacements over 48 px, whose curvature error repeats at every
/// visit of a place in a steady flow (the Lamb–Oseen vortex). Here every
/// point has samples on both sides in time, and the samples are fitted
/// velocities (interior noise ~0.05 px/pulse against ~0.3 for a link),
/// so a local *quadratic* in space, linear in time, fits in a smaller
/// neighbourhood: `radius` px and `±half_window` pulses, weights
/// (1 − r²/R²)² (1 − (Δτ/(T+1))²) times the sample's precision relative
/// to the typical fit (`typical / (typical + fit_var)`: noisy track ends
/// count little). Samples are bucketed by pulse and `radius`-sized cells;
/// a query visits 3 × 3 cells of 2T + 1 pulses in a fixed order:
/// deterministic.
#[derive(Debug, Clone)]
pub struct WholeRunFlow {
    radius: f64,
    half_window: i64,
    typical_var: f64,
    cells: std::collections::HashMap<(i64, i32, i32), Vec<RunSample>>,
}

impl WholeRunFlow {
    /// Index `samples` (any order; kept in that order within a bucket).
    pub fn new(samples: &[RunSample], radius: f64, half_window: i64) -> Self {
        let mut vars: Vec<f64> = samples
            .iter()
            .map(|s| s.fit_var)
            .filter(|v| *v > 0.0)
            .collect();
        vars.sort_by(|a, b| a.total_cmp(b));
        let typical_var = vars.get(vars.len() / 2).copied().unwrap_or(1e-4);
        let mut cells: std::collections::HashMap<(i64, i32, i32), Vec<RunSample>> =
            Default::default();
        for s in samples {
            if let Some(k) = Self::key(radius, s.pulse, s.x, s.y) {
                cells.entry(k).or_default().push(*s);
            }
        }
        WholeRunFlow {
            radius,
            half_window: half_window.max(0),
            typical_var,
            cells,
        }
    }

    fn key(radius: f64, pulse: i64, x: f64, y: f64) -> Option<(i64, i32, i32)> {
        let (fx, fy) = ((x / radius).floor(), (y / radius).floor());
        (fx.abs() < 1e9 && fy.abs() < 1e9).then_some((pulse, fx as i32, fy as i32))
    }

    /// The median noise variance of the samples' fits (px²/pulse² per
    /// axis).
    pub fn typical_fit_variance(&self) -> f64 {
        self.typical_var
    }

    /// The local flow at `(x, y)` at `pulse` from the samples around it
    /// except those whose serial `own` holds (sorted: the track's own
    /// detections, whose fit errors the prior must not share): the
    /// weighted least-squares quadratic (see the type's docs) evaluated
    /// there. Its claimed variance is the weighted residual spread of the
    /// samples about the model times (1 + the model's variance factor at
    /// the point): the flow's variation the model does not follow plus
    /// the model's own noise, conservative by the samples' noise (the
    /// calibration, [`PriorCalibration`], scales it to what is measured).
    /// A quadratic needs [`MIN_RUN_SAMPLES`] samples; with fewer, or a
    /// degenerate spread, `None`.
    pub fn prior(&self, pulse: i64, x: f64, y: f64, own: &[u64]) -> Option<VelocityPrior> {
        let r = self.radius;
        let (_, kx, ky) = Self::key(r, pulse, x, y)?;
        let mut a = [[0.0f64; RUN_TERMS]; RUN_TERMS];
        let mut bu = [0.0f64; RUN_TERMS];
        let mut bv = [0.0f64; RUN_TERMS];
        let (mut sw, mut suu, mut n) = (0.0f64, 0.0f64, 0usize);
        let tw = (self.half_window + 1) as f64;
        for p in pulse - self.half_window..=pulse + self.half_window {
            let dt = (p - pulse) as f64;
            let wt = 1.0 - (dt / tw).powi(2);
            for cy in ky - 1..=ky + 1 {
                for cx in kx - 1..=kx + 1 {
                    let Some(bucket) = self.cells.get(&(p, cx, cy)) else {
                        continue;
                    };
                    for s in bucket {
                        let (dx, dy) = ((s.x - x) / r, (s.y - y) / r);
                        let q = dx * dx + dy * dy;
                        if q >= 1.0 || own.binary_search(&s.serial).is_ok() {
                            continue;
                        }
                        let w = wt
                            * (1.0 - q).powi(2)
                            * (self.typical_var / (self.typical_var + s.fit_var.max(0.0)));
                        let t = dt / tw;
                        let basis = [1.0, dx, dy, t, dx * dx, dx * dy, dy * dy];
                        for i in 0..RUN_TERMS {
                            let wb = w * basis[i];
                            for j in i..RUN_TERMS {
                                a[i][j] += wb * basis[j];
                            }
                            bu[i] += wb * s.u;
                            bv[i] += wb * s.v;
                        }
                        sw += w;
                        suu += w * (s.u * s.u + s.v * s.v);
                        n += 1;
                    }
                }
            }
        }
        if n < MIN_RUN_SAMPLES || !(sw > 0.0) {
            return None;
        }
        for i in 0..RUN_TERMS {
            for j in 0..i {
                a[i][j] = a[j][i];
            }
        }
        let inv = invert_spd(a)?;
        let dot = |r: &[f64; RUN_TERMS], b: &[f64; RUN_TERMS]| -> f64 {
            r.iter().zip(b).map(|(p, q)| p * q).sum()
        };
        let cu: [f64; RUN_TERMS] = std::array::from_fn(|i| dot(&inv[i], &bu));
        let cv: [f64; RUN_TERMS] = std::array::from_fn(|i| dot(&inv[i], &bv));
        // Weighted residual sum of squares of both components.
        let ssr = (suu - dot(&cu, &bu) - dot(&cv, &bv)).max(0.0);
        let dof = (n as f64 - RUN_TERMS as f64).max(1.0) / n as f64;
        let spread2 = ssr / (2.0 * sw * dof);
        // Variance factor of c₀ in units of a weight-1 sample's variance.
        let variance = spread2 * (1.0 + inv[0][0]);
        (variance.is_finite() && cu[0].is_finite() && cv[0].is_finite()).then_some(VelocityPrior {
            u: cu[0],
            v: cv[0],
            variance,
        })
    }
}

/// Inverse of a symmetric positive definite matrix by Gauss–Jordan with
/// the diagonal as pivots (positive for an SPD matrix); `None` when a
/// pivot falls below 1e-10 of its original diagonal (nearly singular:
/// the samples do not span the model).
fn invert_spd<const N: usize>(mut a: [[f64; N]; N]) -> Option<[[f64; N]; N]> {
    let mut inv = [[0.0f64; N]; N];
    for (i, row) in inv.iter_mut().enumerate() {
        row[i] = 1.0;
    }
    let diag: [f64; N] = std::array::from_fn(|i| a[i][i]);
    for k in 0..N {
        let p = a[k][k];
        if !(p > 1e-10 * diag[k]) {
            return None;
        }
        let r = 1.0 / p;
        for j in 0..N {
            a[k][j] *= r;
            inv[k][j] *= r;
        }
        for i in 0..N {
            if i != k {
                let f = a[i][k];
                if f != 0.0 {
                    for j in 0..N {
                        a[i][j] -= f * a[k][j];
                        inv[i][j] -= f * inv[k][j];
                    }
                }
            }
        }
    }
    Some(inv)
}

/// Inverse of a symmetric positive definite 3 × 3 matrix; `None` when it
/// is (nearly) singular.
fn invert3(a: &[[f64; 3]; 3]) -> Option<[[f64; 3]; 3]> {
    let c00 = a[1][1] * a[2][2] - a[1][2] * a[2][1];
    let c01 = a[1][2] * a[2][0] - a[1][0] * a[2][2];
    let c02 = a[1][0] * a[2][1] - a[1][1] * a[2][0];
    let det = a[0][0] * c00 + a[0][1] * c01 + a[0][2] * c02;
    // Relative to the diagonal's scale: links on (nearly) one line.
    let scale = a[0][0] * a[1][1] * a[2][2];
    if !(det > 1e-9 * scale) {
        return None;
    }
    let c11 = a[0][0] * a[2][2] - a[0][2] * a[2][0];
    let c12 = a[0][1] * a[2][0] - a[0][0] * a[2][1];
    let c22 = a[0][0] * a[1][1] - a[0][1] * a[1][0];
    let r = 1.0 / det;
    Some([
        [c00 * r, c01 * r, c02 * r],
        [c01 * r, c11 * r, c12 * r],
        [c02 * r, c12 * r, c22 * r],
    ])
}

/// Smallest factor of the claimed prior variance: a measured excess
/// near zero (a prior almost exactly right) must not make it infinitely
/// sure.
pub const MIN_SCALE: f64 = 0.1;

/// The prior is checked against the fits at pulses divisible by this
/// (and queried elsewhere only where it moves the fit). Every pulse: a
/// stride of 8 saved ~25 % of the CPU with the prior on but calibrated
/// later, and the 60-pulse paper-like scene lost much of the gain
/// (posterior mean, seed 3: 0.080 → 0.098 px/pulse).
pub const CALIBRATION_STRIDE: i64 = 1;

/// Fewest calibration points before the velocity prior is applied.
pub const MIN_CALIBRATION_POINTS: u64 = 200;

/// The empirical check of [`LinearFlow::prior`]'s variance: at points
/// whose own fit is more precise than the prior, the squared difference
/// between the two, less the fit's noise, measures the prior's actual
/// error; over many points its ratio to the claimed variance is the
/// factor the claimed variances are scaled by. The modelled variance
/// misses what the grid cannot see — a track's own links in its
/// neighbourhood (they pull the plane towards it), an optimistic σ, flow
/// structure finer than the cells' — and on a turbulent scene it is low
/// by ~2×: without this the prior shrank the fluctuations.
/// Kept by the finaliser from the tracks fitted so far (in order, like
/// [`crate::track::fit::AccelPrior`]): deterministic.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PriorCalibration {
    /// Σ (|v_fit − v_prior|²/2 − fit variance) per axis.
    excess: f64,
    /// Σ claimed prior variance.
    claimed: f64,
    points: u64,
    /// Histogram of the fits' noise variance per axis over every point:
    /// log₂ bins from 2⁻²⁴ px²/pulse², for its median.
    fit_var_bins: [u64; FIT_VAR_BINS],
}

/// Bins of [`PriorCalibration`]'s fit-variance histogram (log₂, from 2⁻²⁴:
/// ~6e-8 to 1 px²/pulse²).
const FIT_VAR_BINS: usize = 48;

fn fit_var_bin(v: f64) -> usize {
    ((v.log2() + 24.0) * 2.0).clamp(0.0, (FIT_VAR_BINS - 1) as f64) as usize
}

impl Default for PriorCalibration {
    fn default() -> Self {
        PriorCalibration {
            excess: 0.0,
            claimed: 0.0,
            points: 0,
            fit_var_bins: [0; FIT_VAR_BINS],
        }
    }
}

impl PriorCalibration {
    /// Record one point: its fitted velocity and noise variance per axis
    /// and the prior there; points whose fit is less precise than the
    /// prior tell little about it and are left out. (The finaliser checks
    /// every [`CALIBRATION_STRIDE`]-th pulse.)
    pub fn add(&mut self, vx: f64, vy: f64, fit_var: f64, prior: &VelocityPrior) {
        if !(fit_var > 0.0 && fit_var < prior.variance) {
            return;
        }
        let d2 = 0.5 * ((vx - prior.u).powi(2) + (vy - prior.v).powi(2));
        if d2.is_finite() {
            self.excess += d2 - fit_var;
            self.claimed += prior.variance;
            self.points += 1;
        }
    }

    /// Record one point's fit noise variance per axis (for
    /// [`PriorCalibration::typical_fit_variance`]).
    pub fn note_fit_variance(&mut self, fit_var: f64) {
        if fit_var > 0.0 {
            self.fit_var_bins[fit_var_bin(fit_var)] += 1;
        }
    }

    pub fn merge(&mut self, other: &PriorCalibration) {
        self.excess += other.excess;
        self.claimed += other.claimed;
        self.points += other.points;
        for (a, b) in self.fit_var_bins.iter_mut().zip(&other.fit_var_bins) {
            *a += b;
        }
    }

    /// The median noise variance of the fits (px²/pulse² per axis, to
    /// half a binary order): the noise level the grid stage's noise
    /// estimate sees and subtracts ([`combine`]). `None` without points.
    pub fn typical_fit_variance(&self) -> Option<f64> {
        let total: u64 = self.fit_var_bins.iter().sum();
        if total == 0 {
            return None;
        }
        let mut seen = 0;
        for (k, &c) in self.fit_var_bins.iter().enumerate() {
            seen += c;
            if 2 * seen >= total {
                // The bin's geometric centre.
                return Some(((k as f64 + 0.5) / 2.0 - 24.0).exp2());
            }
        }
        None
    }

    /// Factor of the claimed prior variances: the measured over the
    /// claimed (floored at [`MIN_SCALE`]); `None` before
    /// [`MIN_CALIBRATION_POINTS`] points.
    pub fn scale(&self) -> Option<f64> {
        (self.points >= MIN_CALIBRATION_POINTS && self.claimed > 0.0)
            .then(|| (self.excess / self.claimed).max(MIN_SCALE))
    }

    /// The measured over the claimed variance (diagnostics).
    pub fn ratio(&self) -> f64 {
        self.excess / self.claimed
    }
}

/// The posterior mean of a fitted velocity `(vx, vy)` (px per pulse) of
/// noise variance `fit_var` per axis under a [`VelocityPrior`] (its
/// variance divided by `strength`): the precision-weighted mean, least
/// error per point — but it shrinks every point's fluctuation about the
/// local flow (see [`combine`]); `TrackParams::velocity_prior_mean`.
pub fn posterior_mean(
    vx: f64,
    vy: f64,
    fit_var: f64,
    prior: &VelocityPrior,
    strength: f64,
) -> (f64, f64) {
    if !(fit_var > 0.0 && strength > 0.0) {
        return (vx, vy);
    }
    let g = fit_var / (fit_var + prior.variance / strength);
    (vx + g * (prior.u - vx), vy + g * (prior.v - vy))
}

/// A fitted velocity `(vx, vy)` (px per pulse) of noise variance
/// `fit_var` per axis, moved towards a [`VelocityPrior`] (its variance
/// divided by `strength`, 1 = as estimated) only as far as to bring its
/// noise down to `typical_var`, the fits' typical noise — and so that
/// its spread about the prior stays what the truth's spread plus that
/// typical noise would be: `v̂ = m + c·(v − m)` with
/// `c² = (P + typical_var)/(P + fit_var)`, P the prior's variance, for
/// fits noisier than typical; the rest unchanged.
///
/// Why not the posterior mean (`c = P/(P + fit_var)`, least error per
/// point): it shrinks every point's fluctuation about the local flow,
/// the quiet interior too, and the grid stage's stresses, which subtract
/// the measured noise from the samples' spread, came out 3.5–5.5 % low
/// on a turbulent scene (about −2 × the interior noise variance). This variance-matching form ("constrained Bayes") keeps each
/// sample's spread at truth + typical noise, which the noise correction
/// removes; at the ends, where the one-sided fits are several times
/// noisier than typical, it still takes most of the posterior mean's
/// gain.
pub fn combine(
    vx: f64,
    vy: f64,
    fit_var: f64,
    prior: &VelocityPrior,
    strength: f64,
    typical_var: f64,
) -> (f64, f64) {
    if !(fit_var > typical_var && strength > 0.0) {
        return (vx, vy);
    }
    let p = prior.variance / strength;
    if !(p > 0.0) {
        return (vx, vy);
    }
    let c = ((p + typical_var) / (p + fit_var)).sqrt();
    (prior.u + c * (vx - prior.u), prior.v + c * (vy - prior.v))
}

/// Least-squares velocity (px per pulse, τ = pulse index) and mean
/// position of detections `(pulse, x, y)`, with Σ(τ − τ̄)².
pub fn line_fit(dets: &[(i64, f64, f64)]) -> Option<([f64; 2], [f64; 2], f64, f64)> {
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
pub enum FlowCheck {
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
pub fn flow_consistent(
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

#[cfg(test)]
mod tests {
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

    #[test]
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

    #[test]
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

    #[test]
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

    /// Links of the linear field u = 2 + 0.01x − 0.02y, v = −1 + 0.03x
    /// at pulses `pulses`, with a ±`noise` deterministic pattern.
    fn linear_links(pulses: std::ops::Range<i64>, noise: f64) -> Vec<FlowSample> {
        let mut out = Vec::new();
        for pulse in pulses {
            for i in 0..60 {
                let (x, y) = (
                    20.0 + ((i * 7 + pulse as usize * 3) % 40) as f64 * 1.5,
                    30.0 + ((i * 11) % 37) as f64 * 1.3,
                );
                let e = noise
                    * if (i + pulse as usize) % 2 == 0 {
                        1.0
                    } else {
                        -1.0
                    };
                out.push(FlowSample {
                    pulse,
                    x,
                    y,
                    u: 2.0 + 0.01 * x - 0.02 * y + e,
                    v: -1.0 + 0.03 * x - e,
                });
            }
        }
        out
    }

    #[test]
    fn linear_flow_recovers_a_plane_and_its_noise() {
        let mut f = LinearFlow::new(16.0, 8.0);
        for s in linear_links(0..20, 0.0) {
            f.add_sample(s);
        }
        let (x, y) = (50.0, 55.0);
        let p = f.prior(19, x, y, 0.0).unwrap();
        assert!((p.u - (2.0 + 0.01 * x - 0.02 * y)).abs() < 1e-9, "{p:?}");
        assert!((p.v - (-1.0 + 0.03 * x)).abs() < 1e-9, "{p:?}");
        assert!(p.variance < 1e-12, "{p:?}");
        // The mean of LocalFlow carries the gradient across the cells as
        // spread; the plane does not.
        let mut m = LocalFlow::new(16.0, 8.0);
        for s in linear_links(0..20, 0.0) {
            m.add_sample(s);
        }
        assert!(m.at(19, x, y).unwrap().spread2 > 0.01);
        // Noise ±0.3 per axis: spread ≈ 0.09 per axis; with σ² = 0.045
        // (displacement noise 2σ² = 0.09) no variation is left, only the
        // plane's own uncertainty, ~0.09/weight.
        let mut f = LinearFlow::new(16.0, 8.0);
        for s in linear_links(0..20, 0.3) {
            f.add_sample(s);
        }
        let p = f.prior(19, x, y, 0.045f64.sqrt()).unwrap();
        assert!(p.variance > 0.0 && p.variance < 0.01, "{p:?}");
        // Assuming no noise, all of the spread is variation.
        let q = f.prior(19, x, y, 0.0).unwrap();
        assert!((q.variance - 0.09).abs() < 0.015, "{q:?}");
        // Far from any link, or long before: nothing.
        assert!(f.prior(19, 400.0, 400.0, 0.0).is_none());
        assert!(f.prior(19 - 80, x, y, 0.0).is_none());
        assert!(f.prior(19 + 80, x, y, 0.0).is_none());
    }

    #[test]
    fn flow_history_answers_with_the_flow_of_the_moment() {
        // Flow +3 px/pulse in x until pulse 40, then −3.
        let mut h = FlowHistory::new(16.0, 8.0, 4, 32);
        let mut now = LinearFlow::new(16.0, 8.0);
        for s in linear_links(0..80, 0.0) {
            let s = FlowSample {
                u: if s.pulse < 40 { 3.0 } else { -3.0 },
                v: 0.0,
                ..s
            };
            h.add_sample(s);
            now.add_sample(s);
        }
        let early = h.prior(20, 50.0, 55.0, 0.0).unwrap();
        assert!((early.u - 3.0).abs() < 1e-9, "{early:?}");
        // Late: the old flow faded to a trace (e^{−39/8} of its weight).
        let late = h.prior(79, 50.0, 55.0, 0.0).unwrap();
        assert!((late.u + 3.0).abs() < 0.05, "{late:?}");
        // The grid of the end alone has forgotten the early flow.
        assert!(now.prior(20, 50.0, 55.0, 0.0).is_none());
        // Beyond the copies kept: the oldest one, faded.
        let mut h = FlowHistory::new(16.0, 8.0, 4, 2);
        for s in linear_links(0..80, 0.0) {
            h.add_sample(s);
        }
        assert!(h.prior(10, 50.0, 55.0, 0.0).is_none());
    }

    #[test]
    fn combination_matches_the_spread_and_calibration_measures() {
        let prior = VelocityPrior {
            u: 1.0,
            v: 2.0,
            variance: 0.01,
        };
        // Fits as quiet as typical: untouched.
        assert_eq!(combine(1.5, 2.5, 0.001, &prior, 1.0, 0.001), (1.5, 2.5));
        // Off.
        assert_eq!(combine(1.5, 2.5, 0.04, &prior, 0.0, 0.001), (1.5, 2.5));
        // A noisy end: the spread about the prior, P + fit variance, is
        // brought to P + typical.
        let (u, v) = combine(1.5, 2.5, 0.04, &prior, 1.0, 0.001);
        let c = ((0.01f64 + 0.001) / (0.01 + 0.04)).sqrt();
        assert!((u - (1.0 + 0.5 * c)).abs() < 1e-12 && (v - (2.0 + 0.5 * c)).abs() < 1e-12);
        // Calibration: fits off the prior by 0.2 px/pulse per axis with
        // noise 0.002, the prior claiming 0.01: measured 0.038, ratio 3.8.
        let mut cal = PriorCalibration::default();
        for _ in 0..MIN_CALIBRATION_POINTS - 1 {
            cal.add(1.2, 2.2, 0.002, &prior);
            cal.note_fit_variance(0.002);
        }
        assert!(cal.scale().is_none());
        let mut more = PriorCalibration::default();
        more.add(0.8, 1.8, 0.002, &prior);
        // Less precise than the prior: counted for the noise level only.
        more.add(9.0, 9.0, 0.5, &prior);
        more.note_fit_variance(0.5);
        cal.merge(&more);
        assert!((cal.scale().unwrap() - 3.8).abs() < 1e-9, "{cal:?}");
        let typical = cal.typical_fit_variance().unwrap();
        assert!(typical > 0.002 / 1.5 && typical < 0.002 * 1.5, "{typical}");
        // A prior better than claimed strengthens, to a floor.
        let mut exact = PriorCalibration::default();
        for _ in 0..MIN_CALIBRATION_POINTS {
            exact.add(1.0, 2.0, 0.002, &prior);
        }
        assert_eq!(exact.scale(), Some(MIN_SCALE));
    }

    /// Samples of the field u = 1 + 0.02x − 0.01y + 0.001x² + 0.05τ,
    /// v = −2 + 0.0005xy at pulses 0..10 on a jittered lattice, serials
    /// in order.
    fn quadratic_samples(noise: f64) -> Vec<RunSample> {
        let mut out = Vec::new();
        let mut serial = 0;
        for pulse in 0..10i64 {
            for i in 0..12 {
                for j in 0..12 {
                    let x = 40.0 + 4.0 * i as f64 + ((pulse + j) % 3) as f64 * 0.7;
                    let y = 40.0 + 4.0 * j as f64 + ((pulse + i) % 4) as f64 * 0.5;
                    let e = noise * if (i + j + pulse) % 2 == 0 { 1.0 } else { -1.0 };
                    out.push(RunSample {
                        pulse,
                        x,
                        y,
                        u: 1.0 + 0.02 * x - 0.01 * y + 0.001 * x * x + 0.05 * pulse as f64 + e,
                        v: -2.0 + 0.0005 * x * y - e,
                        fit_var: 0.001,
                        serial,
                    });
                    serial += 1;
                }
            }
        }
        out
    }

    #[test]
    fn whole_run_flow_follows_a_quadratic_field() {
        let samples = quadratic_samples(0.0);
        let f = WholeRunFlow::new(&samples, 24.0, 3);
        let (x, y, pulse) = (62.0, 61.0, 5);
        let p = f.prior(pulse, x, y, &[]).unwrap();
        let u = 1.0 + 0.02 * x - 0.01 * y + 0.001 * x * x + 0.05 * pulse as f64;
        let v = -2.0 + 0.0005 * x * y;
        assert!((p.u - u).abs() < 1e-9 && (p.v - v).abs() < 1e-9, "{p:?}");
        assert!(p.variance < 1e-12, "{p:?}");
        // At the first pulse the window is one-sided: still exact.
        let p0 = f.prior(0, x, y, &[]).unwrap();
        assert!((p0.u - (u - 0.25)).abs() < 1e-9, "{p0:?}");
        // Far from the samples, or beyond the window: nothing.
        assert!(f.prior(pulse, 300.0, 300.0, &[]).is_none());
        assert!(f.prior(20, x, y, &[]).is_none());
        // Noise ±0.1: the prior claims about the spread (0.01) and is
        // close to the field.
        let f = WholeRunFlow::new(&quadratic_samples(0.1), 24.0, 3);
        let q = f.prior(pulse, x, y, &[]).unwrap();
        assert!((q.u - u).abs() < 0.03 && (q.v - v).abs() < 0.03, "{q:?}");
        assert!(q.variance > 0.005 && q.variance < 0.02, "{q:?}");
        assert!((f.typical_fit_variance() - 0.001).abs() < 1e-12);
    }

    #[test]
    fn whole_run_flow_leaves_the_own_track_out() {
        let mut samples = quadratic_samples(0.0);
        // One "track": the samples nearest (62, 61), moved 1 px/pulse off.
        let mut own: Vec<u64> = Vec::new();
        for s in samples.iter_mut() {
            if (s.x - 62.0).abs() < 2.5 && (s.y - 61.0).abs() < 2.5 {
                s.u += 1.0;
                own.push(s.serial);
            }
        }
        assert!(own.len() >= 5);
        own.sort_unstable();
        let f = WholeRunFlow::new(&samples, 24.0, 3);
        let (x, y, pulse) = (62.0, 61.0, 5);
        let u = 1.0 + 0.02 * x - 0.01 * y + 0.001 * x * x + 0.05 * pulse as f64;
        let without = f.prior(pulse, x, y, &own).unwrap();
        assert!((without.u - u).abs() < 1e-9, "{without:?}");
        let with = f.prior(pulse, x, y, &[]).unwrap();
        assert!(with.u - u > 0.05, "{with:?}");
    }
}
