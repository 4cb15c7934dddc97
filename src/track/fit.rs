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

    fn coefficients(&self, order: usize) -> Option<Solved> {
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
        let inv = if p == 3 {
            invert_sym3(&ata)?
        } else {
            invert(&ata, p)?
        };
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
        let c = self.coefficients(order.min(2))?;
        let p = c.p;
        // Residual sum of squares of a least-squares fit: xᵀx − cᵀ(Aᵀx).
        let ssr: f64 = self.xx + self.yy
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
        self.velocity_variance_and_bias(order).map(|v| v.1)
    }

    /// `(velocity_variance, velocity_bias_factor)` from one solve.
    fn velocity_variance_and_bias(&self, order: usize) -> Option<(f64, f64)> {
        let c = self.coefficients(order.min(2))?;
        if c.p < 2 {
            return Some((0.0, 0.0));
        }
        let b = (0..c.p).map(|b| c.inv[1][b] * self.s[b + 3]).sum();
        Some((c.inv[1][1], b))
    }

    /// Cubic coefficients (x, y) of an order-3 fit and their variance
    /// factor; `None` with fewer than 5 samples (no spare point to tell a
    /// cubic from noise) or a singular design.
    pub fn cubic(&self) -> Option<(f64, f64, f64)> {
        if self.n < 5 {
            return None;
        }
        let c = self.coefficients(3)?;
        (c.p == 4).then(|| (c.cx[3], c.cy[3], c.inv[3][3]))
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
    let n = tau.len();
    if n == 0 {
        return None;
    }
    let wmax = rule.max_window.clamp(1, n);
    let wmin = rule.min_window.clamp(1, wmax);
    let centre = centre.min(n - 1);
    // Fixed window: the plain fit.
    if wmin == wmax {
        let start = centre.saturating_sub(wmax / 2).min(n - wmax);
        let w = start..start + wmax;
        return fit_eval(&tau[w.clone()], &xs[w.clone()], &ys[w], rule.order, at)
            .map(|f| (f, wmax));
    }
    let pilot = (2 * wmax + 1).min(n);
    let mut sums = Sums::default();
    let (mut lo, mut hi) = (usize::MAX, 0usize);
    // (sums, window, velocity variance factor, bias factor) per candidate;
    // only the chosen one is evaluated in full.
    let mut cands = [(Sums::default(), 0usize, 0.0f64, 0.0f64); MAX_CANDIDATES];
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
            if let Some((v, b)) = sums.velocity_variance_and_bias(rule.order) {
                cands[nc] = (sums, w, v, b);
                nc += 1;
            }
        }
        if w >= pilot {
            break;
        }
        w = if w < wmax { (w + 2).min(wmax) } else { pilot };
    }
    // Squared cubic coefficient (x² + y²) from the pilot, less its noise.
    let c3sq = match (rule.order >= 2).then(|| sums.cubic()).flatten() {
        Some((cx, cy, v)) => (cx * cx + cy * cy - 2.0 * rule.sigma.powi(2) * v).max(0.0),
        None => 0.0,
    };
    let s2 = rule.sigma * rule.sigma;
    let best = cands[..nc]
        .iter()
        .map(|c| (rule.bias_weight * c3sq * c.3 * c.3 + 2.0 * s2 * c.2, c))
        .min_by(|a, b| a.0.total_cmp(&b.0).then(b.1 .1.cmp(&a.1 .1)))?
        .1;
    best.0.solve(rule.order).map(|f| (f, best.1))
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

    #[test]
    fn degenerate_inputs() {
        assert!(fit_eval(&[], &[], &[], 2, 0.0).is_none());
        let one = fit_eval(&[1.0], &[2.0], &[3.0], 2, 5.0).unwrap();
        assert_eq!((one.x, one.y, one.vx), (2.0, 3.0, 0.0));
        assert!(fit_eval(&[1.0, 1.0], &[2.0, 4.0], &[0.0, 0.0], 1, 1.0).is_none());
    }
}
