//! Extrapolation of a turning path: a constant-turn-rate model.
//!
//! # Why
//! A polynomial in time is a poor model of a path that turns: on a circle
//! turned at ω rad per pulse, a quadratic through the last 12 positions
//! misses the next one by ~0.1·ω³·R·12³ — at a vortex core (ω ≈ 0.2
//! rad/pulse, R = 20 px) by ~3 px, beyond any gate, and a line through
//! the last 4 positions by ~1.8 px. Tracks there break every few pulses.
//! A particle in a vortex, a shear layer or a separated flow keeps turning
//! at a rate that changes slowly along its path, so the natural model is
//! the one of manoeuvring-target tracking: the velocity keeps its rate of
//! turn ω and changes its speed linearly,
//!
//! `w(s) = (V + A·s)·e^{iωs}`,  `z(s) = z₀ + V·g₁(s) + A·g₂(s)`,
//!
//! in complex notation (`z = x + iy`), with `g₁(s) = ∫₀ˢ e^{iωσ} dσ`,
//! `g₂(s) = ∫₀ˢ σ e^{iωσ} dσ` and `s` the time (pulses) from the point of
//! evaluation. For a given ω the model is linear in the complex
//! coefficients `z₀, V, A` (six real numbers, as a quadratic in x and y),
//! and at ω = 0 it *is* the quadratic (`g₁ = s`, `g₂ = s²/2`). The rate ω
//! is found by a fixed point: the fit's acceleration across the velocity,
//! `Im(A·V̄)/|V|²`, is turning the model has not yet absorbed and is added
//! to ω until it vanishes (then `A ∥ V`: speed changes, the heading turns
//! at exactly ω). On a straight path ω stays near 0 and the prediction is
//! the quadratic's; on an arc it is exact.
//!
//! The leverage (prediction variance over the per-axis position noise) is
//! the complex least-squares one at the fitted ω, `φ(0)ᴴ G⁻¹ φ(0)`, the
//! polynomial's at ω = 0; it leaves out the noise of ω itself (~×1.5 on
//! an 11-detection arc, `noise_leverage_matches_monte_carlo`).

use std::ops::{Add, Mul, Sub};

/// Largest rate of turn (rad per pulse) the model takes: beyond it a
/// path is sampled too coarsely to tell a turn from noise.
pub(crate) const MAX_TURN: f64 = 0.8;

/// Below this speed (px per pulse) the heading, and so a rate of turn, is
/// noise: the quadratic (ω = 0) is kept.
pub(crate) const MIN_SPEED: f64 = 0.25;

/// Fixed-point iterations for ω ...
const ITERATIONS: usize = 8;

/// ... and for up to 6 samples.
const YOUNG_ITERATIONS: usize = 4;

#[derive(Debug, Clone, Copy, PartialEq, Default)]
struct C {
    re: f64,
    im: f64,
}

impl C {
    const ZERO: C = C { re: 0.0, im: 0.0 };
    fn new(re: f64, im: f64) -> C {
        C { re, im }
    }
    fn conj(self) -> C {
        C::new(self.re, -self.im)
    }
    fn norm2(self) -> f64 {
        self.re * self.re + self.im * self.im
    }
    fn div(self, o: C) -> C {
        let d = o.norm2();
        C::new(
            (self.re * o.re + self.im * o.im) / d,
            (self.im * o.re - self.re * o.im) / d,
        )
    }
}

impl Add for C {
    type Output = C;
    fn add(self, o: C) -> C {
        C::new(self.re + o.re, self.im + o.im)
    }
}

impl Sub for C {
    type Output = C;
    fn sub(self, o: C) -> C {
        C::new(self.re - o.re, self.im - o.im)
    }
}

impl Mul for C {
    type Output = C;
    fn mul(self, o: C) -> C {
        C::new(
            self.re * o.re - self.im * o.im,
            self.re * o.im + self.im * o.re,
        )
    }
}

impl Mul<f64> for C {
    type Output = C;
    fn mul(self, o: f64) -> C {
        C::new(self.re * o, self.im * o)
    }
}

/// `(g₁(s), g₂(s))` at rate `w`.
fn basis(w: f64, s: f64) -> (C, C) {
    let ws = w * s;
    if ws.abs() < 1e-3 {
        // Series to the third order in ωs (relative error ~(ωs)⁴).
        let g1 = C::new(s - w * w * s * s * s / 6.0, w * s * s / 2.0);
        let g2 = C::new(s * s / 2.0 - w * w * s.powi(4) / 8.0, w * s * s * s / 3.0);
        return (g1, g2);
    }
    let e = C::new(ws.cos(), ws.sin());
    let iw = C::new(0.0, w);
    let g1 = (e - C::new(1.0, 0.0)).div(iw);
    // ∫₀ˢ σ e^{iωσ} dσ = s e^{iωs}/(iω) − g₁/(iω)
    let g2 = (e * s - g1).div(iw);
    (g1, g2)
}

/// Solve the Hermitian positive definite `P × P` system `g x = b`
/// (Gaussian elimination; `None` when singular).
fn solve<const P: usize>(mut g: [[C; P]; P], mut b: [C; P]) -> Option<[C; P]> {
    for k in 0..P {
        let piv = g[k][k];
        if !(piv.re.abs() > 1e-12) {
            return None;
        }
        for r in k + 1..P {
            let f = g[r][k].div(piv);
            for c in k..P {
                g[r][c] = g[r][c] - f * g[k][c];
            }
            b[r] = b[r] - f * b[k];
        }
    }
    let mut x = [C::ZERO; P];
    for k in (0..P).rev() {
        let mut s = b[k];
        for c in k + 1..P {
            s = s - g[k][c] * x[c];
        }
        x[k] = s.div(g[k][k]);
    }
    Some(x)
}

/// [`solve`] for two right-hand sides with one elimination (the fits
/// need the coefficients and the leverage from the same matrix); each
/// solution is that of [`solve`], bit for bit (the same operations), and
/// `None` in the same cases (singularity depends on `g` alone).
fn solve2<const P: usize>(
    mut g: [[C; P]; P],
    mut b: [C; P],
    mut e: [C; P],
) -> Option<([C; P], [C; P])> {
    for k in 0..P {
        let piv = g[k][k];
        if !(piv.re.abs() > 1e-12) {
            return None;
        }
        for r in k + 1..P {
            let f = g[r][k].div(piv);
            for c in k..P {
                g[r][c] = g[r][c] - f * g[k][c];
            }
            b[r] = b[r] - f * b[k];
            e[r] = e[r] - f * e[k];
        }
    }
    let (mut x, mut y) = ([C::ZERO; P], [C::ZERO; P]);
    for k in (0..P).rev() {
        let (mut s, mut t) = (b[k], e[k]);
        for c in k + 1..P {
            s = s - g[k][c] * x[c];
            t = t - g[k][c] * y[c];
        }
        x[k] = s.div(g[k][k]);
        y[k] = t.div(g[k][k]);
    }
    Some((x, y))
}

/// Basis values `(g₁, g₂)` of up to 64 samples.
type Bases = [(C, C); 64];

/// The basis `(g₁, g₂)` at rate `w` of each of the (at most 64) times `s`
/// ([`basis`] of each; the fast path of the coefficient fits).
///
/// Samples one pulse apart (most windows) get `e^{iωs}` from their
/// predecessor's times `e^{iω}` instead of a sine and cosine of their own:
/// the same basis to a relative ~1e-15 per step (tested against [`basis`]).
fn bases(s: &[f64], w: f64) -> Bases {
    let mut out = [(C::ZERO, C::ZERO); 64];
    let n = s.len().min(64);
    bases_into(&mut out[..n], &s[..n], w);
    out
}

/// [`bases`] into the first `s.len()` entries of `out`.
fn bases_into(out: &mut [(C, C)], s: &[f64], w: f64) {
    let n = s.len();
    if w == 0.0 || n == 0 {
        for (o, &t) in out.iter_mut().zip(s) {
            *o = basis(w, t);
        }
        return;
    }
    let step = C::new(w.cos(), w.sin());
    let iw = C::new(0.0, w);
    let mut prev: Option<(f64, C)> = None;
    for (o, &t) in out.iter_mut().zip(s) {
        let ws = w * t;
        if ws.abs() < 1e-3 {
            *o = basis(w, t);
            prev = None;
            continue;
        }
        let e = match prev {
            Some((tp, ep)) if t - tp == 1.0 => ep * step,
            _ => C::new(ws.cos(), ws.sin()),
        };
        prev = Some((t, e));
        let g1 = (e - C::new(1.0, 0.0)).div(iw);
        let g2 = (e * t - g1).div(iw);
        *o = (g1, g2);
    }
}

/// A turning-path fit evaluated at one time.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct TurnFit {
    /// Position (px) at the evaluation time.
    pub x: f64,
    pub y: f64,
    /// Velocity (px per unit of `tau`) there.
    pub u: f64,
    pub v: f64,
    /// Acceleration (px per unit of `tau`²) there.
    pub ax: f64,
    pub ay: f64,
    /// Prediction variance over the per-axis position noise variance, at
    /// the fitted ω (the noise of ω itself is not included: on an
    /// 11-detection arc the true variance is ~1.5 times this).
    pub leverage: f64,
    /// Rate of turn (rad per unit of `tau`).
    pub omega: f64,
}

/// The least-squares coefficients `(z₀, V, A)` (`A = 0` for `P = 2`) at a
/// given ω and, with `leverage`, the leverage at `s = 0` (NaN without):
/// what the fits compute, from the samples' times afresh.
#[cfg(feature = "testkit")]
fn coeffs<const P: usize>(
    s: &[f64],
    xs: &[f64],
    ys: &[f64],
    w: f64,
    leverage: bool,
) -> Option<([C; 3], f64)> {
    let n = s.len().min(64);
    Normal::new(&bases(s, w)[..n], xs, ys).solve::<P>(leverage)
}

/// The normal equations `G c = b` of the six-coefficient fit at one ω
/// (`φ = (1, g₁, g₂)`, `G = Σ φᴴφ`, `b = Σ φᴴ(z − z_ref)`) and `Σ|z − z_ref|²`,
/// positions taken about the first sample `z_ref` (the constant term
/// absorbs the shift; small numbers keep the residual sum exact to
/// ~1e-13 px²). The four-coefficient fit (`A = 0`) is its leading 2×2
/// block, so one pass over the samples serves both, and the residual sum
/// of squares of a solution is `Σ|z − z_ref|² − Re(bᴴc)`, without a second
/// pass ([`rss_of`] is the plain sum it is tested against).
#[derive(Clone, Copy)]
struct Normal {
    g: [[C; 3]; 3],
    b: [C; 3],
    zz: f64,
    z_ref: C,
}

impl Normal {
    fn new(bs: &[(C, C)], xs: &[f64], ys: &[f64]) -> Normal {
        let z_ref = C::new(xs[0], ys[0]);
        let mut g = [[C::ZERO; 3]; 3];
        let mut b = [C::ZERO; 3];
        let mut zz = 0.0;
        for (i, &(g1, g2)) in bs.iter().enumerate() {
            let phi = [C::new(1.0, 0.0), g1, g2];
            let z = C::new(xs[i], ys[i]) - z_ref;
            // Hermitian: the upper triangle, the lower one by conjugation.
            for a in 0..3 {
                let pa = phi[a].conj();
                for c in a..3 {
                    g[a][c] = g[a][c] + pa * phi[c];
                }
                b[a] = b[a] + pa * z;
            }
            zz += z.norm2();
        }
        for a in 1..3 {
            for c in 0..a {
                g[a][c] = g[c][a].conj();
            }
        }
        Normal { g, b, zz, z_ref }
    }

    /// The `P`-coefficient solution `(z₀, V, A)` (absolute `z₀`) and, with
    /// `leverage`, the leverage at `s = 0` (NaN without).
    fn solve<const P: usize>(&self, leverage: bool) -> Option<([C; 3], f64)> {
        let (c, lev) = self.solve_rel::<P>(leverage)?;
        let mut out = c;
        out[0] = out[0] + self.z_ref;
        Some((out, lev))
    }

    /// [`Normal::solve`] with `z₀` relative to `z_ref`.
    fn solve_rel<const P: usize>(&self, leverage: bool) -> Option<([C; 3], f64)> {
        let mut g = [[C::ZERO; P]; P];
        let mut b = [C::ZERO; P];
        for a in 0..P {
            g[a].copy_from_slice(&self.g[a][..P]);
            b[a] = self.b[a];
        }
        // φ(0) = (1, 0, 0): the leverage is (G⁻¹)₀₀.
        let (c, lev) = if leverage {
            let mut e0 = [C::ZERO; P];
            e0[0] = C::new(1.0, 0.0);
            let (c, l) = solve2(g, b, e0)?;
            (c, l[0].re)
        } else {
            (solve(g, b)?, f64::NAN)
        };
        let mut out = [C::ZERO; 3];
        out[..P].copy_from_slice(&c);
        Some((out, lev))
    }

    /// Residual sum of squares (both axes) of the relative solution `c`.
    fn rss(&self, c: &[C; 3]) -> f64 {
        let fitted: f64 = (0..3).map(|a| (self.b[a].conj() * c[a]).re).sum();
        (self.zz - fitted).max(0.0)
    }
}

/// Residual sum of squares (both axes) of the six-coefficient fit at ω,
/// summed over the residuals (the plain form; the fits take it from the
/// normal equations, [`Normal::rss`]).
fn rss_at(s: &[f64], xs: &[f64], ys: &[f64], w: f64) -> Option<f64> {
    rss_of(&bases(s, w)[..s.len().min(64)], xs, ys)
}

/// [`rss_at`] from the samples' basis values `bs` (see [`bases`]).
fn rss_of(bs: &[(C, C)], xs: &[f64], ys: &[f64]) -> Option<f64> {
    let (c, _) = Normal::new(bs, xs, ys).solve::<3>(false)?;
    Some(
        bs.iter()
            .zip(xs.iter().zip(ys))
            .map(|(&(g1, g2), (&x, &y))| (C::new(x, y) - (c[0] + c[1] * g1 + c[2] * g2)).norm2())
            .sum(),
    )
}

/// The fixed point for ω of the six-coefficient fit (times `s` from any
/// origin near the samples); 0 when the path is too slow to have a
/// heading.
#[cfg(feature = "testkit")]
fn turn_rate(s: &[f64], xs: &[f64], ys: &[f64]) -> Option<f64> {
    turn_rate_full(s, xs, ys).map(|r| r.w)
}

/// What [`turn_rate_full`] computed on the way: the rate, the normal
/// equations at it, and (when it checked the rate, ≥ 7 samples) the
/// residual sums of squares at it and at ω = 0, for the callers that need
/// them again (the same numbers, not recomputed).
struct Rate {
    w: f64,
    normal: Normal,
    checked: Option<(f64, f64)>,
}

/// [`turn_rate`] with what it computed on the way ([`Rate`]).
fn turn_rate_full(s: &[f64], xs: &[f64], ys: &[f64]) -> Option<Rate> {
    // Up to 6 samples the six coefficients leave too few residuals to
    // check a rate by: a few steps from the quadratic's own rate, no
    // further (more follow the noise; the young tracks' choice between
    // the line and the turning path decides whether it is used).
    let n = s.len().min(64);
    let few = s.len() < 7;
    let iterations = if few { YOUNG_ITERATIONS } else { ITERATIONS };
    // The fit at ω = 0 serves the first step and the final check.
    let mut buf = [(C::ZERO, C::ZERO); 64];
    let bs = &mut buf[..n];
    bases_into(bs, &s[..n], 0.0);
    let n0 = Normal::new(bs, xs, ys);
    let mut r0 = f64::NAN;
    let mut w = 0.0f64;
    let mut at_w = n0;
    for _ in 0..iterations {
        let (c, _) = at_w.solve_rel::<3>(false)?;
        if w.to_bits() == 0 {
            r0 = at_w.rss(&c);
        }
        let (v, a) = (c[1], c[2]);
        let sp2 = v.norm2();
        if sp2 < MIN_SPEED * MIN_SPEED {
            return Some(Rate {
                w: 0.0,
                normal: n0,
                checked: None,
            });
        }
        let next = (w + (a * v.conj()).im / sp2).clamp(-MAX_TURN, MAX_TURN);
        let converged = (next - w).abs() < 1e-5;
        w = next;
        at_w = if w.to_bits() == 0 {
            n0
        } else {
            bases_into(bs, &s[..n], w);
            Normal::new(bs, xs, ys)
        };
        if converged {
            break;
        }
    }
    if few {
        return Some(Rate {
            w,
            normal: at_w,
            checked: None,
        });
    }
    // A rate that fits worse than the quadratic (noise taken for a turn,
    // an iteration run off) is no turn.
    let (c, _) = at_w.solve_rel::<3>(false)?;
    let rw = at_w.rss(&c);
    Some(if rw <= r0 {
        Rate {
            w,
            normal: at_w,
            checked: Some((rw, r0)),
        }
    } else {
        Rate {
            w: 0.0,
            normal: n0,
            checked: Some((r0, r0)),
        }
    })
}

/// How much better (drop of the residual sum of squares, both axes, px²)
/// the turning path fits the samples than the quadratic in time with the
/// same number of coefficients; 0 when it does not (at least 7 samples).
pub(crate) fn turn_rss_gain(tau: &[f64], xs: &[f64], ys: &[f64]) -> Option<f64> {
    let (buf, n) = centred(tau)?;
    let s = &buf[..n];
    let r = turn_rate_full(s, xs, ys)?;
    let (q, t) = match r.checked {
        Some((rw, r0)) => (r0, rw),
        None => (rss_at(s, xs, ys, 0.0)?, rss_at(s, xs, ys, r.w)?),
    };
    Some((q - t).max(0.0))
}

/// Fit the constant-turn-rate path through `(tau, xs, ys)` (times in
/// pulses, any origin, at least 4 samples) and evaluate it at `at`.
/// `accel`: the speed may change linearly (six real coefficients, the
/// quadratic's count); otherwise it is constant (four, with ω found from
/// a fit with acceleration first) — for few samples.
pub(crate) fn turn_eval(
    tau: &[f64],
    xs: &[f64],
    ys: &[f64],
    at: f64,
    accel: bool,
) -> Option<TurnFit> {
    turn_eval_rss(tau, xs, ys, at, accel).map(|(f, _)| f)
}

/// [`turn_eval`], and the residual sums of squares at the fitted ω and
/// at ω = 0 where the rate was checked by them (≥ 7 samples).
fn turn_eval_rss(
    tau: &[f64],
    xs: &[f64],
    ys: &[f64],
    at: f64,
    accel: bool,
) -> Option<(TurnFit, Option<(f64, f64)>)> {
    let n = tau.len();
    if n < 4 || xs.len() < n || ys.len() < n {
        return None;
    }
    let mut s = [0.0; 64];
    let n = n.min(64);
    for i in 0..n {
        s[i] = tau[i] - at;
    }
    let s = &s[..n];
    let r = turn_rate_full(s, xs, ys)?;
    let w = r.w;
    let (c, lev) = if accel {
        r.normal.solve::<3>(true)?
    } else {
        r.normal.solve::<2>(true)?
    };
    let (z0, v, a) = (c[0], c[1], c[2]);
    // d/ds [(V + A s) e^{iωs}] at s = 0.
    let acc = a + C::new(0.0, w) * v;
    let fit = TurnFit {
        x: z0.re,
        y: z0.im,
        u: v.re,
        v: v.im,
        ax: acc.re,
        ay: acc.im,
        leverage: lev,
        omega: w,
    };
    Some((fit, r.checked))
}

/// [`turn_eval`] with speed change, and the drop of the residual sum of
/// squares (px², both axes) from the quadratic in time to it: how much
/// the samples say the path turns beyond what a quadratic follows.
pub(crate) fn turn_eval_with_gain(
    tau: &[f64],
    xs: &[f64],
    ys: &[f64],
    at: f64,
) -> Option<(TurnFit, f64)> {
    let (f, rss) = turn_eval_rss(tau, xs, ys, at, true)?;
    let (q, t) = match rss {
        Some((rw, r0)) => (r0, rw),
        None => {
            let n = tau.len().min(64);
            let mut s = [0.0; 64];
            for i in 0..n {
                s[i] = tau[i] - at;
            }
            let s = &s[..n];
            (rss_at(s, xs, ys, 0.0)?, rss_at(s, xs, ys, f.omega)?)
        }
    };
    Some((f, (q - t).max(0.0)))
}

/// Residual sum of squares (px², both axes) of the turning path with
/// speed change through the samples (at least 7).
pub(crate) fn turn_rss(tau: &[f64], xs: &[f64], ys: &[f64]) -> Option<f64> {
    let (buf, n) = centred(tau)?;
    let s = &buf[..n];
    let r = turn_rate_full(s, xs, ys)?;
    match r.checked {
        Some((rw, _)) => Some(rw),
        None => rss_at(s, xs, ys, r.w),
    }
}

/// The first (at most 64) sample times relative to their mid-range, and
/// how many; `None` below the 7 samples a turning fit needs.
fn centred(tau: &[f64]) -> Option<([f64; 64], usize)> {
    let n = tau.len().min(64);
    if n < 7 {
        return None;
    }
    let mid = 0.5 * (tau[0] + tau[n - 1]);
    let mut s = [0.0; 64];
    for i in 0..n {
        s[i] = tau[i] - mid;
    }
    Some((s, n))
}

/// Heading changes along a track, for a cheap screen of where it turns:
/// prefix sums over the detections of the change of heading between the
/// steps into and out of each detection (rad; 0 across gaps and for slow
/// steps) and of its noise variance (from the position noise `sigma`:
/// three positions, ~6σ²/|step|²), so that a window's sums cost O(1).
pub(crate) fn heading_prefix(pulses: &[i64], xs: &[f64], ys: &[f64], sigma: f64) -> Vec<[f64; 2]> {
    let n = pulses.len();
    let mut out = Vec::with_capacity(n + 1);
    out.push([0.0, 0.0]);
    let mut acc = [0.0, 0.0];
    for i in 0..n {
        if i > 0 && i + 1 < n && pulses[i] == pulses[i - 1] + 1 && pulses[i + 1] == pulses[i] + 1 {
            let (ax, ay) = (xs[i] - xs[i - 1], ys[i] - ys[i - 1]);
            let (bx, by) = (xs[i + 1] - xs[i], ys[i + 1] - ys[i]);
            let (la, lb) = (ax * ax + ay * ay, bx * bx + by * by);
            if la.min(lb) > (MIN_SPEED * 4.0).powi(2) {
                acc[0] += (ax * by - ay * bx).atan2(ax * bx + ay * by);
                acc[1] += 3.0 * sigma * sigma * (1.0 / la + 1.0 / lb);
            }
        }
        out.push(acc);
    }
    out
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;

    /// The recurrence of [`bases`] against each sample's own [`basis`]:
    /// consecutive, gapped and half-integer times, rates from the series
    /// branch's edge to the largest, both signs. Near the series branch
    /// both forms lose digits to `e^{iωs} − 1` (relative ~ε/(ωs)²), so the
    /// tolerance grows there.
    #[ebptv_macros::unit_test]
    fn bases_equal_each_samples_basis() {
        let mut times: Vec<Vec<f64>> = vec![
            (0..12).map(|k| k as f64 - 11.0).collect(),
            (0..12).map(|k| k as f64 - 12.0).collect(),
            (0..11).map(|k| k as f64 - 5.0).collect(),
            (0..64).map(|k| k as f64 - 31.5).collect(),
        ];
        times.push(vec![-9.0, -8.0, -6.0, -5.0, -4.0, -1.0, 0.0, 1.0]);
        for s in &times {
            for w in [1e-5, 2e-4, -0.003, 0.05, -0.2, 0.45, MAX_TURN, -MAX_TURN] {
                let fast = bases(s, w);
                for (k, &t) in s.iter().enumerate() {
                    let (g1, g2) = basis(w, t);
                    let (f1, f2) = fast[k];
                    let ws = (w * t).abs().max(1e-3);
                    let scale = (1.0 + t * t) * (1.0 / (ws * ws)).max(1.0);
                    for (a, b) in [
                        (f1.re, g1.re),
                        (f1.im, g1.im),
                        (f2.re, g2.re),
                        (f2.im, g2.im),
                    ] {
                        assert!((a - b).abs() <= 1e-12 * scale, "w {w} s {t}: {a} vs {b}");
                    }
                }
            }
        }
    }

    fn arc(r: f64, w: f64, speedup: f64, n: usize) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        // Heading turns at w, speed 1 + speedup·t: integrate finely.
        let (mut x, mut y, mut th, mut t) = (r, 0.0, std::f64::consts::FRAC_PI_2, 0.0);
        let (mut tau, mut xs, mut ys) = (vec![], vec![], vec![]);
        let dt = 1e-3;
        let sp0 = r * w;
        for i in 0..=(n * 1000) {
            if i % 1000 == 0 {
                tau.push(t);
                xs.push(x);
                ys.push(y);
            }
            let sp = sp0 * (1.0 + speedup * (t + 0.5 * dt));
            let thm = th + 0.5 * w * dt;
            x += sp * thm.cos() * dt;
            y += sp * thm.sin() * dt;
            th += w * dt;
            t += dt;
        }
        (tau, xs, ys)
    }

    #[ebptv_macros::unit_test]
    fn an_arc_is_extrapolated_exactly_and_a_quadratic_is_not() {
        for (r, w, acc) in [
            (20.0, 0.19, 0.0),
            (10.0, 0.3, 0.0),
            (30.0, 0.13, 0.03),
            (25.0, -0.2, -0.02),
        ] {
            let (tau, xs, ys) = arc(r, w, acc, 12);
            let k = 11;
            let f = turn_eval(&tau[..k], &xs[..k], &ys[..k], tau[k], true).unwrap();
            let err = (f.x - xs[k]).hypot(f.y - ys[k]);
            assert!(err < 0.02, "r {r} w {w}: turn model misses by {err}");
            assert!((f.omega - w).abs() < 0.01, "omega {} vs {w}", f.omega);
            let q = crate::track::fit::fit_eval(&tau[..k], &xs[..k], &ys[..k], 2, tau[k]).unwrap();
            let qerr = (q.x - xs[k]).hypot(q.y - ys[k]);
            assert!(
                qerr > 10.0 * err.max(0.01),
                "quadratic {qerr} vs turn {err}"
            );
        }
    }

    #[ebptv_macros::unit_test]
    fn a_straight_or_accelerating_path_gives_the_quadratic() {
        let tau: Vec<f64> = (0..10).map(|i| i as f64).collect();
        let xs: Vec<f64> = tau.iter().map(|t| 3.0 + 2.0 * t + 0.05 * t * t).collect();
        let ys: Vec<f64> = tau
            .iter()
            .map(|t| -1.0 + 0.5 * t + 0.0125 * t * t)
            .collect();
        let f = turn_eval(&tau, &xs, &ys, 10.0, true).unwrap();
        let q = crate::track::fit::fit_eval(&tau, &xs, &ys, 2, 10.0).unwrap();
        assert!(f.omega.abs() < 1e-6, "{}", f.omega);
        assert!((f.x - q.x).abs() < 1e-6 && (f.y - q.y).abs() < 1e-6);
        assert!((f.leverage - q.leverage).abs() < 1e-6 * q.leverage);
        // Constant speed: the line's leverage.
        let l = crate::track::fit::fit_eval(&tau, &xs, &ys, 1, 10.0).unwrap();
        let g = turn_eval(
            &tau,
            &tau.iter().map(|t| 2.0 * t).collect::<Vec<_>>(),
            &ys.iter().map(|_| 0.0).collect::<Vec<_>>(),
            10.0,
            false,
        )
        .unwrap();
        assert!((g.leverage - l.leverage).abs() < 1e-6 * l.leverage);
        assert!((g.x - 20.0).abs() < 1e-9 && g.y.abs() < 1e-9);
    }

    #[ebptv_macros::unit_test]
    fn noise_leverage_matches_monte_carlo() {
        // The stated leverage is the prediction's variance per unit noise.
        use rand::{Rng, SeedableRng};
        use rand_distr::StandardNormal;
        let (tau, xs, ys) = arc(20.0, 0.15, 0.0, 12);
        let k = 11;
        let mut rng = rand_pcg::Pcg64::seed_from_u64(3);
        let sig = 0.3;
        let (mut s2, mut lev, m) = (0.0, 0.0, 4000);
        for _ in 0..m {
            let nx: Vec<f64> = xs[..k]
                .iter()
                .map(|x| x + sig * rng.sample::<f64, _>(StandardNormal))
                .collect();
            let ny: Vec<f64> = ys[..k]
                .iter()
                .map(|y| y + sig * rng.sample::<f64, _>(StandardNormal))
                .collect();
            let f = turn_eval(&tau[..k], &nx, &ny, tau[k], true).unwrap();
            s2 += 0.5 * ((f.x - xs[k]).powi(2) + (f.y - ys[k]).powi(2));
            lev += f.leverage;
        }
        // The leverage is that of the fit at the fitted ω; the noise of ω
        // itself adds about half as much again on an 11-point arc (1.56
        // here): a known understatement of the gate in turning regions.
        let ratio = s2 / m as f64 / (sig * sig) / (lev / m as f64);
        assert!(
            (1.0..2.0).contains(&ratio),
            "variance / stated leverage = {ratio}"
        );
    }

    #[ebptv_macros::unit_test]
    fn the_joint_solve_equals_two_plain_solves_bit_for_bit() {
        let (tau, xs, ys) = arc(20.0, 0.15, 0.1, 12);
        for (n, w) in [(12, 0.15), (7, -0.4), (5, 1e-4), (12, 0.0)] {
            let s: Vec<f64> = tau[..n].iter().map(|t| t - tau[n - 1]).collect();
            let bs = bases(&s, w);
            let mut g = [[C::ZERO; 3]; 3];
            let mut b = [C::ZERO; 3];
            for i in 0..n {
                let (g1, g2) = bs[i];
                let phi = [C::new(1.0, 0.0), g1, g2];
                let z = C::new(xs[i], ys[i]) - C::new(xs[0], ys[0]);
                for a in 0..3 {
                    for c in 0..3 {
                        g[a][c] = g[a][c] + phi[a].conj() * phi[c];
                    }
                    b[a] = b[a] + phi[a].conj() * z;
                }
            }
            let mut e0 = [C::ZERO; 3];
            e0[0] = C::new(1.0, 0.0);
            let (x, y) = solve2(g, b, e0).unwrap();
            assert_eq!(x, solve(g, b).unwrap());
            assert_eq!(y, solve(g, e0).unwrap());
            let (c, lev) = coeffs::<3>(&s, &xs[..n], &ys[..n], w, true).unwrap();
            let mut x = x;
            x[0] = x[0] + C::new(xs[0], ys[0]);
            assert_eq!(&c[..], &x[..]);
            assert_eq!(lev.to_bits(), y[0].re.to_bits());
        }
        // Singular: both ways refuse.
        let g = [[C::ZERO; 2]; 2];
        assert!(
            solve2(g, [C::ZERO; 2], [C::ZERO; 2]).is_none() && solve(g, [C::ZERO; 2]).is_none()
        );
    }

    #[ebptv_macros::unit_test]
    fn reused_rate_checks_equal_the_fits_recomputed() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(5);
        for (k, (r, w, up)) in [(20.0, 0.15, 0.0), (8.0, -0.4, 0.2), (1e3, 1e-5, 0.0)]
            .into_iter()
            .enumerate()
        {
            let (tau, xs, ys) = arc(r, w, up, 13);
            for n in [5, 7, 11, 13] {
                let nx: Vec<f64> = xs[..n].iter().map(|x| x + 0.3 * rng.gen::<f64>()).collect();
                let ny: Vec<f64> = ys[..n].iter().map(|y| y + 0.3 * rng.gen::<f64>()).collect();
                let at = tau[n - 1] + 1.0 + k as f64;
                let s: Vec<f64> = tau[..n].iter().map(|t| t - at).collect();
                let omega = turn_rate(&s, &nx, &ny).unwrap();
                for accel in [true, false] {
                    let f = turn_eval(&tau[..n], &nx, &ny, at, accel).unwrap();
                    let (c, lev) = if accel {
                        coeffs::<3>(&s, &nx, &ny, omega, true).unwrap()
                    } else {
                        coeffs::<2>(&s, &nx, &ny, omega, true).unwrap()
                    };
                    assert_eq!(f.omega.to_bits(), omega.to_bits());
                    assert_eq!((f.x, f.y, f.u, f.v), (c[0].re, c[0].im, c[1].re, c[1].im));
                    assert_eq!(f.leverage.to_bits(), lev.to_bits());
                }
                let (f, gain) = turn_eval_with_gain(&tau[..n], &nx, &ny, at).unwrap();
                let q = rss_at(&s, &nx, &ny, 0.0).unwrap();
                let t = rss_at(&s, &nx, &ny, f.omega).unwrap();
                // From the normal equations against the residuals summed.
                let close = |a: f64, b: f64, scale: f64| (a - b).abs() <= 1e-9 * (1.0 + scale);
                assert!(close(gain, (q - t).max(0.0), q), "gain {gain} vs {q} - {t}");
                if n >= 7 {
                    let c: Vec<f64> = tau[..n]
                        .iter()
                        .map(|t| t - 0.5 * (tau[0] + tau[n - 1]))
                        .collect();
                    let wc = turn_rate(&c, &nx, &ny).unwrap();
                    let (q, t) = (
                        rss_at(&c, &nx, &ny, 0.0).unwrap(),
                        rss_at(&c, &nx, &ny, wc).unwrap(),
                    );
                    let g = turn_rss_gain(&tau[..n], &nx, &ny).unwrap();
                    assert!(close(g, (q - t).max(0.0), q), "gain {g} vs {q} - {t}");
                    let r = turn_rss(&tau[..n], &nx, &ny).unwrap();
                    assert!(close(r, t, t), "rss {r} vs {t}");
                }
            }
        }
    }
}
