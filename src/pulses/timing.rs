//! Pulse-train timing: least-squares fit of recorded triggers, and the
//! estimate of the period from the events themselves (periodogram with a
//! harmonic sum, refined by epoch folding), plus the small signal helpers
//! (circular cross-correlation, weighted line fit) the streaming solver uses.

use std::collections::BTreeMap;

use ebptv_fft::{plan_f32, plan_f64, Complex, Direction, Fft};
use serde::{Deserialize, Serialize};

use super::accum::Fold;
use crate::error::{Error, Result};

/// Rising and falling trigger edges of one channel, in stream order.
#[derive(Debug, Clone, Default)]
pub(crate) struct ChannelEdges {
    pub rising: Vec<i64>,
    pub falling: Vec<i64>,
}

/// What was seen on one trigger channel.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct ChannelSummary {
    pub channel: u8,
    pub rising: u64,
    pub falling: u64,
    /// Median interval between rising edges (µs), when ≥ 2 rising edges.
    pub median_interval_us: Option<f64>,
    /// Fraction of rising-edge intervals within 10 % of an integer multiple
    /// of the median interval: 1 for a clean pulse train.
    pub regularity: f64,
}

/// Summarise every channel (sorted by channel id).
pub(crate) fn summarize_channels(channels: &BTreeMap<u8, ChannelEdges>) -> Vec<ChannelSummary> {
    channels
        .iter()
        .map(|(&channel, e)| {
            let mut diffs: Vec<f64> = e
                .rising
                .windows(2)
                .map(|w| (w[1] - w[0]) as f64)
                .filter(|d| *d > 0.0)
                .collect();
            let median = median_f64(&mut diffs);
            let regularity = match median {
                Some(m) if m > 0.0 => {
                    let ok = diffs
                        .iter()
                        .filter(|d| {
                            let r = **d / m;
                            r >= 0.5 && (r - r.round()).abs() < 0.1
                        })
                        .count();
                    ok as f64 / diffs.len().max(1) as f64
                }
                _ => 0.0,
            };
            ChannelSummary {
                channel,
                rising: e.rising.len() as u64,
                falling: e.falling.len() as u64,
                median_interval_us: median,
                regularity,
            }
        })
        .collect()
}

/// True when a channel carries a usable pulse train.
pub(crate) fn is_regular(s: &ChannelSummary) -> bool {
    s.rising >= 4 && s.regularity >= 0.5
}

/// Human-readable list of what the trigger channels hold (error messages).
pub(crate) fn describe_channels(summaries: &[ChannelSummary]) -> String {
    if summaries.is_empty() {
        return "the recording holds no trigger events".into();
    }
    let parts: Vec<String> = summaries
        .iter()
        .map(|s| match s.median_interval_us {
            Some(m) => format!(
                "channel {}: {} rising / {} falling edges, {} at ~{:.1} Hz",
                s.channel,
                s.rising,
                s.falling,
                if is_regular(s) {
                    "a regular train"
                } else {
                    "irregular"
                },
                1e6 / m
            ),
            None => format!(
                "channel {}: {} rising / {} falling edges",
                s.channel, s.rising, s.falling
            ),
        })
        .collect();
    parts.join("; ")
}

/// Result of fitting `t = first + n · period` to the rising trigger edges.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct TriggerFit {
    pub channel: u8,
    pub period_us: f64,
    /// Fitted start of the pulse numbered 0 (the first kept rising edge).
    pub first_us: f64,
    /// Pulse number of the last kept edge.
    pub last_number: i64,
    pub rising_used: u64,
    /// Pulses of the train with no rising edge recorded.
    pub missing: u64,
    /// Rising edges that do not fit the train (duplicates, glitches).
    pub spurious: u64,
    pub falling: u64,
    /// RMS residual of the fit (µs): the trigger timing jitter.
    pub residual_rms_us: f64,
    /// Median pulse width from falling edges (µs).
    pub width_us: Option<f64>,
}

/// Fit a regular train to rising edges, numbering pulses by integers so a
/// missing trigger leaves a gap instead of shifting the numbering, and a
/// spurious edge (not near an integer number of periods after the last kept
/// one) is dropped and counted.
pub(crate) fn fit_trigger_train(channel: u8, edges: &ChannelEdges) -> Result<TriggerFit> {
    let rising = &edges.rising;
    if rising.len() < 3 {
        return Err(Error::analysis(format!(
            "trigger channel {channel}: only {} rising edges, need at least 3 to fit a pulse train",
            rising.len()
        )));
    }
    let mut diffs: Vec<f64> = rising
        .windows(2)
        .map(|w| (w[1] - w[0]) as f64)
        .filter(|d| *d > 0.0)
        .collect();
    let p0 = median_f64(&mut diffs).filter(|p| *p > 0.0).ok_or_else(|| {
        Error::analysis(format!(
            "trigger channel {channel}: rising edges carry no interval"
        ))
    })?;
    // Start at the first edge whose next interval looks like one period, so a
    // glitch at the very start cannot poison the numbering.
    let start = (0..rising.len() - 1)
        .find(|&i| ((rising[i + 1] - rising[i]) as f64 / p0 - 1.0).abs() < 0.1)
        .unwrap_or(0);
    let mut spurious = start as u64;
    let mut ns: Vec<i64> = vec![0];
    let mut ts: Vec<i64> = vec![rising[start]];
    let mut period = p0;
    let mut missing = 0u64;
    for &t in &rising[start + 1..] {
        let last_t = *ts.last().unwrap();
        let r = (t - last_t) as f64 / period;
        let k = r.round();
        if k < 1.0 || (r - k).abs() > 0.25 {
            spurious += 1;
            continue;
        }
        missing += k as u64 - 1;
        let n = ns.last().unwrap() + k as i64;
        ns.push(n);
        ts.push(t);
        if n >= 8 {
            period = (t - ts[0]) as f64 / n as f64;
        }
    }
    // Least squares, then one pass of outlier rejection (late edges).
    let mut keep = vec![true; ns.len()];
    let mut fit = line_fit(&ns, &ts, &keep);
    let rms = fit.2;
    let limit = (5.0 * rms).max(3.0);
    let mut rejected = 0u64;
    for i in 0..ns.len() {
        let res = ts[i] as f64 - (fit.0 + fit.1 * ns[i] as f64);
        if res.abs() > limit {
            keep[i] = false;
            rejected += 1;
        }
    }
    if rejected > 0 && keep.iter().filter(|k| **k).count() >= 3 {
        fit = line_fit(&ns, &ts, &keep);
    }
    let (a, b, rms) = fit;
    // Pulse widths: falling edge minus the preceding rising edge, if it lies
    // within one period.
    let mut widths = Vec::new();
    let mut j = 0usize;
    for &f in &edges.falling {
        while j + 1 < rising.len() && rising[j + 1] <= f {
            j += 1;
        }
        if j < rising.len() && rising[j] <= f {
            let w = (f - rising[j]) as f64;
            if w > 0.0 && w < b {
                widths.push(w);
            }
        }
    }
    Ok(TriggerFit {
        channel,
        period_us: b,
        first_us: a,
        last_number: *ns.last().unwrap(),
        rising_used: ns.len() as u64 - rejected,
        missing,
        spurious: spurious + rejected,
        falling: edges.falling.len() as u64,
        residual_rms_us: rms,
        width_us: median_f64(&mut widths),
    })
}

/// Unweighted least-squares line `t = a + b n` over the kept points;
/// returns (a, b, rms residual).
fn line_fit(ns: &[i64], ts: &[i64], keep: &[bool]) -> (f64, f64, f64) {
    // Centre the data: trigger times are ~1e10 µs and numbers ~1e5, so the
    // raw normal equations would lose digits.
    let idx: Vec<usize> = (0..ns.len()).filter(|&i| keep[i]).collect();
    let m = idx.len() as f64;
    let n0 = ns[idx[0]];
    let t0 = ts[idx[0]];
    let mn = idx.iter().map(|&i| (ns[i] - n0) as f64).sum::<f64>() / m;
    let mt = idx.iter().map(|&i| (ts[i] - t0) as f64).sum::<f64>() / m;
    let mut sxx = 0.0;
    let mut sxy = 0.0;
    for &i in &idx {
        let dx = (ns[i] - n0) as f64 - mn;
        let dy = (ts[i] - t0) as f64 - mt;
        sxx += dx * dx;
        sxy += dx * dy;
    }
    let b = if sxx > 0.0 { sxy / sxx } else { 0.0 };
    // t = t0 + mt + b (n - n0 - mn)
    let a = t0 as f64 + mt - b * (n0 as f64 + mn);
    let mut ss = 0.0;
    for &i in &idx {
        let r = ts[i] as f64 - (a + b * ns[i] as f64);
        ss += r * r;
    }
    (a, b, (ss / m).sqrt())
}

/// Weighted least-squares line `y = a + b x`; returns (a, b, weighted rms).
pub(crate) fn weighted_line_fit(x: &[f64], y: &[f64], w: &[f64]) -> (f64, f64, f64) {
    let sw: f64 = w.iter().sum();
    if sw <= 0.0 || x.is_empty() {
        return (0.0, 0.0, 0.0);
    }
    let mx = x.iter().zip(w).map(|(a, b)| a * b).sum::<f64>() / sw;
    let my = y.iter().zip(w).map(|(a, b)| a * b).sum::<f64>() / sw;
    let mut sxx = 0.0;
    let mut sxy = 0.0;
    for i in 0..x.len() {
        sxx += w[i] * (x[i] - mx) * (x[i] - mx);
        sxy += w[i] * (x[i] - mx) * (y[i] - my);
    }
    let b = if sxx > 0.0 { sxy / sxx } else { 0.0 };
    let a = my - b * mx;
    let ss: f64 = (0..x.len())
        .map(|i| w[i] * (y[i] - a - b * x[i]).powi(2))
        .sum();
    (a, b, (ss / sw).sqrt())
}

/// Periodicity found in an event-rate series.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct Periodicity {
    pub period_us: f64,
    /// Power at the fundamental over the median power of the searched band.
    pub snr: f64,
    /// Harmonic whose peak refined the frequency.
    pub harmonic: u32,
}

/// Minimum periodogram SNR of a genuine pulse train. Poisson noise alone
/// gives an exponential power distribution: its maximum over ~1e5 bins is
/// ~12 × the mean (~17 × the median); pulsed recordings reach thousands.
pub(crate) const MIN_SNR: f64 = 60.0;

const HARMONICS_IN_SUM: usize = 5;
const MAX_REFINE_HARMONIC: usize = 16;

fn too_few(n: f64) -> Error {
    Error::analysis(format!(
        "only {n} events: too few to estimate the pulse period"
    ))
}

/// The pulse period (periodogram, harmonic sum, epoch folding) of an event-rate series: `counts[i]` events in the
/// µs `i` (the streaming pass builds it from its time runs, without
/// keeping event times).
pub(crate) fn estimate_period_from_counts(
    counts: &[f32],
    range_hz: (f64, f64),
) -> Result<Periodicity> {
    let total: f64 = counts.iter().map(|&c| c as f64).sum();
    if total < 100.0 {
        return Err(too_few(total));
    }
    let span = counts.len();
    let n = span.next_power_of_two().max(1024);
    let nyquist_hz = 0.5e6;
    let df = 1e6 / n as f64;
    let (lo_hz, hi_hz) = range_hz;
    if hi_hz * 2.0 > nyquist_hz || lo_hz <= 0.0 || lo_hz > hi_hz {
        return Err(Error::param(
            "pulse_hz_range",
            format!("{lo_hz}..{hi_hz} Hz is outside 0..250 kHz or empty"),
        ));
    }
    let min_cycles = 4.0;
    if (span as f64) < min_cycles * 1e6 / lo_hz {
        return Err(Error::analysis(format!(
            "the events span only {span} µs: fewer than {min_cycles} pulse periods at {lo_hz:.0} Hz"
        )));
    }
    let mean = (total / span as f64) as f32;
    let mut buf: Vec<Complex<f32>> = counts
        .iter()
        .map(|&c| Complex::new(c - mean, 0.0))
        .collect();
    buf.resize(n, Complex::new(0.0, 0.0));
    plan_f32(n, Direction::Forward).process(&mut buf);
    let power: Vec<f64> = buf[..n / 2].iter().map(|c| c.norm_sqr() as f64).collect();
    drop(buf);

    let band = |lo: f64, hi: f64| -> Option<(usize, f64, f64)> {
        let kmin = ((lo / df).floor() as usize).max(1);
        let kmax = ((hi / df).ceil() as usize).min(power.len() / HARMONICS_IN_SUM - 1);
        if kmin > kmax {
            return None;
        }
        let mut best = (kmin, f64::MIN);
        for k in kmin..=kmax {
            let mut s = 0.0;
            for h in 1..=HARMONICS_IN_SUM {
                s += max_around(&power, h * k, h / 2);
            }
            if s > best.1 {
                best = (k, s);
            }
        }
        // Fundamental: strongest bin at the chosen spot.
        let k = (best.0.saturating_sub(1)..=best.0 + 1)
            .max_by(|&a, &b| power[a].total_cmp(&power[b]))
            .unwrap();
        // The noise level around the band: a narrow band (±2 % of a short
        // recording) holds few bins, mostly the peak's own sidelobes.
        let lo = kmin.saturating_sub(64).max(1);
        let hi = (kmax + 64).min(power.len() - 1);
        let mut band_pow: Vec<f64> = power[lo..=hi].to_vec();
        let med = median_f64(&mut band_pow).unwrap_or(0.0).max(1e-12);
        Some((k, power[k] / med, med))
    };
    let found = band(lo_hz, hi_hz);
    let ok = matches!(found, Some((_, snr, _)) if snr >= MIN_SNR);
    if !ok {
        // Say what is there instead.
        let global = band(
            200.0,
            100_000.0f64.min(nyquist_hz / HARMONICS_IN_SUM as f64),
        );
        let here = found.map(|f| f.1).unwrap_or(0.0);
        return Err(match global {
            Some((k, snr, _)) if snr >= MIN_SNR => Error::analysis(format!(
                "no pulse train between {lo_hz:.1} and {hi_hz:.1} Hz (periodogram SNR {here:.1}); the strongest periodicity of the event rate is at {:.1} Hz (SNR {snr:.0}): check --pulse-hz / --pulse-hz-range",
                k as f64 * df
            )),
            Some((k, snr, _)) => Error::analysis(format!(
                "no pulses detectable: the event rate shows no periodicity between {lo_hz:.1} and {hi_hz:.1} Hz (SNR {here:.1}) nor anywhere in 200 Hz..100 kHz (best {:.1} Hz, SNR {snr:.1} < {MIN_SNR}): continuous illumination, or a saturated readout?",
                k as f64 * df
            )),
            None => Error::analysis("no pulses detectable: too few data to search a periodicity"),
        });
    }
    let (k1, snr, med) = found.unwrap();
    // Refine on the highest strong harmonic: relative resolution improves h-fold.
    let mut h_best = 1usize;
    let mut k_h = k1 as f64;
    for h in (2..=MAX_REFINE_HARMONIC).rev() {
        let centre = h * k1;
        if centre + h >= power.len() {
            continue;
        }
        let (kp, pp) = argmax_around(&power, centre, h);
        if pp >= 0.25 * power[k1] && pp > MIN_SNR * med {
            h_best = h;
            k_h = kp as f64
                + parabolic_offset(power[kp - 1].sqrt(), power[kp].sqrt(), power[kp + 1].sqrt());
            break;
        }
    }
    if h_best == 1 {
        k_h = k1 as f64
            + parabolic_offset(power[k1 - 1].sqrt(), power[k1].sqrt(), power[k1 + 1].sqrt());
    }
    let f = k_h * df / h_best as f64;
    let p = 1e6 / f;
    // Epoch folding around the estimate: the uncertainty is ~ one
    // resolution cell of the harmonic.
    let dp = p * p * df / h_best as f64 / 1e6;
    let nz: Vec<(i64, f32)> = counts
        .iter()
        .enumerate()
        .filter(|(_, c)| **c > 0.0)
        .map(|(i, c)| (i as i64, *c))
        .collect();
    let steps = 40;
    let mut grid = Vec::with_capacity(steps + 1);
    for s in 0..=steps {
        let pp = p - 2.0 * dp + 4.0 * dp * s as f64 / steps as f64;
        grid.push((pp, fold_variance(&nz, pp)));
    }
    let (ib, _) = grid
        .iter()
        .enumerate()
        .max_by(|a, b| a.1 .1.total_cmp(&b.1 .1))
        .unwrap();
    let period = if ib > 0 && ib < steps {
        let step = grid[1].0 - grid[0].0;
        grid[ib].0 + step * parabolic_offset(grid[ib - 1].1, grid[ib].1, grid[ib + 1].1)
    } else {
        grid[ib].0
    };
    Ok(Periodicity {
        period_us: period,
        snr,
        harmonic: h_best as u32,
    })
}

/// Variance of the series folded at `period` (2 µs fold bins): the epoch
/// folding statistic, maximal at the true period. The fold bin of sample
/// `i` is that of its centre `i + ½` ([`Fold::bin`], fixed-point: no float
/// floor per sample, which was half the warm-up's time).
fn fold_variance(nz: &[(i64, f32)], period: f64) -> f64 {
    let nb = ((period / 2.0).round() as usize).max(8);
    let fold = Fold::new(0, period, nb);
    let mut h = vec![0f64; nb];
    for &(t, c) in nz {
        h[fold.bin(t)] += c as f64;
    }
    variance(&h)
}

fn variance(h: &[f64]) -> f64 {
    let nb = h.len() as f64;
    let m = h.iter().sum::<f64>() / nb;
    h.iter().map(|v| (v - m) * (v - m)).sum::<f64>() / nb
}

fn max_around(p: &[f64], k: usize, r: usize) -> f64 {
    argmax_around(p, k, r).1
}

fn argmax_around(p: &[f64], k: usize, r: usize) -> (usize, f64) {
    let lo = k.saturating_sub(r).max(1);
    let hi = (k + r).min(p.len() - 2);
    let mut best = (lo, f64::MIN);
    for (i, &v) in p.iter().enumerate().take(hi + 1).skip(lo) {
        if v > best.1 {
            best = (i, v);
        }
    }
    best
}

/// Offset in (-0.5, 0.5) of the vertex of the parabola through three
/// equally spaced samples around a maximum.
pub(crate) fn parabolic_offset(a: f64, b: f64, c: f64) -> f64 {
    let den = a - 2.0 * b + c;
    if den.abs() < 1e-300 {
        return 0.0;
    }
    (0.5 * (a - c) / den).clamp(-0.5, 0.5)
}

/// Median of a slice (reorders it); `None` when empty.
pub(crate) fn median_f64(v: &mut [f64]) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    let mid = v.len() / 2;
    let (_, m, _) = v.select_nth_unstable_by(mid, |a, b| a.total_cmp(b));
    Some(*m)
}

/// Circular cross-correlation of histograms against a template, via FFT.
pub(crate) struct CircularCorrelator {
    n: usize,
    template_conj: Vec<Complex<f64>>,
    fwd: std::sync::Arc<dyn Fft<f64>>,
    inv: std::sync::Arc<dyn Fft<f64>>,
}

impl CircularCorrelator {
    pub(crate) fn new(template: &[f64]) -> Self {
        let n = template.len();
        let fwd = plan_f64(n, Direction::Forward);
        let inv = plan_f64(n, Direction::Inverse);
        let mean = template.iter().sum::<f64>() / n as f64;
        let mut t: Vec<Complex<f64>> = template
            .iter()
            .map(|&v| Complex::new(v - mean, 0.0))
            .collect();
        fwd.process(&mut t);
        for c in &mut t {
            *c = c.conj();
        }
        CircularCorrelator {
            n,
            template_conj: t,
            fwd,
            inv,
        }
    }

    /// Shift `s` (bins, fractional, in [0, n)) such that `hist[j] ≈
    /// template[j - s]`, and the correlation peak's height.
    pub(crate) fn shift_of(&self, hist: &[f64]) -> (f64, f64) {
        let n = self.n;
        let mean = hist.iter().sum::<f64>() / n as f64;
        let mut h: Vec<Complex<f64>> = hist.iter().map(|&v| Complex::new(v - mean, 0.0)).collect();
        self.fwd.process(&mut h);
        for (a, b) in h.iter_mut().zip(&self.template_conj) {
            *a *= b;
        }
        self.inv.process(&mut h);
        let c: Vec<f64> = h.iter().map(|z| z.re).collect();
        let (k, _) = c
            .iter()
            .enumerate()
            .max_by(|a, b| a.1.total_cmp(b.1))
            .unwrap();
        let off = parabolic_offset(c[(k + n - 1) % n], c[k], c[(k + 1) % n]);
        ((k as f64 + off).rem_euclid(n as f64), c[k])
    }
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;

    /// Direct O(n²) circular correlation: the oracle for the FFT path.
    fn direct_shift(hist: &[f64], template: &[f64]) -> usize {
        let n = hist.len();
        (0..n)
            .max_by(|&a, &b| {
                let ca: f64 = (0..n).map(|j| hist[(j + a) % n] * template[j]).sum();
                let cb: f64 = (0..n).map(|j| hist[(j + b) % n] * template[j]).sum();
                ca.total_cmp(&cb)
            })
            .unwrap()
    }

    /// The fixed-point epoch folding against the float definition
    /// (fold phase of the sample centre `(i + ½) / P`).
    #[ebptv_macros::unit_test]
    fn fold_variance_matches_float_reference() {
        let mut s: u64 = 7;
        let nz: Vec<(i64, f32)> = (0..50_000i64)
            .map(|i| {
                s = s
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                (i * 3 + (s >> 62) as i64, 1.0 + ((s >> 40) % 7) as f32)
            })
            .collect();
        for period in [100.0, 199.9931, 50.0007, 37.51] {
            let nb = ((period / 2.0f64).round() as usize).max(8);
            let mut h = vec![0f64; nb];
            for &(t, c) in &nz {
                let ph = (t as f64 + 0.5) / period;
                let b = (((ph - ph.floor()) * nb as f64) as usize).min(nb - 1);
                h[b] += c as f64;
            }
            let (fast, slow) = (fold_variance(&nz, period), variance(&h));
            assert!(
                (fast - slow).abs() <= 1e-9 * slow,
                "{period}: {fast} vs {slow}"
            );
        }
    }

    #[ebptv_macros::unit_test]
    fn fft_correlation_matches_direct() {
        let n = 97;
        let template: Vec<f64> = (0..n)
            .map(|j| (-(((j as f64) - 20.0) / 4.0).powi(2)).exp() + 0.1)
            .collect();
        for shift in [0usize, 5, 33, 90] {
            let hist: Vec<f64> = (0..n)
                .map(|j| template[(j + n - shift) % n] * 3.0)
                .collect();
            let c = CircularCorrelator::new(&template);
            let (s, _) = c.shift_of(&hist);
            assert_eq!(direct_shift(&hist, &template), shift);
            assert!(
                (s - shift as f64).abs() < 0.05 || (s - shift as f64).abs() > n as f64 - 0.05,
                "{s} vs {shift}"
            );
        }
    }

    #[ebptv_macros::unit_test]
    fn trigger_fit_handles_missing_and_spurious() {
        let p = 100.003;
        let mut rising = Vec::new();
        for k in 0..5000i64 {
            if k % 97 == 5 {
                continue; // missing
            }
            rising.push((1000.0 + k as f64 * p).round() as i64);
            if k % 211 == 7 {
                rising.push((1000.0 + k as f64 * p + 37.0).round() as i64); // glitch
            }
        }
        let e = ChannelEdges {
            rising,
            falling: vec![],
        };
        let f = fit_trigger_train(1, &e).unwrap();
        assert!((f.period_us - p).abs() < 1e-4, "{}", f.period_us);
        assert!((f.first_us - 1000.0).abs() < 0.5);
        assert_eq!(f.missing, (0..5000).filter(|k| k % 97 == 5).count() as u64);
        assert_eq!(
            f.spurious,
            (0..5000).filter(|k| k % 211 == 7 && k % 97 != 5).count() as u64
        );
    }
}
