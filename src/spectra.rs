//! Power spectra of time-resolved fields (Welch, rustfft).
//!
//! The paper's spectra (vortex shedding behind a rib, pre-multiplied
//! spectra across a shear layer) come from velocity time series at grid
//! points. This module turns such a series into a one-sided power spectral
//! density by Welch's method — Hann-windowed segments with overlap, the mean
//! removed per segment, periodograms averaged — and finds the dominant peak
//! with sub-bin precision.
//!
//! Normalisation (the scipy `density` convention): for a segment `x` with
//! window `w`, `P_k = c·|X_k|²/(f_s Σw²)` with `c = 2` except at DC and
//! Nyquist, so `Σ P_k Δf = Σ(w x)²/Σw²` — the window-weighted variance
//! (Parseval) — and a sine of amplitude A integrates to A²/2. The FFT path
//! is tested against a direct DFT.
//!
//! Time series from binned tracks have gaps (a bin with no particle at some
//! pulse); [`fill_gaps`] interpolates them linearly and reports the fraction
//! filled. The noise floor is the median PSD over the top quarter of the
//! band, where a smooth flow has no energy left; white noise of variance σ²
//! has the one-sided density 2σ²/f_s, so σ = √(floor·f_s/2). The dynamic
//! velocity range is then the largest velocity over that noise rms.

use std::sync::Arc;

use rustfft::{num_complex::Complex, Fft, FftPlanner};
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};

/// Parameters of Welch's method.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct WelchOptions {
    /// Segment length (samples).
    pub nperseg: usize,
    /// Overlap of consecutive segments, fraction in [0, 1).
    pub overlap: f64,
}

impl Default for WelchOptions {
    fn default() -> Self {
        WelchOptions {
            nperseg: 256,
            overlap: 0.5,
        }
    }
}

/// A one-sided power spectral density.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Psd {
    pub f_hz: Vec<f64>,
    /// Density in (unit)²/Hz.
    pub psd: Vec<f64>,
    pub fs_hz: f64,
    pub n_segments: usize,
}

impl Psd {
    pub fn df(&self) -> f64 {
        if self.f_hz.len() > 1 {
            self.f_hz[1] - self.f_hz[0]
        } else {
            0.0
        }
    }
    /// Pre-multiplied spectrum f·E(f) (unit²): equal areas under a
    /// log-frequency axis mean equal energy.
    pub fn premultiplied(&self) -> Vec<f64> {
        self.f_hz
            .iter()
            .zip(&self.psd)
            .map(|(f, p)| f * p)
            .collect()
    }
    /// ∫ P df (the variance the spectrum holds).
    pub fn total_power(&self) -> f64 {
        self.psd.iter().sum::<f64>() * self.df()
    }
}

/// Periodic Hann window (the spectral-analysis variant).
pub fn hann(n: usize) -> Vec<f64> {
    (0..n)
        .map(|i| 0.5 - 0.5 * (2.0 * std::f64::consts::PI * i as f64 / n as f64).cos())
        .collect()
}

/// Welch PSD of `x` sampled at `fs_hz`.
pub fn welch(x: &[f64], fs_hz: f64, opt: &WelchOptions) -> Result<Psd> {
    if !(fs_hz.is_finite() && fs_hz > 0.0) {
        return Err(Error::param(
            "fs",
            format!("sampling rate must be > 0 Hz, got {fs_hz}"),
        ));
    }
    if !(opt.overlap.is_finite() && (0.0..1.0).contains(&opt.overlap)) {
        return Err(Error::param(
            "overlap",
            format!("segment overlap must be in [0, 1), got {}", opt.overlap),
        ));
    }
    if opt.nperseg < 4 {
        return Err(Error::param(
            "nperseg",
            format!(
                "segment length must be at least 4 samples, got {}",
                opt.nperseg
            ),
        ));
    }
    if x.iter().any(|v| !v.is_finite()) {
        return Err(Error::analysis(
            "spectrum: time series contains NaN/inf (fill gaps first)",
        ));
    }
    if x.len() < opt.nperseg {
        return Err(Error::analysis(format!(
            "spectrum: time series of {} samples is shorter than one segment ({}); record longer or use a shorter segment",
            x.len(),
            opt.nperseg
        )));
    }
    let n = opt.nperseg;
    let step = ((n as f64 * (1.0 - opt.overlap)).round() as usize).max(1);
    let w = hann(n);
    let s2: f64 = w.iter().map(|v| v * v).sum();
    let fft: Arc<dyn Fft<f64>> = FftPlanner::new().plan_fft_forward(n);
    let nf = n / 2 + 1;
    let mut acc = vec![0.0f64; nf];
    let mut buf = vec![Complex::new(0.0, 0.0); n];
    let mut segs = 0;
    let mut start = 0;
    while start + n <= x.len() {
        let seg = &x[start..start + n];
        let mean = seg.iter().sum::<f64>() / n as f64;
        for i in 0..n {
            buf[i] = Complex::new((seg[i] - mean) * w[i], 0.0);
        }
        fft.process(&mut buf);
        for (k, a) in acc.iter_mut().enumerate() {
            *a += buf[k].norm_sqr();
        }
        segs += 1;
        start += step;
    }
    let scale = 1.0 / (fs_hz * s2 * segs as f64);
    let psd = acc
        .iter()
        .enumerate()
        .map(|(k, a)| {
            let one_sided = if k == 0 || (n % 2 == 0 && k == n / 2) {
                1.0
            } else {
                2.0
            };
            a * scale * one_sided
        })
        .collect();
    let f_hz = (0..nf).map(|k| k as f64 * fs_hz / n as f64).collect();
    Ok(Psd {
        f_hz,
        psd,
        fs_hz,
        n_segments: segs,
    })
}

/// A spectral peak.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Peak {
    /// Interpolated frequency (Hz).
    pub f_hz: f64,
    /// PSD at the peak bin.
    pub psd: f64,
    pub bin: usize,
}

/// The largest PSD value in `[f_min, f_max]` (DC excluded), its frequency
/// refined by a parabola through the logarithms of the three bins around it
/// (exact for a Gaussian-shaped lobe, close for the Hann main lobe).
pub fn find_peak(p: &Psd, f_min: f64, f_max: f64) -> Option<Peak> {
    let (mut best, mut k0) = (f64::NEG_INFINITY, None);
    for k in 1..p.psd.len() {
        if p.f_hz[k] >= f_min && p.f_hz[k] <= f_max && p.psd[k] > best {
            best = p.psd[k];
            k0 = Some(k);
        }
    }
    let k = k0?;
    let mut f = p.f_hz[k];
    if k > 0 && k + 1 < p.psd.len() && p.psd[k - 1] > 0.0 && p.psd[k + 1] > 0.0 && p.psd[k] > 0.0 {
        let (a, b, c) = (p.psd[k - 1].ln(), p.psd[k].ln(), p.psd[k + 1].ln());
        let den = a - 2.0 * b + c;
        if den < 0.0 {
            let delta = (0.5 * (a - c) / den).clamp(-0.5, 0.5);
            f += delta * p.df();
        }
    }
    Some(Peak {
        f_hz: f,
        psd: best,
        bin: k,
    })
}

/// Noise floor: the median density over the top quarter of the band.
pub fn noise_floor(p: &Psd) -> f64 {
    let n = p.psd.len();
    let mut top: Vec<f64> = p.psd[(3 * n / 4).max(1)..].to_vec();
    if top.is_empty() {
        return f64::NAN;
    }
    let mid = top.len() / 2;
    let (_, m, _) = top.select_nth_unstable_by(mid, |a, b| a.total_cmp(b));
    *m
}

/// RMS of the white noise that would produce the floor `floor` at `fs_hz`.
pub fn noise_rms_from_floor(floor: f64, fs_hz: f64) -> f64 {
    (floor * fs_hz / 2.0).sqrt()
}

/// Linear interpolation over NaN gaps (ends take the nearest value).
/// Returns the filled series and the fraction of samples that were missing;
/// an error when there is no valid sample at all.
pub fn fill_gaps(x: &[f64]) -> Result<(Vec<f64>, f64)> {
    let valid: Vec<usize> = (0..x.len()).filter(|&i| x[i].is_finite()).collect();
    if valid.is_empty() {
        return Err(Error::analysis(
            "time series has no valid sample (no particle ever in this bin)",
        ));
    }
    let mut y = x.to_vec();
    let first = valid[0];
    let last = *valid.last().unwrap();
    for v in y.iter_mut().take(first) {
        *v = x[first];
    }
    for v in y.iter_mut().skip(last + 1) {
        *v = x[last];
    }
    for w in valid.windows(2) {
        let (a, b) = (w[0], w[1]);
        for i in a + 1..b {
            let t = (i - a) as f64 / (b - a) as f64;
            y[i] = x[a] + t * (x[b] - x[a]);
        }
    }
    Ok((y, 1.0 - valid.len() as f64 / x.len() as f64))
}

/// RMS about a centred moving average of `n` samples (the paper's laminar
/// case: slow drifts of the mean are not turbulence, the remainder
/// measures the noise). Ends use the truncated window.
pub fn rms_about_moving_average(x: &[f64], n: usize) -> Result<f64> {
    if n < 2 {
        return Err(Error::param(
            "moving-average",
            "window must be at least 2 samples",
        ));
    }
    if x.len() < 2 {
        return Err(Error::analysis(
            "time series too short for a moving average",
        ));
    }
    let mut prefix = vec![0.0f64; x.len() + 1];
    for (i, v) in x.iter().enumerate() {
        prefix[i + 1] = prefix[i] + v;
    }
    let h = n / 2;
    let mut ss = 0.0;
    for i in 0..x.len() {
        let lo = i.saturating_sub(h);
        let hi = (i + n - h).min(x.len());
        let ma = (prefix[hi] - prefix[lo]) / (hi - lo) as f64;
        ss += (x[i] - ma).powi(2);
    }
    // A window of n samples removes ~1/n of the noise variance with the mean.
    let corr = 1.0 - 1.0 / n as f64;
    Ok((ss / x.len() as f64 / corr).sqrt())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fill_gaps_interpolates() {
        let (y, frac) = fill_gaps(&[f64::NAN, 1.0, f64::NAN, f64::NAN, 4.0, f64::NAN]).unwrap();
        assert_eq!(y, vec![1.0, 1.0, 2.0, 3.0, 4.0, 4.0]);
        assert!((frac - 4.0 / 6.0).abs() < 1e-12);
        assert!(fill_gaps(&[f64::NAN; 3]).is_err());
    }

    #[test]
    fn bad_parameters() {
        let x = vec![0.0; 100];
        assert!(welch(&x, 0.0, &WelchOptions::default()).is_err());
        assert!(welch(
            &x,
            1.0,
            &WelchOptions {
                nperseg: 2,
                overlap: 0.5
            }
        )
        .is_err());
        assert!(welch(
            &x,
            1.0,
            &WelchOptions {
                nperseg: 16,
                overlap: 1.0
            }
        )
        .is_err());
        assert!(welch(
            &x,
            1.0,
            &WelchOptions {
                nperseg: 256,
                overlap: 0.5
            }
        )
        .is_err());
        assert!(welch(
            &[f64::NAN; 64],
            1.0,
            &WelchOptions {
                nperseg: 16,
                overlap: 0.5
            }
        )
        .is_err());
    }
}

/// Options of [`point_spectra`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SpectraOptions {
    pub lattice: crate::grid::Lattice,
    pub weighting: crate::grid::Weighting,
    /// One frame every `every` pulses (sample periods).
    pub every: usize,
    pub welch: WelchOptions,
    /// Peak search band (Hz).
    pub f_min: f64,
    pub f_max: f64,
    /// Also report the rms about a moving average of this many frames.
    pub moving_average: Option<usize>,
    /// Bins with fewer samples are ignored for the maximum velocity.
    pub min_count: u64,
}

/// The spectrum at one point.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PointSpectrum {
    /// Requested point (px).
    pub x: f64,
    pub y: f64,
    /// Centre of the bin used (px).
    pub bin_x: f64,
    pub bin_y: f64,
    pub psd_u: Psd,
    pub psd_v: Psd,
    /// Peak of the summed spectrum of u and v.
    pub peak: Option<Peak>,
    pub peak_u: Option<Peak>,
    pub peak_v: Option<Peak>,
    /// Fraction of frames without a sample (filled by interpolation).
    pub gap_fraction: f64,
    pub mean_u: f64,
    pub mean_v: f64,
    pub rms_u: f64,
    pub rms_v: f64,
    /// RMS of the noise floor (px/s) per component.
    pub noise_rms_u: f64,
    pub noise_rms_v: f64,
    pub rms_ma_u: Option<f64>,
    pub rms_ma_v: Option<f64>,
}

impl PointSpectrum {
    /// Summed spectrum u + v.
    pub fn psd_sum(&self) -> Vec<f64> {
        self.psd_u
            .psd
            .iter()
            .zip(&self.psd_v.psd)
            .map(|(a, b)| a + b)
            .collect()
    }
}

/// Everything [`point_spectra`] found.
#[derive(Debug, Clone)]
pub struct SpectraResult {
    pub frames: crate::grid::fields::Frames,
    pub points: Vec<PointSpectrum>,
    /// Largest mean speed over the grid's bins (px/s).
    pub max_speed: f64,
    /// Noise rms (px/s): the median over points of the per-component floors.
    pub noise_rms: f64,
    /// max_speed / noise_rms.
    pub dynamic_range: f64,
}

/// Spectra of the binned velocity time series at `points` (px).
pub fn point_spectra(
    samples: &[crate::grid::Sample],
    points: &[(f64, f64)],
    opt: &SpectraOptions,
) -> Result<SpectraResult> {
    use crate::grid::fields::{time_resolved, Frames};
    use crate::grid::{estimate, extent, EstimateOptions, GridAccumulator, GridSpec};
    if points.is_empty() {
        return Err(Error::param("point", "no point given"));
    }
    let (x0, x1, y0, y1) = extent(samples, "tracks")?;
    let spec = GridSpec::covering(opt.lattice, opt.weighting, x0, x1, y0, y1)?;
    let frames = Frames::from_samples(samples, opt.every)?;
    let xs = spec.xs();
    let ys = spec.ys();
    let nearest = |v: &[f64], t: f64| {
        v.iter()
            .enumerate()
            .min_by(|a, b| (a.1 - t).abs().total_cmp(&(b.1 - t).abs()))
            .map(|(i, _)| i)
            .unwrap()
    };
    let mut bins = Vec::with_capacity(points.len());
    for &(px, py) in points {
        if !(px.is_finite() && py.is_finite())
            || px < x0 - opt.lattice.bin_w
            || px > x1 + opt.lattice.bin_w
            || py < y0 - opt.lattice.bin_h
            || py > y1 + opt.lattice.bin_h
        {
            return Err(Error::param("point", format!("point ({px}, {py}) is outside the tracks' extent x [{x0:.1}, {x1:.1}] y [{y0:.1}, {y1:.1}]")));
        }
        let (ix, iy) = (nearest(&xs, px), nearest(&ys, py));
        bins.push(iy * spec.nx + ix);
    }
    let mut uniq = bins.clone();
    uniq.sort_unstable();
    uniq.dedup();
    let series = time_resolved(samples, &spec, &frames, Some(&uniq))?;
    let fs = frames.rate_hz();
    let mut out = Vec::with_capacity(points.len());
    for (p, &b) in points.iter().zip(&bins) {
        let slot = uniq.binary_search(&b).expect("bin selected");
        let (u, gap) = fill_gaps(series.u_series(slot))
            .map_err(|e| Error::analysis(format!("point ({}, {}): {e}", p.0, p.1)))?;
        let (v, _) = fill_gaps(series.v_series(slot))?;
        let psd_u = welch(&u, fs, &opt.welch)?;
        let psd_v = welch(&v, fs, &opt.welch)?;
        let sum = Psd {
            psd: psd_u
                .psd
                .iter()
                .zip(&psd_v.psd)
                .map(|(a, b)| a + b)
                .collect(),
            ..psd_u.clone()
        };
        let stats = |x: &[f64]| {
            let m = x.iter().sum::<f64>() / x.len() as f64;
            (
                m,
                (x.iter().map(|v| (v - m).powi(2)).sum::<f64>() / x.len() as f64).sqrt(),
            )
        };
        let (mean_u, rms_u) = stats(&u);
        let (mean_v, rms_v) = stats(&v);
        let ma = |x: &[f64]| {
            opt.moving_average
                .map(|n| rms_about_moving_average(x, n))
                .transpose()
        };
        out.push(PointSpectrum {
            x: p.0,
            y: p.1,
            bin_x: xs[b % spec.nx],
            bin_y: ys[b / spec.nx],
            peak: find_peak(&sum, opt.f_min, opt.f_max),
            peak_u: find_peak(&psd_u, opt.f_min, opt.f_max),
            peak_v: find_peak(&psd_v, opt.f_min, opt.f_max),
            gap_fraction: gap,
            mean_u,
            mean_v,
            rms_u,
            rms_v,
            noise_rms_u: noise_rms_from_floor(noise_floor(&psd_u), fs),
            noise_rms_v: noise_rms_from_floor(noise_floor(&psd_v), fs),
            rms_ma_u: ma(&u)?,
            rms_ma_v: ma(&v)?,
            psd_u,
            psd_v,
        });
    }
    // The largest mean speed anywhere in the field.
    let mut acc = GridAccumulator::new(spec);
    acc.add_all(samples);
    let g = estimate(
        &acc,
        &EstimateOptions {
            min_count: opt.min_count.max(1),
            ..EstimateOptions::default()
        },
    )?;
    let max_speed = g
        .bins
        .iter()
        .filter(|b| b.u.is_finite())
        .map(|b| b.u.hypot(b.v))
        .fold(0.0, f64::max);
    let mut floors: Vec<f64> = out
        .iter()
        .flat_map(|p| [p.noise_rms_u, p.noise_rms_v])
        .filter(|v| v.is_finite())
        .collect();
    floors.sort_by(|a, b| a.total_cmp(b));
    let noise_rms = floors.get(floors.len() / 2).copied().unwrap_or(f64::NAN);
    Ok(SpectraResult {
        frames,
        points: out,
        max_speed,
        noise_rms,
        dynamic_range: max_speed / noise_rms,
    })
}

/// `n` points evenly spaced on the segment from `a` to `b` (inclusive).
pub fn line_points(a: (f64, f64), b: (f64, f64), n: usize) -> Vec<(f64, f64)> {
    if n <= 1 {
        return vec![a];
    }
    (0..n)
        .map(|k| {
            let t = k as f64 / (n - 1) as f64;
            (a.0 + t * (b.0 - a.0), a.1 + t * (b.1 - a.1))
        })
        .collect()
}
