//! Steps in a track: where one track's detections jump from one particle
//! to a close neighbour and stay there (a *swap*), found in hindsight.
//!
//! # Why
//! On the paper-like synthetic scene (384², session 8, `tests/ptv_swaps.rs`)
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
//! again. Cost: a few 4 × 4 normal-equation solves per detection of an
//! ended track.

/// Most detections on each side of a candidate step that its fits use
/// (paper-like scene, threshold 12: 4 / 5 / 6 / 8 / 10 give precision
/// 0.9639 / 0.9646 / 0.9652 / 0.9659 / 0.9660 at recall 0.9526 / 0.9526 /
/// 0.9523 / 0.9484 / 0.9402: wider windows see smaller steps but take
/// the flow's curvature for steps).
pub const STEP_HALF_WINDOW: usize = 6;

/// Fewest detections on each side of a step.
pub const STEP_MIN_SIDE: usize = 3;

#[cfg(test)]
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
/// by a single outlier at `s − 1` or `s`), in units of σ². One quadratic
/// fit per axis; the drops follow from its residuals r and hat matrix H
/// (adding a column e lowers the RSS by (e·r)² / e·(I − H)e), which is
/// what [`gains_reference`] gets by refitting.
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
    let s2 = sigma * sigma;
    Some(((erx * erx + ery * ery) / qe / s2, outlier / s2))
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
pub fn step_cuts(
    dets: &[(i64, f64, f64)],
    sigma: f64,
    threshold: f64,
    first_cut: usize,
) -> Vec<usize> {
    let mut cuts = Vec::new();
    if threshold > 0.0 && sigma > 0.0 {
        find_cuts(dets, 0, dets.len(), sigma, threshold, first_cut, &mut cuts);
    }
    cuts.sort_unstable();
    cuts
}

fn find_cuts(
    dets: &[(i64, f64, f64)],
    lo: usize,
    hi: usize,
    sigma: f64,
    threshold: f64,
    first_cut: usize,
    cuts: &mut Vec<usize>,
) {
    if hi - lo < 2 * STEP_MIN_SIDE {
        return;
    }
    let mut best: Option<(f64, usize)> = None;
    for s in (lo + STEP_MIN_SIDE).max(first_cut)..=hi - STEP_MIN_SIDE {
        let Some((gain, outlier)) = gains(dets, s, lo, hi, sigma) else {
            continue;
        };
        if gain > threshold && gain - outlier > 0.5 * threshold && best.is_none_or(|b| gain > b.0) {
            best = Some((gain, s));
        }
    }
    if let Some((_, s)) = best {
        cuts.push(s);
        find_cuts(dets, lo, s, sigma, threshold, first_cut, cuts);
        find_cuts(dets, s, hi, sigma, threshold, first_cut, cuts);
    }
}

#[cfg(test)]
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

#[cfg(test)]
mod tests {
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

    #[test]
    fn finds_a_jump_to_a_neighbour() {
        let t = track(20, 0.3, 11, 1.5, -1.2);
        assert_eq!(step_cuts(&t, 0.4, 12.0, 0), vec![11]);
        // Not before `first_cut`.
        assert!(step_cuts(&t, 0.4, 12.0, 12).is_empty());
        // Off.
        assert!(step_cuts(&t, 0.4, 0.0, 0).is_empty());
    }

    #[test]
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
    #[test]
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

    #[test]
    fn two_steps_give_two_cuts() {
        let mut t = track(30, 0.2, 10, 2.0, 0.0);
        for d in &mut t[20..] {
            d.2 += 2.0;
        }
        assert_eq!(step_cuts(&t, 0.4, 12.0, 0), vec![10, 20]);
    }

    /// The normal-equation fit against a plain check: an exact quadratic
    /// has no residual, and a step column absorbs an exact step.
    #[test]
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
