//! The searches that fit a candidate effect's parameters in the unit cube:
//! golden-section minimisation in one dimension ([`minimise_1d_in`]),
//! and the Nelder–Mead simplex ([`nelder_mead`]) for several parameters;
//! [`FitMemo`] evaluates a fit's objective once per parameter point.

use super::*;

/// Minimise `f` on `[lo, hi]` ⊂ [0, 1]: a grid, then golden-section
/// search in the bracket around the best grid point. Returns (argmin, min,
/// evaluations).
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

/// Half width (unit-cube coordinates) of the second-stage search.
pub(super) const REFINE_HALF_WIDTH: f64 = 0.15;

/// The objective of one candidate fit, evaluated once per parameter point.
///
/// A fit uses common random numbers (one seed for every point), so its
/// objective is a function of the parameter values alone, and the searches
/// come back to points they have seen (a bound a step clamps to, the best
/// grid point that starts the simplex, a vertex kept from one step to the
/// next): such a point is simulated once. Points are keyed by the effect's
/// parameter values (bit patterns), as the simulator receives them.
#[derive(Debug, Default)]
pub(crate) struct FitMemo {
    seen: HashMap<Vec<u64>, f64>,
}

impl FitMemo {
    /// The objective at `candidate`: from the memo, or `eval(candidate)`
    /// the first time.
    pub(crate) fn value(
        &mut self,
        candidate: EffectSetting,
        eval: impl FnOnce(EffectSetting) -> Result<f64>,
    ) -> Result<f64> {
        let key: Vec<u64> = candidate.parameters.values().map(|v| v.to_bits()).collect();
        if let Some(&v) = self.seen.get(&key) {
            return Ok(v);
        }
        let v = eval(candidate)?;
        self.seen.insert(key, v);
        Ok(v)
    }
}
