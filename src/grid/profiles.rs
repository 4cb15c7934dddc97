//! Profiles and walls: a profile at x, the wall, wall shear, inner units.
//!
//! Near a wall the mean velocity is linear in the viscous sublayer,
//! U = (dU/dy)_w · (y − y_w), so a straight line through the few valid
//! points nearest the wall gives the wall gradient and, where the wall is
//! not given, the wall position as the zero crossing. The wall shear stress
//! is τ_w = ρν (dU/dy)_w, the friction velocity u_τ = √(ν |dU/dy|_w) and the
//! viscous length δ_ν = ν/u_τ; velocities in px/s and lengths in px convert
//! with the image scale (px/mm). (dU/dy in px/s per px is already 1/s.)
//! Use thin bins (`--bin 64 --bin-h 4`) to resolve the sublayer.

use serde::{Deserialize, Serialize};

use super::estimate::GridStats;
use crate::error::{Error, Result};

/// One point of a profile (a column of bins).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub(crate) struct ProfilePoint {
    /// Bin centre y (px).
    pub y: f64,
    /// Number of samples in the bin.
    pub count: u64,
    /// Mean velocity along x (px/s).
    pub u: f64,
    /// Mean velocity along y (px/s).
    pub v: f64,
    /// Reynolds normal stress ⟨u′u′⟩ ((px/s)²).
    pub uu: f64,
    /// Reynolds normal stress ⟨v′v′⟩ ((px/s)²).
    pub vv: f64,
    /// Reynolds shear stress ⟨u′v′⟩ ((px/s)²).
    pub uv: f64,
}

/// The column of bins nearest `x`, and its x.
pub(crate) fn profile_at_x(g: &GridStats, x: f64) -> (f64, Vec<ProfilePoint>) {
    let (ix, _) = g.nearest(x, g.ys[0]);
    let pts = (0..g.spec.ny)
        .map(|iy| {
            let b = g.at(ix, iy);
            ProfilePoint {
                y: g.ys[iy],
                count: b.count,
                u: b.u,
                v: b.v,
                uu: b.uu,
                vv: b.vv,
                uv: b.uv,
            }
        })
        .collect();
    (g.xs[ix], pts)
}

/// Which end of the profile the wall is at.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum WallSide {
    /// Smallest y (top of the image).
    Top,
    /// Largest y (bottom of the image).
    Bottom,
}

/// How [`wall_fit`] finds the wall and converts to physical units.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub(crate) struct WallOptions {
    /// Which end of the profile the wall is at.
    pub side: WallSide,
    /// Known wall position (px); `None`: the zero crossing of the fit.
    pub wall_y: Option<f64>,
    /// Number of valid points nearest the wall in the linear fit (≥ 2).
    pub n_fit: usize,
    /// Kinematic viscosity (m²/s), e.g. 1.0e-6 for water at 20 °C.
    pub nu_m2_s: f64,
    /// Image scale (px/mm).
    pub px_per_mm: f64,
}

/// The wall and its shear, from [`wall_fit`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub(crate) struct WallFit {
    /// Wall position y (px): the given one or the fit's zero crossing.
    pub wall_y_px: f64,
    /// True when the wall position was estimated (not given).
    pub wall_estimated: bool,
    /// Mean-velocity gradient at the wall (1/s), sign as measured.
    pub dudy_per_s: f64,
    /// Wall shear stress over density τ_w/ρ = ν dU/dy (m²/s²).
    pub tau_w_over_rho: f64,
    /// Friction velocity u_τ = √(ν |dU/dy|_w) (m/s).
    pub u_tau_m_s: f64,
    /// Viscous length ν/u_τ in px.
    pub viscous_length_px: f64,
    /// Number of profile points in the linear fit.
    pub points_used: usize,
}

impl WallFit {
    /// Inner-scaled coordinates of a profile point: (y⁺, u⁺, u'u'⁺).
    pub(crate) fn inner(&self, p: &ProfilePoint, px_per_mm: f64) -> (f64, f64, f64) {
        let to_ms = 1.0 / (px_per_mm * 1000.0);
        let y_plus = (p.y - self.wall_y_px).abs() / self.viscous_length_px;
        let u_plus = p.u * to_ms / self.u_tau_m_s;
        let uu_plus = p.uu * to_ms * to_ms / (self.u_tau_m_s * self.u_tau_m_s);
        (y_plus, u_plus, uu_plus)
    }
}

/// Wall position and shear from the near-wall points of a profile.
pub(crate) fn wall_fit(profile: &[ProfilePoint], opt: &WallOptions) -> Result<WallFit> {
    if !(opt.nu_m2_s.is_finite() && opt.nu_m2_s > 0.0) {
        return Err(Error::param(
            "nu",
            format!("kinematic viscosity must be > 0 m²/s, got {}", opt.nu_m2_s),
        ));
    }
    if !(opt.px_per_mm.is_finite() && opt.px_per_mm > 0.0) {
        return Err(Error::param(
            "px-per-mm",
            format!("scale must be > 0 px/mm, got {}", opt.px_per_mm),
        ));
    }
    if opt.n_fit < 2 {
        return Err(Error::param(
            "wall-points",
            "need at least 2 points for the wall gradient",
        ));
    }
    let mut pts: Vec<&ProfilePoint> = profile.iter().filter(|p| p.u.is_finite()).collect();
    if let Some(w) = opt.wall_y {
        // Only points on the flow side of a known wall.
        pts.retain(|p| match opt.side {
            WallSide::Top => p.y > w,
            WallSide::Bottom => p.y < w,
        });
    }
    match opt.side {
        WallSide::Top => pts.sort_by(|a, b| a.y.total_cmp(&b.y)),
        WallSide::Bottom => pts.sort_by(|a, b| b.y.total_cmp(&a.y)),
    }
    pts.truncate(opt.n_fit);
    if pts.len() < 2 {
        return Err(Error::analysis(format!(
            "wall fit: only {} valid profile points near the wall",
            pts.len()
        )));
    }
    let (wall_y, slope) = match opt.wall_y {
        Some(yw) => {
            // Line through (y_w, 0).
            let (mut num, mut den) = (0.0, 0.0);
            for p in &pts {
                num += p.u * (p.y - yw);
                den += (p.y - yw) * (p.y - yw);
            }
            (yw, num / den)
        }
        None => {
            let n = pts.len() as f64;
            let my = pts.iter().map(|p| p.y).sum::<f64>() / n;
            let mu = pts.iter().map(|p| p.u).sum::<f64>() / n;
            let sxy: f64 = pts.iter().map(|p| (p.y - my) * (p.u - mu)).sum();
            let sxx: f64 = pts.iter().map(|p| (p.y - my) * (p.y - my)).sum();
            let b = sxy / sxx;
            if !(b.is_finite() && b != 0.0) {
                return Err(Error::analysis(
                    "wall fit: near-wall velocity has no gradient; cannot locate the wall",
                ));
            }
            (my - mu / b, b)
        }
    };
    if !slope.is_finite() || slope == 0.0 {
        return Err(Error::analysis("wall fit: zero or undefined wall gradient"));
    }
    let tau = opt.nu_m2_s * slope.abs();
    let u_tau = tau.sqrt();
    let visc_px = opt.nu_m2_s / u_tau * 1000.0 * opt.px_per_mm;
    Ok(WallFit {
        wall_y_px: wall_y,
        wall_estimated: opt.wall_y.is_none(),
        dudy_per_s: slope,
        tau_w_over_rho: tau,
        u_tau_m_s: u_tau,
        viscous_length_px: visc_px,
        points_used: pts.len(),
    })
}
