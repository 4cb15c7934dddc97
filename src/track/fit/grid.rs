//! The integer-grid fast path of the adaptive fit: for tracks with regular
//! pulse times the candidate windows' moments, solves and pilot rows are
//! tabulated once ([`GridTables`]) and [`fit_adaptive_grid`] evaluates a
//! sample from the tables.

use super::*;

/// One candidate window on the integer grid: what [`fit_adaptive`]
/// derives from the window's time moments alone, tabulated.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct GridWindow {
    /// The moments give a fit at all (never false for distinct τ).
    pub(super) ok: bool,
    /// Velocity variance factor `(XᵀX)⁻¹₁₁` and cubic bias factor.
    pub(super) variance: f64,
    pub(super) bias: f64,
    /// Coefficients of the fit (`p = order + 1`, lowered to what the
    /// window allows) and the inverse normal matrix.
    pub(super) p: usize,
    pub(super) inv: [[f64; 3]; 3],
    /// `(XᵀX)⁻¹Xᵀs³`: the regression of the cubic on the basis (`bias`
    /// is its velocity entry), for the bias under the curvature prior.
    pub(super) cubic_regression: [f64; 3],
}

impl GridWindow {
    /// The inverse normal matrix with the curvature prior's `ridge` on
    /// the quadratic coefficient (Sherman–Morrison on the tabulated
    /// inverse: `(A + ρe₂e₂ᵀ)⁻¹ = A⁻¹ − k·A⁻¹e₂e₂ᵀA⁻¹`, `k = ρ/(1 +
    /// ρA⁻¹₂₂)`), and `k` (0 without a prior or below order 2).
    #[inline]
    pub(super) fn inverse_with_prior(&self, ridge: f64) -> ([[f64; 3]; 3], f64) {
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
    pub(super) fn variance_and_bias(&self, ridge: f64) -> (f64, f64) {
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
/// data: they are computed once here (with the reference's own `Sums`
/// arithmetic on the exact integer moments) and a sample costs the
/// pilot's cubic dot products and the chosen window's moments.
/// [`fit_adaptive_grid`] is the fast path; [`fit_adaptive`] the reference
/// and the path for windows with gaps or irregular times.
#[derive(Debug, Clone)]
#[ebptv_macros::testkit]
pub(crate) struct GridTables {
    pub(super) min_window: usize,
    pub(super) max_window: usize,
    pub(super) order: usize,
    /// Candidate windows, `w` in 1..=max_window, offset `o = start −
    /// centre` in −(w−1)..=0, at `w(w−1)/2 + (o + w − 1)`.
    pub(super) windows: Vec<GridWindow>,
    /// Pilot windows, `w` in 1..=2·max_window+1: start of the cubic
    /// filter in `cubic_weights` (length `w`; the quadratic coefficient's
    /// filter at the same place in `quadratic_weights`), and the two
    /// variance factors (cubic, quadratic); `None` where [`Sums::cubic`]
    /// gives none.
    pub(super) cubic: Vec<Option<(usize, f64, f64)>>,
    pub(super) cubic_weights: Vec<f64>,
    pub(super) quadratic_weights: Vec<f64>,
    /// Whether the centred candidates (every window centred on its
    /// sample, windows `min_window, min_window + 2, …, max_window`) have a
    /// unimodal criterion for any cubic coefficient (see
    /// [`GridTables::centred_unimodal`]): then the search runs down from
    /// the largest window and stops at the first rise.
    pub(super) centred_unimodal: bool,
    /// The full-length pilot (window `2·max_window + 1`) with the sample
    /// at index i of it: rows 3 and 2 of its cubic fit's inverse normal
    /// matrix (the cubic and quadratic coefficients are these rows times
    /// the window's moments `Σ sᵃ·x`, a = 0..=3, s the offset from the
    /// sample) and their variance factors, at i; empty where a cubic fit
    /// of that window has none. [`GridRunFit`] takes the coefficients
    /// from running moments.
    pub(super) pilot_rows: Vec<PilotRows>,
}

/// See [`GridTables::pilot_rows`].
#[derive(Debug, Clone, Copy)]
pub(super) struct PilotRows {
    pub(super) cubic_row: [f64; 4],
    pub(super) quadratic_row: [f64; 4],
    pub(super) cubic_var: f64,
    pub(super) quadratic_var: f64,
}

#[inline]
pub(super) fn grid_index(w: usize, offset: isize) -> usize {
    w * (w - 1) / 2 + (offset + w as isize - 1) as usize
}

impl GridTables {
    /// Tables for the window shape of `rule` (its σ and bias weight are
    /// applied per sample, so they do not enter).
    #[ebptv_macros::testkit]
    pub(crate) fn new(rule: &WindowRule) -> Self {
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
    pub(super) fn centred_unimodal(&self) -> bool {
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
    pub(crate) fn serves(&self, rule: &WindowRule) -> bool {
        let max_window = rule.max_window.max(1);
        self.max_window == max_window
            && self.min_window == rule.min_window.clamp(1, max_window)
            && self.order == rule.order
    }

    /// Shared tables for `rule`'s shape, built once per process.
    pub(crate) fn cached(rule: &WindowRule) -> std::sync::Arc<GridTables> {
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
    pub(super) fn window(&self, w: usize, start: usize, centre: usize) -> &GridWindow {
        &self.windows[grid_index(w, start as isize - centre as isize)]
    }
}

/// [`fit_adaptive`] for samples on the integer τ grid: the points `xy`
/// (x, y) of `adaptive_span``(xy.len(), centre, rule)` are at τ = index
/// (their pulses consecutive, their times regular) and the evaluation is
/// at sample `centre`. The caller checks that; the result then equals
/// [`fit_adaptive`]'s up to rounding (tested), the same window chosen
/// unless two candidates' criteria agree to rounding. `tables` must
/// `GridTables::serves` `rule` (else the reference is used). Points are
/// interleaved so that x and y go through the sums side by side (the
/// compiler pairs them in one vector register).
#[ebptv_macros::testkit]
pub(crate) fn fit_adaptive_grid(
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
        && (wmax - wmin).div_ceil(2) < MAX_CANDIDATES
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
            if best.is_none_or(|b| crit.total_cmp(&b.0).is_le()) {
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
pub(super) fn grid_solve(
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
pub(super) fn grid_solve_inv(
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
