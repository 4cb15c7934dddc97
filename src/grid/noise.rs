//! Velocity measurement noise from the tracks themselves, and the dynamic
//! velocity range (largest velocity over noise rms).
//!
//! A track sample's velocity is u = U(x) + u'(x, t) + n: the mean field,
//! the flow's fluctuation, and the measurement noise n (centroid noise
//! propagated through the track fit). Over one bin, stresses hold u'² + n²
//! and cannot tell them apart; a time series cannot either when the flow
//! fluctuates at all frequencies. What separates them is *space at one
//! instant*: two particles a small distance d apart at the same pulse see
//! nearly the same flow but independent noise. With δ = u − U(x) (the mean
//! field, bilinearly interpolated from the grid, removed first so that
//! mean gradients do not count as difference),
//!
//! E[(δ_a − δ_b)²] / 2 = σ_n² + D'(d) / 2,
//!
//! where D'(d) = E[(u'_a − u'_b)²] is the fluctuations' structure function,
//! which vanishes like d² for a smooth flow. So pairs are sorted into
//! shells of d² between `min_sep` and `max_sep`, each shell gives a robust
//! mean (median / ln 2: for Gaussian noise the pair statistic averaged over
//! u and v is exponentially distributed; the median ignores wrong links),
//! and a straight line in d² extrapolated to d = 0 gives σ_n². Pairs closer
//! than `min_sep` are left out: their images merge or swap, and their
//! errors are not independent.
//!
//! The dynamic velocity range is then max |U| over the grid / σ_n, per
//! sample (one track point). Means over n independent samples have σ_n/√n.

use serde::{Deserialize, Serialize};

use super::estimate::GridStats;
use super::Sample;
use crate::error::{Error, Result};

/// Options of [`velocity_noise`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[ebptv_macros::testkit]
pub(crate) struct NoiseOptions {
    /// Closest pair separation used (px).
    pub min_sep: f64,
    /// Farthest pair separation used (px).
    pub max_sep: f64,
    /// Number of shells in d² between the two.
    pub shells: usize,
}

impl Default for NoiseOptions {
    fn default() -> Self {
        NoiseOptions {
            min_sep: 2.0,
            max_sep: 8.0,
            shells: 6,
        }
    }
}

/// The noise estimate.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NoiseEstimate {
    /// Velocity noise rms per component and per track sample (px/s).
    pub noise_rms: f64,
    /// Pairs used.
    pub pairs: u64,
    /// Per shell: (mean d² (px²), robust mean of the pair statistic ((px/s)²), pairs).
    pub shells: Vec<(f64, f64, u64)>,
    /// Largest mean speed over the grid's valid bins (px/s).
    pub max_speed: f64,
    /// max_speed / noise_rms.
    pub dynamic_range: f64,
}

/// Mean field at (x, y), bilinear between the four surrounding bin centres;
/// `None` outside the grid or next to an empty bin.
fn mean_at(g: &GridStats, x: f64, y: f64) -> Option<(f64, f64)> {
    let (nx, ny) = (g.spec.nx, g.spec.ny);
    if nx < 2 || ny < 2 {
        return None;
    }
    let fx = (x - g.xs[0]) / (g.xs[1] - g.xs[0]);
    let fy = (y - g.ys[0]) / (g.ys[1] - g.ys[0]);
    if !(fx >= 0.0 && fy >= 0.0) {
        return None;
    }
    let (i, j) = (fx.floor() as usize, fy.floor() as usize);
    if i + 1 >= nx || j + 1 >= ny {
        return None;
    }
    let (ax, ay) = (fx - i as f64, fy - j as f64);
    let (mut u, mut v) = (0.0, 0.0);
    for (di, dj, w) in [
        (0, 0, (1.0 - ax) * (1.0 - ay)),
        (1, 0, ax * (1.0 - ay)),
        (0, 1, (1.0 - ax) * ay),
        (1, 1, ax * ay),
    ] {
        let b = g.at(i + di, j + dj);
        if !(b.u.is_finite() && b.v.is_finite()) {
            return None;
        }
        u += w * b.u;
        v += w * b.v;
    }
    Some((u, v))
}

fn median(v: &mut [f64]) -> f64 {
    let mid = v.len() / 2;
    let (_, m, _) = v.select_nth_unstable_by(mid, |a, b| a.total_cmp(b));
    *m
}

/// Estimate the per-sample velocity noise from pairs of samples of
/// different tracks at the same time (see the module docs). `g` is the
/// mean field of the same samples (any bin size, fit or weighting).
#[ebptv_macros::testkit]
pub(crate) fn velocity_noise(
    samples: &[Sample],
    g: &GridStats,
    opt: &NoiseOptions,
) -> Result<NoiseEstimate> {
    if !(opt.min_sep >= 0.0 && opt.max_sep > opt.min_sep && opt.max_sep.is_finite()) {
        return Err(Error::param(
            "noise separations",
            format!(
                "need 0 ≤ min_sep < max_sep, got {} and {}",
                opt.min_sep, opt.max_sep
            ),
        ));
    }
    if opt.shells < 2 {
        return Err(Error::param("noise shells", "need at least 2 shells"));
    }
    // Residuals about the mean field, grouped by time.
    let mut res: Vec<(f64, f64, f64, f64, f64, u64)> = samples
        .iter()
        .filter(|s| s.x.is_finite() && s.y.is_finite() && s.u.is_finite() && s.v.is_finite())
        .filter_map(|s| {
            mean_at(g, s.x, s.y).map(|(u, v)| (s.t_us, s.x, s.y, s.u - u, s.v - v, s.track_id))
        })
        .collect();
    res.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.total_cmp(&b.1)));
    let (d2_lo, d2_hi) = (opt.min_sep * opt.min_sep, opt.max_sep * opt.max_sep);
    let shell_w = (d2_hi - d2_lo) / opt.shells as f64;
    let mut stat: Vec<Vec<f64>> = vec![Vec::new(); opt.shells];
    let mut d2_sum = vec![0.0f64; opt.shells];
    let mut start = 0;
    while start < res.len() {
        let t = res[start].0;
        let mut end = start;
        while end < res.len() && res[end].0 == t {
            end += 1;
        }
        // Sorted by x within the instant: scan forward while Δx ≤ max_sep.
        let group = &res[start..end];
        for (a, p) in group.iter().enumerate() {
            for q in &group[a + 1..] {
                let dx = q.1 - p.1;
                if dx > opt.max_sep {
                    break;
                }
                if q.5 == p.5 {
                    continue;
                }
                let dy = q.2 - p.2;
                let d2 = dx * dx + dy * dy;
                if d2 < d2_lo || d2 >= d2_hi {
                    continue;
                }
                let k = (((d2 - d2_lo) / shell_w) as usize).min(opt.shells - 1);
                stat[k].push(((p.3 - q.3).powi(2) + (p.4 - q.4).powi(2)) / 4.0);
                d2_sum[k] += d2;
            }
        }
        start = end;
    }
    let mut shells = Vec::new();
    for (k, s) in stat.iter_mut().enumerate() {
        if s.len() >= 20 {
            let n = s.len();
            shells.push((
                d2_sum[k] / n as f64,
                median(s) / std::f64::consts::LN_2,
                n as u64,
            ));
        }
    }
    let pairs: u64 = shells.iter().map(|s| s.2).sum();
    if shells.len() < 2 {
        return Err(Error::analysis(format!(
            "noise estimate: too few sample pairs {}–{} px apart at the same pulse ({pairs}); seeding too sparse or too few tracks",
            opt.min_sep, opt.max_sep
        )));
    }
    // Weighted least squares y = a + b d², weights = pair counts.
    let (mut sw, mut sx, mut sy, mut sxx, mut sxy) = (0.0, 0.0, 0.0, 0.0, 0.0);
    for &(x, y, n) in &shells {
        let w = n as f64;
        sw += w;
        sx += w * x;
        sy += w * y;
        sxx += w * x * x;
        sxy += w * x * y;
    }
    let det = sw * sxx - sx * sx;
    let intercept = if det > 0.0 {
        (sxx * sy - sx * sxy) / det
    } else {
        sy / sw
    };
    // A negative intercept (noise far below the flow's small-scale
    // variation) cannot be resolved: fall back to the closest shell, an
    // upper bound.
    let var = if intercept > 0.0 {
        intercept
    } else {
        shells[0].1
    };
    let noise_rms = var.sqrt();
    let max_speed = g
        .bins
        .iter()
        .filter(|b| b.u.is_finite() && b.v.is_finite())
        .map(|b| b.u.hypot(b.v))
        .fold(0.0, f64::max);
    Ok(NoiseEstimate {
        noise_rms,
        pairs,
        shells,
        max_speed,
        dynamic_range: max_speed / noise_rms,
    })
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;
    use crate::grid::{bin_samples, estimate, EstimateOptions, Fit, Lattice, Weighting};
    use rand::{Rng, SeedableRng};
    use rand_distr::{Distribution, Normal};
    use rand_pcg::Pcg64;

    /// Particles in a sheared flow with a travelling wave (fluctuations
    /// shared by neighbours) plus white noise of known rms: the estimate
    /// recovers the noise, not the wave or the mean shear.
    /// The samples binned on 16 px top-hat bins.
    fn top_hat_16(s: &[Sample]) -> crate::grid::GridAccumulator {
        bin_samples(s, Lattice::new(16.0, 16.0, 0.0).unwrap(), Weighting::TopHat).unwrap()
    }

    fn samples(sigma: f64, wave: f64, seed: u64) -> Vec<Sample> {
        let mut rng = Pcg64::seed_from_u64(seed);
        let noise = Normal::new(0.0, sigma).unwrap();
        let mut out = Vec::new();
        for k in 0..200 {
            let t = 100.0 * k as f64;
            for id in 0..400u64 {
                let (x, y): (f64, f64) = (rng.gen_range(0.0..256.0), rng.gen_range(0.0..128.0));
                let phase = 0.05 * x - 0.002 * t;
                out.push(Sample {
                    x,
                    y,
                    u: 1000.0 + 20.0 * y + wave * phase.cos() + noise.sample(&mut rng),
                    v: wave * (0.04 * y + 0.001 * t).sin() + noise.sample(&mut rng),
                    t_us: t,
                    track_id: k * 1000 + id,
                });
            }
        }
        out
    }

    #[ebptv_macros::unit_test]
    fn recovers_white_noise_under_shear_and_waves() {
        for (sigma, wave) in [(50.0, 0.0), (50.0, 300.0), (200.0, 1000.0)] {
            let s = samples(sigma, wave, 7);
            let acc = top_hat_16(&s);
            let g = estimate(
                &acc,
                &EstimateOptions {
                    fit: Fit::Linear,
                    min_count: 10,
                    noise_rms: 0.0,
                },
            )
            .unwrap();
            let e = velocity_noise(&s, &g, &NoiseOptions::default()).unwrap();
            assert!(
                (e.noise_rms / sigma - 1.0).abs() < 0.08,
                "σ {sigma}, wave {wave}: estimate {}",
                e.noise_rms
            );
            assert!((e.dynamic_range - e.max_speed / e.noise_rms).abs() < 1e-9);
        }
    }

    /// The sorted sweep finds exactly the pairs of a brute-force search.
    #[ebptv_macros::unit_test]
    fn sweep_equals_brute_force_pairs() {
        let s: Vec<Sample> = samples(80.0, 200.0, 3).into_iter().take(4000).collect();
        let acc = top_hat_16(&s);
        let g = estimate(&acc, &EstimateOptions::default()).unwrap();
        let opt = NoiseOptions::default();
        let e = velocity_noise(&s, &g, &opt).unwrap();
        let (lo, hi) = (opt.min_sep.powi(2), opt.max_sep.powi(2));
        let w = (hi - lo) / opt.shells as f64;
        let mut stat: Vec<Vec<f64>> = vec![vec![]; opt.shells];
        for (i, p) in s.iter().enumerate() {
            for q in &s[i + 1..] {
                if p.t_us != q.t_us || p.track_id == q.track_id {
                    continue;
                }
                let d2 = (p.x - q.x).powi(2) + (p.y - q.y).powi(2);
                let (Some(mp), Some(mq)) = (mean_at(&g, p.x, p.y), mean_at(&g, q.x, q.y)) else {
                    continue;
                };
                if d2 < lo || d2 >= hi {
                    continue;
                }
                let k = (((d2 - lo) / w) as usize).min(opt.shells - 1);
                let (du, dv) = ((p.u - mp.0) - (q.u - mq.0), (p.v - mp.1) - (q.v - mq.1));
                stat[k].push((du * du + dv * dv) / 4.0);
            }
        }
        let brute: Vec<(u64, f64)> = stat
            .iter_mut()
            .filter(|v| v.len() >= 20)
            .map(|v| (v.len() as u64, median(v) / std::f64::consts::LN_2))
            .collect();
        assert_eq!(brute.len(), e.shells.len());
        for (b, s) in brute.iter().zip(&e.shells) {
            assert_eq!(b.0, s.2);
            assert!((b.1 - s.1).abs() <= 1e-9 * b.1, "{b:?} vs {s:?}");
        }
    }

    #[ebptv_macros::unit_test]
    fn bad_options_and_sparse_data() {
        let s = samples(50.0, 0.0, 1);
        let acc = top_hat_16(&s);
        let g = estimate(&acc, &EstimateOptions::default()).unwrap();
        let bad = NoiseOptions {
            min_sep: 5.0,
            max_sep: 2.0,
            shells: 6,
        };
        assert!(velocity_noise(&s, &g, &bad).is_err());
        // One sample per instant: no pairs.
        let lone: Vec<Sample> = s
            .iter()
            .enumerate()
            .map(|(i, p)| Sample {
                t_us: i as f64,
                ..*p
            })
            .collect();
        let err = velocity_noise(&lone, &g, &NoiseOptions::default()).unwrap_err();
        assert!(err.to_string().contains("pairs"), "{err}");
    }
}
