//! Least-squares polynomial fits of a track's positions over time.
//!
//! Both the predictor (extrapolating the last few detections to the next
//! pulse) and the output (position, velocity and acceleration at each pulse
//! from a sliding window) are the same small problem: fit x(τ) and y(τ) with a
//! polynomial of order ≤ 2 in a scaled time τ and evaluate it and its
//! derivatives at one τ. The 3×3 normal equations are solved directly; the
//! leverage `eᵀ(XᵀX)⁻¹e` of the evaluation point tells how much the fit
//! amplifies the position noise there, which sets the predictor's search
//! radius.
//!
//! # Adaptive window (the output fit)
//! A fixed window trades noise against bias the same way everywhere: on a
//! straight track a long window averages the centroid noise down, on a
//! curved one it bends the path (a quadratic over `w` points misses the
//! cubic term: on a circle the speed comes out low by ω²⟨τ⁴⟩/(6⟨τ²⟩), ω
//! the turning angle per pulse), and at a track's ends the one-sided fit
//! amplifies the noise several-fold. [`fit_adaptive`] chooses the window
//! per sample by a plug-in bias–variance criterion: over nested windows of
//! `min_window, min_window + 2, …, max_window` detections (as centred on
//! the sample as the track's ends allow) the velocity of the order-2 fit
//! has the noise variance `σ²·(XᵀX)⁻¹₁₁` per component and, from the
//! path's cubic term `c₃s³` that the quadratic cannot follow, the bias
//! `c₃·[(XᵀX)⁻¹Xᵀs³]₁` (on a centred window `c₃⟨s⁴⟩/⟨s²⟩`). `c₃` comes from
//! a pilot cubic fit over a window twice as long, with its own noise
//! variance subtracted from `c₃²` (an unbiased estimate of the squared
//! bias, floored at zero); the window of least predicted mean square
//! velocity error is taken, the squared bias weighted by `bias_weight`
//! (default 4 in the tracker: samples feed Eulerian means, where the noise
//! of many tracks averages out and the bias does not, so a sample's bias
//! is held to about half its noise rather than equal to it; on the
//! Lamb–Oseen vortex weight 1 leaves 1.07 % of v_max, weight 4 0.86 %).
//! `σ` is the position noise (the tracker's
//! estimate from its innovations), so the choice follows the expected
//! noise, not a short track's own few residuals. Straight stretches get
//! the longest window, sharp turns short ones. (An intersection of
//! confidence intervals rule was tried first: it lets the bias grow to a
//! few noise widths before it reacts and was worse than the fixed window
//! on the synthetic scene.)
//! Linear fits as further candidates at the track ends were tried as well
//! (bias from the pilot's quadratic coefficient): on short tracks that
//! coefficient is too noisy, and the ends of the synthetic scene's tracks
//! got worse (0.24 → 0.28 px/pulse at the last point), so only the order
//! asked for is fitted. The nested windows share their sums ([`Sums`]),
//! so a sample costs one pass over the pilot window and a small solve per
//! candidate; [`fit_eval`] is the reference the sums are tested against.
//!
//! # Curvature prior (short tracks and track ends)
//! At a track's ends and on short tracks the candidates are one-sided or
//! few-point quadratics whose own curvature is mostly noise (on a 5-point
//! track the quadratic coefficient's noise, 0.27 σ, exceeds the synthetic
//! flow's typical curvature, ~0.05 px/pulse²), and the slope at the end
//! of a quadratic is several times noisier than a line's; a line instead
//! is biased by the acceleration times the distance to the window's
//! centre (a choice between the two by the track's own curvature was tried
//! and is too noisy, above). With [`WindowRule::accel_rms`] every
//! quadratic candidate is the posterior mean under a Gaussian prior
//! c₂ ~ N(0, (a/2)²) per axis — a ridge `ρ = 4σ²/a²` on the quadratic
//! coefficient's normal equation — and the criterion takes its posterior
//! velocity variance `σ²·[(XᵀX + ρe₂e₂ᵀ)⁻¹]₁₁` (noise plus the prior's
//! expected shrinkage bias) and the cubic bias of the ridge fit. Short
//! and one-sided windows move towards the line as far as the flow's
//! typical curvature allows; long windows, whose curvature is measured
//! (noise ≪ a), are unaffected. `a` is a population quantity:
//! [`AccelPrior`] estimates it from the quadratic coefficients of disjoint
//! 7-detection stretches of the tracks kept so far, less their noise
//! (on the paper-like scene 0.105 px/pulse², where fixed values
//! 0.08–0.12 give the same result). A flow whose curvature varies
//! strongly (a vortex: large in the core, small outside) is not one
//! Gaussian: where the pilot's own curvature exceeds the prior's by more
//! than four times its noise variance, the prior widens to it (without
//! this the demo's track velocity error rose 0.0236 → 0.0262 px/pulse;
//! with it 0.0231). Paper-like 384² scene: velocity rms 0.149 → 0.134
//! px/pulse over all points, the last point of clean tracks 0.251 →
//! 0.200, tracks of 5–9 points 0.329 → 0.270, interior unchanged (0.063).
//! A prior mean of zero is the simple choice; the pilot's own c₂ as prior
//! mean would use the data twice.
//!
//! # The integer grid (fast path)
//! Detections sit at integer pulse indices and pulse times are regular, so
//! on a window without gaps τ − τ_centre is an exact integer offset and
//! everything in the criterion except the data — the normal matrices and
//! their inverses, the candidates' variance and bias factors, the pilot's
//! cubic-coefficient weights (Savitzky–Golay-like) — depends only on the
//! window's length and offset. [`GridTables`] holds these per window rule
//! (built once with the reference's own arithmetic on exact integer
//! moments), and [`fit_adaptive_grid`] costs a sample two short dot
//! products: ~5× fewer instructions than [`fit_adaptive`], which stays the
//! reference and the path for windows with gaps or irregular times. The
//! two agree to rounding (tests): the reference's τ, computed from µs
//! times, are off the integers by ~1e-11. With the curvature prior the
//! tables still serve: the ridge is a rank-one update of the tabulated
//! inverse (Sherman–Morrison), so a candidate's posterior variance and
//! bias cost a few flops more (the tabulated `(XᵀX)⁻¹Xᵀs³` gives the
//! bias); the short search from the largest window, shown unimodal for
//! the plain factors only, gives way to the full search over the
//! candidates. [`LeaveOneOut`] does the same for the tracker's outlier
//! pass.
//!
//! # Running moments along a track (the output fit's path)
//! The pilot's coefficients are its tabulated inverse rows times the
//! window's moments `Σ sᵃ·x` (a = 0..=3, s the offset from the sample),
//! and a candidate's fit is its inverse times `Σ sᵃ·x` (a = 0..=2). From
//! one sample to the next the pilot window slides by one (or stays, near
//! the track's ends) and the offsets shift by one, so the moments move in
//! O(1): [`GridRunFit`] keeps them (and the largest candidate's) as
//! running sums, summed afresh every [`RUN_RESTART`] samples, and caches
//! the centred candidates' prior-updated factors per track (they change
//! only where a sample's pilot widens the prior). A sample then costs a
//! few dozen flops for the moments and the criterion of each candidate
//! instead of two 43-point filters and the window's sums (~2 300 → ~830
//! instructions per sample on the water jet, ends and widened priors
//! included). The running sums are taken about a reference point rather
//! than the sample itself, which changes the last digits (~1e-13 px) but
//! not the window chosen except at ties to rounding; the tests compare it
//! with [`fit_adaptive`] at 1e-9.

/// A fitted state at one evaluation time (in the caller's τ units).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FitState {
    pub x: f64,
    pub y: f64,
    /// dx/dτ, dy/dτ.
    pub vx: f64,
    pub vy: f64,
    /// d²x/dτ², d²y/dτ².
    pub ax: f64,
    pub ay: f64,
    /// Residual rms per axis (px); 0 when the fit has no spare points.
    pub rms_residual: f64,
    /// Variance factor of the fitted position at the evaluation point.
    pub leverage: f64,
    /// Variance factor of the fitted velocity dx/dτ (0 for order 0): its
    /// noise is `σ·√velocity_variance` for position noise σ.
    pub velocity_variance: f64,
}

/// Fit `xs`, `ys` against `tau` with a polynomial of order `order` (0..=2,
/// lowered to what the number of points allows) and evaluate at `at`.
/// `None` for no points or a singular design (all τ equal with order ≥ 1).
pub fn fit_eval(tau: &[f64], xs: &[f64], ys: &[f64], order: usize, at: f64) -> Option<FitState> {
    let n = tau.len();
    if n == 0 {
        return None;
    }
    // The polynomial's size as a constant: the loops below unroll (the
    // output fit calls this ~2 times per track point). The arithmetic is
    // the same sequence for every size, so results do not depend on it.
    match order.min(2).min(n - 1) {
        0 => fit_eval_sized::<1>(tau, xs, ys, at),
        1 => fit_eval_sized::<2>(tau, xs, ys, at),
        _ => fit_eval_sized::<3>(tau, xs, ys, at),
    }
}

/// [`fit_eval`] with `P = order + 1` coefficients (`P` ≤ `tau.len()`).
fn fit_eval_sized<const P: usize>(
    tau: &[f64],
    xs: &[f64],
    ys: &[f64],
    at: f64,
) -> Option<FitState> {
    let n = tau.len();
    let (xs, ys) = (&xs[..n], &ys[..n]);
    let p = P;
    // Centre time on the evaluation point for conditioning and so that the
    // coefficients are directly the value and derivatives there.
    let mut ata = [[0.0f64; 3]; 3];
    let mut atx = [0.0f64; 3];
    let mut aty = [0.0f64; 3];
    for i in 0..n {
        let s = tau[i] - at;
        let row = [1.0, s, s * s];
        for a in 0..p {
            for b in 0..p {
                ata[a][b] += row[a] * row[b];
            }
            atx[a] += row[a] * xs[i];
            aty[a] += row[a] * ys[i];
        }
    }
    let inv = invert(&ata, P)?;
    let mut cx = [0.0; 3];
    let mut cy = [0.0; 3];
    for a in 0..p {
        for b in 0..p {
            cx[a] += inv[a][b] * atx[b];
            cy[a] += inv[a][b] * aty[b];
        }
    }
    let mut ssr = 0.0;
    for i in 0..n {
        let s = tau[i] - at;
        let fx = cx[0] + cx[1] * s + cx[2] * s * s;
        let fy = cy[0] + cy[1] * s + cy[2] * s * s;
        ssr += (xs[i] - fx).powi(2) + (ys[i] - fy).powi(2);
    }
    let dof = n - p;
    let rms_residual = if dof > 0 {
        (ssr / (2 * dof) as f64).sqrt()
    } else {
        0.0
    };
    Some(FitState {
        x: cx[0],
        y: cy[0],
        vx: cx[1],
        vy: cy[1],
        ax: 2.0 * cx[2],
        ay: 2.0 * cy[2],
        rms_residual,
        leverage: inv[0][0],
        velocity_variance: if p > 1 { inv[1][1] } else { 0.0 },
    })
}

/// Least-squares sums of a window of samples `(s, x, y)`, `s` the time
/// relative to the evaluation point, positions relative to the first
/// sample added (for conditioning). Samples can only be added, which is
/// what nested windows need. Enough moments for fits up to order 3.
#[derive(Debug, Clone, Copy, Default)]
pub struct Sums {
    n: usize,
    /// Σ sᵏ, k = 0..=6.
    s: [f64; 7],
    sx: [f64; 4],
    sy: [f64; 4],
    xx: f64,
    yy: f64,
    x0: f64,
    y0: f64,
}

/// Coefficients (of 1, s, s², s³) and the inverse normal matrix of a fit.
struct Solved {
    cx: [f64; 4],
    cy: [f64; 4],
    inv: [[f64; 4]; 4],
    p: usize,
}

impl Sums {
    pub fn add(&mut self, s: f64, x: f64, y: f64) {
        if self.n == 0 {
            (self.x0, self.y0) = (x, y);
        }
        self.n += 1;
        let (x, y) = (x - self.x0, y - self.y0);
        let mut sk = 1.0;
        for k in 0..7 {
            self.s[k] += sk;
            if k < 4 {
                self.sx[k] += sk * x;
                self.sy[k] += sk * y;
            }
            sk *= s;
        }
        self.xx += x * x;
        self.yy += y * y;
    }

    pub fn len(&self) -> usize {
        self.n
    }

    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    /// The inverse normal matrix of the fit of order ≤ `order` and its
    /// size `p` (the order lowered to what the samples allow, plus one);
    /// `ridge` (≥ 0) is added to the quadratic coefficient's diagonal
    /// entry of a quadratic fit (`p` = 3): the prior on the curvature
    /// (see [`WindowRule::accel_rms`]).
    fn inverse(&self, order: usize, ridge: f64) -> Option<([[f64; 4]; 4], usize)> {
        if self.n == 0 {
            return None;
        }
        let p = order.min(3).min(self.n - 1) + 1;
        let mut ata = [[0.0f64; 4]; 4];
        for (a, row) in ata.iter_mut().enumerate().take(p) {
            for (b, v) in row.iter_mut().enumerate().take(p) {
                *v = self.s[a + b];
            }
        }
        if p == 3 {
            ata[2][2] += ridge;
        }
        let inv = if p == 3 {
            invert_sym3(&ata)?
        } else {
            invert(&ata, p)?
        };
        Some((inv, p))
    }

    fn coefficients(&self, order: usize, ridge: f64) -> Option<Solved> {
        let (inv, p) = self.inverse(order, ridge)?;
        let (mut cx, mut cy) = ([0.0; 4], [0.0; 4]);
        for (a, row) in inv.iter().enumerate().take(p) {
            let dot = |v: &[f64; 4]| row[..p].iter().zip(&v[..p]).map(|(i, x)| i * x).sum();
            cx[a] = dot(&self.sx);
            cy[a] = dot(&self.sy);
        }
        Some(Solved { cx, cy, inv, p })
    }

    /// The fit of order ≤ `order` (≤ 2, lowered to what the points allow)
    /// evaluated at s = 0; `None` when empty or singular. Equal to
    /// [`fit_eval`] over the same samples up to rounding.
    pub fn solve(&self, order: usize) -> Option<FitState> {
        self.solve_with_prior(order, 0.0)
    }

    /// [`Sums::solve`] with the curvature prior: `ridge` = σ²/var(c₂)
    /// added to the quadratic coefficient's normal equation (a quadratic
    /// fit only; 0 gives [`Sums::solve`]). `leverage` and
    /// `velocity_variance` are then the posterior variance factors (noise
    /// plus the prior's expected shrinkage bias).
    pub fn solve_with_prior(&self, order: usize, ridge: f64) -> Option<FitState> {
        let c = self.coefficients(order.min(2), ridge)?;
        let p = c.p;
        // Residual sum of squares: xᵀx − cᵀ(Aᵀx) for least squares; the
        // ridge's normal equations (AᵀA + R)c = Aᵀx take off ρ·c₂² more.
        let shrink = if p == 3 {
            ridge * (c.cx[2] * c.cx[2] + c.cy[2] * c.cy[2])
        } else {
            0.0
        };
        let ssr: f64 = self.xx + self.yy
            - shrink
            - (0..p)
                .map(|a| c.cx[a] * self.sx[a] + c.cy[a] * self.sy[a])
                .sum::<f64>();
        let dof = self.n - p;
        Some(FitState {
            x: c.cx[0] + self.x0,
            y: c.cy[0] + self.y0,
            vx: c.cx[1],
            vy: c.cy[1],
            ax: 2.0 * c.cx[2],
            ay: 2.0 * c.cy[2],
            rms_residual: if dof > 0 {
                (ssr.max(0.0) / (2 * dof) as f64).sqrt()
            } else {
                0.0
            },
            leverage: c.inv[0][0],
            velocity_variance: if p > 1 { c.inv[1][1] } else { 0.0 },
        })
    }

    /// The fit's velocity error per unit cubic coefficient: a path
    /// `x = … + c₃s³` gives the fit of order `order` the velocity bias
    /// `c₃ · velocity_bias_factor` (the regression of s³ on the basis).
    pub fn velocity_bias_factor(&self, order: usize) -> Option<f64> {
        self.velocity_variance_and_bias(order, 0.0).map(|v| v.1)
    }

    /// `(velocity_variance, velocity_bias_factor)` from one solve (with
    /// the curvature prior `ridge`, as [`Sums::solve_with_prior`]).
    fn velocity_variance_and_bias(&self, order: usize, ridge: f64) -> Option<(f64, f64)> {
        // Only the inverse: the candidates' coefficients are not needed.
        let (inv, p) = self.inverse(order.min(2), ridge)?;
        if p < 2 {
            return Some((0.0, 0.0));
        }
        let b = (0..p).map(|b| inv[1][b] * self.s[b + 3]).sum();
        Some((inv[1][1], b))
    }

    /// Cubic coefficients (x, y) of an order-3 fit and their variance
    /// factor; `None` with fewer than 5 samples (no spare point to tell a
    /// cubic from noise) or a singular design.
    pub fn cubic(&self) -> Option<(f64, f64, f64)> {
        self.pilot().map(|p| (p.c3[0], p.c3[1], p.c3_var))
    }

    /// The pilot's cubic fit: its cubic and quadratic coefficients and
    /// their variance factors; `None` as [`Sums::cubic`].
    fn pilot(&self) -> Option<Pilot> {
        if self.n < 5 {
            return None;
        }
        let c = self.coefficients(3, 0.0)?;
        (c.p == 4).then(|| Pilot {
            c3: [c.cx[3], c.cy[3]],
            c3_var: c.inv[3][3],
            c2: [c.cx[2], c.cy[2]],
            c2_var: c.inv[2][2],
        })
    }
}

/// The pilot's curvature widens the prior only beyond this many times its
/// noise variance: a short track's pilot curvature is mostly noise, and
/// widening by it (noise subtracted once) took back half the prior's gain
/// on the synthetic scene.
const WIDEN_NOISE: f64 = 4.0;

/// What the pilot cubic tells the window choice (x, y coefficients).
struct Pilot {
    c3: [f64; 2],
    c3_var: f64,
    c2: [f64; 2],
    c2_var: f64,
}

/// The curvature prior's ridge for one sample: `ridge` (σ²/var(c₂) of
/// the population prior, 0 for none), widened where the pilot's own
/// squared curvature `c2sq` (x² + y², less its noise) is larger than the
/// prior's variance — a vortex core's tracks are not shrunk towards the
/// straight line the slow outer flow sets (the demo's velocity error went
/// up by 11 % without this).
fn widened_ridge(ridge: f64, sigma: f64, c2sq: f64) -> f64 {
    if ridge > 0.0 && c2sq > 0.0 {
        ridge.min(2.0 * sigma * sigma / c2sq)
    } else {
        ridge
    }
}

/// How [`fit_adaptive`] chooses its window.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WindowRule {
    /// Smallest window (detections).
    pub min_window: usize,
    /// Largest window (detections); `min_window ≥ max_window` gives the
    /// fixed window `max_window`.
    pub max_window: usize,
    /// Polynomial order (≤ 2).
    pub order: usize,
    /// Position noise per axis (px).
    pub sigma: f64,
    /// Weight of the squared bias against the noise variance in the
    /// criterion (1: least mean square error of one sample).
    pub bias_weight: f64,
    /// Prior rms acceleration per axis (px/τ²) of the quadratic fits; 0
    /// (or not finite) for none. With it each quadratic candidate is the
    /// posterior mean under a Gaussian prior on the curvature (a ridge
    /// `4σ²/accel_rms²` on the quadratic coefficient's normal equation),
    /// and its velocity variance factor the posterior one: a short or
    /// one-sided window, whose own curvature is mostly noise, is pulled
    /// towards the straight line as far as the flow's typical curvature
    /// allows; a long window is unaffected (module docs).
    pub accel_rms: f64,
}

impl WindowRule {
    /// The ridge σ²/var(c₂) of the curvature prior (c₂ = a/2), 0 without
    /// one or for fits below order 2.
    pub fn ridge(&self) -> f64 {
        if self.order >= 2 && self.accel_rms.is_finite() && self.accel_rms > 0.0 {
            let c2 = 0.5 * self.accel_rms;
            let r = self.sigma * self.sigma / (c2 * c2);
            if r.is_finite() {
                return r;
            }
        }
        0.0
    }
}

/// Candidate windows of one sample at most (min 2, step 2 up to 64).
const MAX_CANDIDATES: usize = 32;

/// Fit the samples `(tau, xs, ys)` (sorted by τ) around index `centre`
/// and evaluate at `at`, with the window of `min_window, min_window + 2, …,
/// max_window` samples (each as centred on `centre` as the ends allow, so
/// each holds the one before) of least predicted velocity error (module
/// docs). Returns the fit and its window; `None` when no window can be
/// fitted.
pub fn fit_adaptive(
    tau: &[f64],
    xs: &[f64],
    ys: &[f64],
    centre: usize,
    at: f64,
    rule: &WindowRule,
) -> Option<(FitState, usize)> {
    fit_adaptive_with(tau, xs, ys, centre, at, rule, true)
}

/// [`fit_adaptive`]; without `residual` and with the curvature prior the
/// residual pass is skipped and `rms_residual` is NaN (the output fit
/// does not read it); every other field is the same, bit for bit.
pub(crate) fn fit_adaptive_with(
    tau: &[f64],
    xs: &[f64],
    ys: &[f64],
    centre: usize,
    at: f64,
    rule: &WindowRule,
    residual: bool,
) -> Option<(FitState, usize)> {
    let n = tau.len();
    if n == 0 {
        return None;
    }
    let wmax = rule.max_window.clamp(1, n);
    let wmin = rule.min_window.clamp(1, wmax);
    let centre = centre.min(n - 1);
    let ridge = rule.ridge();
    // Fixed window: the plain fit (with the prior, its sums).
    if wmin == wmax {
        let start = centre.saturating_sub(wmax / 2).min(n - wmax);
        let w = start..start + wmax;
        if ridge > 0.0 {
            let mut sums = Sums::default();
            for i in w.clone() {
                sums.add(tau[i] - at, xs[i], ys[i]);
            }
            return sums.solve_with_prior(rule.order, ridge).map(|f| {
                (
                    with_direct_residual(f, tau, xs, ys, w, at, rule.order),
                    wmax,
                )
            });
        }
        return fit_eval(&tau[w.clone()], &xs[w.clone()], &ys[w], rule.order, at)
            .map(|f| (f, wmax));
    }
    let pilot = (2 * wmax + 1).min(n);
    let mut sums = Sums::default();
    let (mut lo, mut hi) = (usize::MAX, 0usize);
    // (sums, window, velocity variance factor, bias factor) per candidate;
    // only the chosen one is evaluated in full. A vector of the candidates
    // there are, not an array of MAX_CANDIDATES: zeroing that array (6 KB)
    // cost more than the rest of the call.
    let mut cands: Vec<(Sums, usize, f64, f64)> =
        Vec::with_capacity(((wmax - wmin) / 2 + 2).min(MAX_CANDIDATES));
    let mut nc = 0;
    let mut w = wmin;
    loop {
        let start = centre.saturating_sub(w / 2).min(n - w);
        if lo == usize::MAX {
            (lo, hi) = (start, start);
        }
        while lo > start {
            lo -= 1;
            sums.add(tau[lo] - at, xs[lo], ys[lo]);
        }
        while hi < start + w {
            sums.add(tau[hi] - at, xs[hi], ys[hi]);
            hi += 1;
        }
        if w <= wmax && nc < MAX_CANDIDATES {
            cands.push((sums, w, 0.0, 0.0));
            nc += 1;
        }
        if w >= pilot {
            break;
        }
        w = if w < wmax { (w + 2).min(wmax) } else { pilot };
    }
    // Squared cubic coefficient (x² + y²) from the pilot, less its noise;
    // the prior widened to the pilot's own curvature where that is
    // clearly larger.
    let (c3sq, ridge) = match (rule.order >= 2).then(|| sums.pilot()).flatten() {
        Some(p) => {
            let s2 = rule.sigma.powi(2);
            let c3sq = (p.c3[0].powi(2) + p.c3[1].powi(2) - 2.0 * s2 * p.c3_var).max(0.0);
            let c2sq =
                (p.c2[0].powi(2) + p.c2[1].powi(2) - WIDEN_NOISE * 2.0 * s2 * p.c2_var).max(0.0);
            (c3sq, widened_ridge(ridge, rule.sigma, c2sq))
        }
        None => (0.0, ridge),
    };
    // The candidates' factors under this sample's prior.
    let mut ok = 0;
    for k in 0..nc {
        if let Some((v, b)) = cands[k].0.velocity_variance_and_bias(rule.order, ridge) {
            (cands[k].2, cands[k].3) = (v, b);
            cands[ok] = cands[k];
            ok += 1;
        }
    }
    let nc = ok;
    let s2 = rule.sigma * rule.sigma;
    let best = cands[..nc]
        .iter()
        .map(|c| (rule.bias_weight * c3sq * c.3 * c.3 + 2.0 * s2 * c.2, c))
        .min_by(|a, b| a.0.total_cmp(&b.0).then(b.1 .1.cmp(&a.1 .1)))?
        .1;
    let fit = best.0.solve_with_prior(rule.order, ridge)?;
    if ridge > 0.0 && !residual {
        let fit = FitState {
            rms_residual: f64::NAN,
            ..fit
        };
        return Some((fit, best.1));
    }
    if ridge > 0.0 {
        let start = centre.saturating_sub(best.1 / 2).min(n - best.1);
        let w = start..start + best.1;
        return Some((
            with_direct_residual(fit, tau, xs, ys, w, at, rule.order),
            best.1,
        ));
    }
    Some((fit, best.1))
}

/// `f` with its residual rms taken from the residuals themselves: with the
/// curvature prior the sums' shortcut (xᵀx less the fitted part) loses
/// the digits of a nearly exact fit to cancellation, which the tabulated
/// path's different (equal to rounding) inverse would not reproduce.
fn with_direct_residual(
    mut f: FitState,
    tau: &[f64],
    xs: &[f64],
    ys: &[f64],
    w: std::ops::Range<usize>,
    at: f64,
    order: usize,
) -> FitState {
    let p = order.min(2).min(w.len() - 1) + 1;
    let dof = w.len() - p;
    let mut ssr = 0.0;
    for i in w {
        let s = tau[i] - at;
        let rx = xs[i] - (f.x + s * (f.vx + 0.5 * s * f.ax));
        let ry = ys[i] - (f.y + s * (f.vy + 0.5 * s * f.ay));
        ssr += rx * rx + ry * ry;
    }
    f.rms_residual = if dof > 0 {
        (ssr / (2 * dof) as f64).sqrt()
    } else {
        0.0
    };
    f
}

/// Tolerance (in pulse periods) within which a detection's τ counts as
/// lying on the integer grid: [`grid_tolerance`] adds the rounding of the
/// time values themselves.
const GRID_TOLERANCE: f64 = 1e-9;

/// How far (in τ units) a τ computed from times up to `t_max_abs` µs with
/// period `period_us` may stray from its integer value by rounding alone:
/// the fast path takes a detection as on the grid within this distance.
pub fn grid_tolerance(t_max_abs: f64, period_us: f64) -> f64 {
    GRID_TOLERANCE + 64.0 * f64::EPSILON * (t_max_abs / period_us.abs().max(1e-300))
}

/// The samples one [`fit_adaptive`] call reads (its pilot window; for a
/// fixed window, that window): `n` samples, evaluation at `centre`.
pub fn adaptive_span(n: usize, centre: usize, rule: &WindowRule) -> std::ops::Range<usize> {
    if n == 0 {
        return 0..0;
    }
    let wmax = rule.max_window.clamp(1, n);
    let wmin = rule.min_window.clamp(1, wmax);
    let centre = centre.min(n - 1);
    let w = if wmin == wmax {
        wmax
    } else {
        (2 * wmax + 1).min(n)
    };
    let start = centre.saturating_sub(w / 2).min(n - w);
    start..start + w
}

/// One candidate window on the integer grid: what [`fit_adaptive`]
/// derives from the window's time moments alone, tabulated.
#[derive(Debug, Clone, Copy, Default)]
struct GridWindow {
    /// The moments give a fit at all (never false for distinct τ).
    ok: bool,
    /// Velocity variance factor `(XᵀX)⁻¹₁₁` and cubic bias factor.
    variance: f64,
    bias: f64,
    /// Coefficients of the fit (`p = order + 1`, lowered to what the
    /// window allows) and the inverse normal matrix.
    p: usize,
    inv: [[f64; 3]; 3],
    /// `(XᵀX)⁻¹Xᵀs³`: the regression of the cubic on the basis (`bias`
    /// is its velocity entry), for the bias under the curvature prior.
    cubic_regression: [f64; 3],
}

impl GridWindow {
    /// The inverse normal matrix with the curvature prior's `ridge` on
    /// the quadratic coefficient (Sherman–Morrison on the tabulated
    /// inverse: `(A + ρe₂e₂ᵀ)⁻¹ = A⁻¹ − k·A⁻¹e₂e₂ᵀA⁻¹`, `k = ρ/(1 +
    /// ρA⁻¹₂₂)`), and `k` (0 without a prior or below order 2).
    #[inline]
    fn inverse_with_prior(&self, ridge: f64) -> ([[f64; 3]; 3], f64) {
        if self.p < 3 || ridge <= 0.0 {
            return (self.inv, 0.0);
        }
        let k = ridge / (1.0 + ridge * self.inv[2][2]);
        let mut inv = self.inv;
        for (a, row) in inv.iter_mut().enumerate() {
            for (b, v) in row.iter_mut().enumerate() {
                *v -= k * self.inv[a][2] * self.inv[2][b];
            }
        }
        (inv, k)
    }

    /// Velocity variance and cubic bias factors under the prior `ridge`
    /// (the tabulated ones without).
    #[inline]
    fn variance_and_bias(&self, ridge: f64) -> (f64, f64) {
        if self.p < 3 || ridge <= 0.0 {
            return (self.variance, self.bias);
        }
        let k = ridge / (1.0 + ridge * self.inv[2][2]);
        let i12 = self.inv[1][2];
        (
            self.variance - k * i12 * i12,
            self.bias - k * i12 * self.cubic_regression[2],
        )
    }
}

/// Tables of [`fit_adaptive`] for samples on the integer τ grid without
/// gaps (detections at consecutive pulses, evaluation at one of them).
///
/// On such a window the normal matrix `XᵀX`, its inverse, the velocity
/// variance and bias factors of every candidate and the pilot's cubic
/// coefficient filter (Savitzky–Golay-like weights) depend only on the
/// window's length and its offset from the evaluation sample, not on the
/// data: they are computed once here (with the reference's own [`Sums`]
/// arithmetic on the exact integer moments) and a sample costs the
/// pilot's cubic dot products and the chosen window's moments.
/// [`fit_adaptive_grid`] is the fast path; [`fit_adaptive`] the reference
/// and the path for windows with gaps or irregular times.
#[derive(Debug, Clone)]
pub struct GridTables {
    min_window: usize,
    max_window: usize,
    order: usize,
    /// Candidate windows, `w` in 1..=max_window, offset `o = start −
    /// centre` in −(w−1)..=0, at `w(w−1)/2 + (o + w − 1)`.
    windows: Vec<GridWindow>,
    /// Pilot windows, `w` in 1..=2·max_window+1: start of the cubic
    /// filter in `cubic_weights` (length `w`; the quadratic coefficient's
    /// filter at the same place in `quadratic_weights`), and the two
    /// variance factors (cubic, quadratic); `None` where [`Sums::cubic`]
    /// gives none.
    cubic: Vec<Option<(usize, f64, f64)>>,
    cubic_weights: Vec<f64>,
    quadratic_weights: Vec<f64>,
    /// Whether the centred candidates (every window centred on its
    /// sample, windows `min_window, min_window + 2, …, max_window`) have a
    /// unimodal criterion for any cubic coefficient (see
    /// [`GridTables::centred_unimodal`]): then the search runs down from
    /// the largest window and stops at the first rise.
    centred_unimodal: bool,
    /// The full-length pilot (window `2·max_window + 1`) with the sample
    /// at index i of it: rows 3 and 2 of its cubic fit's inverse normal
    /// matrix (the cubic and quadratic coefficients are these rows times
    /// the window's moments `Σ sᵃ·x`, a = 0..=3, s the offset from the
    /// sample) and their variance factors, at i; empty where a cubic fit
    /// of that window has none. [`GridRunFit`] takes the coefficients
    /// from running moments.
    pilot_rows: Vec<PilotRows>,
}

/// See [`GridTables::pilot_rows`].
#[derive(Debug, Clone, Copy)]
struct PilotRows {
    cubic_row: [f64; 4],
    quadratic_row: [f64; 4],
    cubic_var: f64,
    quadratic_var: f64,
}

#[inline]
fn grid_index(w: usize, offset: isize) -> usize {
    w * (w - 1) / 2 + (offset + w as isize - 1) as usize
}

impl GridTables {
    /// Tables for the window shape of `rule` (its σ and bias weight are
    /// applied per sample, so they do not enter).
    pub fn new(rule: &WindowRule) -> Self {
        let max_window = rule.max_window.max(1);
        let min_window = rule.min_window.clamp(1, max_window);
        let sums_of = |w: usize, o: isize| {
            let mut s = Sums::default();
            for k in 0..w {
                s.add((o + k as isize) as f64, 0.0, 0.0);
            }
            s
        };
        let mut windows = Vec::with_capacity(grid_index(max_window + 1, 0));
        for w in 1..=max_window {
            for o in -(w as isize - 1)..=0 {
                let s = sums_of(w, o);
                let vb = s.velocity_variance_and_bias(rule.order, 0.0);
                let c = s.coefficients(rule.order.min(2), 0.0);
                let mut gw = GridWindow::default();
                if let (Some((variance, bias)), Some(c)) = (vb, c) {
                    gw.ok = true;
                    gw.variance = variance;
                    gw.bias = bias;
                    gw.p = c.p;
                    for a in 0..3 {
                        gw.inv[a].copy_from_slice(&c.inv[a][..3]);
                        if a < c.p {
                            gw.cubic_regression[a] =
                                (0..c.p).map(|b| c.inv[a][b] * s.s[b + 3]).sum();
                        }
                    }
                }
                debug_assert_eq!(windows.len(), grid_index(w, o));
                windows.push(gw);
            }
        }
        let pilot_max = 2 * max_window + 1;
        let mut cubic = Vec::with_capacity(grid_index(pilot_max + 1, 0));
        let mut cubic_weights = Vec::new();
        let mut quadratic_weights = Vec::new();
        for w in 1..=pilot_max {
            for o in -(w as isize - 1)..=0 {
                let s = sums_of(w, o);
                let entry = match (s.n >= 5).then(|| s.coefficients(3, 0.0)).flatten() {
                    Some(c) if c.p == 4 => {
                        let at = cubic_weights.len();
                        for k in 0..w {
                            let t = (o + k as isize) as f64;
                            let filter =
                                |row: &[f64; 4]| row[0] + t * (row[1] + t * (row[2] + t * row[3]));
                            cubic_weights.push(filter(&c.inv[3]));
                            quadratic_weights.push(filter(&c.inv[2]));
                        }
                        Some((at, c.inv[3][3], c.inv[2][2]))
                    }
                    _ => None,
                };
                cubic.push(entry);
            }
        }
        let mut t = GridTables {
            min_window,
            max_window,
            order: rule.order,
            windows,
            cubic,
            cubic_weights,
            quadratic_weights,
            centred_unimodal: false,
            pilot_rows: Vec::new(),
        };
        t.centred_unimodal = t.centred_unimodal();
        let pilot_rows: Option<Vec<PilotRows>> = (0..pilot_max)
            .map(
                |i| match sums_of(pilot_max, -(i as isize)).coefficients(3, 0.0) {
                    Some(c) if c.p == 4 && pilot_max >= 5 => Some(PilotRows {
                        cubic_row: c.inv[3],
                        quadratic_row: c.inv[2],
                        cubic_var: c.inv[3][3],
                        quadratic_var: c.inv[2][2],
                    }),
                    _ => None,
                },
            )
            .collect();
        t.pilot_rows = pilot_rows.unwrap_or_default();
        t
    }

    /// The criterion of candidate k is `λ·Bₖ + Vₖ` (`Bₖ` the squared bias
    /// factor, `Vₖ` the variance factor, λ ≥ 0 from the sample's cubic
    /// coefficient). With `B` increasing and `V` decreasing in the window,
    /// going from window k+1 down to k lowers the criterion iff λ exceeds
    /// `λₖ = (Vₖ − Vₖ₊₁)/(Bₖ₊₁ − Bₖ)`; when `λₖ` never increases with k
    /// the windows where it does form a top run for every λ, so a search
    /// down from the largest window that stops at the first rise finds the
    /// least criterion.
    fn centred_unimodal(&self) -> bool {
        let mut ws = Vec::new();
        let mut w = self.min_window;
        while ws.len() < MAX_CANDIDATES {
            ws.push(w);
            if w >= self.max_window {
                break;
            }
            w = (w + 2).min(self.max_window);
        }
        let c = self.max_window; // any sample far enough from the ends
        let g: Vec<&GridWindow> = ws.iter().map(|&w| self.window(w, c - w / 2, c)).collect();
        if ws.len() < 2 || g.iter().any(|g| !g.ok) {
            return false;
        }
        let mut last = f64::INFINITY;
        for k in 0..g.len() - 1 {
            let db = g[k + 1].bias.powi(2) - g[k].bias.powi(2);
            let dv = g[k].variance - g[k + 1].variance;
            if !(db > 0.0 && dv > 0.0) {
                return false;
            }
            let lambda = dv / db;
            if lambda > last {
                return false;
            }
            last = lambda;
        }
        true
    }

    /// Whether these tables serve `rule` (same windows and order).
    pub fn serves(&self, rule: &WindowRule) -> bool {
        let max_window = rule.max_window.max(1);
        self.max_window == max_window
            && self.min_window == rule.min_window.clamp(1, max_window)
            && self.order == rule.order
    }

    /// Shared tables for `rule`'s shape, built once per process.
    pub fn cached(rule: &WindowRule) -> std::sync::Arc<GridTables> {
        use std::sync::{Arc, Mutex, OnceLock};
        static CACHE: OnceLock<Mutex<Vec<Arc<GridTables>>>> = OnceLock::new();
        let mut cache = CACHE
            .get_or_init(Default::default)
            .lock()
            .unwrap_or_else(|e| e.into_inner());
        if let Some(t) = cache.iter().find(|t| t.serves(rule)) {
            return t.clone();
        }
        let t = Arc::new(GridTables::new(rule));
        cache.push(t.clone());
        t
    }

    #[inline]
    fn window(&self, w: usize, start: usize, centre: usize) -> &GridWindow {
        &self.windows[grid_index(w, start as isize - centre as isize)]
    }
}

/// [`fit_adaptive`] for samples on the integer τ grid: the points `xy`
/// (x, y) of [`adaptive_span`]`(xy.len(), centre, rule)` are at τ = index
/// (their pulses consecutive, their times regular) and the evaluation is
/// at sample `centre`. The caller checks that; the result then equals
/// [`fit_adaptive`]'s up to rounding (tested), the same window chosen
/// unless two candidates' criteria agree to rounding. `tables` must
/// [`GridTables::serves`] `rule` (else the reference is used). Points are
/// interleaved so that x and y go through the sums side by side (the
/// compiler pairs them in one vector register).
pub fn fit_adaptive_grid(
    tables: &GridTables,
    xy: &[[f64; 2]],
    centre: usize,
    rule: &WindowRule,
) -> Option<(FitState, usize)> {
    fit_adaptive_grid_with(tables, xy, centre, rule, true)
}

/// [`fit_adaptive_grid`]; without `residual` the state's `rms_residual`
/// is not computed (NaN): the output fit does not use it, and with the
/// curvature prior it costs a second pass over the window.
pub(crate) fn fit_adaptive_grid_with(
    tables: &GridTables,
    xy: &[[f64; 2]],
    centre: usize,
    rule: &WindowRule,
    residual: bool,
) -> Option<(FitState, usize)> {
    let n = xy.len();
    if n == 0 {
        return None;
    }
    if !tables.serves(rule) {
        let tau: Vec<f64> = (0..n).map(|i| i as f64).collect();
        let (xs, ys): (Vec<f64>, Vec<f64>) = xy.iter().map(|p| (p[0], p[1])).unzip();
        let c = centre.min(n - 1);
        return fit_adaptive(&tau, &xs, &ys, c, c as f64, rule);
    }
    let wmax = rule.max_window.clamp(1, n);
    let wmin = rule.min_window.clamp(1, wmax);
    let centre = centre.min(n - 1);
    let ridge = rule.ridge();
    let start_of = |w: usize| centre.saturating_sub(w / 2).min(n - w);
    if wmin == wmax {
        let start = start_of(wmax);
        return grid_solve(
            tables.window(wmax, start, centre),
            xy,
            start,
            wmax,
            centre,
            ridge,
            residual,
        )
        .map(|f| (f, wmax));
    }
    let pilot = (2 * wmax + 1).min(n);
    let (c3sq, ridge) = if rule.order >= 2 {
        let start = start_of(pilot);
        match tables.cubic[grid_index(pilot, start as isize - centre as isize)] {
            Some((at, v, v2)) => {
                let g = &tables.cubic_weights[at..at + pilot];
                let p0 = xy[centre];
                let s2 = rule.sigma.powi(2);
                let mut c = [0.0f64; 2];
                if ridge > 0.0 {
                    // The pilot's curvature too, for the widened prior.
                    let h = &tables.quadratic_weights[at..at + pilot];
                    let mut q = [0.0f64; 2];
                    for ((g, h), p) in g.iter().zip(h).zip(&xy[start..start + pilot]) {
                        let d = [p[0] - p0[0], p[1] - p0[1]];
                        c[0] += g * d[0];
                        c[1] += g * d[1];
                        q[0] += h * d[0];
                        q[1] += h * d[1];
                    }
                    let c2sq = (q[0] * q[0] + q[1] * q[1] - WIDEN_NOISE * 2.0 * s2 * v2).max(0.0);
                    (
                        (c[0] * c[0] + c[1] * c[1] - 2.0 * s2 * v).max(0.0),
                        widened_ridge(ridge, rule.sigma, c2sq),
                    )
                } else {
                    for (g, p) in g.iter().zip(&xy[start..start + pilot]) {
                        c[0] += g * (p[0] - p0[0]);
                        c[1] += g * (p[1] - p0[1]);
                    }
                    ((c[0] * c[0] + c[1] * c[1] - 2.0 * s2 * v).max(0.0), 0.0)
                }
            }
            None => (0.0, ridge),
        }
    } else {
        (0.0, ridge)
    };
    let s2 = rule.sigma * rule.sigma;
    let criterion = |g: &GridWindow| {
        let (variance, bias) = g.variance_and_bias(ridge);
        rule.bias_weight * c3sq * bias * bias + 2.0 * s2 * variance
    };
    // Every candidate centred (the sample at least max_window/2 from both
    // ends) and the criterion unimodal in the window: search down from the
    // largest window, stop at the first rise. The same window as the full
    // search below (up to criteria equal to rounding). Shown for the
    // tabulated factors only: with a curvature prior, the full search.
    if ridge == 0.0
        && tables.centred_unimodal
        && wmax == tables.max_window
        && centre >= wmax / 2
        && centre + wmax - wmax / 2 <= n
        && (wmax - wmin + 1) / 2 < MAX_CANDIDATES
    {
        let mut w = wmax;
        let g = tables.window(w, centre - w / 2, centre);
        let mut best = (criterion(g), w);
        while w > wmin {
            let next = if (w - wmin) % 2 == 1 { w - 1 } else { w - 2 };
            let crit = criterion(tables.window(next, centre - next / 2, centre));
            if crit < best.0 {
                best = (crit, next);
                w = next;
            } else {
                break;
            }
        }
        let w = best.1;
        return grid_solve(
            tables.window(w, centre - w / 2, centre),
            xy,
            centre - w / 2,
            w,
            centre,
            0.0,
            residual,
        )
        .map(|f| (f, w));
    }
    // The candidates in increasing size: the least criterion wins, on a
    // tie the larger window (as in the reference).
    let mut best: Option<(f64, usize, usize)> = None;
    let (mut w, mut nc) = (wmin, 0);
    while nc < MAX_CANDIDATES {
        let start = start_of(w);
        let g = tables.window(w, start, centre);
        if g.ok {
            nc += 1;
            let crit = criterion(g);
            if best.map_or(true, |b| crit.total_cmp(&b.0).is_le()) {
                best = Some((crit, w, start));
            }
        }
        if w >= wmax {
            break;
        }
        w = (w + 2).min(wmax);
    }
    let (_, w, start) = best?;
    grid_solve(
        tables.window(w, start, centre),
        xy,
        start,
        w,
        centre,
        ridge,
        residual,
    )
    .map(|f| (f, w))
}

/// The fit over points `start..start + w` at τ = index, evaluated at
/// `centre`, from the tabulated inverse: [`Sums::solve_with_prior`]'s
/// arithmetic on moments taken about the centre point.
/// Without `residual`, `rms_residual` is NaN (not computed).
fn grid_solve(
    g: &GridWindow,
    xy: &[[f64; 2]],
    start: usize,
    w: usize,
    centre: usize,
    ridge: f64,
    residual: bool,
) -> Option<FitState> {
    if !g.ok {
        return None;
    }
    let (inv, k) = g.inverse_with_prior(ridge);
    grid_solve_inv(g.p, &inv, k, xy, start, w, centre, ridge, residual)
}

/// [`grid_solve`] with the (prior-updated) inverse and its `k` given.
#[allow(clippy::too_many_arguments)]
#[inline]
fn grid_solve_inv(
    p: usize,
    inv: &[[f64; 3]; 3],
    k: f64,
    xy: &[[f64; 2]],
    start: usize,
    w: usize,
    centre: usize,
    ridge: f64,
    residual: bool,
) -> Option<FitState> {
    let ridge = if k > 0.0 { ridge } else { 0.0 };
    let p0 = xy[centre];
    // Σ sᵃ·d for a = 0, 1, 2 and Σ d², d the offset from the centre point.
    let (mut m0, mut m1, mut m2, mut sq) = ([0.0f64; 2], [0.0f64; 2], [0.0f64; 2], [0.0f64; 2]);
    let mut s = start as f64 - centre as f64;
    for q in &xy[start..start + w] {
        let d = [q[0] - p0[0], q[1] - p0[1]];
        let ss = s * s;
        for k in 0..2 {
            m0[k] += d[k];
            m1[k] += s * d[k];
            m2[k] += ss * d[k];
            sq[k] += d[k] * d[k];
        }
        s += 1.0;
    }
    let (mx, my) = ([m0[0], m1[0], m2[0]], [m0[1], m1[1], m2[1]]);
    let (mut cx, mut cy) = ([0.0f64; 3], [0.0f64; 3]);
    for a in 0..p {
        for b in 0..p {
            cx[a] += inv[a][b] * mx[b];
            cy[a] += inv[a][b] * my[b];
        }
    }
    let ssr: f64 = if !residual {
        f64::NAN
    } else if ridge > 0.0 {
        // As the reference: from the residuals (see with_direct_residual).
        let mut ssr = 0.0;
        let mut s = start as f64 - centre as f64;
        for q in &xy[start..start + w] {
            let rx = q[0] - p0[0] - (cx[0] + s * (cx[1] + s * cx[2]));
            let ry = q[1] - p0[1] - (cy[0] + s * (cy[1] + s * cy[2]));
            ssr += rx * rx + ry * ry;
            s += 1.0;
        }
        ssr
    } else {
        sq[0] + sq[1] - (0..p).map(|a| cx[a] * mx[a] + cy[a] * my[a]).sum::<f64>()
    };
    let dof = w - p;
    Some(FitState {
        x: cx[0] + p0[0],
        y: cy[0] + p0[1],
        vx: cx[1],
        vy: cy[1],
        ax: 2.0 * cx[2],
        ay: 2.0 * cy[2],
        rms_residual: if !residual {
            f64::NAN
        } else if dof > 0 {
            (ssr.max(0.0) / (2 * dof) as f64).sqrt()
        } else {
            0.0
        },
        leverage: inv[0][0],
        velocity_variance: if p > 1 { inv[1][1] } else { 0.0 },
    })
}

/// Steps of [`GridRunFit`]'s running moments before they are summed
/// afresh: bounds the rounding they pick up (each step's re-centring
/// carries an error of the zeroth moment into the higher ones with
/// powers of the distance travelled).
const RUN_RESTART: usize = 32;

/// Running moments `Σ sᵃ·(x − origin)` (a < `A`, per axis) of a window of
/// samples, `s` the offset from the evaluation sample: moved to the next
/// sample in O(1) — the window slides by one (one sample out, one in) or
/// stays (at a track's ends), then the offsets shift by one (binomial).
#[derive(Debug, Clone, Copy)]
struct RunningMoments<const A: usize> {
    start: usize,
    m: [[f64; 2]; A],
}

impl<const A: usize> RunningMoments<A> {
    /// Summed afresh over `start..start + len` about sample `centre`.
    fn new(xy: &[[f64; 2]], origin: [f64; 2], start: usize, len: usize, centre: usize) -> Self {
        let mut m = [[0.0f64; 2]; A];
        let mut s = start as f64 - centre as f64;
        for q in &xy[start..start + len] {
            let d = [q[0] - origin[0], q[1] - origin[1]];
            let mut sa = 1.0;
            for row in m.iter_mut() {
                row[0] += sa * d[0];
                row[1] += sa * d[1];
                sa *= s;
            }
            s += 1.0;
        }
        RunningMoments { start, m }
    }

    /// From sample `centre` to `centre + 1`, the window now at `start`
    /// (the old start or one more).
    #[inline]
    fn step(&mut self, xy: &[[f64; 2]], origin: [f64; 2], len: usize, centre: usize, start: usize) {
        let m = &mut self.m;
        if start != self.start {
            let (out, inn) = (xy[self.start], xy[self.start + len]);
            let so = self.start as f64 - centre as f64;
            let si = so + len as f64;
            let (mut po, mut pi) = (1.0, 1.0);
            for row in m.iter_mut() {
                for a in 0..2 {
                    row[a] += pi * (inn[a] - origin[a]) - po * (out[a] - origin[a]);
                }
                po *= so;
                pi *= si;
            }
            self.start = start;
        }
        // s → s − 1: Σ (s − 1)ᵃ·d = Σ_b C(a, b)(−1)^(a−b) Σ sᵇ·d.
        for a in 0..2 {
            let c: [f64; 4] = std::array::from_fn(|k| if k < A { m[k][a] } else { 0.0 });
            if A > 1 {
                m[1][a] = c[1] - c[0];
            }
            if A > 2 {
                m[2][a] = c[2] - 2.0 * c[1] + c[0];
            }
            if A > 3 {
                m[3][a] = c[3] - 3.0 * c[2] + 3.0 * c[1] - c[0];
            }
        }
    }
}

/// One candidate window of [`GridRunFit`] at a centred sample: its table
/// entry and its factors and prior-updated inverse under the track's
/// population prior, computed once per track with [`GridWindow`]'s own
/// arithmetic (so bit for bit what [`fit_adaptive_grid`] computes per
/// sample).
#[derive(Debug, Clone, Copy)]
struct CentredCandidate {
    w: usize,
    window: usize,
    variance: f64,
    bias: f64,
    inv: [[f64; 3]; 3],
    k: f64,
}

/// [`fit_adaptive_grid`] along a gap-free run of a track of at least
/// `2·max_window + 1` samples, called for consecutive samples: instead of
/// the pilot's two filters over its `2·max_window + 1` samples and the
/// chosen window's sums, it keeps the pilot's moments `Σ sᵃ·x` (a =
/// 0..=3, s the offset from the sample) and the largest candidate
/// window's (a = 0..=2) as running sums, moved per sample in O(1)
/// ([`RunningMoments`]), summed afresh every [`RUN_RESTART`] samples; the
/// pilot's coefficients are its tabulated inverse rows (per offset of the
/// sample in the pilot window) times the moments. The centred candidates'
/// factors under the track's prior are computed once
/// ([`CentredCandidate`]); a sample whose pilot widens the prior, and the
/// samples near a track's ends, compute their own. Positions in the
/// running sums are taken from a reference point (the sample at the last
/// restart), which changes nothing but rounding: the candidates' fits and
/// the pilot's coefficients do not depend on a constant offset (the prior
/// acts on the curvature only). The result equals [`fit_adaptive_grid`]'s
/// to rounding (~1e-13 px; tested against [`fit_adaptive`]), the same
/// window chosen unless two candidates' criteria agree to rounding;
/// `rms_residual` is not computed (NaN).
#[derive(Debug, Clone)]
pub struct GridRunFit<'t> {
    tables: &'t GridTables,
    rule: WindowRule,
    ridge: f64,
    /// The candidate windows in the order of the search, centred.
    centred: Vec<CentredCandidate>,
    /// The running state: the sample it is centred on, the points it
    /// belongs to (address and length), the steps since the restart, the
    /// reference point, the pilot's and the largest window's moments.
    at: Option<usize>,
    of: (usize, usize),
    steps: usize,
    origin: [f64; 2],
    pilot: RunningMoments<4>,
    largest: RunningMoments<3>,
}

impl<'t> GridRunFit<'t> {
    /// `None` where the running path does not apply (a fixed window, an
    /// order below 2, tables for another rule, more candidates than the
    /// search takes): the caller takes [`fit_adaptive_grid`].
    pub fn new(tables: &'t GridTables, rule: &WindowRule) -> Option<Self> {
        let wmax = rule.max_window;
        if !tables.serves(rule)
            || rule.order < 2
            || tables.min_window >= wmax
            || wmax != tables.max_window
            || tables.pilot_rows.len() != 2 * wmax + 1
        {
            return None;
        }
        let ridge = rule.ridge();
        let centre = wmax; // a sample with max_window samples either side
        let mut centred = Vec::new();
        let mut w = tables.min_window;
        loop {
            let window = grid_index(w, -((w / 2) as isize));
            let g = &tables.windows[window];
            if !g.ok || centred.len() + 1 >= MAX_CANDIDATES {
                return None;
            }
            debug_assert!(std::ptr::eq(g, tables.window(w, centre - w / 2, centre)));
            let (variance, bias) = g.variance_and_bias(ridge);
            let (inv, k) = g.inverse_with_prior(ridge);
            centred.push(CentredCandidate {
                w,
                window,
                variance,
                bias,
                inv,
                k,
            });
            if w >= wmax {
                break;
            }
            w = (w + 2).min(wmax);
        }
        Some(GridRunFit {
            tables,
            rule: *rule,
            ridge,
            centred,
            at: None,
            of: (0, 0),
            steps: 0,
            origin: [0.0; 2],
            pilot: RunningMoments {
                start: 0,
                m: [[0.0; 2]; 4],
            },
            largest: RunningMoments {
                start: 0,
                m: [[0.0; 2]; 3],
            },
        })
    }

    /// Whether a track of `n` samples takes the running path (its pilot
    /// window has full length).
    #[inline]
    pub fn serves_track(&self, n: usize) -> bool {
        n > 2 * self.rule.max_window
    }

    /// The fit at sample `centre` of the track's points `xy` (τ = index;
    /// [`GridRunFit::serves_track`]), whose pilot window
    /// ([`adaptive_span`]) must be gap-free with regular times (the
    /// caller's check, as for [`fit_adaptive_grid`]). Consecutive samples
    /// of the same `xy` move the running sums; anything else starts them
    /// afresh.
    pub fn fit(&mut self, xy: &[[f64; 2]], centre: usize) -> Option<(FitState, usize)> {
        let n = xy.len();
        let h = self.rule.max_window;
        let (pl, wmax) = (2 * h + 1, h);
        if n < pl || centre >= n {
            return fit_adaptive_grid_with(self.tables, xy, centre, &self.rule, false);
        }
        let pilot_start = centre.saturating_sub(h).min(n - pl);
        let largest_start = centre.saturating_sub(wmax / 2).min(n - wmax);
        let same = self.of == (xy.as_ptr() as usize, n);
        match self.at {
            Some(c) if same && c + 1 == centre && self.steps < RUN_RESTART => {
                self.pilot.step(xy, self.origin, pl, c, pilot_start);
                self.largest.step(xy, self.origin, wmax, c, largest_start);
                self.steps += 1;
            }
            Some(c) if same && c == centre => {}
            _ => {
                self.origin = xy[centre];
                self.pilot = RunningMoments::new(xy, self.origin, pilot_start, pl, centre);
                self.largest = RunningMoments::new(xy, self.origin, largest_start, wmax, centre);
                (self.steps, self.of) = (0, (xy.as_ptr() as usize, n));
            }
        }
        self.at = Some(centre);
        let rule = &self.rule;
        let tables = self.tables;
        let wmin = tables.min_window;
        let s2 = rule.sigma * rule.sigma;
        // The pilot's cubic and quadratic coefficients from its moments.
        let rows = &tables.pilot_rows[centre - pilot_start];
        let pm = &self.pilot.m;
        let (mut c3, mut c2) = ([0.0f64; 2], [0.0f64; 2]);
        for a in 0..2 {
            for (b, m) in pm.iter().enumerate() {
                c3[a] += rows.cubic_row[b] * m[a];
                c2[a] += rows.quadratic_row[b] * m[a];
            }
        }
        let c3sq = (c3[0] * c3[0] + c3[1] * c3[1] - 2.0 * s2 * rows.cubic_var).max(0.0);
        let ridge = if self.ridge > 0.0 {
            let c2sq = (c2[0] * c2[0] + c2[1] * c2[1]
                - WIDEN_NOISE * 2.0 * s2 * rows.quadratic_var)
                .max(0.0);
            widened_ridge(self.ridge, rule.sigma, c2sq)
        } else {
            0.0
        };
        let own = ridge.to_bits() != self.ridge.to_bits();
        let interior = centre >= h && centre + h < n;
        let crit =
            |variance: f64, bias: f64| rule.bias_weight * c3sq * bias * bias + 2.0 * s2 * variance;
        // The window choice of fit_adaptive_grid: (window length, table
        // entry, index into `centred` when centred and cached).
        let (w, window, cached) = if interior
            && ridge == 0.0
            && tables.centred_unimodal
            && (wmax - wmin + 1) / 2 < MAX_CANDIDATES
        {
            // Down from the largest window to the first rise (the table
            // entries of windows between the candidates too).
            let criterion = |w: usize| {
                let (v, b) =
                    tables.windows[grid_index(w, -((w / 2) as isize))].variance_and_bias(0.0);
                crit(v, b)
            };
            let mut w = wmax;
            let mut best = (criterion(w), w);
            while w > wmin {
                let next = if (w - wmin) % 2 == 1 { w - 1 } else { w - 2 };
                let c = criterion(next);
                if c < best.0 {
                    best = (c, next);
                    w = next;
                } else {
                    break;
                }
            }
            let w = best.1;
            let window = grid_index(w, -((w / 2) as isize));
            (
                w,
                window,
                self.centred.iter().position(|c| c.window == window),
            )
        } else if interior {
            // Every candidate, the least criterion (on a tie the larger).
            let mut best = (f64::INFINITY, 0usize);
            for (i, c) in self.centred.iter().enumerate() {
                let (v, b) = if own {
                    tables.windows[c.window].variance_and_bias(ridge)
                } else {
                    (c.variance, c.bias)
                };
                let q = crit(v, b);
                if i == 0 || q.total_cmp(&best.0).is_le() {
                    best = (q, i);
                }
            }
            let c = &self.centred[best.1];
            (c.w, c.window, Some(best.1))
        } else {
            // Near an end: the candidates as centred as the ends allow.
            let mut best: Option<(f64, usize, usize)> = None;
            for c in &self.centred {
                let start = centre.saturating_sub(c.w / 2).min(n - c.w);
                let window = grid_index(c.w, start as isize - centre as isize);
                let g = &tables.windows[window];
                if g.ok {
                    let (v, b) = g.variance_and_bias(ridge);
                    let q = crit(v, b);
                    if best.map_or(true, |b| q.total_cmp(&b.0).is_le()) {
                        best = Some((q, c.w, window));
                    }
                }
            }
            let (_, w, window) = best?;
            (w, window, None)
        };
        let g = &tables.windows[window];
        if !g.ok {
            return None;
        }
        let (inv, k) = match cached {
            Some(i) if !own => (self.centred[i].inv, self.centred[i].k),
            _ => g.inverse_with_prior(ridge),
        };
        if w != wmax {
            let start = centre.saturating_sub(w / 2).min(n - w);
            return grid_solve_inv(g.p, &inv, k, xy, start, w, centre, ridge, false)
                .map(|f| (f, w));
        }
        // The largest window from its running moments.
        let p = g.p;
        let fm = &self.largest.m;
        let (mut cx, mut cy) = ([0.0f64; 3], [0.0f64; 3]);
        for a in 0..p {
            for b in 0..p {
                cx[a] += inv[a][b] * fm[b][0];
                cy[a] += inv[a][b] * fm[b][1];
            }
        }
        Some((
            FitState {
                x: cx[0] + self.origin[0],
                y: cy[0] + self.origin[1],
                vx: cx[1],
                vy: cy[1],
                ax: 2.0 * cx[2],
                ay: 2.0 * cy[2],
                rms_residual: f64::NAN,
                leverage: inv[0][0],
                velocity_variance: if p > 1 { inv[1][1] } else { 0.0 },
            },
            w,
        ))
    }
}

/// Detections per window of [`AccelPrior`]'s curvature samples.
const PRIOR_WINDOW: usize = 7;
/// ⟨s²⟩ and Σ (s² − ⟨s²⟩)² over s = −3..=3: the quadratic coefficient of
/// a centred 7-point fit is `Σ (s² − 4)·x / 84`, its noise variance
/// factor `1/84`.
const PRIOR_MEAN_S2: isize = 4;
const PRIOR_NORM: f64 = 84.0;
/// Curvature samples before the estimate is used (fewer: no prior).
const PRIOR_MIN_SAMPLES: u64 = 20;

/// The population estimate behind [`WindowRule::accel_rms`]: the flow's
/// rms acceleration per axis, from the quadratic coefficients of disjoint
/// gap-free 7-detection stretches of finished tracks, less their noise
/// variance `σ²/84` (unbiased; 7 rather than 11 detections so that the
/// estimate exists a few pulses earlier in a recording — tracks that end
/// before it do without a prior — which on the 60-pulse synthetic scene
/// gave 0.134 → 0.132 px/pulse before the widening).
/// The tracker adds each kept track in output order, so the estimate a
/// track is fitted with does not depend on the thread count.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct AccelPrior {
    /// Σ (c₂ₓ² + c₂ᵧ²) and the number of stretches.
    sum_sq: f64,
    samples: u64,
}

impl AccelPrior {
    /// Add the gap-free runs of a track: `pulses` (increasing) and its
    /// positions `xy`, τ in pulses.
    pub fn add_track(&mut self, pulses: &[i64], xy: &[[f64; 2]]) {
        let n = pulses.len().min(xy.len());
        let mut start = 0;
        while start + PRIOR_WINDOW <= n {
            let end = start + PRIOR_WINDOW;
            // The first break in the run restarts the stretch after it.
            if let Some(k) = (start + 1..end).find(|&k| pulses[k] != pulses[k - 1] + 1) {
                start = k;
                continue;
            }
            let c = PRIOR_WINDOW as isize / 2;
            let p0 = xy[start + c as usize];
            let mut c2 = [0.0f64; 2];
            for (k, p) in xy[start..end].iter().enumerate() {
                let s = k as isize - c;
                let g = (s * s - PRIOR_MEAN_S2) as f64 / PRIOR_NORM;
                c2[0] += g * (p[0] - p0[0]);
                c2[1] += g * (p[1] - p0[1]);
            }
            if c2[0].is_finite() && c2[1].is_finite() {
                self.sum_sq += c2[0] * c2[0] + c2[1] * c2[1];
                self.samples += 1;
            }
            start = end;
        }
    }

    /// Add another estimate's samples.
    pub fn merge(&mut self, other: &AccelPrior) {
        self.sum_sq += other.sum_sq;
        self.samples += other.samples;
    }

    /// Curvature samples so far.
    pub fn samples(&self) -> u64 {
        self.samples
    }

    /// The rms acceleration per axis (px/pulse²) for position noise
    /// `sigma`, 0 (no prior) before [`PRIOR_MIN_SAMPLES`] stretches. A
    /// flow without measurable curvature gets a floor of a quarter of the
    /// stretches' own noise variance, which pulls short fits nearly
    /// straight but keeps the ridge finite.
    pub fn accel_rms(&self, sigma: f64) -> f64 {
        if self.samples < PRIOR_MIN_SAMPLES {
            return 0.0;
        }
        let noise = sigma * sigma / PRIOR_NORM;
        let c2_var = (self.sum_sq / (2 * self.samples) as f64 - noise).max(0.25 * noise);
        2.0 * c2_var.sqrt()
    }
}

/// Leave-one-out quadratic predictions on the integer grid, for the
/// tracker's outlier pass: a quadratic fitted to `w + 1` samples at
/// consecutive τ with sample `e` left out, evaluated at sample `e`. On a
/// gap-free window the prediction is a fixed weighting of the other
/// samples (and its leverage a number): tabulated here for every `w` up to
/// `max_window` and every `e`, from the reference's own normal matrices
/// ([`fit_eval`] is what the tables are tested against).
#[derive(Debug, Clone)]
pub struct LeaveOneOut {
    max_window: usize,
    /// Per `w` (index `w`), per `e` in `0..=w`: weights of the `w + 1`
    /// samples (0 at `e`) and the leverage; `None` when the fit is singular.
    table: Vec<Vec<Option<(Vec<f64>, f64)>>>,
}

impl LeaveOneOut {
    /// Tables for windows of up to `max_window` fitted samples.
    pub fn new(max_window: usize) -> Self {
        let mut table = vec![Vec::new()];
        for w in 1..=max_window {
            let mut per_e = Vec::with_capacity(w + 1);
            for e in 0..=w {
                let taus: Vec<f64> = (0..=w)
                    .filter(|&k| k != e)
                    .map(|k| k as f64 - e as f64)
                    .collect();
                let p = 2.min(w - 1) + 1;
                let mut ata = [[0.0f64; 3]; 3];
                for &t in &taus {
                    let row = [1.0, t, t * t];
                    for a in 0..p {
                        for b in 0..p {
                            ata[a][b] += row[a] * row[b];
                        }
                    }
                }
                per_e.push(invert(&ata, p).map(|inv| {
                    let weights = (0..=w)
                        .map(|k| {
                            if k == e {
                                return 0.0;
                            }
                            let t = k as f64 - e as f64;
                            let row = [1.0, t, t * t];
                            (0..p).map(|b| inv[0][b] * row[b]).sum()
                        })
                        .collect();
                    (weights, inv[0][0])
                }));
            }
            table.push(per_e);
        }
        LeaveOneOut { max_window, table }
    }

    /// Shared tables for `max_window`, built once per process.
    pub fn cached(max_window: usize) -> std::sync::Arc<LeaveOneOut> {
        use std::sync::{Arc, Mutex, OnceLock};
        static CACHE: OnceLock<Mutex<Vec<Arc<LeaveOneOut>>>> = OnceLock::new();
        let mut cache = CACHE
            .get_or_init(Default::default)
            .lock()
            .unwrap_or_else(|e| e.into_inner());
        if let Some(t) = cache.iter().find(|t| t.max_window == max_window) {
            return t.clone();
        }
        let t = Arc::new(LeaveOneOut::new(max_window));
        cache.push(t.clone());
        t
    }

    /// `(dx, dy, leverage)`: the quadratic through the points `xy` (at τ
    /// = index, `w + 1 = xy.len()` points, `w ≤ max_window`) without
    /// point `e`, evaluated at τ = `e`, minus point `e`. The same as
    /// [`fit_eval`] over the other points (order 2) up to rounding; `None`
    /// outside the tables or for a singular fit.
    pub fn predict(&self, xy: &[[f64; 2]], e: usize) -> Option<(f64, f64, f64)> {
        let w = xy.len().checked_sub(1)?;
        let (weights, leverage) = self.table.get(w)?.get(e)?.as_ref()?;
        let p0 = xy[e];
        let mut d = [0.0f64; 2];
        for (g, p) in weights.iter().zip(xy) {
            d[0] += g * (p[0] - p0[0]);
            d[1] += g * (p[1] - p0[1]);
        }
        Some((d[0], d[1], *leverage))
    }
}

/// Inverse of the leading 3×3 block of a symmetric positive (semi)definite
/// matrix by cofactors — the hot path of [`fit_adaptive`]'s candidates;
/// `None` when (numerically) singular. [`invert`] is the reference.
fn invert_sym3(m: &[[f64; 4]; 4]) -> Option<[[f64; 4]; 4]> {
    let (a, b, c) = (m[0][0], m[0][1], m[0][2]);
    let (d, e, f) = (m[1][1], m[1][2], m[2][2]);
    let (ca, cb, cc) = (d * f - e * e, c * e - b * f, b * e - c * d);
    let (cd, ce, cf) = (a * f - c * c, b * c - a * e, a * d - b * b);
    let det = a * ca + b * cb + c * cc;
    if !det.is_finite() || det <= 1e-12 * (a * d * f).abs() {
        return None;
    }
    let r = 1.0 / det;
    let mut inv = [[0.0; 4]; 4];
    inv[0][..3].copy_from_slice(&[ca * r, cb * r, cc * r]);
    inv[1][..3].copy_from_slice(&[cb * r, cd * r, ce * r]);
    inv[2][..3].copy_from_slice(&[cc * r, ce * r, cf * r]);
    Some(inv)
}

/// Inverse of the leading `p`×`p` block (Gauss–Jordan with pivoting).
fn invert<const N: usize>(m: &[[f64; N]; N], p: usize) -> Option<[[f64; N]; N]> {
    let mut a = *m;
    let mut inv = [[0.0; N]; N];
    for (i, row) in inv.iter_mut().enumerate().take(p) {
        row[i] = 1.0;
    }
    let scale = (0..p).map(|i| a[i][i].abs()).fold(0.0, f64::max);
    for col in 0..p {
        let piv = (col..p).max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs()))?;
        if a[piv][col].abs() <= 1e-12 * scale.max(1e-300) {
            return None;
        }
        a.swap(col, piv);
        inv.swap(col, piv);
        let d = a[col][col];
        for k in 0..p {
            a[col][k] /= d;
            inv[col][k] /= d;
        }
        for r in 0..p {
            if r != col {
                let f = a[r][col];
                if f != 0.0 {
                    for k in 0..p {
                        a[r][k] -= f * a[col][k];
                        inv[r][k] -= f * inv[col][k];
                    }
                }
            }
        }
    }
    Some(inv)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exact_quadratic_is_recovered() {
        let tau: Vec<f64> = (0..7).map(|i| i as f64).collect();
        let xs: Vec<f64> = tau.iter().map(|t| 3.0 + 2.0 * t + 0.25 * t * t).collect();
        let ys: Vec<f64> = tau.iter().map(|t| -1.0 - 0.5 * t).collect();
        let f = fit_eval(&tau, &xs, &ys, 2, 8.0).unwrap();
        assert!((f.x - (3.0 + 16.0 + 16.0)).abs() < 1e-9);
        assert!((f.vx - (2.0 + 0.5 * 8.0)).abs() < 1e-9);
        assert!((f.ax - 0.5).abs() < 1e-9);
        assert!((f.y + 5.0).abs() < 1e-9 && (f.vy + 0.5).abs() < 1e-9 && f.ay.abs() < 1e-9);
        assert!(f.rms_residual < 1e-9);
    }

    #[test]
    fn linear_fit_leverage_matches_formula() {
        // Linear LSQ over τ = 0..n-1: var factor at τ0 is 1/n + (τ0-τ̄)²/Sxx.
        let tau: Vec<f64> = (0..5).map(|i| i as f64).collect();
        let z = vec![0.0; 5];
        let f = fit_eval(&tau, &z, &z, 1, 5.0).unwrap();
        let want = 1.0 / 5.0 + 9.0 / 10.0;
        assert!((f.leverage - want).abs() < 1e-12);
    }

    fn noisy_track(n: usize, seed: u64) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
        let tau: Vec<f64> = (0..n).map(|i| i as f64 + 0.01 * (i % 3) as f64).collect();
        let xs = tau
            .iter()
            .map(|t| 300.0 + 7.0 * t + 0.1 * t * t + rng.gen_range(-0.5..0.5))
            .collect();
        let ys = tau
            .iter()
            .map(|t| 80.0 - 2.0 * t + rng.gen_range(-0.5..0.5))
            .collect();
        (tau, xs, ys)
    }

    #[test]
    fn sums_match_the_reference_fit() {
        let (tau, xs, ys) = noisy_track(15, 3);
        for order in 0..=2 {
            for (lo, hi) in [(0, 15), (3, 8), (10, 15), (4, 6)] {
                let at = tau[(lo + hi) / 2] + 0.3;
                let mut s = Sums::default();
                for i in lo..hi {
                    s.add(tau[i] - at, xs[i], ys[i]);
                }
                let a = s.solve(order).unwrap();
                let b = fit_eval(&tau[lo..hi], &xs[lo..hi], &ys[lo..hi], order, at).unwrap();
                for (p, q) in [
                    (a.x, b.x),
                    (a.y, b.y),
                    (a.vx, b.vx),
                    (a.vy, b.vy),
                    (a.ax, b.ax),
                    (a.ay, b.ay),
                    (a.rms_residual, b.rms_residual),
                    (a.leverage, b.leverage),
                    (a.velocity_variance, b.velocity_variance),
                ] {
                    assert!((p - q).abs() < 1e-7, "{order} {lo}..{hi}: {p} vs {q}");
                }
            }
        }
    }

    #[test]
    fn fixed_window_rule_is_the_plain_centred_fit() {
        let (tau, xs, ys) = noisy_track(20, 4);
        let rule = WindowRule {
            min_window: 11,
            max_window: 11,
            order: 2,
            sigma: 0.3,
            bias_weight: 1.0,
            accel_rms: 0.0,
        };
        for c in 0..20 {
            let (f, w) = fit_adaptive(&tau, &xs, &ys, c, tau[c], &rule).unwrap();
            assert_eq!(w, 11);
            let start = c.saturating_sub(5).min(9);
            let r = fit_eval(
                &tau[start..start + 11],
                &xs[start..start + 11],
                &ys[start..start + 11],
                2,
                tau[c],
            )
            .unwrap();
            assert!((f.vx - r.vx).abs() < 1e-8 && (f.y - r.y).abs() < 1e-8);
        }
    }

    #[test]
    fn adaptive_window_is_long_on_smooth_tracks_and_short_on_sharp_turns() {
        let rule = WindowRule {
            min_window: 5,
            max_window: 21,
            order: 2,
            sigma: 0.3,
            bias_weight: 1.0,
            accel_rms: 0.0,
        };
        // Straight track with noise: the largest window.
        let (tau, xs, ys) = noisy_track(41, 5);
        let (_, w) = fit_adaptive(&tau, &xs, &ys, 20, tau[20], &rule).unwrap();
        assert!(w >= 15, "window {w}");
        // A tight circle (0.3 rad per pulse, radius 30 px), noise-free: the
        // quadratic's bias is far above the noise of the short windows.
        let tau: Vec<f64> = (0..41).map(|i| i as f64).collect();
        let xs: Vec<f64> = tau.iter().map(|t| 30.0 * (0.3 * t).cos()).collect();
        let ys: Vec<f64> = tau.iter().map(|t| 30.0 * (0.3 * t).sin()).collect();
        let (f, w) = fit_adaptive(&tau, &xs, &ys, 20, 20.0, &rule).unwrap();
        assert!(w <= 9, "window {w}");
        let speed = f.vx.hypot(f.vy);
        let fixed = fit_eval(&tau[10..31], &xs[10..31], &ys[10..31], 2, 20.0).unwrap();
        assert!((speed - 9.0).abs() < (fixed.vx.hypot(fixed.vy) - 9.0).abs() / 4.0);
    }

    #[test]
    fn cofactor_inverse_matches_gauss_jordan() {
        let mut s = Sums::default();
        for i in 0..9 {
            s.add(i as f64 - 6.3, 0.0, 0.0);
        }
        let mut m = [[0.0; 4]; 4];
        for (a, row) in m.iter_mut().enumerate().take(3) {
            for (b, v) in row.iter_mut().enumerate().take(3) {
                *v = s.s[a + b];
            }
        }
        let (x, y) = (invert_sym3(&m).unwrap(), invert(&m, 3).unwrap());
        for a in 0..3 {
            for b in 0..3 {
                assert!((x[a][b] - y[a][b]).abs() < 1e-9 * y[a][b].abs().max(1e-3));
            }
        }
        let mut two = Sums::default();
        two.add(0.0, 0.0, 0.0);
        two.add(1.0, 0.0, 0.0);
        two.add(1.0, 0.0, 0.0);
        let mut m = [[0.0; 4]; 4];
        for (a, row) in m.iter_mut().enumerate().take(3) {
            for (b, v) in row.iter_mut().enumerate().take(3) {
                *v = two.s[a + b];
            }
        }
        assert!(invert_sym3(&m).is_none());
    }

    /// Compare two fits to ~1e-9 relative (absolute below 1).
    fn assert_close(a: &FitState, b: &FitState, what: &str) {
        for (name, p, q) in [
            ("x", a.x, b.x),
            ("y", a.y, b.y),
            ("vx", a.vx, b.vx),
            ("vy", a.vy, b.vy),
            ("ax", a.ax, b.ax),
            ("ay", a.ay, b.ay),
            ("rms", a.rms_residual, b.rms_residual),
            ("leverage", a.leverage, b.leverage),
            (
                "velocity_variance",
                a.velocity_variance,
                b.velocity_variance,
            ),
        ] {
            assert!(
                (p - q).abs() <= 1e-9 * q.abs().max(1.0),
                "{what}: {name} {p} vs {q}"
            );
        }
    }

    #[test]
    fn grid_fit_matches_the_reference() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(11);
        // The last column: the curvature prior (0: none).
        let rules = [
            (5, 21, 2, 1.0, 0.0),
            (5, 21, 2, 4.0, 0.0),
            (3, 9, 1, 1.0, 0.0),
            (2, 11, 2, 4.0, 0.0),
            (7, 7, 2, 1.0, 0.0),
            (1, 5, 0, 1.0, 0.0),
            (5, 21, 2, 4.0, 0.1),
            (2, 11, 2, 1.0, 0.5),
            (5, 21, 2, 4.0, 0.005),
            (7, 7, 2, 1.0, 0.1),
            (3, 9, 1, 1.0, 0.1),
        ];
        let mut compared = 0;
        for (case, &(min_window, max_window, order, bias_weight, accel_rms)) in
            rules.iter().enumerate()
        {
            let tables = GridTables::new(&WindowRule {
                min_window,
                max_window,
                order,
                sigma: 0.0,
                bias_weight,
                accel_rms: 0.0,
            });
            for n in [1usize, 2, 4, 6, 9, 15, 22, 30, 43, 44, 80] {
                // Straight, curved and sharply turning paths with noise; τ
                // off the integers by rounding-sized amounts, as computed
                // from real pulse times.
                let turn = [0.0, 0.05, 0.4][n % 3];
                let sigma = [0.05, 0.3, 1.0][case % 3];
                let rule = WindowRule {
                    min_window,
                    max_window,
                    order,
                    sigma,
                    bias_weight,
                    accel_rms,
                };
                let tau: Vec<f64> = (0..n).map(|i| i as f64 * (1.0 + 1e-15) + 1e-13).collect();
                let xs: Vec<f64> = (0..n)
                    .map(|i| {
                        400.0
                            + 40.0 * (turn * i as f64).sin()
                            + 6.0 * i as f64
                            + rng.gen_range(-sigma..=sigma)
                    })
                    .collect();
                let ys: Vec<f64> = (0..n)
                    .map(|i| {
                        90.0 + 40.0 * (turn * i as f64).cos() - 2.0 * i as f64
                            + rng.gen_range(-sigma..=sigma)
                    })
                    .collect();
                let xy: Vec<[f64; 2]> = xs.iter().zip(&ys).map(|(&x, &y)| [x, y]).collect();
                for c in 0..n {
                    let r = fit_adaptive(&tau, &xs, &ys, c, tau[c], &rule);
                    let f = fit_adaptive_grid(&tables, &xy, c, &rule);
                    match (f, r) {
                        (Some((f, fw)), Some((r, rw))) => {
                            let what = format!("rule {case} n {n} centre {c}");
                            assert_eq!(fw, rw, "{what}: window");
                            assert_close(&f, &r, &what);
                            compared += 1;
                        }
                        (None, None) => {}
                        (f, r) => panic!("rule {case} n {n} centre {c}: {f:?} vs {r:?}"),
                    }
                }
            }
        }
        assert!(compared > 2800, "{compared}");
    }

    #[test]
    fn running_grid_fit_matches_the_reference() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(12);
        // (min, max window, bias weight, prior): with and without the
        // prior, the default rule among them; an even largest window.
        let rules = [
            (5, 21, 4.0, 0.0),
            (5, 21, 4.0, 0.1),
            (5, 21, 4.0, 0.005),
            (5, 21, 1.0, 0.5),
            (2, 11, 1.0, 0.5),
            (3, 10, 4.0, 0.1),
            (4, 9, 1.0, 0.0),
        ];
        let (mut compared, mut widened, mut largest) = (0, 0, 0);
        for (case, &(min_window, max_window, bias_weight, accel_rms)) in rules.iter().enumerate() {
            for (path, &n) in [20usize, 43, 44, 60, 300, 700].iter().enumerate() {
                let sigma = [0.05, 0.2, 1.0][(case + path) % 3];
                let rule = WindowRule {
                    min_window,
                    max_window,
                    order: 2,
                    sigma,
                    bias_weight,
                    accel_rms,
                };
                let tables = GridTables::new(&rule);
                // Straight stretches and turns of varying sharpness, far
                // from the origin (as in a full frame).
                let turn = [0.0, 0.02, 0.3, 0.08, 0.5][(case + path) % 5];
                let mut xy = Vec::with_capacity(n);
                for i in 0..n {
                    let s = i as f64;
                    let bend = turn * (1.0 + (0.01 * s).sin());
                    xy.push([
                        900.0 + 7.0 * s + 40.0 * (bend * s).sin() + rng.gen_range(-sigma..=sigma),
                        300.0 - 3.0 * s + 40.0 * (bend * s).cos() + rng.gen_range(-sigma..=sigma),
                    ]);
                }
                let tau: Vec<f64> = (0..n).map(|i| i as f64).collect();
                let (xs, ys): (Vec<f64>, Vec<f64>) = xy.iter().map(|p| (p[0], p[1])).unzip();
                let mut run = GridRunFit::new(&tables, &rule).expect("running path");
                // Consecutive samples, and now and then a jump (restart).
                let mut c = 0;
                while c < n {
                    if run.serves_track(n) {
                        let what = format!("rule {case} n {n} centre {c}");
                        let (f, fw) = run.fit(&xy, c).expect(&what);
                        let (_, gw) = fit_adaptive_grid(&tables, &xy, c, &rule).expect(&what);
                        let (r, rw) =
                            fit_adaptive(&tau, &xs, &ys, c, c as f64, &rule).expect(&what);
                        assert_eq!(fw, rw, "{what}: window");
                        assert_eq!(gw, rw, "{what}: window");
                        // Without the residual pass: the same fit otherwise.
                        let (q, qw) = fit_adaptive_with(&tau, &xs, &ys, c, c as f64, &rule, false)
                            .expect(&what);
                        assert_eq!(qw, rw, "{what}");
                        assert_eq!(
                            FitState {
                                rms_residual: r.rms_residual,
                                ..q
                            },
                            r,
                            "{what}"
                        );
                        for (name, p, q) in [
                            ("x", f.x, r.x),
                            ("y", f.y, r.y),
                            ("vx", f.vx, r.vx),
                            ("vy", f.vy, r.vy),
                            ("ax", f.ax, r.ax),
                            ("ay", f.ay, r.ay),
                            ("leverage", f.leverage, r.leverage),
                            (
                                "velocity_variance",
                                f.velocity_variance,
                                r.velocity_variance,
                            ),
                        ] {
                            assert!((p - q).abs() <= 1e-9, "{what}: {name} {p} vs {q}");
                        }
                        assert!(f.rms_residual.is_nan());
                        compared += 1;
                        widened += (rule.ridge() > 0.0
                            && f.velocity_variance
                                > tables
                                    .window(fw, c - fw / 2, c)
                                    .variance_and_bias(rule.ridge())
                                    .0) as usize;
                        largest += (fw == max_window) as usize;
                    }
                    c += if rng.gen_range(0.0..1.0) < 0.03 { 3 } else { 1 };
                }
            }
        }
        // Both window kinds and the widened prior were exercised.
        assert!(compared > 7000, "{compared}");
        assert!(
            largest > 300 && largest + 300 < compared,
            "{largest} of {compared}"
        );
        assert!(widened > 100, "{widened}");
    }

    #[test]
    fn grid_tables_follow_the_rule_and_span() {
        let rule = WindowRule {
            min_window: 5,
            max_window: 21,
            order: 2,
            sigma: 0.2,
            bias_weight: 4.0,
            accel_rms: 0.0,
        };
        let t = GridTables::cached(&rule);
        // The default windows take the short search in the interior
        // (which grid_fit_matches_the_reference compares).
        assert!(t.centred_unimodal);
        assert!(t.serves(&WindowRule { sigma: 3.0, ..rule }));
        assert!(!t.serves(&WindowRule {
            max_window: 19,
            ..rule
        }));
        assert!(std::sync::Arc::ptr_eq(&t, &GridTables::cached(&rule)));
        // The pilot window: 43 samples, centred where the ends allow.
        assert_eq!(adaptive_span(100, 50, &rule), 29..72);
        assert_eq!(adaptive_span(100, 3, &rule), 0..43);
        assert_eq!(adaptive_span(30, 29, &rule), 0..30);
        assert_eq!(adaptive_span(0, 0, &rule), 0..0);
        let fixed = WindowRule {
            min_window: 21,
            ..rule
        };
        assert_eq!(adaptive_span(100, 99, &fixed), 79..100);
        // Tables for another shape fall back to the reference.
        let other = WindowRule {
            max_window: 9,
            ..rule
        };
        let xs: Vec<f64> = (0..30).map(|i| (i * i) as f64 * 0.1).collect();
        let tau: Vec<f64> = (0..30).map(|i| i as f64).collect();
        assert_eq!(
            fit_adaptive_grid(
                &t,
                &xs.iter().map(|&x| [x, x]).collect::<Vec<_>>(),
                12,
                &other
            ),
            fit_adaptive(&tau, &xs, &xs, 12, 12.0, &other)
        );
        // Rounding-sized τ errors are on the grid, real jitter is not.
        assert!(grid_tolerance(1e6, 200.0) < 1e-8);
        assert!(grid_tolerance(1e6, 200.0) > 1e-11 / 200.0);
    }

    #[test]
    fn leave_one_out_matches_the_reference() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(12);
        let loo = LeaveOneOut::new(11);
        for w in 2..=11 {
            for e in 0..=w {
                let xs: Vec<f64> = (0..=w)
                    .map(|k| 500.0 + 4.0 * k as f64 + rng.gen_range(-1.0..1.0))
                    .collect();
                let ys: Vec<f64> = (0..=w)
                    .map(|k| 20.0 - 0.1 * (k * k) as f64 + rng.gen_range(-1.0..1.0))
                    .collect();
                let others: Vec<usize> = (0..=w).filter(|&k| k != e).collect();
                let tau: Vec<f64> = others.iter().map(|&k| k as f64 - e as f64).collect();
                let ox: Vec<f64> = others.iter().map(|&k| xs[k]).collect();
                let oy: Vec<f64> = others.iter().map(|&k| ys[k]).collect();
                let r = fit_eval(&tau, &ox, &oy, 2, 0.0).unwrap();
                let xy: Vec<[f64; 2]> = xs.iter().zip(&ys).map(|(&x, &y)| [x, y]).collect();
                let (dx, dy, lev) = loo.predict(&xy, e).unwrap();
                assert!((xs[e] + dx - r.x).abs() < 1e-9 * r.x.abs(), "{w} {e}");
                assert!(
                    (ys[e] + dy - r.y).abs() < 1e-9 * r.y.abs().max(1.0),
                    "{w} {e}"
                );
                assert_eq!(lev, r.leverage, "{w} {e}");
            }
        }
        assert!(loo.predict(&[[0.0; 2]; 13], 0).is_none());
        assert!(loo.predict(&[], 0).is_none());
        assert!(std::sync::Arc::ptr_eq(
            &LeaveOneOut::cached(11),
            &LeaveOneOut::cached(11)
        ));
    }

    /// Short noisy tracks on paths of random curvature (acceleration
    /// N(0, a²) per axis), as on the synthetic scene: the rms velocity
    /// error over all samples with and without the curvature prior.
    fn short_track_velocity_rms(accel_rms: f64, lengths: std::ops::Range<usize>) -> f64 {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(21);
        let (sigma, a) = (0.4, 0.1);
        let noise = Normal::new(0.0, sigma).unwrap();
        let accel = Normal::new(0.0, a).unwrap();
        let rule = WindowRule {
            min_window: 5,
            max_window: 21,
            order: 2,
            sigma,
            bias_weight: 4.0,
            accel_rms,
        };
        let (mut se, mut count) = (0.0, 0usize);
        for track in 0..3000 {
            let n = lengths.start + track % lengths.len();
            let (ax, ay) = (accel.sample(&mut rng), accel.sample(&mut rng));
            let (u, v) = (6.0, -2.0);
            let tau: Vec<f64> = (0..n).map(|i| i as f64).collect();
            let xs: Vec<f64> = tau
                .iter()
                .map(|t| u * t + 0.5 * ax * t * t + noise.sample(&mut rng))
                .collect();
            let ys: Vec<f64> = tau
                .iter()
                .map(|t| v * t + 0.5 * ay * t * t + noise.sample(&mut rng))
                .collect();
            for c in 0..n {
                let (f, _) = fit_adaptive(&tau, &xs, &ys, c, tau[c], &rule).unwrap();
                se += (f.vx - (u + ax * tau[c])).powi(2) + (f.vy - (v + ay * tau[c])).powi(2);
                count += 2;
            }
        }
        (se / count as f64).sqrt()
    }

    #[test]
    fn curvature_prior_cuts_the_velocity_error_of_short_tracks() {
        // Tracks of 4-9 detections, where the quadratic's own curvature
        // is mostly noise: the prior at the population's rms acceleration.
        let plain = short_track_velocity_rms(0.0, 4..10);
        let prior = short_track_velocity_rms(0.1, 4..10);
        println!("4-9 detections: {plain:.4} -> {prior:.4} px/pulse");
        assert!(prior < 0.7 * plain, "{plain} -> {prior}");
        // Long tracks: the prior barely acts (their curvature is measured).
        let plain = short_track_velocity_rms(0.0, 30..31);
        let prior = short_track_velocity_rms(0.1, 30..31);
        println!("30 detections: {plain:.4} -> {prior:.4} px/pulse");
        assert!(prior < 1.02 * plain, "{plain} -> {prior}");
    }

    #[test]
    fn accel_prior_recovers_the_flow_curvature() {
        use rand::{Rng, SeedableRng};
        use rand_distr::{Distribution, Normal};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(22);
        let sigma = 0.4;
        let noise = Normal::new(0.0, sigma).unwrap();
        for a in [0.0f64, 0.1, 0.3] {
            let accel = Normal::new(0.0, a.max(1e-12)).unwrap();
            let mut prior = AccelPrior::default();
            assert_eq!(prior.accel_rms(sigma), 0.0, "no prior before samples");
            for _ in 0..1000 {
                let n = rng.gen_range(3..40);
                let (ax, ay) = (accel.sample(&mut rng), accel.sample(&mut rng));
                // A gap somewhere: stretches do not cross it.
                let gap = rng.gen_range(0..n);
                let pulses: Vec<i64> = (0..n as i64)
                    .map(|k| 500 + k + (k >= gap as i64) as i64 * 2)
                    .collect();
                let xy: Vec<[f64; 2]> = pulses
                    .iter()
                    .map(|&p| {
                        let t = (p - 500) as f64;
                        [
                            7.0 * t + 0.5 * ax * t * t + noise.sample(&mut rng),
                            1.0 * t + 0.5 * ay * t * t + noise.sample(&mut rng),
                        ]
                    })
                    .collect();
                prior.add_track(&pulses, &xy);
            }
            let est = prior.accel_rms(sigma);
            println!("a {a}: {est:.4} from {} stretches", prior.samples());
            assert!(prior.samples() > 1500);
            if a > 0.0 {
                assert!((est / a - 1.0).abs() < 0.15, "a {a}: {est}");
            } else {
                // The floor: a quarter of one stretch's noise variance.
                assert!(est < 0.05, "{est}");
            }
        }
    }

    #[test]
    fn degenerate_inputs() {
        assert!(fit_eval(&[], &[], &[], 2, 0.0).is_none());
        let one = fit_eval(&[1.0], &[2.0], &[3.0], 2, 5.0).unwrap();
        assert_eq!((one.x, one.y, one.vx), (2.0, 3.0, 0.0));
        assert!(fit_eval(&[1.0, 1.0], &[2.0, 4.0], &[0.0, 0.0], 1, 1.0).is_none());
    }
}
