//! The adaptive window of the output fit (see the module doc): the window
//! rule, [`fit_adaptive`] — every candidate window's fit at one sample,
//! the window chosen from the position noise and the pilot curvature —
//! and the spans it uses.

use super::*;

/// The pilot's curvature widens the prior only beyond this many times its
/// noise variance: a short track's pilot curvature is mostly noise, and
/// widening by it (noise subtracted once) took back half the prior's gain
/// on the synthetic scene.
pub(super) const WIDEN_NOISE: f64 = 4.0;

/// What the pilot cubic tells the window choice (x, y coefficients).
pub(super) struct Pilot {
    pub(super) c3: [f64; 2],
    pub(super) c3_var: f64,
    pub(super) c2: [f64; 2],
    pub(super) c2_var: f64,
}

/// The curvature prior's ridge for one sample: `ridge` (σ²/var(c₂) of
/// the population prior, 0 for none), widened where the pilot's own
/// squared curvature `c2sq` (x² + y², less its noise) is larger than the
/// prior's variance — a vortex core's tracks are not shrunk towards the
/// straight line the slow outer flow sets (the demo's velocity error went
/// up by 11 % without this).
pub(super) fn widened_ridge(ridge: f64, sigma: f64, c2sq: f64) -> f64 {
    if ridge > 0.0 && c2sq > 0.0 {
        ridge.min(2.0 * sigma * sigma / c2sq)
    } else {
        ridge
    }
}

/// How [`fit_adaptive`] chooses its window.
#[derive(Debug, Clone, Copy, PartialEq)]
#[ebptv_macros::testkit]
pub(crate) struct WindowRule {
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
    pub(crate) fn ridge(&self) -> f64 {
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
pub(super) const MAX_CANDIDATES: usize = 32;

thread_local! {
    /// [`fit_adaptive_with`]'s candidates (kept between calls).
    static CANDIDATES: std::cell::Cell<Vec<(Sums, usize, f64, f64)>> =
        const { std::cell::Cell::new(Vec::new()) };
}

/// Fit the samples `(tau, xs, ys)` (sorted by τ) around index `centre`
/// and evaluate at `at`, with the window of `min_window, min_window + 2, …,
/// max_window` samples (each as centred on `centre` as the ends allow, so
/// each holds the one before) of least predicted velocity error (module
/// docs). Returns the fit and its window; `None` when no window can be
/// fitted.
#[ebptv_macros::testkit]
pub(crate) fn fit_adaptive(
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
    // cost more than the rest of the call; the thread's own vector, reused
    // from call to call (no allocation per call).
    let mut cands = CANDIDATES.take();
    cands.clear();
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
            if ok != k {
                cands[ok] = cands[k];
            }
            ok += 1;
        }
    }
    let nc = ok;
    let s2 = rule.sigma * rule.sigma;
    let best = cands[..nc]
        .iter()
        .map(|c| (rule.bias_weight * c3sq * c.3 * c.3 + 2.0 * s2 * c.2, c))
        .min_by(|a, b| a.0.total_cmp(&b.0).then(b.1 .1.cmp(&a.1 .1)))
        .map(|(_, c)| (c.0.solve_with_prior(rule.order, ridge), c.1));
    CANDIDATES.set(cands);
    let (fit, best_w) = best?;
    let fit = fit?;
    if ridge > 0.0 && !residual {
        let fit = FitState {
            rms_residual: f64::NAN,
            ..fit
        };
        return Some((fit, best_w));
    }
    if ridge > 0.0 {
        let start = centre.saturating_sub(best_w / 2).min(n - best_w);
        let w = start..start + best_w;
        return Some((
            with_direct_residual(fit, tau, xs, ys, w, at, rule.order),
            best_w,
        ));
    }
    Some((fit, best_w))
}

/// `f` with its residual rms taken from the residuals themselves: with the
/// curvature prior the sums' shortcut (xᵀx less the fitted part) loses
/// the digits of a nearly exact fit to cancellation, which the tabulated
/// path's different (equal to rounding) inverse would not reproduce.
pub(super) fn with_direct_residual(
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
pub(super) const GRID_TOLERANCE: f64 = 1e-9;

/// How far (in τ units) a τ computed from times up to `t_max_abs` µs with
/// period `period_us` may stray from its integer value by rounding alone:
/// the fast path takes a detection as on the grid within this distance.
pub(crate) fn grid_tolerance(t_max_abs: f64, period_us: f64) -> f64 {
    GRID_TOLERANCE + 64.0 * f64::EPSILON * (t_max_abs / period_us.abs().max(1e-300))
}

/// The samples one [`fit_adaptive`] call reads (its pilot window; for a
/// fixed window, that window): `n` samples, evaluation at `centre`.
pub(crate) fn adaptive_span(n: usize, centre: usize, rule: &WindowRule) -> std::ops::Range<usize> {
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
