//! The curvature prior of short tracks and track ends ([`AccelPrior`]: the
//! rms acceleration estimated from the tracks kept so far) and the
//! leave-one-out residuals of a fit ([`LeaveOneOut`]).

use super::*;

/// Detections per window of [`AccelPrior`]'s curvature samples.
pub(super) const PRIOR_WINDOW: usize = 7;
/// ⟨s²⟩ and Σ (s² − ⟨s²⟩)² over s = −3..=3: the quadratic coefficient of
/// a centred 7-point fit is `Σ (s² − 4)·x / 84`, its noise variance
/// factor `1/84`.
pub(super) const PRIOR_MEAN_S2: isize = 4;
pub(super) const PRIOR_NORM: f64 = 84.0;
/// Curvature samples before the estimate is used (fewer: no prior).
pub(super) const PRIOR_MIN_SAMPLES: u64 = 20;

/// The population estimate behind [`WindowRule::accel_rms`]: the flow's
/// rms acceleration per axis, from the quadratic coefficients of disjoint
/// gap-free 7-detection stretches of finished tracks, less their noise
/// variance `σ²/84` (unbiased; 7 rather than 11 detections so that the
/// estimate exists a few pulses earlier in a recording — tracks that end
/// before it do without a prior — which on the 60-pulse synthetic scene
/// gave 0.134 → 0.132 px/pulse before the widening).
/// The tracker adds each kept track in output order, so the estimate a
/// track is fitted with does not depend on the thread count.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub(crate) struct AccelPrior {
    /// Σ (c₂ₓ² + c₂ᵧ²) and the number of stretches.
    pub(super) sum_sq: f64,
    pub(super) samples: u64,
}

impl AccelPrior {
    /// Add the gap-free runs of a track: `pulses` (increasing) and its
    /// positions `xy`, τ in pulses.
    pub(crate) fn add_track(&mut self, pulses: &[i64], xy: &[[f64; 2]]) {
        let n = pulses.len().min(xy.len());
        let mut start = 0;
        while start + PRIOR_WINDOW <= n {
            let end = start + PRIOR_WINDOW;
            // The first break in the run restarts the stretch after it.
            if let Some(k) = (start + 1..end).find(|&k| pulses[k] != pulses[k - 1] + 1) {
                start = k;
                continue;
            }
            let c = PRIOR_WINDOW as isize / 2;
            let p0 = xy[start + c as usize];
            let mut c2 = [0.0f64; 2];
            for (k, p) in xy[start..end].iter().enumerate() {
                let s = k as isize - c;
                let g = (s * s - PRIOR_MEAN_S2) as f64 / PRIOR_NORM;
                c2[0] += g * (p[0] - p0[0]);
                c2[1] += g * (p[1] - p0[1]);
            }
            if c2[0].is_finite() && c2[1].is_finite() {
                self.sum_sq += c2[0] * c2[0] + c2[1] * c2[1];
                self.samples += 1;
            }
            start = end;
        }
    }

    /// Add another estimate's samples.
    pub(crate) fn merge(&mut self, other: &AccelPrior) {
        self.sum_sq += other.sum_sq;
        self.samples += other.samples;
    }

    #[cfg(feature = "testkit")]
    /// Curvature samples so far.
    pub(crate) fn samples(&self) -> u64 {
        self.samples
    }

    /// The rms acceleration per axis (px/pulse²) for position noise
    /// `sigma`, 0 (no prior) before [`PRIOR_MIN_SAMPLES`] stretches. A
    /// flow without measurable curvature gets a floor of a quarter of the
    /// stretches' own noise variance, which pulls short fits nearly
    /// straight but keeps the ridge finite.
    pub(crate) fn accel_rms(&self, sigma: f64) -> f64 {
        if self.samples < PRIOR_MIN_SAMPLES {
            return 0.0;
        }
        let noise = sigma * sigma / PRIOR_NORM;
        let c2_var = (self.sum_sq / (2 * self.samples) as f64 - noise).max(0.25 * noise);
        2.0 * c2_var.sqrt()
    }
}

/// Leave-one-out quadratic predictions on the integer grid, for the
/// tracker's outlier pass: a quadratic fitted to `w + 1` samples at
/// consecutive τ with sample `e` left out, evaluated at sample `e`. On a
/// gap-free window the prediction is a fixed weighting of the other
/// samples (and its leverage a number): tabulated here for every `w` up to
/// `max_window` and every `e`, from the reference's own normal matrices
/// ([`fit_eval`] is what the tables are tested against).
#[derive(Debug, Clone)]
#[ebptv_macros::testkit]
pub(crate) struct LeaveOneOut {
    pub(super) max_window: usize,
    /// Per `w` (index `w`), per `e` in `0..=w`: weights of the `w + 1`
    /// samples (0 at `e`) and the leverage; `None` when the fit is singular.
    #[allow(clippy::type_complexity)]
    pub(super) table: Vec<Vec<Option<(Vec<f64>, f64)>>>,
}

impl LeaveOneOut {
    /// Tables for windows of up to `max_window` fitted samples.
    #[ebptv_macros::testkit]
    pub(crate) fn new(max_window: usize) -> Self {
        let mut table = vec![Vec::new()];
        for w in 1..=max_window {
            let mut per_e = Vec::with_capacity(w + 1);
            for e in 0..=w {
                let taus: Vec<f64> = (0..=w)
                    .filter(|&k| k != e)
                    .map(|k| k as f64 - e as f64)
                    .collect();
                let p = 2.min(w - 1) + 1;
                let mut ata = [[0.0f64; 3]; 3];
                for &t in &taus {
                    let row = [1.0, t, t * t];
                    for a in 0..p {
                        for b in 0..p {
                            ata[a][b] += row[a] * row[b];
                        }
                    }
                }
                per_e.push(invert(&ata, p).map(|inv| {
                    let weights = (0..=w)
                        .map(|k| {
                            if k == e {
                                return 0.0;
                            }
                            let t = k as f64 - e as f64;
                            let row = [1.0, t, t * t];
                            (0..p).map(|b| inv[0][b] * row[b]).sum()
                        })
                        .collect();
                    (weights, inv[0][0])
                }));
            }
            table.push(per_e);
        }
        LeaveOneOut { max_window, table }
    }

    /// Shared tables for `max_window`, built once per process.
    pub(crate) fn cached(max_window: usize) -> std::sync::Arc<LeaveOneOut> {
        use std::sync::{Arc, Mutex, OnceLock};
        static CACHE: OnceLock<Mutex<Vec<Arc<LeaveOneOut>>>> = OnceLock::new();
        let mut cache = CACHE
            .get_or_init(Default::default)
            .lock()
            .unwrap_or_else(|e| e.into_inner());
        if let Some(t) = cache.iter().find(|t| t.max_window == max_window) {
            return t.clone();
        }
        let t = Arc::new(LeaveOneOut::new(max_window));
        cache.push(t.clone());
        t
    }

    /// `(dx, dy, leverage)`: the quadratic through the points `xy` (at τ
    /// = index, `w + 1 = xy.len()` points, `w ≤ max_window`) without
    /// point `e`, evaluated at τ = `e`, minus point `e`. The same as
    /// [`fit_eval`] over the other points (order 2) up to rounding; `None`
    /// outside the tables or for a singular fit.
    #[ebptv_macros::testkit]
    pub(crate) fn predict(&self, xy: &[[f64; 2]], e: usize) -> Option<(f64, f64, f64)> {
        let w = xy.len().checked_sub(1)?;
        let (weights, leverage) = self.table.get(w)?.get(e)?.as_ref()?;
        let p0 = xy[e];
        let mut d = [0.0f64; 2];
        for (g, p) in weights.iter().zip(xy) {
            d[0] += g * (p[0] - p0[0]);
            d[1] += g * (p[1] - p0[1]);
        }
        Some((d[0], d[1], *leverage))
    }
}
