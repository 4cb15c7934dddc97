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
    let inv = invert::<P>(&ata)?;
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
    })
}

/// Inverse of the leading `p`×`p` block (Gauss–Jordan with pivoting).
fn invert<const P: usize>(m: &[[f64; 3]; 3]) -> Option<[[f64; 3]; 3]> {
    let p = P;
    let mut a = *m;
    let mut inv = [[0.0; 3]; 3];
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

    #[test]
    fn degenerate_inputs() {
        assert!(fit_eval(&[], &[], &[], 2, 0.0).is_none());
        let one = fit_eval(&[1.0], &[2.0], &[3.0], 2, 5.0).unwrap();
        assert_eq!((one.x, one.y, one.vx), (2.0, 3.0, 0.0));
        assert!(fit_eval(&[1.0, 1.0], &[2.0, 4.0], &[0.0, 0.0], 1, 1.0).is_none());
    }
}
