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
//! amplifies the noise several-fold. `fit_adaptive` chooses the window
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
//! asked for is fitted. The nested windows share their sums (`Sums`),
//! so a sample costs one pass over the pilot window and a small solve per
//! candidate; `fit_eval` is the reference the sums are tested against.
//!
//! # Curvature prior (short tracks and track ends)
//! At a track's ends and on short tracks the candidates are one-sided or
//! few-point quadratics whose own curvature is mostly noise (on a 5-point
//! track the quadratic coefficient's noise, 0.27 σ, exceeds the synthetic
//! flow's typical curvature, ~0.05 px/pulse²), and the slope at the end
//! of a quadratic is several times noisier than a line's; a line instead
//! is biased by the acceleration times the distance to the window's
//! centre (a choice between the two by the track's own curvature was tried
//! and is too noisy, above). With `WindowRule::accel_rms` every
//! quadratic candidate is the posterior mean under a Gaussian prior
//! c₂ ~ N(0, (a/2)²) per axis — a ridge `ρ = 4σ²/a²` on the quadratic
//! coefficient's normal equation — and the criterion takes its posterior
//! velocity variance `σ²·[(XᵀX + ρe₂e₂ᵀ)⁻¹]₁₁` (noise plus the prior's
//! expected shrinkage bias) and the cubic bias of the ridge fit. Short
//! and one-sided windows move towards the line as far as the flow's
//! typical curvature allows; long windows, whose curvature is measured
//! (noise ≪ a), are unaffected. `a` is a population quantity:
//! `AccelPrior` estimates it from the quadratic coefficients of disjoint
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
//! window's length and offset. `GridTables` holds these per window rule
//! (built once with the reference's own arithmetic on exact integer
//! moments), and `fit_adaptive_grid` costs a sample two short dot
//! products: ~5× fewer instructions than `fit_adaptive`, which stays the
//! reference and the path for windows with gaps or irregular times. The
//! two agree to rounding (tests): the reference's τ, computed from µs
//! times, are off the integers by ~1e-11. With the curvature prior the
//! tables still serve: the ridge is a rank-one update of the tabulated
//! inverse (Sherman–Morrison), so a candidate's posterior variance and
//! bias cost a few flops more (the tabulated `(XᵀX)⁻¹Xᵀs³` gives the
//! bias); the short search from the largest window, shown unimodal for
//! the plain factors only, gives way to the full search over the
//! candidates. `LeaveOneOut` does the same for the tracker's outlier
//! pass.
//!
//! # Running moments along a track (the output fit's path)
//! The pilot's coefficients are its tabulated inverse rows times the
//! window's moments `Σ sᵃ·x` (a = 0..=3, s the offset from the sample),
//! and a candidate's fit is its inverse times `Σ sᵃ·x` (a = 0..=2). From
//! one sample to the next the pilot window slides by one (or stays, near
//! the track's ends) and the offsets shift by one, so the moments move in
//! O(1): `GridRunFit` keeps them (and the largest candidate's) as
//! running sums, summed afresh every `RUN_RESTART` samples, and caches
//! the centred candidates' prior-updated factors (they change only where
//! a sample's pilot widens the prior) per window rule, the last rule's
//! kept per thread. A sample then costs a
//! few dozen flops for the moments and the criterion of each candidate
//! instead of two 43-point filters and the window's sums (~2 300 → ~830
//! instructions per sample on the water jet, ends and widened priors
//! included). The running sums are taken about a reference point rather
//! than the sample itself, which changes the last digits (~1e-13 px) but
//! not the window chosen except at ties to rounding; the tests compare it
//! with `fit_adaptive` at 1e-9.
//!
//! # Windows with gaps, and one API (`local.rs`)
//! A missed detection takes every sample within a pilot window of it (up
//! to 43 detections each side of a gap) and every missing pulse off the
//! tables. On the pulse grid the offsets are still exact integers, so
//! `GapFit` keeps the pilot window's moments `Σ sᵏ` (k = 0..=6) and
//! `Σ sᵃ·x` (a = 0..=3) along the track as `GridRunFit` does: from one
//! sample to the next (a pulse later, at a detection or a missing pulse)
//! they shift by the binomial expansion and take the detections entering
//! and leaving the window, summed afresh every `RUN_RESTART` samples and
//! wherever an offset leaves the power table. The integer moments stay
//! exact (the values a fresh sum gives; tested), the data moments pick
//! up rounding only. The pilot's cubic and quadratic coefficients and
//! their variance factors come from the Schur complement of the
//! quadratic block (the 3×3 cofactors) rather than the whole 4×4
//! inverse. The nested candidates' moments are summed in one pass over
//! the largest candidate about the sample's own detection, each
//! candidate's criterion from the cofactors of its 3×3 system (the
//! normal matrices depend on the gap pattern, so every sample solves
//! them), the chosen one's inverse once; the offsets' powers come from a
//! table (exact integers, the values the products give). On the
//! speeddev_shedding recording this takes a gap sample from ~3 800 to
//! ~2 700 instructions; the candidates' criteria (~500) and their pass
//! (~20 detections) are most of what is left. All four paths sit behind
//! one trait, `LocalPolyFit`, with `PlainFit` (`fit_adaptive`) as the
//! oracle the others are tested against; `OutputFit` chains them for the
//! tracker.

mod adaptive;
mod grid;
pub(crate) mod local;
mod prior;
mod running;
#[ebptv_macros::testkit]
pub(crate) use adaptive::*;
#[ebptv_macros::testkit]
pub(crate) use grid::*;
pub(crate) use local::*;
#[ebptv_macros::testkit]
pub(crate) use prior::*;
pub(crate) use running::*;

/// A fitted state at one evaluation time (in the caller's τ units).
#[derive(Debug, Clone, Copy, PartialEq)]
#[ebptv_macros::testkit]
pub(crate) struct FitState {
    /// Fitted position x (px).
    pub x: f64,
    /// Fitted position y (px).
    pub y: f64,
    /// dx/dτ, dy/dτ.
    pub vx: f64,
    /// dy/dτ.
    pub vy: f64,
    /// d²x/dτ², d²y/dτ².
    pub ax: f64,
    /// d²y/dτ².
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
#[ebptv_macros::testkit]
pub(crate) fn fit_eval(
    tau: &[f64],
    xs: &[f64],
    ys: &[f64],
    order: usize,
    at: f64,
) -> Option<FitState> {
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
pub(crate) struct Sums {
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
    pub(crate) fn add(&mut self, s: f64, x: f64, y: f64) {
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

    #[cfg(feature = "testkit")]
    /// The fit of order ≤ `order` (≤ 2, lowered to what the points allow)
    /// evaluated at s = 0; `None` when empty or singular. Equal to
    /// [`fit_eval`] over the same samples up to rounding.
    pub(crate) fn solve(&self, order: usize) -> Option<FitState> {
        self.solve_with_prior(order, 0.0)
    }

    /// [`Sums::solve`] with the curvature prior: `ridge` = σ²/var(c₂)
    /// added to the quadratic coefficient's normal equation (a quadratic
    /// fit only; 0 gives [`Sums::solve`]). `leverage` and
    /// `velocity_variance` are then the posterior variance factors (noise
    /// plus the prior's expected shrinkage bias).
    pub(crate) fn solve_with_prior(&self, order: usize, ridge: f64) -> Option<FitState> {
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
    invert_inline(m, p)
}

/// [`invert`]'s body, inlined where `p` is a constant.
#[inline(always)]
fn invert_inline<const N: usize>(m: &[[f64; N]; N], p: usize) -> Option<[[f64; N]; N]> {
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

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;

    #[ebptv_macros::unit_test]
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

    #[ebptv_macros::unit_test]
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

    #[ebptv_macros::unit_test]
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

    #[ebptv_macros::unit_test]
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

    #[ebptv_macros::unit_test]
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

    #[ebptv_macros::unit_test]
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
    /// Every field of two fits within 1e-9 (relative above 1); the rms
    /// residual only when `with_rms` (backends that skip it leave it 0).
    pub(super) fn assert_close_with(a: &FitState, b: &FitState, what: &str, with_rms: bool) {
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
            if name == "rms" && !with_rms {
                continue;
            }
            assert!(
                (p - q).abs() <= 1e-9 * q.abs().max(1.0),
                "{what}: {name} {p} vs {q}"
            );
        }
    }

    #[ebptv_macros::unit_test]
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
                            assert_close_with(&f, &r, &what, true);
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

    #[ebptv_macros::unit_test]
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

    #[ebptv_macros::unit_test]
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

    #[ebptv_macros::unit_test]
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

    #[ebptv_macros::unit_test]
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

    #[ebptv_macros::unit_test]
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

    #[ebptv_macros::unit_test]
    fn degenerate_inputs() {
        assert!(fit_eval(&[], &[], &[], 2, 0.0).is_none());
        let one = fit_eval(&[1.0], &[2.0], &[3.0], 2, 5.0).unwrap();
        assert_eq!((one.x, one.y, one.vx), (2.0, 3.0, 0.0));
        assert!(fit_eval(&[1.0, 1.0], &[2.0, 4.0], &[0.0, 0.0], 1, 1.0).is_none());
    }
}
