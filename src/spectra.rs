//! Power spectra of time-resolved fields (Welch; RustFFT plans from `ebptv-fft`).
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
//! pulse); `fill_gaps` interpolates them linearly and reports the fraction
//! filled. The noise floor is the median PSD over the top quarter of the
//! band, where a smooth flow has no energy left; white noise of variance σ²
//! has the one-sided density 2σ²/f_s, so σ = √(floor·f_s/2). The dynamic
//! velocity range is then the largest velocity over that noise rms.

use std::sync::Arc;

use ebptv_fft::{plan_f64, Complex, Direction, Fft};
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};

mod dir;
mod run;
pub use dir::{spectra_to_dir, SpectraDirOptions};
pub(crate) use run::run_on_samples;
pub use run::{run_on_tracks, Component, LineSpectra, RunOptions, SpectraRun};

/// Parameters of Welch's method.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[ebptv_macros::testkit]
pub(crate) struct WelchOptions {
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
    /// Frequencies (Hz), from 0 in steps of `Psd::df`.
    pub f_hz: Vec<f64>,
    /// Density in (unit)²/Hz.
    pub psd: Vec<f64>,
    /// Sampling frequency (Hz).
    pub fs_hz: f64,
    /// Welch segments averaged.
    pub n_segments: usize,
}

impl Psd {
    /// Frequency resolution (Hz); 0 with fewer than two frequencies.
    pub(crate) fn df(&self) -> f64 {
        if self.f_hz.len() > 1 {
            self.f_hz[1] - self.f_hz[0]
        } else {
            0.0
        }
    }
    /// Pre-multiplied spectrum f·E(f) (unit²): equal areas under a
    /// log-frequency axis mean equal energy.
    #[ebptv_macros::testkit]
    pub(crate) fn premultiplied(&self) -> Vec<f64> {
        self.f_hz
            .iter()
            .zip(&self.psd)
            .map(|(f, p)| f * p)
            .collect()
    }
    #[cfg(feature = "testkit")]
    /// ∫ P df (the variance the spectrum holds).
    pub(crate) fn total_power(&self) -> f64 {
        self.psd.iter().sum::<f64>() * self.df()
    }
}

/// Periodic Hann window (the spectral-analysis variant).
pub(crate) fn hann(n: usize) -> Vec<f64> {
    (0..n)
        .map(|i| 0.5 - 0.5 * (2.0 * std::f64::consts::PI * i as f64 / n as f64).cos())
        .collect()
}

/// Welch PSD of `x` sampled at `fs_hz`.
pub(crate) fn welch(x: &[f64], fs_hz: f64, opt: &WelchOptions) -> Result<Psd> {
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
    let fft: Arc<dyn Fft<f64>> = plan_f64(n, Direction::Forward);
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
    /// Index of the peak bin in `f_hz`.
    pub bin: usize,
}

/// The largest PSD value in `[f_min, f_max]` (DC excluded), its frequency
/// refined by a parabola through the logarithms of the three bins around it
/// (exact for a Gaussian-shaped lobe, close for the Hann main lobe). No
/// test of significance: see `significant_peak`.
pub(crate) fn find_peak(p: &Psd, f_min: f64, f_max: f64) -> Option<Peak> {
    let (mut best, mut k0) = (f64::NEG_INFINITY, None);
    for k in 1..p.psd.len() {
        if p.f_hz[k] >= f_min && p.f_hz[k] <= f_max && p.psd[k] > best {
            best = p.psd[k];
            k0 = Some(k);
        }
    }
    let k = k0?;
    Some(Peak {
        f_hz: refine(p, k),
        psd: best,
        bin: k,
    })
}

/// Frequency of bin `k` refined by the log-parabola through its neighbours.
fn refine(p: &Psd, k: usize) -> f64 {
    let mut f = p.f_hz[k];
    if k > 0 && k + 1 < p.psd.len() && p.psd[k - 1] > 0.0 && p.psd[k + 1] > 0.0 && p.psd[k] > 0.0 {
        let (a, b, c) = (p.psd[k - 1].ln(), p.psd[k].ln(), p.psd[k + 1].ln());
        let den = a - 2.0 * b + c;
        if den < 0.0 {
            let delta = (0.5 * (a - c) / den).clamp(-0.5, 0.5);
            f += delta * p.df();
        }
    }
    f
}

/// False-alarm probability at which a spectral peak is reported: the
/// chance that noise alone puts a peak this high anywhere in the band.
pub(crate) const PEAK_FALSE_ALARM: f64 = 0.01;

/// Result of `significant_peak`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PeakTest {
    /// The strongest local maximum that passes the test, if any.
    pub peak: Option<Peak>,
    /// False-alarm probability (corrected for the bins tested) of the
    /// reported peak, or of the most significant candidate when none
    /// passes.
    pub false_alarm: f64,
    /// The largest PSD value in the band, significant or not.
    pub strongest: Option<Peak>,
    /// Degrees of freedom the test used (see `significant_peak`).
    pub dof: f64,
}

/// Equivalent degrees of freedom of a Welch estimate (Welch 1967): the
/// `n_segments` periodograms of `nperseg` Hann-windowed samples, `step`
/// apart, are correlated where they overlap;
/// ν = 2K / (1 + 2 Σ_j (1 − j/K) ρ_j), ρ_j the squared normalised overlap
/// product of the window with itself shifted by j steps.
pub(crate) fn welch_dof(nperseg: usize, overlap: f64, n_segments: usize) -> f64 {
    let k = n_segments.max(1);
    let w = hann(nperseg);
    let s2: f64 = w.iter().map(|v| v * v).sum();
    let step = ((nperseg as f64 * (1.0 - overlap)).round() as usize).max(1);
    let mut corr = 0.0;
    for j in 1..k {
        let shift = j * step;
        if shift >= nperseg {
            break;
        }
        let c: f64 = (0..nperseg - shift)
            .map(|i| w[i] * w[i + shift])
            .sum::<f64>()
            / s2;
        corr += (1.0 - j as f64 / k as f64) * c * c;
    }
    2.0 * k as f64 / (1.0 + 2.0 * corr)
}

/// The spectral peak in `[f_min, f_max]` that stands above the noise at
/// false-alarm probability `alpha`.
///
/// Under noise alone each Welch bin is the local mean density S times
/// χ²_ν/ν. S at bin k is estimated from the median of the bins around it
/// (k±3 … k±(3+h), h = max(8, bins/16); the main lobe k±2 left out),
/// divided by the median of χ²_ν/ν. ν is the smaller of `dof` (Welch's
/// equivalent degrees of freedom, see [`welch_dof`]) and the value whose
/// χ² distribution reproduces the observed interquartile range of
/// ln(P_k / local median) over the spectrum: velocity series from binned
/// tracks are not Gaussian (particles entering and leaving a bin make
/// jumps), and their spectra scatter more than the segment count says.
/// A local maximum P_k has the tail probability p = P(χ²_ν > ν·P_k/S);
/// corrected for the N bins tested (Šidák: 1 − (1 − p)^N) it must fall
/// below `alpha`. Of the local maxima that pass, the strongest is reported.
pub(crate) fn significant_peak(p: &Psd, f_min: f64, f_max: f64, dof: f64, alpha: f64) -> PeakTest {
    let strongest = find_peak(p, f_min, f_max);
    let nf = p.psd.len();
    let h = (nf / 16).max(8);
    // Local median of every bin (DC and the main lobe left out).
    let local: Vec<Option<f64>> = (0..nf)
        .map(|k| {
            if k == 0 {
                return None;
            }
            let mut near: Vec<f64> = (k.saturating_sub(3 + h)..(k + 4 + h).min(nf))
                .filter(|&j| j >= 1 && j.abs_diff(k) >= 3)
                .map(|j| p.psd[j])
                .collect();
            if near.len() < 3 {
                return None;
            }
            let mid = near.len() / 2;
            let (_, m, _) = near.select_nth_unstable_by(mid, |a, b| a.total_cmp(b));
            (*m > 0.0).then_some(*m)
        })
        .collect();
    let mut logs: Vec<f64> = (1..nf)
        .filter_map(|k| {
            local[k]
                .filter(|_| p.psd[k] > 0.0)
                .map(|m| (p.psd[k] / m).ln())
        })
        .collect();
    let mut nu = dof;
    if logs.len() >= 8 {
        logs.sort_by(|a, b| a.total_cmp(b));
        let q = |f: f64| logs[((logs.len() - 1) as f64 * f).round() as usize];
        let iqr = q(0.75) - q(0.25);
        nu = nu.min(dof_from_log_iqr(iqr));
    }
    let band: Vec<usize> = (1..nf)
        .filter(|&k| p.f_hz[k] >= f_min && p.f_hz[k] <= f_max)
        .collect();
    let n_tested = band.len().max(1) as f64;
    let median_factor = chi2_quantile(0.5, nu) / nu;
    let mut best: Option<(usize, f64)> = None;
    let mut min_fa = 1.0f64;
    for &k in &band {
        let v = p.psd[k];
        let left = if k > 1 { p.psd[k - 1] } else { 0.0 };
        let right = if k + 1 < nf { p.psd[k + 1] } else { 0.0 };
        let Some(m) = local[k] else { continue };
        if !(v > 0.0 && v >= left && v >= right) {
            continue;
        }
        let floor = m / median_factor;
        let tail = chi2_sf(nu * v / floor, nu);
        let fa = -((n_tested * (-tail).ln_1p()).exp_m1());
        min_fa = min_fa.min(fa);
        if fa < alpha && best.is_none_or(|(b, _)| v > p.psd[b]) {
            best = Some((k, fa));
        }
    }
    PeakTest {
        peak: best.map(|(k, _)| Peak {
            f_hz: refine(p, k),
            psd: p.psd[k],
            bin: k,
        }),
        false_alarm: best.map_or(min_fa, |(_, fa)| fa),
        strongest,
        dof: nu,
    }
}

/// The degrees of freedom ν whose ln χ²_ν has interquartile range `iqr`
/// (bisection on log ν over [0.5, 10⁴]; the range shrinks as ν grows).
fn dof_from_log_iqr(iqr: f64) -> f64 {
    let spread = |nu: f64| (chi2_quantile(0.75, nu) / chi2_quantile(0.25, nu)).ln();
    let (mut lo, mut hi) = (0.5f64.ln(), 1e4f64.ln());
    if !(iqr.is_finite()) || iqr >= spread(0.5) {
        return 0.5;
    }
    for _ in 0..60 {
        let mid = 0.5 * (lo + hi);
        if spread(mid.exp()) > iqr {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    (0.5 * (lo + hi)).exp()
}

/// ln Γ(x), x > 0 (Lanczos, g = 7, 9 terms; ~1e-15 relative).
fn ln_gamma(x: f64) -> f64 {
    const C: [f64; 9] = [
        0.999_999_999_999_809_9,
        676.520_368_121_885_1,
        -1_259.139_216_722_402_8,
        771.323_428_777_653_1,
        -176.615_029_162_140_6,
        12.507_343_278_686_905,
        -0.138_571_095_265_720_12,
        9.984_369_578_019_572e-6,
        1.505_632_735_149_311_6e-7,
    ];
    if x < 0.5 {
        let pi = std::f64::consts::PI;
        return (pi / (pi * x).sin()).ln() - ln_gamma(1.0 - x);
    }
    let x = x - 1.0;
    let mut a = C[0];
    let t = x + 7.5;
    for (i, c) in C.iter().enumerate().skip(1) {
        a += c / (x + i as f64);
    }
    0.5 * (2.0 * std::f64::consts::PI).ln() + (x + 0.5) * t.ln() - t + a.ln()
}

/// Regularised upper incomplete gamma Q(a, x) (series below a + 1,
/// continued fraction above).
fn gamma_q(a: f64, x: f64) -> f64 {
    if x <= 0.0 {
        return 1.0;
    }
    let lead = -x + a * x.ln() - ln_gamma(a);
    if x < a + 1.0 {
        let (mut sum, mut term, mut n) = (1.0 / a, 1.0 / a, a);
        for _ in 0..1000 {
            n += 1.0;
            term *= x / n;
            sum += term;
            if term.abs() < sum.abs() * 1e-15 {
                break;
            }
        }
        (1.0 - sum * lead.exp()).clamp(0.0, 1.0)
    } else {
        // Modified Lentz.
        let tiny = 1e-300;
        let mut b = x + 1.0 - a;
        let mut c = 1.0 / tiny;
        let mut d = 1.0 / b;
        let mut h = d;
        for i in 1..1000 {
            let an = -(i as f64) * (i as f64 - a);
            b += 2.0;
            d = an * d + b;
            if d.abs() < tiny {
                d = tiny;
            }
            c = b + an / c;
            if c.abs() < tiny {
                c = tiny;
            }
            d = 1.0 / d;
            let del = d * c;
            h *= del;
            if (del - 1.0).abs() < 1e-15 {
                break;
            }
        }
        (lead.exp() * h).clamp(0.0, 1.0)
    }
}

/// P(χ²_ν > x).
pub(crate) fn chi2_sf(x: f64, nu: f64) -> f64 {
    gamma_q(nu / 2.0, x / 2.0)
}

/// The `q` quantile of χ²_ν (bisection on [`chi2_sf`]).
fn chi2_quantile(q: f64, nu: f64) -> f64 {
    let (mut lo, mut hi) = (0.0, nu + 20.0 * (2.0 * nu).sqrt() + 50.0);
    for _ in 0..100 {
        let m = 0.5 * (lo + hi);
        if chi2_sf(m, nu) > 1.0 - q {
            lo = m;
        } else {
            hi = m;
        }
    }
    0.5 * (lo + hi)
}

/// Noise floor: the median density over the top quarter of the band.
pub(crate) fn noise_floor(p: &Psd) -> f64 {
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
pub(crate) fn noise_rms_from_floor(floor: f64, fs_hz: f64) -> f64 {
    (floor * fs_hz / 2.0).sqrt()
}

/// Linear interpolation over NaN gaps (ends take the nearest value).
/// Returns the filled series and the fraction of samples that were missing;
/// an error when there is no valid sample at all.
pub(crate) fn fill_gaps(x: &[f64]) -> Result<(Vec<f64>, f64)> {
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
pub(crate) fn rms_about_moving_average(x: &[f64], n: usize) -> Result<f64> {
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

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;

    #[ebptv_macros::unit_test]
    fn fill_gaps_interpolates() {
        let (y, frac) = fill_gaps(&[f64::NAN, 1.0, f64::NAN, f64::NAN, 4.0, f64::NAN]).unwrap();
        assert_eq!(y, vec![1.0, 1.0, 2.0, 3.0, 4.0, 4.0]);
        assert!((frac - 4.0 / 6.0).abs() < 1e-12);
        assert!(fill_gaps(&[f64::NAN; 3]).is_err());
    }

    #[ebptv_macros::unit_test]
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
#[ebptv_macros::testkit]
pub(crate) struct SpectraOptions {
    /// The bins of the time-resolved grid.
    pub lattice: crate::grid::Lattice,
    /// How samples are weighted into the bins.
    pub weighting: crate::grid::Weighting,
    /// One frame every `every` pulses (sample periods).
    pub every: usize,
    /// Welch segment length and overlap.
    pub welch: WelchOptions,
    /// Peak search band (Hz).
    pub f_min: f64,
    /// Upper end of the peak search band (Hz).
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
    /// Requested point, y (px).
    pub y: f64,
    /// Centre of the bin used (px).
    pub bin_x: f64,
    /// Centre of the bin used, y (px).
    pub bin_y: f64,
    /// Spectrum of u ((px/s)²/Hz).
    pub psd_u: Psd,
    /// Spectrum of v ((px/s)²/Hz).
    pub psd_v: Psd,
    /// Significant peak (at `PEAK_FALSE_ALARM`) of the summed spectrum
    /// of u and v; `None` when no peak stands above the noise.
    pub peak: Option<Peak>,
    /// Significant peak of the u spectrum alone, if any.
    pub peak_u: Option<Peak>,
    /// Significant peak of the v spectrum alone, if any.
    pub peak_v: Option<Peak>,
    /// The test behind `peak` (false-alarm probability, strongest bin).
    pub peak_test: PeakTest,
    /// Welch's equivalent degrees of freedom of the estimates.
    pub dof: f64,
    /// Highest frequency the bin resolves at its mean velocity,
    /// |U|/(2b) with b the bin's extent along the flow (Hz); peaks are
    /// searched below it.
    pub f_resolved_hz: f64,
    /// Fraction of frames without a sample (filled by interpolation).
    pub gap_fraction: f64,
    /// Mean of u over the frames (px/s).
    pub mean_u: f64,
    /// Mean of v over the frames (px/s).
    pub mean_v: f64,
    /// RMS of u about its mean (px/s).
    pub rms_u: f64,
    /// RMS of v about its mean (px/s).
    pub rms_v: f64,
    /// RMS of the noise floor (px/s) per component.
    pub noise_rms_u: f64,
    /// RMS of the noise floor of v (px/s).
    pub noise_rms_v: f64,
    /// RMS of u about its moving average (px/s), when asked for.
    pub rms_ma_u: Option<f64>,
    /// RMS of v about its moving average (px/s), when asked for.
    pub rms_ma_v: Option<f64>,
}

impl PointSpectrum {
    /// Summed spectrum u + v.
    pub(crate) fn psd_sum(&self) -> Vec<f64> {
        self.psd_u
            .psd
            .iter()
            .zip(&self.psd_v.psd)
            .map(|(a, b)| a + b)
            .collect()
    }
}

/// Everything `point_spectra` found.
#[derive(Debug, Clone)]
pub struct SpectraResult {
    /// The time axis of the frames.
    pub frames: crate::grid::fields::Frames,
    /// The spectrum at each requested point, in order.
    pub points: Vec<PointSpectrum>,
    /// Largest mean speed over the grid's bins (px/s).
    pub max_speed: f64,
    /// Noise rms (px/s): the median over points of the per-component floors.
    pub noise_rms: f64,
    /// max_speed / noise_rms.
    pub dynamic_range: f64,
}

/// Spectra of the binned velocity time series at `points` (px).
#[ebptv_macros::testkit]
pub(crate) fn point_spectra(
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
        // The sum of the u and v estimates has between ν and 2ν degrees of
        // freedom; ν is the conservative choice.
        let dof = welch_dof(opt.welch.nperseg, opt.welch.overlap, psd_u.n_segments);
        let stats = |x: &[f64]| {
            let m = x.iter().sum::<f64>() / x.len() as f64;
            (
                m,
                (x.iter().map(|v| (v - m).powi(2)).sum::<f64>() / x.len() as f64).sqrt(),
            )
        };
        let (mean_u, rms_u) = stats(&u);
        let (mean_v, rms_v) = stats(&v);
        // Resolved band: a pattern carried through the bin at the mean
        // velocity is averaged over the bin's extent along the flow, b; a
        // wavelength |U|/f shorter than 2b is not resolved (and particles
        // crossing the bin make artefacts there), so f ≤ |U|/(2b).
        let speed = mean_u.hypot(mean_v);
        let f_resolved = if speed > 0.0 {
            let b = (mean_u.abs() * opt.lattice.bin_w + mean_v.abs() * opt.lattice.bin_h) / speed;
            (speed / (2.0 * b)).min(fs / 2.0)
        } else {
            fs / 2.0
        };
        let f_top = opt.f_max.min(f_resolved);
        let test = significant_peak(&sum, opt.f_min, f_top, dof, PEAK_FALSE_ALARM);
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
            peak: test.peak,
            peak_u: significant_peak(&psd_u, opt.f_min, f_top, dof, PEAK_FALSE_ALARM).peak,
            peak_v: significant_peak(&psd_v, opt.f_min, f_top, dof, PEAK_FALSE_ALARM).peak,
            f_resolved_hz: f_resolved,
            peak_test: test,
            dof,
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
#[ebptv_macros::testkit]
pub(crate) fn line_points(a: (f64, f64), b: (f64, f64), n: usize) -> Vec<(f64, f64)> {
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

#[cfg(feature = "testkit")]
pub(crate) mod significance_tests {
    use super::*;

    #[ebptv_macros::unit_test]
    fn chi_square_tail_matches_closed_forms() {
        // ν = 2: P(χ² > x) = exp(−x/2); ν = 1 at 3.841: 0.05; ν = 10 at 23.209: 0.01.
        for x in [0.1, 1.0, 5.0, 20.0] {
            assert!((chi2_sf(x, 2.0) - (-x / 2.0).exp()).abs() < 1e-12);
        }
        assert!((chi2_sf(3.841_458_820_694_124, 1.0) - 0.05).abs() < 1e-9);
        assert!((chi2_sf(23.209_251_158_954_36, 10.0) - 0.01).abs() < 1e-9);
        assert!((chi2_quantile(0.5, 2.0) - 2.0 * std::f64::consts::LN_2).abs() < 1e-9);
        // The interquartile range of ln χ²_ν is inverted.
        let iqr = (chi2_quantile(0.75, 7.0) / chi2_quantile(0.25, 7.0)).ln();
        assert!((dof_from_log_iqr(iqr) - 7.0).abs() < 1e-3);
    }

    #[ebptv_macros::unit_test]
    fn welch_dof_of_hann_half_overlap() {
        // One segment: 2; many: ≈ 2K/(1 + 2·(1/6)²) (Welch's ratio).
        assert!((welch_dof(256, 0.5, 1) - 2.0).abs() < 1e-12);
        let d = welch_dof(256, 0.5, 100);
        let expect = 200.0 / (1.0 + 2.0 * 0.99 / 36.0);
        assert!((d - expect).abs() < 0.05 * expect, "{d} vs {expect}");
    }

    /// White noise: no significant peak in (nearly) every realisation, the
    /// false-alarm rate near the stated level; a sine well above the
    /// noise is found.
    #[ebptv_macros::unit_test]
    fn significance_of_peaks_in_white_noise() {
        use rand::SeedableRng;
        use rand_distr::{Distribution, Normal};
        let opt = WelchOptions {
            nperseg: 128,
            overlap: 0.5,
        };
        let nz = Normal::new(0.0, 1.0).unwrap();
        let mut alarms = 0;
        let runs = 300;
        for seed in 0..runs {
            let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
            let x: Vec<f64> = (0..1024).map(|_| nz.sample(&mut rng)).collect();
            let p = welch(&x, 1000.0, &opt).unwrap();
            let dof = welch_dof(128, 0.5, p.n_segments);
            let t = significant_peak(&p, 1.0, 500.0, dof, PEAK_FALSE_ALARM);
            assert!(t.strongest.is_some());
            if t.peak.is_some() {
                alarms += 1;
            }
        }
        // Expected 1 % (3 of 300); the median floor is itself noisy, so
        // allow up to 4 %.
        assert!(alarms <= 12, "{alarms} false alarms in {runs}");
        let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
        let x: Vec<f64> = (0..1024)
            .map(|i| {
                nz.sample(&mut rng)
                    + 0.8 * (2.0 * std::f64::consts::PI * 123.0 * i as f64 / 1000.0).sin()
            })
            .collect();
        let p = welch(&x, 1000.0, &opt).unwrap();
        let t = significant_peak(&p, 1.0, 500.0, welch_dof(128, 0.5, p.n_segments), 0.01);
        let pk = t.peak.expect("the sine is significant");
        assert!((pk.f_hz - 123.0).abs() < 3.0, "{}", pk.f_hz);
        assert!(t.false_alarm < 1e-6);
    }
}
