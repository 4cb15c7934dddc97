//! Time-resolved fields: u(x, y, t) on the grid.
//!
//! Frame k is centred at `t0 + k·step` and collects the samples with
//! `|t − t_k| < window/2` (typically step = k pulse periods, window = one
//! period, so each pulse's samples land in exactly one frame). Each frame's
//! bin value is the (weighted) mean of its samples; a bin without samples in
//! a frame is NaN. Samples are visited once, in any order: every sample is
//! added to the frames and bins that contain it, so memory is
//! `frames × selected bins` and no sorting is needed.
//!
//! [`FieldSeries`] for all bins is the u(x, y, t) array; selecting a few
//! bins gives point time series for spectra at a fraction of the memory.

use super::spec::GridSpec;
use super::Sample;
use crate::error::{Error, Result};

/// The time axis of time-resolved fields.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Frames {
    /// Centre time of frame 0 (µs).
    pub t0_us: f64,
    /// Time between frame centres (µs).
    pub step_us: f64,
    /// Width of a frame's time window (µs), centred on its time.
    pub window_us: f64,
    /// Number of frames.
    pub n: usize,
}

/// Upper limit on frames × bins of one series (memory guard, 3 f64 each).
pub(crate) const MAX_FIELD_VALUES: usize = 200_000_000;

impl Frames {
    pub(crate) fn validate(&self) -> Result<()> {
        if !(self.step_us.is_finite() && self.step_us > 0.0) {
            return Err(Error::param(
                "step",
                format!("frame step must be > 0 µs, got {}", self.step_us),
            ));
        }
        if !(self.window_us.is_finite() && self.window_us > 0.0) {
            return Err(Error::param(
                "window",
                format!("frame window must be > 0 µs, got {}", self.window_us),
            ));
        }
        if self.n == 0 {
            return Err(Error::param("frames", "no frames (empty time range)"));
        }
        Ok(())
    }

    /// Frames every `every` sample periods over the samples' time span, the
    /// window one period wide. The period is the median time step between
    /// consecutive samples of a track (the pulse period for tracks.csv).
    pub(crate) fn from_samples(samples: &[Sample], every: usize) -> Result<Frames> {
        let period = sample_period_us(samples)?;
        let (mut t0, mut t1) = (f64::INFINITY, f64::NEG_INFINITY);
        for s in samples {
            if s.t_us.is_finite() {
                t0 = t0.min(s.t_us);
                t1 = t1.max(s.t_us);
            }
        }
        let step = period * every.max(1) as f64;
        let n = ((t1 - t0) / step).floor() as usize + 1;
        Ok(Frames {
            t0_us: t0,
            step_us: step,
            window_us: period,
            n,
        })
    }

    pub(crate) fn time_us(&self, k: usize) -> f64 {
        self.t0_us + k as f64 * self.step_us
    }
    /// Frame rate (Hz): one over the step.
    #[ebptv_macros::testkit]
    pub(crate) fn rate_hz(&self) -> f64 {
        1e6 / self.step_us
    }
}

/// Median positive time step between consecutive samples of the same track.
pub(crate) fn sample_period_us(samples: &[Sample]) -> Result<f64> {
    let mut d: Vec<f64> = samples
        .windows(2)
        .filter(|w| w[0].track_id == w[1].track_id)
        .map(|w| (w[1].t_us - w[0].t_us).abs())
        .filter(|d| d.is_finite() && *d > 0.0)
        .collect();
    if d.is_empty() {
        return Err(Error::analysis(
            "cannot infer the pulse period: no track has two samples at different times (give the frame step explicitly)",
        ));
    }
    let mid = d.len() / 2;
    let (_, m, _) = d.select_nth_unstable_by(mid, |a, b| a.total_cmp(b));
    Ok(*m)
}

/// Mean u, v per frame for a set of bins; entry `[slot * n_frames + k]`.
#[derive(Debug, Clone)]
pub(crate) struct FieldSeries {
    /// The time axis.
    pub frames: Frames,
    /// Flat bin indices (of `spec`) of the slots.
    pub bins: Vec<usize>,
    /// Number of samples per slot and frame (layout as `u`).
    pub count: Vec<u32>,
    /// Mean velocity along x (px/s) per slot and frame; NaN without samples.
    pub u: Vec<f64>,
    /// Mean velocity along y (px/s) per slot and frame; NaN without samples.
    pub v: Vec<f64>,
}

impl FieldSeries {
    pub(crate) fn u_series(&self, slot: usize) -> &[f64] {
        &self.u[slot * self.frames.n..(slot + 1) * self.frames.n]
    }
    pub(crate) fn v_series(&self, slot: usize) -> &[f64] {
        &self.v[slot * self.frames.n..(slot + 1) * self.frames.n]
    }
}

/// Time-resolved means on `spec` for the bins `bins` (all bins if `None`).
pub(crate) fn time_resolved(
    samples: &[Sample],
    spec: &GridSpec,
    frames: &Frames,
    bins: Option<&[usize]>,
) -> Result<FieldSeries> {
    frames.validate()?;
    let all: Vec<usize>;
    let bins = match bins {
        Some(b) => b,
        None => {
            all = (0..spec.n_bins()).collect();
            &all
        }
    };
    if bins.iter().any(|&b| b >= spec.n_bins()) {
        return Err(Error::param("bins", "bin index outside the grid"));
    }
    let nt = frames.n;
    if bins.len().saturating_mul(nt) > MAX_FIELD_VALUES {
        return Err(Error::param(
            "frames",
            format!("{} bins x {} frames is too large; select fewer bins, a larger step or a shorter time range", bins.len(), nt),
        ));
    }
    let mut slot_of = vec![u32::MAX; spec.n_bins()];
    for (s, &b) in bins.iter().enumerate() {
        slot_of[b] = s as u32;
    }
    let n = bins.len() * nt;
    let mut w = vec![0.0f64; n];
    let mut su = vec![0.0f64; n];
    let mut sv = vec![0.0f64; n];
    let mut count = vec![0u32; n];
    let lat = &spec.lattice;
    let half = 0.5 * frames.window_us;
    for s in samples {
        if !(s.x.is_finite()
            && s.y.is_finite()
            && s.u.is_finite()
            && s.v.is_finite()
            && s.t_us.is_finite())
        {
            continue;
        }
        let rel = s.t_us - frames.t0_us;
        let k_lo = ((rel - half) / frames.step_us).ceil().max(0.0);
        let k_hi = ((rel + half) / frames.step_us).floor().min(nt as f64 - 1.0);
        if k_hi < k_lo {
            continue;
        }
        let ((ilo, ihi), (jlo, jhi)) = lat.candidates(s.x, s.y, spec.weighting);
        for j in jlo..=jhi {
            let eta = (s.y - lat.centre_y(j)) / lat.bin_h;
            for i in ilo..=ihi {
                let xi = (s.x - lat.centre_x(i)) / lat.bin_w;
                let Some(wt) = spec.weighting.weight(xi, eta) else {
                    continue;
                };
                let Some(b) = spec.flat(i, j) else { continue };
                let slot = slot_of[b];
                if slot == u32::MAX {
                    continue;
                }
                for k in k_lo as usize..=k_hi as usize {
                    // Half-open window [t_k − w/2, t_k + w/2).
                    let dt = s.t_us - frames.time_us(k);
                    if dt < -half || dt >= half {
                        continue;
                    }
                    let e = slot as usize * nt + k;
                    w[e] += wt;
                    su[e] += wt * s.u;
                    sv[e] += wt * s.v;
                    count[e] += 1;
                }
            }
        }
    }
    let u = (0..n)
        .map(|e| if w[e] > 0.0 { su[e] / w[e] } else { f64::NAN })
        .collect();
    let v = (0..n)
        .map(|e| if w[e] > 0.0 { sv[e] / w[e] } else { f64::NAN })
        .collect();
    Ok(FieldSeries {
        frames: *frames,
        bins: bins.to_vec(),
        count,
        u,
        v,
    })
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;
    use crate::grid::{Lattice, Weighting};

    #[ebptv_macros::unit_test]
    fn each_pulse_lands_in_one_frame() {
        let lat = Lattice::new(10.0, 10.0, 0.0).unwrap();
        let spec = GridSpec::covering(lat, Weighting::TopHat, 0.0, 9.0, 0.0, 9.0).unwrap();
        let samples: Vec<Sample> = (0..100)
            .map(|k| Sample {
                x: 4.0,
                y: 4.0,
                u: k as f64,
                v: -(k as f64),
                t_us: 50.0 * k as f64,
                track_id: 1,
            })
            .collect();
        let fr = Frames::from_samples(&samples, 1).unwrap();
        assert_eq!(fr.step_us, 50.0);
        assert_eq!(fr.n, 100);
        let f = time_resolved(&samples, &spec, &fr, None).unwrap();
        let slot = f
            .bins
            .iter()
            .position(|&b| b == spec.flat(0, 0).unwrap())
            .unwrap();
        for k in 0..100 {
            assert_eq!(f.u_series(slot)[k], k as f64);
            assert_eq!(f.v_series(slot)[k], -(k as f64));
            assert_eq!(f.count[slot * 100 + k], 1);
        }
        let fr2 = Frames::from_samples(&samples, 4).unwrap();
        assert_eq!(fr2.n, 25);
        let f2 = time_resolved(&samples, &spec, &fr2, None).unwrap();
        assert_eq!(f2.u_series(slot)[3], 12.0);
    }
}
