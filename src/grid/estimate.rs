//! From bin sums to statistics: top-hat / Gaussian means and in-bin fits.
//!
//! A top-hat bin of size b in a mean gradient dU/dy sees the samples'
//! spread of mean velocity as if it were turbulence: the variance grows by
//! about (dU/dy)²·b²/12. Fitting the mean velocity *inside* the bin by a
//! linear or quadratic polynomial of position (Agüera et al. 2016,
//! Godbersen & Schröder 2020) takes the resolved part of the spatial
//! variation out; the fit's constant term is the mean at the bin centre and
//! the residuals are the fluctuations. All of it follows from the power sums
//! of `super::accumulate`: solve `G a = Σ w φ u` on the p×p leading block
//! of the Gram matrix, and the residual sum of squares is
//! `Σ w u² − aᵀ Σ w φ u`.
//!
//! Bias of the variance: residuals of a p-parameter fit have `n − p` degrees
//! of freedom; with weights, `n` becomes the effective count
//! `n_eff = (Σw)²/Σw²`, so the denominator is `Σw·(1 − p/n_eff)`.
//! A bin with too few samples, or with samples too clustered in position
//! for the requested fit, falls back to a lower order (quadratic → linear →
//! mean); the order used is reported per bin.

use serde::{Deserialize, Serialize};

use super::accumulate::{gidx, BinAcc, GridAccumulator, NB};
use super::spec::GridSpec;
use crate::error::{Error, Result};

/// The in-bin model of the mean velocity.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Fit {
    /// Constant: the (weighted) bin mean.
    None,
    /// u = a0 + a1 ξ + a2 η.
    Linear,
    /// u = a0 + a1 ξ + a2 η + a3 ξ² + a4 ξη + a5 η².
    Quadratic,
}

impl Fit {
    /// Number of fit parameters: 1, 3 or 6.
    pub(crate) fn n_params(&self) -> usize {
        match self {
            Fit::None => 1,
            Fit::Linear => 3,
            Fit::Quadratic => 6,
        }
    }
    fn lower(&self) -> Option<Fit> {
        match self {
            Fit::Quadratic => Some(Fit::Linear),
            Fit::Linear => Some(Fit::None),
            Fit::None => None,
        }
    }
}

/// Options of the final estimate (none of them changes the accumulated sums,
/// so one accumulation can be evaluated several ways).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct EstimateOptions {
    /// The in-bin model of the mean velocity (falls back to a lower order
    /// in bins with too few or too clustered samples).
    pub fit: Fit,
    /// Bins with fewer samples are empty (NaN).
    pub min_count: u64,
    /// RMS of the velocity measurement noise (px/s) per component; its
    /// square is subtracted from uu and vv (clamped at 0). Zero: no correction.
    pub noise_rms: f64,
}

impl Default for EstimateOptions {
    fn default() -> Self {
        EstimateOptions {
            fit: Fit::None,
            min_count: 1,
            noise_rms: 0.0,
        }
    }
}

impl EstimateOptions {
    /// An error when `min_count` is 0 or `noise_rms` is negative or not finite.
    pub(crate) fn validate(&self) -> Result<()> {
        if self.min_count == 0 {
            return Err(Error::param("min-count", "must be at least 1"));
        }
        if !(self.noise_rms.is_finite() && self.noise_rms >= 0.0) {
            return Err(Error::param(
                "noise-rms",
                format!(
                    "must be a finite non-negative velocity (px/s), got {}",
                    self.noise_rms
                ),
            ));
        }
        Ok(())
    }
}

/// Statistics of one bin.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct BinStats {
    /// Number of samples in the bin.
    pub count: u64,
    /// Number of per-track clusters in the bin (distinct tracks when the
    /// input is grouped by track).
    pub n_tracks: u64,
    /// Mean velocity along x at the bin centre (px/s).
    pub u: f64,
    /// Mean velocity along y at the bin centre (px/s).
    pub v: f64,
    /// Reynolds normal stress ⟨u′u′⟩ ((px/s)²), noise-corrected if asked.
    pub uu: f64,
    /// Reynolds normal stress ⟨v′v′⟩ ((px/s)²), noise-corrected if asked.
    pub vv: f64,
    /// Reynolds shear stress ⟨u′v′⟩ ((px/s)²).
    pub uv: f64,
    /// Standard errors of u, v (cluster-robust, track = independent unit).
    pub se_u: f64,
    /// Standard error of v (px/s).
    pub se_v: f64,
    /// Standard errors of the stresses (Gaussian approximation with the
    /// number of tracks as the independent count).
    pub se_uu: f64,
    /// Standard error of vv ((px/s)²).
    pub se_vv: f64,
    /// Standard error of uv ((px/s)²).
    pub se_uv: f64,
    /// Mean velocity gradients from the fit (px/s per px; NaN without fit).
    pub dudx: f64,
    /// ∂u/∂y from the fit (px/s per px; NaN without fit).
    pub dudy: f64,
    /// ∂v/∂x from the fit (px/s per px; NaN without fit).
    pub dvdx: f64,
    /// ∂v/∂y from the fit (px/s per px; NaN without fit).
    pub dvdy: f64,
    /// Number of fit parameters actually used (1, 3, 6; 0 for an empty bin).
    pub fit_params: u8,
}

impl BinStats {
    fn empty(count: u64, n_tracks: u64) -> BinStats {
        let n = f64::NAN;
        BinStats {
            count,
            n_tracks,
            u: n,
            v: n,
            uu: n,
            vv: n,
            uv: n,
            se_u: n,
            se_v: n,
            se_uu: n,
            se_vv: n,
            se_uv: n,
            dudx: n,
            dudy: n,
            dvdx: n,
            dvdy: n,
            fit_params: 0,
        }
    }
}

/// The statistics of a whole grid, row-major (`ny` rows of `nx`, row 0 at
/// the smallest y).
#[derive(Debug, Clone)]
pub struct GridStats {
    /// The bins.
    pub spec: GridSpec,
    /// The options the statistics were estimated with.
    pub options: EstimateOptions,
    /// Bin centres along x (px), `nx` values.
    pub xs: Vec<f64>,
    /// Bin centres along y (px), `ny` values.
    pub ys: Vec<f64>,
    /// Statistics per bin, row-major (`iy·nx + ix`).
    pub bins: Vec<BinStats>,
}

impl GridStats {
    /// The statistics of bin `(ix, iy)`; panics outside the grid.
    pub(crate) fn at(&self, ix: usize, iy: usize) -> &BinStats {
        &self.bins[iy * self.spec.nx + ix]
    }
    /// Empties (NaN statistics, as a bin below `min_count`) every bin more
    /// than half of whose pixels are masked: a wall is no flow, not a flow
    /// at rest. Returns the number of bins emptied.
    pub(crate) fn apply_mask(&mut self, mask: &crate::calib::PixelMask) -> usize {
        let (hw, hh) = (self.spec.lattice.bin_w / 2.0, self.spec.lattice.bin_h / 2.0);
        let nx = self.spec.nx;
        let mut masked = 0;
        for (k, b) in self.bins.iter_mut().enumerate() {
            let (x, y) = (self.xs[k % nx], self.ys[k / nx]);
            if mask.masked_fraction(x - hw, x + hw, y - hh, y + hh) > 0.5 {
                *b = BinStats::empty(b.count, b.n_tracks);
                masked += 1;
            }
        }
        masked
    }
    /// One quantity as a row-major map.
    pub(crate) fn map(&self, f: impl Fn(&BinStats) -> f64) -> Vec<f64> {
        self.bins.iter().map(f).collect()
    }
    /// Index of the bin whose centre is nearest (x, y).
    pub(crate) fn nearest(&self, x: f64, y: f64) -> (usize, usize) {
        let near = |v: &[f64], t: f64| {
            v.iter()
                .enumerate()
                .min_by(|a, b| (a.1 - t).abs().total_cmp(&(b.1 - t).abs()))
                .map(|(i, _)| i)
                .unwrap_or(0)
        };
        (near(&self.xs, x), near(&self.ys, y))
    }
}

/// Solve the symmetric positive-definite p×p system `G a = b` by Cholesky;
/// `None` when G is (numerically) singular relative to its diagonal.
fn solve_spd(g: &[[f64; NB]; NB], b: &[f64], p: usize) -> Option<[f64; NB]> {
    let mut l = [[0.0f64; NB]; NB];
    for i in 0..p {
        for j in 0..=i {
            let mut s = g[i][j];
            for k in 0..j {
                s -= l[i][k] * l[j][k];
            }
            if i == j {
                // A pivot that lost all but 1e-9 of its diagonal means the
                // sample positions cannot resolve this basis function.
                if !(s > 1e-9 * g[i][i]) || g[i][i] <= 0.0 {
                    return None;
                }
                l[i][i] = s.sqrt();
            } else {
                l[i][j] = s / l[j][j];
            }
        }
    }
    let mut y = [0.0f64; NB];
    for i in 0..p {
        let mut s = b[i];
        for k in 0..i {
            s -= l[i][k] * y[k];
        }
        y[i] = s / l[i][i];
    }
    let mut x = [0.0f64; NB];
    for i in (0..p).rev() {
        let mut s = y[i];
        for k in i + 1..p {
            s -= l[k][i] * x[k];
        }
        x[i] = s / l[i][i];
    }
    Some(x)
}

/// Statistics of one bin.
pub(crate) fn estimate_bin(b: &BinAcc, spec: &GridSpec, opt: &EstimateOptions) -> BinStats {
    let n_tracks = b.n_tracks();
    if b.n < opt.min_count.max(1) {
        return BinStats::empty(b.n, n_tracks);
    }
    let mut g = [[0.0f64; NB]; NB];
    for (i, row) in g.iter_mut().enumerate() {
        for (j, e) in row.iter_mut().enumerate() {
            *e = b.gram[gidx(i, j)].value();
        }
    }
    let pu: Vec<f64> = b.pu.iter().map(|k| k.value()).collect();
    let pv: Vec<f64> = b.pv.iter().map(|k| k.value()).collect();
    let w = g[0][0];
    let w2 = b.w2.value();
    let n_eff = w * w / w2;

    let mut fit = opt.fit;
    let (p, au, av) = loop {
        let p = fit.n_params();
        // Need more samples than parameters to have residuals at all, and a
        // solvable system; otherwise drop to a lower order.
        if (b.n as usize) > p && n_eff > p as f64 {
            if let (Some(au), Some(av)) = (solve_spd(&g, &pu, p), solve_spd(&g, &pv, p)) {
                break (p, au, av);
            }
        }
        match fit.lower() {
            Some(f) => fit = f,
            None => {
                // A single sample (or all weight on one): mean only.
                let mut au = [0.0; NB];
                let mut av = [0.0; NB];
                au[0] = pu[0] / w;
                av[0] = pv[0] / w;
                break (1, au, av);
            }
        }
    };

    let dot = |a: &[f64; NB], m: &[f64]| (0..p).map(|k| a[k] * m[k]).sum::<f64>();
    let dof = w * (1.0 - p as f64 / n_eff);
    let (mut uu, mut vv, uv) = if dof > 0.0 {
        (
            (b.uu.value() - dot(&au, &pu)).max(0.0) / dof,
            (b.vv.value() - dot(&av, &pv)).max(0.0) / dof,
            // Symmetrised: at the exact solution both forms are equal.
            (b.uv.value() - 0.5 * (dot(&au, &pv) + dot(&av, &pu))) / dof,
        )
    } else {
        (f64::NAN, f64::NAN, f64::NAN)
    };
    let s2 = opt.noise_rms * opt.noise_rms;
    uu = (uu - s2).max(0.0);
    vv = (vv - s2).max(0.0);

    // Cluster-robust variance of the weighted mean about the weighted mean
    // (for fits this slightly overestimates: the gradient's share of the
    // between-track spread is included).
    let c = b.all_clusters();
    let gk = c.n as f64;
    let se = |s: f64, ws: f64, ss: f64| {
        if c.n < 2 {
            return f64::NAN;
        }
        let mu = s / w;
        let var =
            (ss - 2.0 * mu * ws + mu * mu * c.ww.value()).max(0.0) / (w * w) * gk / (gk - 1.0);
        var.sqrt()
    };
    let se_u = se(pu[0], c.wsu.value(), c.susu.value());
    let se_v = se(pv[0], c.wsv.value(), c.svsv.value());
    let nt = n_tracks as f64;
    let (se_uu, se_vv, se_uv) = if n_tracks >= 2 {
        (
            uu * (2.0 / nt).sqrt(),
            vv * (2.0 / nt).sqrt(),
            ((uu * vv + uv * uv) / nt).sqrt(),
        )
    } else {
        (f64::NAN, f64::NAN, f64::NAN)
    };
    let lat = &spec.lattice;
    let (dudx, dudy, dvdx, dvdy) = if p >= 3 {
        (
            au[1] / lat.bin_w,
            au[2] / lat.bin_h,
            av[1] / lat.bin_w,
            av[2] / lat.bin_h,
        )
    } else {
        (f64::NAN, f64::NAN, f64::NAN, f64::NAN)
    };
    BinStats {
        count: b.n,
        n_tracks,
        u: au[0],
        v: av[0],
        uu,
        vv,
        uv,
        se_u,
        se_v,
        se_uu,
        se_vv,
        se_uv,
        dudx,
        dudy,
        dvdx,
        dvdy,
        fit_params: p as u8,
    }
}

/// Statistics of every bin.
pub fn estimate(acc: &GridAccumulator, opt: &EstimateOptions) -> Result<GridStats> {
    opt.validate()?;
    let bins = acc
        .bins
        .iter()
        .map(|b| estimate_bin(b, &acc.spec, opt))
        .collect();
    Ok(GridStats {
        spec: acc.spec,
        options: *opt,
        xs: acc.spec.xs(),
        ys: acc.spec.ys(),
        bins,
    })
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;

    #[ebptv_macros::unit_test]
    fn cholesky_solves_a_known_system() {
        let mut g = [[0.0; NB]; NB];
        let m = [[4.0, 1.0, 0.5], [1.0, 3.0, 0.2], [0.5, 0.2, 2.0]];
        for i in 0..3 {
            for j in 0..3 {
                g[i][j] = m[i][j];
            }
        }
        let x_true = [1.0, -2.0, 0.5];
        let b: Vec<f64> = (0..3)
            .map(|i| (0..3).map(|j| m[i][j] * x_true[j]).sum())
            .collect();
        let x = solve_spd(&g, &b, 3).unwrap();
        for i in 0..3 {
            assert!((x[i] - x_true[i]).abs() < 1e-12);
        }
        let mut sing = g;
        sing[1] = sing[0];
        for r in sing.iter_mut() {
            r[1] = r[0];
        }
        assert!(solve_spd(&sing, &b, 3).is_none());
    }
}
