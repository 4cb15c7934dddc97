//! Steps in a track: where one track's detections jump from one particle
//! to a close neighbour and stay there (a *swap*), found in hindsight.
//!
//! # Why
//! On the paper-like synthetic scene (384², `benches/examples/ptv_swaps.rs`)
//! 356 of a track's links inside the track join clean images of two
//! different particles; 284 of them are *exchanges*: the track goes on
//! with the other particle. In 149 the track's own particle was not
//! detected at that pulse (it left the sheet, did not fire or its image
//! merged with another), and the track took an untracked neighbour 1–4 px
//! away whose image lay inside its gate (n_σ σ ≈ 1.5 px with σ ≈ 0.41 px
//! per axis). Two neighbours 1–4 px apart move with nearly the same
//! velocity in a flow whose structures are hundreds of pixels, so the
//! track stays smooth apart from a jump of the position by their
//! distance: no forward gate can see it, but a look at the detections on
//! both sides can.
//!
//! # How
//! For every detection `s` of an ended track with at least `min_side`
//! detections on each side, the detections within `half` on each side
//! are fitted (per axis, τ = pulse index) by a quadratic, by the
//! quadratic plus a step `Δ·[τ ≥ τ_s]`, and by the quadratic plus a
//! single outlier at `s − 1` or at `s`. The step's gain is the drop of
//! the residual sum of squares over σ², a χ² of 2 degrees of freedom for
//! a track without a step; it has to exceed `threshold` and beat both
//! single-outlier models by `threshold / 2` (an excursion through one
//! wrong image, which the output fit's outlier gate removes, is no
//! step). The best step of a track is cut, and both pieces are searched
//! again. Cost: per detection of an ended track, a screen of
//! one quadratic fit with tabulated window terms ([`surely_below`]); the
//! exact gains ([`gains`]: tabulated terms, the data's residuals) only
//! where the screen cannot rule a step out — ~470 instructions per
//! candidate in all (1 210 before), the direct fits kept as references.

/// Most detections on each side of a candidate step that its fits use
/// (paper-like scene, threshold 12: 4 / 5 / 6 / 8 / 10 give precision
/// 0.9639 / 0.9646 / 0.9652 / 0.9659 / 0.9660 at recall 0.9526 / 0.9526 /
/// 0.9523 / 0.9484 / 0.9402: wider windows see smaller steps but take
/// the flow's curvature for steps).
pub(crate) const STEP_HALF_WINDOW: usize = 6;

/// Fewest detections on each side of a step.
pub(crate) const STEP_MIN_SIDE: usize = 3;

#[cfg(feature = "testkit")]
/// Residual sum of squares (both axes) of the least-squares fit of
/// `xs`, `ys` on the columns 1, τ, τ² (as many as `order + 1`) and, when
/// given, one extra column `extra`. `None` when the fit is singular.
fn rss(tau: &[f64], xs: &[f64], ys: &[f64], order: usize, extra: Option<&[f64]>) -> Option<f64> {
    const M: usize = 4;
    let n = tau.len();
    let m = order + 1 + extra.is_some() as usize;
    if n <= m {
        return None;
    }
    let col = |j: usize, i: usize| -> f64 {
        if j <= order {
            tau[i].powi(j as i32)
        } else {
            extra.expect("extra column")[i]
        }
    };
    // Normal equations with both right-hand sides.
    let mut a = [[0.0f64; M + 2]; M];
    for i in 0..n {
        let mut c = [0.0; M];
        for (j, cj) in c.iter_mut().enumerate().take(m) {
            *cj = col(j, i);
        }
        for j in 0..m {
            for k in 0..m {
                a[j][k] += c[j] * c[k];
            }
            a[j][M] += c[j] * xs[i];
            a[j][M + 1] += c[j] * ys[i];
        }
    }
    // Gaussian elimination with partial pivoting.
    for p in 0..m {
        let piv = (p..m).max_by(|&r, &s| a[r][p].abs().total_cmp(&a[s][p].abs()))?;
        if a[piv][p].abs() < 1e-9 {
            return None;
        }
        a.swap(p, piv);
        for r in 0..m {
            if r != p {
                let f = a[r][p] / a[p][p];
                for k in p..M + 2 {
                    a[r][k] -= f * a[p][k];
                }
            }
        }
    }
    let mut out = 0.0;
    for i in 0..n {
        let (mut fx, mut fy) = (0.0, 0.0);
        for j in 0..m {
            let c = col(j, i);
            fx += c * a[j][M] / a[j][j];
            fy += c * a[j][M + 1] / a[j][j];
        }
        out += (xs[i] - fx).powi(2) + (ys[i] - fy).powi(2);
    }
    Some(out)
}

/// Gains at detection `s` of `dets` (`(pulse, x, y)`, increasing pulses),
/// fitting the detections of `lo..hi` within `STEP_HALF_WINDOW` of it:
/// (drop of the residual sum of squares by a step at `s`, the larger drop
/// by a single outlier at `s − 1` or `s`), in units of σ² — bit for bit
/// [`gains_direct`]. Everything in it but the data's own sums depends
/// only on the window's τ values: when the window has no missed pulse,
/// those parts (the inverse normal matrix, the step column's and the two
/// outlier rows' leverages) come from [`WindowTerms::table`], computed
/// once by the same code on the same τ values; windows with missed
/// pulses (about half of them: a 12-pulse window misses one of a
/// particle's images often) from a small per-thread cache keyed by their
/// pattern of pulses ([`WindowTerms::with_gaps`]). The step scan was the
/// output fits' largest per-detection cost, and these parts most of it.
/// Windows spanning 64 pulses or more take [`gains_direct`].
fn gains(
    dets: &[(i64, f64, f64)],
    s: usize,
    lo: usize,
    hi: usize,
    sigma: f64,
) -> Option<(f64, f64)> {
    let a = s.saturating_sub(STEP_HALF_WINDOW).max(lo);
    let b = (s + STEP_HALF_WINDOW).min(hi);
    let w = &dets[a..b];
    if w.len() <= 4 {
        return None;
    }
    let terms = if dets[b - 1].0 - dets[a].0 == (b - 1 - a) as i64 {
        WindowTerms::table()[s - a][b - s]
    } else {
        match WindowTerms::with_gaps(w, s - a) {
            Some(terms) => terms,
            None => return gains_direct(dets, s, lo, hi, sigma),
        }
    };
    let terms = terms.as_ref()?;
    let inv = &terms.inv;
    // From here on the operations of `gains_direct` on the data, in its
    // order.
    let t0 = dets[s].0;
    let row = |d: &(i64, f64, f64)| {
        let t = (d.0 - t0) as f64;
        [1.0, t, t * t]
    };
    let (mut gx, mut gy) = ([0.0f64; 3], [0.0f64; 3]);
    for d in w {
        let c = row(d);
        for j in 0..3 {
            gx[j] += c[j] * d.1;
            gy[j] += c[j] * d.2;
        }
    }
    let mul = |v: &[f64; 3]| -> [f64; 3] {
        std::array::from_fn(|j| (0..3).map(|k| inv[j][k] * v[k]).sum())
    };
    let (cx, cy) = (mul(&gx), mul(&gy));
    let dot = |u: &[f64; 3], v: &[f64; 3]| u[0] * v[0] + u[1] * v[1] + u[2] * v[2];
    let (mut erx, mut ery) = (0.0, 0.0);
    let mut outlier = 0.0f64;
    for (i, d) in w.iter().enumerate() {
        let c = row(d);
        let (rx, ry) = (d.1 - dot(&c, &cx), d.2 - dot(&c, &cy));
        if a + i >= s {
            erx += rx;
            ery += ry;
        }
        if a + i + 1 == s || a + i == s {
            let q = terms.q[a + i + 1 - s];
            if q > 1e-9 {
                outlier = outlier.max((rx * rx + ry * ry) / q);
            }
        }
    }
    let s2 = sigma * sigma;
    Some(((erx * erx + ery * ery) / terms.qe / s2, outlier / s2))
}

/// The parts of [`gains_direct`] that depend only on the τ values of a
/// window without missed pulses: `before` = s − a detections before the
/// candidate and `from` = b − s from it on.
#[derive(Debug, Clone, Copy)]
struct WindowTerms {
    /// Inverse of the quadratic's normal matrix.
    inv: [[f64; 3]; 3],
    /// 1 − leverage of the detections at s − 1 and at s.
    q: [f64; 2],
    /// The step column's residual norm e·(I − H)e (> 1e-9).
    qe: f64,
    /// X'e: the sums of 1, τ, τ² over the detections from the candidate on.
    ge: [f64; 3],
}

impl WindowTerms {
    /// For every `before` and `from` ≤ `STEP_HALF_WINDOW`: the terms, or
    /// `None` where [`gains_direct`] returns `None` whatever the data
    /// (singular normal matrix, step column in the quadratic's span).
    fn table() -> &'static [[Option<WindowTerms>; STEP_HALF_WINDOW + 1]; STEP_HALF_WINDOW + 1] {
        static TABLE: std::sync::OnceLock<
            [[Option<WindowTerms>; STEP_HALF_WINDOW + 1]; STEP_HALF_WINDOW + 1],
        > = std::sync::OnceLock::new();
        TABLE.get_or_init(|| {
            std::array::from_fn(|before| {
                std::array::from_fn(|from| WindowTerms::consecutive(before, from))
            })
        })
    }

    /// [`WindowTerms::new`] for a window of consecutive pulses, τ =
    /// −before … from − 1.
    fn consecutive(before: usize, from: usize) -> Option<WindowTerms> {
        let tau: Vec<i64> = (0..before + from)
            .map(|i| i as i64 - before as i64)
            .collect();
        WindowTerms::new(&tau, before)
    }

    /// The terms of window `w` (no longer than `2 · STEP_HALF_WINDOW`),
    /// the candidate at `w[before]`, from the calling thread's cache of
    /// pulse patterns: `None` when the window spans 64 pulses or more (no
    /// pattern key), else what [`WindowTerms::new`] gives (cached: the
    /// same τ values give the same bits).
    fn with_gaps(w: &[(i64, f64, f64)], before: usize) -> Option<Option<WindowTerms>> {
        let p0 = w[0].0;
        if w[w.len() - 1].0 - p0 >= 64 {
            return None;
        }
        // The pattern: which pulses of the span hold a detection (bit 0,
        // the first, always does); with `before` it fixes every τ.
        let mut mask = 0u64;
        for d in w {
            mask |= 1u64 << (d.0 - p0);
        }
        let slot = ((mask ^ ((before as u64) << 58)).wrapping_mul(0x9E37_79B9_7F4A_7C15)
            >> (64 - GAP_SLOTS_LOG2)) as usize;
        GAP_TERMS.with(|cache| {
            let mut cache = cache.borrow_mut();
            let entry = &mut cache[slot];
            if entry.mask != mask || entry.before != before {
                let t0 = w[before].0;
                let mut tau = [0i64; 2 * STEP_HALF_WINDOW];
                for (t, d) in tau.iter_mut().zip(w) {
                    *t = d.0 - t0;
                }
                *entry = GapEntry {
                    mask,
                    before,
                    terms: WindowTerms::new(&tau[..w.len()], before),
                };
            }
            Some(entry.terms)
        })
    }

    /// The terms as [`gains_direct`] computes them for a window whose
    /// detections lie at `tau` (pulses after the candidate, increasing;
    /// the candidate is `tau[before]`): the same operations on the same
    /// values, so the same bits.
    fn new(tau: &[i64], before: usize) -> Option<WindowTerms> {
        let n = tau.len();
        if n <= 4 {
            return None;
        }
        let row = |i: usize| {
            let t = tau[i] as f64;
            [1.0, t, t * t]
        };
        let (mut g, mut ge) = ([[0.0f64; 3]; 3], [0.0; 3]);
        let mut ne = 0.0;
        for i in 0..n {
            let c = row(i);
            for j in 0..3 {
                for k in 0..3 {
                    g[j][k] += c[j] * c[k];
                }
                if i >= before {
                    ge[j] += c[j];
                }
            }
            if i >= before {
                ne += 1.0;
            }
        }
        let inv = invert3(&g)?;
        let mul = |v: &[f64; 3]| -> [f64; 3] {
            std::array::from_fn(|j| (0..3).map(|k| inv[j][k] * v[k]).sum())
        };
        let dot = |u: &[f64; 3], v: &[f64; 3]| u[0] * v[0] + u[1] * v[1] + u[2] * v[2];
        let leverage_gap = |i: Option<usize>| match i {
            Some(i) if i < n => {
                let c = row(i);
                1.0 - dot(&c, &mul(&c))
            }
            _ => 0.0, // no such detection: never read
        };
        let q = [
            leverage_gap(before.checked_sub(1)),
            leverage_gap(Some(before)),
        ];
        let qe = ne - dot(&ge, &mul(&ge));
        if qe <= 1e-9 {
            return None;
        }
        Some(WindowTerms { inv, q, qe, ge })
    }
}

/// log₂ of the slots of the per-thread cache of windows with missed pulses
/// (direct-mapped; a few hundred patterns are common).
const GAP_SLOTS_LOG2: u32 = 10;

/// A slot of that cache (`mask` 0: empty — a pattern always has bit 0).
#[derive(Clone, Copy)]
struct GapEntry {
    mask: u64,
    before: usize,
    terms: Option<WindowTerms>,
}

thread_local! {
    static GAP_TERMS: std::cell::RefCell<Vec<GapEntry>> = std::cell::RefCell::new(vec![
        GapEntry {
            mask: 0,
            before: 0,
            terms: None,
        };
        1 << GAP_SLOTS_LOG2
    ]);
}

/// [`gains`] computed directly: the normal equations of the window, their
/// inverse, the residuals and the drops (the reference of [`gains`], and
/// its path for windows with missed pulses). One quadratic
/// fit per axis; the drops follow from its residuals r and hat matrix H
/// (adding a column e lowers the RSS by (e·r)² / e·(I − H)e), which is
/// what [`gains_reference`] gets by refitting.
fn gains_direct(
    dets: &[(i64, f64, f64)],
    s: usize,
    lo: usize,
    hi: usize,
    sigma: f64,
) -> Option<(f64, f64)> {
    let (erx, ery, qe, outlier) = direct_parts(dets, s, lo, hi)?;
    let s2 = sigma * sigma;
    Some(((erx * erx + ery * ery) / qe / s2, outlier / s2))
}

/// The sums behind [`gains_direct`]: the step column's residual sums
/// e·r per axis, its residual norm e·(I − H)e and the larger outlier
/// drop at `s − 1` or `s` (px², not yet over σ²).
fn direct_parts(
    dets: &[(i64, f64, f64)],
    s: usize,
    lo: usize,
    hi: usize,
) -> Option<(f64, f64, f64, f64)> {
    let a = s.saturating_sub(STEP_HALF_WINDOW).max(lo);
    let b = (s + STEP_HALF_WINDOW).min(hi);
    let w = &dets[a..b];
    if w.len() <= 4 {
        return None;
    }
    let t0 = dets[s].0;
    let row = |d: &(i64, f64, f64)| {
        let t = (d.0 - t0) as f64;
        [1.0, t, t * t]
    };
    // Normal matrix and right-hand sides; X'e of the step column.
    let (mut g, mut gx, mut gy, mut ge) = ([[0.0f64; 3]; 3], [0.0; 3], [0.0; 3], [0.0; 3]);
    let mut ne = 0.0;
    for (i, d) in w.iter().enumerate() {
        let c = row(d);
        for j in 0..3 {
            for k in 0..3 {
                g[j][k] += c[j] * c[k];
            }
            gx[j] += c[j] * d.1;
            gy[j] += c[j] * d.2;
            if a + i >= s {
                ge[j] += c[j];
            }
        }
        if a + i >= s {
            ne += 1.0;
        }
    }
    let inv = invert3(&g)?;
    let mul = |v: &[f64; 3]| -> [f64; 3] {
        std::array::from_fn(|j| (0..3).map(|k| inv[j][k] * v[k]).sum())
    };
    let (cx, cy) = (mul(&gx), mul(&gy));
    let dot = |u: &[f64; 3], v: &[f64; 3]| u[0] * v[0] + u[1] * v[1] + u[2] * v[2];
    let (mut erx, mut ery) = (0.0, 0.0);
    let mut outlier = 0.0f64;
    for (i, d) in w.iter().enumerate() {
        let c = row(d);
        let (rx, ry) = (d.1 - dot(&c, &cx), d.2 - dot(&c, &cy));
        if a + i >= s {
            erx += rx;
            ery += ry;
        }
        if a + i + 1 == s || a + i == s {
            let q = 1.0 - dot(&c, &mul(&c));
            if q > 1e-9 {
                outlier = outlier.max((rx * rx + ry * ry) / q);
            }
        }
    }
    let qe = ne - dot(&ge, &mul(&ge));
    if qe <= 1e-9 {
        return None;
    }
    Some((erx, ery, qe, outlier))
}

/// Inverse of a symmetric positive definite 3 × 3 matrix (cofactors);
/// `None` when it is (nearly) singular.
fn invert3(m: &[[f64; 3]; 3]) -> Option<[[f64; 3]; 3]> {
    let c =
        |r0: usize, r1: usize, c0: usize, c1: usize| m[r0][c0] * m[r1][c1] - m[r0][c1] * m[r1][c0];
    let cof = [
        [c(1, 2, 1, 2), -c(1, 2, 0, 2), c(1, 2, 0, 1)],
        [-c(0, 2, 1, 2), c(0, 2, 0, 2), -c(0, 2, 0, 1)],
        [c(0, 1, 1, 2), -c(0, 1, 0, 2), c(0, 1, 0, 1)],
    ];
    let det = m[0][0] * cof[0][0] + m[0][1] * cof[0][1] + m[0][2] * cof[0][2];
    let scale = m[0][0] * m[1][1] * m[2][2];
    if !(det.abs() > 1e-12 * scale.abs().max(1e-300)) {
        return None;
    }
    // The inverse is the transposed cofactor matrix over the determinant.
    Some(std::array::from_fn(|j| {
        std::array::from_fn(|k| cof[k][j] / det)
    }))
}

/// Where to cut a track's detections `dets` (`(pulse, x, y)`, increasing
/// pulses) at steps (see the module docs): indices of the first
/// detection of each later piece, increasing. Cuts are only made at
/// indices ≥ `first_cut`. `threshold` ≤ 0: none.
pub(crate) fn step_cuts(
    dets: &[(i64, f64, f64)],
    sigma: f64,
    threshold: f64,
    first_cut: usize,
) -> Vec<usize> {
    step_cuts_with(dets, sigma, threshold, first_cut, true)
}

/// [`step_cuts`] with or without the screening of candidates
/// ([`surely_below`]); without, every candidate's gains are computed (the
/// reference the tests compare the screened search with).
fn step_cuts_with(
    dets: &[(i64, f64, f64)],
    sigma: f64,
    threshold: f64,
    first_cut: usize,
    screen: bool,
) -> Vec<usize> {
    let mut cuts = Vec::new();
    if threshold > 0.0 && sigma > 0.0 {
        find_cuts(
            dets,
            0,
            dets.len(),
            sigma,
            threshold,
            first_cut,
            screen,
            &mut cuts,
        );
    }
    cuts.sort_unstable();
    cuts
}

/// Whether the step gain of [`gains`] at `s` is surely at most
/// `threshold`, so that `s` cannot be cut and its exact gains need not be
/// computed (nearly every detection of a track: a χ² of 2 degrees of
/// freedom rarely reaches a threshold of 12).
///
/// The step's residual sum e·r (r the quadratic's residuals, e the step
/// column) is Σ_{i≥s} x_i − (X'e)·ĉ: one dot product with the
/// coefficients ĉ instead of [`gains`]' residual of every detection, and
/// mathematically the same number; [`gains`] computes ĉ by the same
/// operations, so the two sums differ by their rounding only, a few ulps
/// of the magnitudes summed. The bound allows 10⁻⁹ of those magnitudes
/// (≥ 10⁵ times the rounding), so a screened-out candidate's exact gain
/// is below the threshold; anything in doubt (and windows without
/// tabulated terms) is left to [`gains`].
fn surely_below(
    dets: &[(i64, f64, f64)],
    s: usize,
    lo: usize,
    hi: usize,
    sigma: f64,
    threshold: f64,
) -> bool {
    let a = s.saturating_sub(STEP_HALF_WINDOW).max(lo);
    let b = (s + STEP_HALF_WINDOW).min(hi);
    let w = &dets[a..b];
    if w.len() <= 4 {
        return false;
    }
    let terms = if dets[b - 1].0 - dets[a].0 == (b - 1 - a) as i64 {
        WindowTerms::table()[s - a][b - s]
    } else {
        match WindowTerms::with_gaps(w, s - a) {
            Some(terms) => terms,
            None => return false,
        }
    };
    let Some(terms) = terms else {
        return false;
    };
    let inv = &terms.inv;
    let t0 = dets[s].0;
    let row = |d: &(i64, f64, f64)| {
        let t = (d.0 - t0) as f64;
        [1.0, t, t * t]
    };
    let (mut gx, mut gy) = ([0.0f64; 3], [0.0f64; 3]);
    // Σ x and Σ |x| over the detections from s on.
    let (mut sx, mut sy, mut ax, mut ay) = (0.0f64, 0.0f64, 0.0f64, 0.0f64);
    for (i, d) in w.iter().enumerate() {
        let c = row(d);
        for j in 0..3 {
            gx[j] += c[j] * d.1;
            gy[j] += c[j] * d.2;
        }
        if a + i >= s {
            sx += d.1;
            sy += d.2;
            ax += d.1.abs();
            ay += d.2.abs();
        }
    }
    let mul = |v: &[f64; 3]| -> [f64; 3] {
        std::array::from_fn(|j| (0..3).map(|k| inv[j][k] * v[k]).sum())
    };
    let (cx, cy) = (mul(&gx), mul(&gy));
    let ge = &terms.ge;
    let dot = |u: &[f64; 3], v: &[f64; 3]| u[0] * v[0] + u[1] * v[1] + u[2] * v[2];
    let (erx, ery) = (sx - dot(ge, &cx), sy - dot(ge, &cy));
    // Magnitudes summed on either path: the detections, and the fitted
    // values c_i·ĉ (|τ| ≤ the window's largest).
    let n_after = (b - s) as f64;
    let t_max = ((dets[a].0 - t0).abs().max(dets[b - 1].0 - t0)) as f64;
    let fitted =
        |c: &[f64; 3]| n_after * (c[0].abs() + t_max * c[1].abs() + t_max * t_max * c[2].abs());
    let bound_x = 1e-9 * (ax + fitted(&cx) + 1.0);
    let bound_y = 1e-9 * (ay + fitted(&cy) + 1.0);
    let (ex, ey) = (erx.abs() + bound_x, ery.abs() + bound_y);
    let upper = (ex * ex + ey * ey) / terms.qe / (sigma * sigma);
    // `!(… >= …)` would also screen out NaN; this form leaves it to `gains`.
    upper * (1.0 + 1e-9) < threshold
}

/// The recursive search of [`step_cuts`]: the best step of `lo..hi` is
/// cut and both sides searched again (the best is the largest gain over
/// the threshold). With `screen`, candidates that [`surely_below`] rules
/// out are skipped (the same cuts: those could not pass the
/// `gain > threshold` test).
#[allow(clippy::too_many_arguments)]
fn find_cuts(
    dets: &[(i64, f64, f64)],
    lo: usize,
    hi: usize,
    sigma: f64,
    threshold: f64,
    first_cut: usize,
    screen: bool,
    cuts: &mut Vec<usize>,
) {
    if hi - lo < 2 * STEP_MIN_SIDE {
        return;
    }
    let mut best: Option<(f64, usize)> = None;
    for s in (lo + STEP_MIN_SIDE).max(first_cut)..=hi - STEP_MIN_SIDE {
        if screen && surely_below(dets, s, lo, hi, sigma, threshold) {
            continue;
        }
        let Some((gain, outlier)) = gains(dets, s, lo, hi, sigma) else {
            continue;
        };
        let passes = |t: f64| gain > t && gain - outlier > 0.5 * t;
        let used = passes(threshold).then_some(threshold);
        // A path that turns is no step: the gain must hold against the
        // turning path's fit as well as against the quadratic's.
        let used = used.filter(|&t| {
            let a = s.saturating_sub(STEP_HALF_WINDOW).max(lo);
            let b = (s + STEP_HALF_WINDOW).min(hi);
            let w = &dets[a..b];
            let tau: Vec<f64> = w.iter().map(|d| d.0 as f64).collect();
            let xs: Vec<f64> = w.iter().map(|d| d.1).collect();
            let ys: Vec<f64> = w.iter().map(|d| d.2).collect();
            let turn = crate::track::turn::turn_rss_gain(&tau, &xs, &ys).unwrap_or(0.0);
            gain - turn / (sigma * sigma) > t
        });
        if let Some(t) = used {
            let score = gain / t;
            if best.is_none_or(|b| score > b.0) {
                best = Some((score, s));
            }
        }
    }
    if let Some((_, s)) = best {
        cuts.push(s);
        find_cuts(dets, lo, s, sigma, threshold, first_cut, screen, cuts);
        find_cuts(dets, s, hi, sigma, threshold, first_cut, screen, cuts);
    }
}

#[cfg(feature = "testkit")]
/// [`gains`] by refitting with each extra column (the reference).
/// Gains at detection `s` of `dets` (`(pulse, x, y)`, increasing pulses),
/// fitting the detections of `lo..hi` within `STEP_HALF_WINDOW` of it:
/// (drop of the residual sum of squares by a step at `s`, the larger drop
/// by a single outlier at `s − 1` or `s`), in units of σ².
fn gains_reference(
    dets: &[(i64, f64, f64)],
    s: usize,
    lo: usize,
    hi: usize,
    sigma: f64,
) -> Option<(f64, f64)> {
    let a = s.saturating_sub(STEP_HALF_WINDOW).max(lo);
    let b = (s + STEP_HALF_WINDOW).min(hi);
    let w = &dets[a..b];
    let t0 = dets[s].0;
    let n = w.len();
    let mut tau = [0.0; 2 * STEP_HALF_WINDOW];
    let mut xs = [0.0; 2 * STEP_HALF_WINDOW];
    let mut ys = [0.0; 2 * STEP_HALF_WINDOW];
    let mut step = [0.0; 2 * STEP_HALF_WINDOW];
    for (i, d) in w.iter().enumerate() {
        tau[i] = (d.0 - t0) as f64;
        xs[i] = d.1;
        ys[i] = d.2;
        step[i] = if a + i >= s { 1.0 } else { 0.0 };
    }
    let (tau, xs, ys) = (&tau[..n], &xs[..n], &ys[..n]);
    // A quadratic needs three detections per side to be told from a step.
    let order = 2;
    let base = rss(tau, xs, ys, order, None)?;
    let with_step = rss(tau, xs, ys, order, Some(&step[..n]))?;
    let mut outlier = 0.0f64;
    for j in [s - 1, s] {
        let mut e = [0.0; 2 * STEP_HALF_WINDOW];
        e[j - a] = 1.0;
        if let Some(r) = rss(tau, xs, ys, order, Some(&e[..n])) {
            outlier = outlier.max(base - r);
        }
    }
    let s2 = sigma * sigma;
    Some(((base - with_step) / s2, outlier / s2))
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;

    /// A curved track with a deterministic ±`noise` px wobble and a jump
    /// of `(jx, jy)` px from detection `at` on.
    fn track(n: usize, noise: f64, at: usize, jx: f64, jy: f64) -> Vec<(i64, f64, f64)> {
        (0..n)
            .map(|i| {
                let t = i as f64;
                let w = noise * [1.0, -0.5, -1.0, 0.5, 0.8, -0.8, 0.2][i % 7];
                let j = if i >= at { 1.0 } else { 0.0 };
                (
                    100 + i as i64,
                    50.0 + 6.0 * t + 0.05 * t * t + w + j * jx,
                    80.0 - 3.0 * t + 0.08 * t * t - w + j * jy,
                )
            })
            .collect()
    }

    #[ebptv_macros::unit_test]
    fn finds_a_jump_to_a_neighbour() {
        let t = track(20, 0.3, 11, 1.5, -1.2);
        assert_eq!(step_cuts(&t, 0.4, 12.0, 0), vec![11]);
        // Not before `first_cut`.
        assert!(step_cuts(&t, 0.4, 12.0, 12).is_empty());
        // Off.
        assert!(step_cuts(&t, 0.4, 0.0, 0).is_empty());
    }

    #[ebptv_macros::unit_test]
    fn smooth_tracks_and_single_outliers_are_not_cut() {
        assert!(step_cuts(&track(30, 0.3, 99, 0.0, 0.0), 0.4, 12.0, 0).is_empty());
        // An excursion: one image 2 px off, then back.
        let mut t = track(20, 0.3, 99, 0.0, 0.0);
        t[9].1 += 2.0;
        t[9].2 -= 1.0;
        assert!(step_cuts(&t, 0.4, 12.0, 0).is_empty());
    }

    /// The projection formulas against refitting with each extra column,
    /// on tracks with and without steps, outliers and missed pulses.
    #[ebptv_macros::unit_test]
    fn gains_match_the_refitting_reference() {
        let mut t = track(30, 0.3, 12, 1.7, -0.9);
        t[20].1 += 1.5;
        t.remove(7);
        t.remove(15);
        for lo in [0, 3] {
            for s in lo + STEP_MIN_SIDE..=t.len() - STEP_MIN_SIDE {
                let (g, o) = gains(&t, s, lo, t.len(), 0.4).unwrap();
                let (gr, or) = gains_reference(&t, s, lo, t.len(), 0.4).unwrap();
                assert!(
                    (g - gr).abs() <= 1e-6 * gr.abs().max(1.0),
                    "{s}: {g} vs {gr}"
                );
                assert!(
                    (o - or).abs() <= 1e-6 * or.abs().max(1.0),
                    "{s}: {o} vs {or}"
                );
            }
        }
    }

    /// The tabulated and cached paths against the direct one, bit for
    /// bit, at every candidate of random tracks (curved, noisy, with
    /// steps, missed pulses of 1–3 and now and then 60–89) and every
    /// piece bound `lo..hi` the recursive search can make; gap-free and
    /// gapped windows (and `None`s) must occur.
    #[ebptv_macros::unit_test]
    fn tabulated_gains_are_the_direct_ones_bit_for_bit() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(9);
        let (mut tabulated, mut direct, mut nones, mut compared) = (0, 0, 0, 0);
        let mut wide = 0;
        for k in 0..300 {
            let n = rng.gen_range(5..40);
            let mut pulse = rng.gen_range(-50i64..5000);
            let (ax, ay) = (rng.gen_range(-0.1..0.1), rng.gen_range(-0.1..0.1));
            let (ux, uy) = (rng.gen_range(-12.0..12.0), rng.gen_range(-12.0..12.0));
            let (x0, y0) = (rng.gen_range(0.0..1280.0), rng.gen_range(0.0..720.0));
            let mut t: Vec<(i64, f64, f64)> = Vec::with_capacity(n);
            for i in 0..n {
                // Every other track has missed pulses now and then.
                if k % 2 == 1 && rng.gen_bool(0.1) {
                    // Now and then a gap too long for a pattern key.
                    pulse += if rng.gen_bool(0.05) {
                        rng.gen_range(60..90)
                    } else {
                        rng.gen_range(1..4)
                    };
                }
                let tau = (pulse % 1000) as f64;
                let jump = if i > n / 2 { 1.5 } else { 0.0 };
                t.push((
                    pulse,
                    x0 + ux * tau + ax * tau * tau + rng.gen_range(-0.4..0.4) + jump,
                    y0 + uy * tau + ay * tau * tau + rng.gen_range(-0.4..0.4),
                ));
                pulse += 1;
            }
            for lo in 0..n.min(4) {
                for hi in (n.saturating_sub(3)..=n).filter(|&h| h > lo) {
                    for s in lo..hi {
                        let a = s.saturating_sub(STEP_HALF_WINDOW).max(lo);
                        let b = (s + STEP_HALF_WINDOW).min(hi);
                        if b - a > 4 && t[b - 1].0 - t[a].0 == (b - 1 - a) as i64 {
                            tabulated += 1;
                        } else {
                            direct += 1;
                            wide += (b - a > 4 && t[b - 1].0 - t[a].0 >= 64) as usize;
                        }
                        let fast = gains(&t, s, lo, hi, 0.4);
                        let reference = gains_direct(&t, s, lo, hi, 0.4);
                        let bits =
                            |g: Option<(f64, f64)>| g.map(|(x, y)| (x.to_bits(), y.to_bits()));
                        assert_eq!(bits(fast), bits(reference), "track {k}, {lo}..{hi}, s {s}");
                        nones += fast.is_none() as usize;
                        compared += 1;
                    }
                }
            }
        }
        assert!(
            tabulated > 10_000 && direct > 1_000 && wide > 10 && nones > 100,
            "{compared}: {tabulated} tabulated, {direct} gapped or short ({wide} \
             spanning ≥ 64 pulses), {nones} none"
        );
    }

    /// The screen never rules out a candidate whose exact gain exceeds
    /// the threshold: at every candidate of random tracks (with steps,
    /// gaps), thresholds just below, at and above the exact gain; and
    /// the screened search cuts exactly where the unscreened one does,
    /// also at thresholds that make many cuts.
    #[ebptv_macros::unit_test]
    fn screening_keeps_every_cut() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(13);
        let (mut screened, mut kept, mut cut_tracks) = (0, 0, 0);
        for k in 0..400 {
            let n = rng.gen_range(6..60);
            let mut pulse = rng.gen_range(0i64..5000);
            let (ux, uy) = (rng.gen_range(-12.0..12.0), rng.gen_range(-12.0..12.0));
            let (x0, y0) = (rng.gen_range(0.0..1280.0), rng.gen_range(0.0..720.0));
            let noise = [0.05, 0.3, 1.0][k % 3];
            let mut t: Vec<(i64, f64, f64)> = Vec::with_capacity(n);
            let (mut jx, mut jy) = (0.0, 0.0);
            for i in 0..n {
                if k % 2 == 1 && rng.gen_bool(0.1) {
                    pulse += rng.gen_range(1..4);
                }
                if rng.gen_bool(0.08) {
                    jx += rng.gen_range(-3.0..3.0);
                    jy += rng.gen_range(-3.0..3.0);
                }
                let tau = i as f64;
                t.push((
                    pulse,
                    x0 + ux * tau + 0.02 * tau * tau + rng.gen_range(-noise..noise) + jx,
                    y0 + uy * tau + rng.gen_range(-noise..noise) + jy,
                ));
                pulse += 1;
            }
            let sigma = 0.4;
            for s in STEP_MIN_SIDE..=n - STEP_MIN_SIDE {
                let Some((gain, _)) = gains(&t, s, 0, n, sigma) else {
                    continue;
                };
                let below = if gain > 0.0 {
                    f64::from_bits(gain.to_bits() - 1)
                } else {
                    0.0
                };
                for threshold in [below, gain * (1.0 - 1e-12), gain, gain * 1.01, 12.0] {
                    if !(threshold > 0.0) {
                        continue;
                    }
                    let out = surely_below(&t, s, 0, n, sigma, threshold);
                    assert!(
                        !(out && gain > threshold),
                        "track {k}, s {s}: gain {gain} > {threshold} screened out"
                    );
                    if out {
                        screened += 1;
                    } else {
                        kept += 1;
                    }
                }
            }
            for threshold in [2.0, 6.0, 12.0, 30.0] {
                let fast = step_cuts_with(&t, sigma, threshold, 1, true);
                assert_eq!(
                    fast,
                    step_cuts_with(&t, sigma, threshold, 1, false),
                    "track {k}"
                );
                cut_tracks += !fast.is_empty() as usize;
            }
        }
        assert!(
            screened > 5_000 && kept > 5_000 && cut_tracks > 200,
            "{screened} screened, {kept} kept, {cut_tracks} tracks cut"
        );
    }

    #[ebptv_macros::unit_test]
    fn two_steps_give_two_cuts() {
        let mut t = track(30, 0.2, 10, 2.0, 0.0);
        for d in &mut t[20..] {
            d.2 += 2.0;
        }
        assert_eq!(step_cuts(&t, 0.4, 12.0, 0), vec![10, 20]);
    }

    /// The normal-equation fit against a plain check: an exact quadratic
    /// has no residual, and a step column absorbs an exact step.
    #[ebptv_macros::unit_test]
    fn rss_is_exact_on_its_model() {
        let tau: Vec<f64> = (0..8).map(|i| i as f64 - 4.0).collect();
        let xs: Vec<f64> = tau.iter().map(|t| 1.0 + 2.0 * t - 0.3 * t * t).collect();
        let step: Vec<f64> = tau.iter().map(|&t| (t >= 0.0) as u8 as f64).collect();
        let ys: Vec<f64> = tau
            .iter()
            .zip(&step)
            .map(|(t, s)| 4.0 - t + 0.1 * t * t + 1.7 * s)
            .collect();
        assert!(rss(&tau, &xs, &xs, 2, None).unwrap() < 1e-18);
        assert!(rss(&tau, &xs, &ys, 2, None).unwrap() > 0.1);
        assert!(rss(&tau, &xs, &ys, 2, Some(&step)).unwrap() < 1e-18);
    }
}
