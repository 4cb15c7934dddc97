//! Welch PSD against a direct DFT, Parseval, known sine amplitudes, peak
//! interpolation, noise floor, moving-average rms.

use crate::spectra::*;
use rand::SeedableRng;
use rand_distr::{Distribution, Normal};
use std::f64::consts::PI;

/// Reference: the one-sided density of one Hann segment by a direct O(N²)
/// DFT, written straight from the definition.
fn direct_psd(x: &[f64], fs: f64) -> Vec<f64> {
    let n = x.len();
    let w = hann(n);
    let mean = x.iter().sum::<f64>() / n as f64;
    let s2: f64 = w.iter().map(|v| v * v).sum();
    (0..=n / 2)
        .map(|k| {
            let (mut re, mut im) = (0.0, 0.0);
            for (i, v) in x.iter().enumerate() {
                let ph = -2.0 * PI * (k * i) as f64 / n as f64;
                re += (v - mean) * w[i] * ph.cos();
                im += (v - mean) * w[i] * ph.sin();
            }
            let c = if k == 0 || k == n / 2 { 1.0 } else { 2.0 };
            c * (re * re + im * im) / (fs * s2)
        })
        .collect()
}

fn noise(n: usize, sigma: f64, seed: u64) -> Vec<f64> {
    let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
    let d = Normal::new(0.0, sigma).unwrap();
    (0..n).map(|_| d.sample(&mut rng)).collect()
}

#[ebptv_macros::unit_test]
fn fft_matches_direct_dft() {
    let fs = 1000.0;
    let x: Vec<f64> = noise(256, 1.0, 1)
        .iter()
        .enumerate()
        .map(|(i, v)| v + 3.0 * (2.0 * PI * 37.3 * i as f64 / fs).sin() + 5.0)
        .collect();
    let p = welch(
        &x,
        fs,
        &WelchOptions {
            nperseg: 256,
            overlap: 0.0,
        },
    )
    .unwrap();
    let r = direct_psd(&x, fs);
    assert_eq!(p.psd.len(), r.len());
    assert_eq!(p.n_segments, 1);
    let scale = r.iter().cloned().fold(0.0, f64::max);
    for (k, (a, b)) in p.psd.iter().zip(&r).enumerate() {
        assert!((a - b).abs() < 1e-10 * scale, "bin {k}: {a} vs {b}");
    }
    // Averaging: Welch over 3 non-overlapping segments = mean of 3 direct PSDs.
    let y = noise(768, 2.0, 2);
    let p3 = welch(
        &y,
        fs,
        &WelchOptions {
            nperseg: 256,
            overlap: 0.0,
        },
    )
    .unwrap();
    assert_eq!(p3.n_segments, 3);
    let refs: Vec<Vec<f64>> = (0..3)
        .map(|s| direct_psd(&y[s * 256..(s + 1) * 256], fs))
        .collect();
    for k in 0..p3.psd.len() {
        let m = (refs[0][k] + refs[1][k] + refs[2][k]) / 3.0;
        assert!((p3.psd[k] - m).abs() < 1e-10 * (1.0 + m));
    }
}

#[ebptv_macros::unit_test]
fn parseval_holds_per_segment_and_on_average() {
    let fs = 2000.0;
    let x = noise(512, 3.0, 3);
    let p = welch(
        &x,
        fs,
        &WelchOptions {
            nperseg: 512,
            overlap: 0.0,
        },
    )
    .unwrap();
    let w = hann(512);
    let mean = x.iter().sum::<f64>() / 512.0;
    let weighted_var = x
        .iter()
        .zip(&w)
        .map(|(v, w)| ((v - mean) * w).powi(2))
        .sum::<f64>()
        / w.iter().map(|w| w * w).sum::<f64>();
    assert!(
        (p.total_power() - weighted_var).abs() < 1e-10 * weighted_var,
        "{} vs {}",
        p.total_power(),
        weighted_var
    );
    // Long white noise: Welch total power ≈ σ², density ≈ 2σ²/fs everywhere.
    let y = noise(1 << 16, 3.0, 4);
    let q = welch(
        &y,
        fs,
        &WelchOptions {
            nperseg: 256,
            overlap: 0.5,
        },
    )
    .unwrap();
    assert!(
        (q.total_power() - 9.0).abs() < 0.03 * 9.0,
        "{}",
        q.total_power()
    );
    let floor = noise_floor(&q);
    assert!(
        (noise_rms_from_floor(floor, fs) - 3.0).abs() < 0.1 * 3.0,
        "floor rms {}",
        noise_rms_from_floor(floor, fs)
    );
}

#[ebptv_macros::unit_test]
fn sine_amplitude_and_frequency_are_recovered() {
    let fs = 1000.0;
    for &(a, f0) in &[(2.0, 35.4), (0.5, 125.0), (10.0, 7.81)] {
        let x: Vec<f64> = (0..8192)
            .map(|i| a * (2.0 * PI * f0 * i as f64 / fs + 0.3).sin())
            .collect();
        let p = welch(
            &x,
            fs,
            &WelchOptions {
                nperseg: 1024,
                overlap: 0.5,
            },
        )
        .unwrap();
        let pk = find_peak(&p, 1.0, 500.0).unwrap();
        let df = p.df();
        // Power in the main lobe ± 3 bins = A²/2 (Hann lobe is ±2 bins).
        let lobe: f64 = p.psd[pk.bin.saturating_sub(3)..=(pk.bin + 3)]
            .iter()
            .sum::<f64>()
            * df;
        assert!(
            (lobe - a * a / 2.0).abs() < 0.01 * a * a / 2.0,
            "A {a} f {f0}: {lobe} vs {}",
            a * a / 2.0
        );
        assert!(
            (pk.f_hz - f0).abs() < 0.1 * df,
            "f {f0}: peak {} (df {df})",
            pk.f_hz
        );
    }
}

#[ebptv_macros::unit_test]
fn moving_average_rms_measures_noise_under_a_slow_drift() {
    let x: Vec<f64> = noise(20_000, 2.0, 5)
        .iter()
        .enumerate()
        .map(|(i, v)| 100.0 + 30.0 * (i as f64 / 3000.0).sin() + v)
        .collect();
    let plain = {
        let m = x.iter().sum::<f64>() / x.len() as f64;
        (x.iter().map(|v| (v - m).powi(2)).sum::<f64>() / x.len() as f64).sqrt()
    };
    let r = rms_about_moving_average(&x, 25).unwrap();
    assert!(plain > 10.0);
    assert!((r - 2.0).abs() < 0.05 * 2.0, "{r}");
    assert!(rms_about_moving_average(&x, 1).is_err());
}
