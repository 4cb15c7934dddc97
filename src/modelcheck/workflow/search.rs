//! The searches that fit a candidate effect's parameters in the unit cube:
//! golden-section minimisation in one dimension ([`minimise_1d`]),
//! Nelder–Mead simplex ([`nelder_mead`]), and the profile searches that seed
//! the simplex of two-parameter effects (a coarse grid over the first
//! parameter with a 1-D fit of the second at each point).

use super::*;

/// Minimise `f` on [0, 1]: a grid, then golden-section search in the
/// bracket around the best grid point. Returns (argmin, min, evaluations).
pub(crate) fn minimise_1d(
    f: &mut dyn FnMut(f64) -> Result<f64>,
    max_evals: usize,
) -> Result<(f64, f64, usize)> {
    minimise_1d_in(f, 0.0, 1.0, max_evals)
}

/// [`minimise_1d`] on `[lo, hi]` ⊂ [0, 1].
pub(crate) fn minimise_1d_in(
    f: &mut dyn FnMut(f64) -> Result<f64>,
    lo: f64,
    hi: f64,
    max_evals: usize,
) -> Result<(f64, f64, usize)> {
    let (lo, hi) = (lo.clamp(0.0, 1.0), hi.clamp(0.0, 1.0));
    let grid = 9usize.min(max_evals.max(3));
    let mut evals = 0;
    let mut best = (lo, f64::INFINITY);
    let mut values = Vec::with_capacity(grid);
    for k in 0..grid {
        let u = lo + (hi - lo) * k as f64 / (grid - 1) as f64;
        let v = f(u)?;
        evals += 1;
        values.push(v);
        if v < best.1 {
            best = (u, v);
        }
    }
    let h = (hi - lo) / (grid - 1) as f64;
    let (mut a, mut b) = ((best.0 - h).max(lo), (best.0 + h).min(hi));
    let g = (5f64.sqrt() - 1.0) / 2.0;
    let mut c = b - g * (b - a);
    let mut d = a + g * (b - a);
    let (mut fc, mut fd) = (f(c)?, f(d)?);
    evals += 2;
    while evals < max_evals {
        if fc < fd {
            b = d;
            d = c;
            fd = fc;
            c = b - g * (b - a);
            fc = f(c)?;
        } else {
            a = c;
            c = d;
            fc = fd;
            d = a + g * (b - a);
            fd = f(d)?;
        }
        evals += 1;
    }
    for (u, v) in [(c, fc), (d, fd)] {
        if v < best.1 {
            best = (u, v);
        }
    }
    Ok((best.0, best.1, evals))
}

/// Nelder–Mead in the unit cube (points clamped). Returns (argmin, min,
/// evaluations).
pub(crate) fn nelder_mead(
    f: &mut dyn FnMut(&[f64]) -> Result<f64>,
    start: &[f64],
    step: f64,
    max_evals: usize,
) -> Result<(Vec<f64>, f64, usize)> {
    let n = start.len();
    let clamp = |v: Vec<f64>| v.into_iter().map(|x| x.clamp(0.0, 1.0)).collect::<Vec<_>>();
    let mut simplex: Vec<(Vec<f64>, f64)> = Vec::with_capacity(n + 1);
    let mut evals = 0;
    let x0 = clamp(start.to_vec());
    simplex.push((x0.clone(), f(&x0)?));
    evals += 1;
    for i in 0..n {
        let mut x = x0.clone();
        x[i] = if x[i] + step <= 1.0 {
            x[i] + step
        } else {
            x[i] - step
        };
        let x = clamp(x);
        let v = f(&x)?;
        evals += 1;
        simplex.push((x, v));
    }
    while evals < max_evals {
        simplex.sort_by(|a, b| a.1.total_cmp(&b.1));
        let centroid: Vec<f64> = (0..n)
            .map(|j| simplex[..n].iter().map(|p| p.0[j]).sum::<f64>() / n as f64)
            .collect();
        let worst = simplex[n].clone();
        let along = |t: f64| {
            clamp(
                (0..n)
                    .map(|j| centroid[j] + t * (worst.0[j] - centroid[j]))
                    .collect(),
            )
        };
        let xr = along(-1.0);
        let fr = f(&xr)?;
        evals += 1;
        if fr < simplex[0].1 {
            let xe = along(-2.0);
            let fe = f(&xe)?;
            evals += 1;
            simplex[n] = if fe < fr { (xe, fe) } else { (xr, fr) };
        } else if fr < simplex[n - 1].1 {
            simplex[n] = (xr, fr);
        } else {
            let xc = if fr < worst.1 {
                along(-0.5)
            } else {
                along(0.5)
            };
            let fc = f(&xc)?;
            evals += 1;
            if fc < worst.1.min(fr) {
                simplex[n] = (xc, fc);
            } else {
                // Shrink towards the best point.
                let best = simplex[0].0.clone();
                for p in simplex.iter_mut().skip(1) {
                    let x = clamp((0..n).map(|j| best[j] + 0.5 * (p.0[j] - best[j])).collect());
                    p.1 = f(&x)?;
                    p.0 = x;
                    evals += 1;
                }
            }
        }
    }
    simplex.sort_by(|a, b| a.1.total_cmp(&b.1));
    let (x, v) = simplex.swap_remove(0);
    Ok((x, v, evals))
}

/// Outer grid of [`profile_then_simplex`]: values of the first parameter
/// (cell centres of the unit interval).
pub(super) const PROFILE_OUTER: [f64; 4] = [0.125, 0.375, 0.625, 0.875];

/// First-stage search for two parameters: the profile of the objective
/// along the first (for each of [`PROFILE_OUTER`], the second parameter
/// fitted by [`minimise_1d`]), then Nelder–Mead from the best profile point.
///
/// Why not Nelder–Mead from the centre: two parameters of one effect often
/// trade off along a narrow curved valley (the arbiter's row and event time
/// both lengthen the readout of a burst: only row·groups + event·events is
/// pinned sharply, the split between them only weakly). A simplex started
/// far from the valley falls into it wherever it first meets it and then
/// shrinks there, 5× off along the valley. The profile meets the valley at
/// every outer value and compares the objective *along* it.
pub(super) fn profile_then_simplex(
    objective: &mut dyn FnMut(&[f64]) -> Result<f64>,
    max_evaluations: usize,
) -> Result<(Vec<f64>, f64, usize)> {
    // Budget: about 4.5 × max_evaluations + 8 (each inner search needs
    // enough points to land in the valley: it is often narrow, 15 % of a
    // range spanning decades).
    let inner = max_evaluations.max(5);
    let mut evals = 0;
    let mut best = (vec![0.5, 0.5], f64::INFINITY);
    for &a in &PROFILE_OUTER {
        let (b, v, e) = minimise_1d(&mut |b| objective(&[a, b]), inner)?;
        evals += e;
        if v < best.1 {
            best = (vec![a, b], v);
        }
    }
    let rest = (max_evaluations / 2).max(6);
    let (x, v, e) = nelder_mead(objective, &best.0, 0.5 / PROFILE_OUTER.len() as f64, rest)?;
    evals += e;
    Ok(if v <= best.1 {
        (x, v, evals)
    } else {
        (best.0, best.1, evals)
    })
}

/// Outer offsets (unit-cube coordinates of the first parameter) of
/// [`local_profile_then_simplex`] around the stage-1 value.
pub(super) const LOCAL_PROFILE_OUTER: [f64; 3] = [-0.15, 0.0, 0.15];

/// Half width of the inner search of [`local_profile_then_simplex`] around
/// the stage-1 value of the second parameter.
pub(super) const LOCAL_PROFILE_INNER_HALF_WIDTH: f64 = 0.25;

/// Second-stage search for two parameters (with `profile_fit`): the
/// profile along the first parameter at the stage-1 value and
/// ± [`LOCAL_PROFILE_OUTER`], the second fitted by [`minimise_1d_in`] in a
/// window around its stage-1 value, then Nelder–Mead from the best
/// profile point.
///
/// Why: the stage-1 weights can leave a valley flat (intensity latency:
/// exponent and reference trade off, τ ∝ reference^exponent, and the
/// stage-1 objective is 246 at exponent 0.31 vs 253 at the true 0.55),
/// so stage 1 stops anywhere along it. The stage-2 weights tilt the
/// valley towards the truth (104.6 vs 110.2), but a simplex started on the
/// valley's floor with a step across it shrinks before it has walked
/// along it. Stepping the first parameter and re-finding the valley's
/// floor in the second at each step walks along it by construction. Local
/// (not over the whole box), so a stage-1 fit already in the right basin
/// stays there.
pub(super) fn local_profile_then_simplex(
    objective: &mut dyn FnMut(&[f64]) -> Result<f64>,
    u0: &[f64],
    max_evaluations: usize,
) -> Result<(Vec<f64>, f64, usize)> {
    let inner = (2 * max_evaluations / 3).max(5);
    let mut evals = 0;
    let mut best = (u0.to_vec(), f64::INFINITY);
    let mut outer: Vec<f64> = LOCAL_PROFILE_OUTER
        .iter()
        .map(|d| (u0[0] + d).clamp(0.0, 1.0))
        .collect();
    outer.dedup_by(|a, b| (*a - *b).abs() < 1e-9);
    for a in outer {
        let (b, v, e) = minimise_1d_in(
            &mut |b| objective(&[a, b]),
            u0[1] - LOCAL_PROFILE_INNER_HALF_WIDTH,
            u0[1] + LOCAL_PROFILE_INNER_HALF_WIDTH,
            inner,
        )?;
        evals += e;
        if v < best.1 {
            best = (vec![a, b], v);
        }
    }
    // The profile's outer steps are coarse (a factor 2.5 on a parameter
    // spanning decades); the simplex walks the rest of the way along the
    // valley, with the budget the plain second stage had.
    let (x, v, e) = nelder_mead(
        objective,
        &best.0,
        0.5 * LOCAL_PROFILE_OUTER[2],
        2 * max_evaluations,
    )?;
    evals += e;
    Ok(if v <= best.1 {
        (x, v, evals)
    } else {
        (best.0, best.1, evals)
    })
}

/// Initial simplex step of the second-stage search for several
/// parameters: wide enough to move along a valley the first stage's
/// weights left flat (intensity latency: exponent and reference trade off,
/// and only the second stage's weights tell them apart).
pub(super) const REFINE_SIMPLEX_STEP: f64 = 0.25;

/// Half width (unit-cube coordinates) of the second-stage search.
pub(super) const REFINE_HALF_WIDTH: f64 = 0.15;
