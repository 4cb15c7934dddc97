//! Vortex shedding in a synthetic wake: the frequency found from binned
//! tracks within 1.5 Hz; the pre-multiplied spectrum peaks on the wake
//! centre line; noise floor and dynamic range reported.

use ebptv::grid::{Lattice, Sample, Weighting};
use ebptv::spectra::*;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal};
use std::f64::consts::PI;

/// A convected wave v = A(y) sin(2π f (t − x/U)) on a uniform stream U
/// (wavelength U/f ≈ 56 px, well above the 16 px bin),
/// A(y) Gaussian around the wake centre line y_c; particles live for 20
/// pulses; velocity noise `noise` px/s.
fn wake(f_shed: f64, noise: f64, seed: u64) -> Vec<Sample> {
    wake_sized(f_shed, noise, seed, 4096, 400)
}

fn wake_sized(f_shed: f64, noise: f64, seed: u64, n_pulses: usize, n_live: usize) -> Vec<Sample> {
    let (w, h, yc, u0, amp) = (256.0, 128.0, 64.0, 2000.0, 80.0);
    let period_us = 500.0; // 2 kHz pulses
    let life = 20;
    let mut rng = rand_pcg::Pcg64::seed_from_u64(seed);
    let nz = Normal::new(0.0, noise).unwrap();
    let mut out = Vec::with_capacity(n_pulses * n_live);
    // Particle state: (x, y, id, age); staggered ages.
    let mut parts: Vec<(f64, f64, u64, usize)> = (0..n_live)
        .map(|i| {
            (
                rng.gen::<f64>() * w,
                rng.gen::<f64>() * h,
                i as u64,
                i % life,
            )
        })
        .collect();
    let mut next_id = n_live as u64;
    for k in 0..n_pulses {
        let t = k as f64 * period_us * 1e-6;
        for p in parts.iter_mut() {
            if p.3 >= life || p.0 >= w {
                *p = (rng.gen::<f64>() * w, rng.gen::<f64>() * h, next_id, 0);
                next_id += 1;
            }
            let a = amp * (-((p.1 - yc) / 25.0).powi(2)).exp();
            let v = a * (2.0 * PI * f_shed * (t - p.0 / u0)).sin();
            out.push(Sample {
                x: p.0,
                y: p.1,
                u: u0 + nz.sample(&mut rng),
                v: v + nz.sample(&mut rng),
                t_us: k as f64 * period_us,
                track_id: p.2,
            });
            p.0 += u0 * period_us * 1e-6;
            p.1 += v * period_us * 1e-6;
            p.3 += 1;
        }
    }
    // tracks.csv groups rows by track.
    out.sort_by_key(|s| (s.track_id, s.t_us as i64));
    out
}

fn options() -> SpectraOptions {
    SpectraOptions {
        lattice: Lattice::new(16.0, 16.0, 0.0).unwrap(),
        weighting: Weighting::TopHat,
        every: 1,
        welch: WelchOptions {
            nperseg: 512,
            overlap: 0.5,
        },
        f_min: 2.0,
        f_max: 500.0,
        moving_average: Some(9),
        min_count: 10,
    }
}

#[test]
fn shedding_frequency_within_one_and_a_half_hertz() {
    let f_shed = 35.4;
    let s = wake(f_shed, 20.0, 1);
    let r = point_spectra(&s, &[(128.0, 64.0)], &options()).unwrap();
    assert!((r.frames.rate_hz() - 2000.0).abs() < 1e-6);
    let p = &r.points[0];
    let peak = p.peak.unwrap();
    eprintln!(
        "peak {:.2} Hz (true {f_shed}), gaps {:.3}, noise rms u {:.2} v {:.2}, max speed {:.1}, dynamic range {:.1}",
        peak.f_hz, p.gap_fraction, p.noise_rms_u, p.noise_rms_v, r.max_speed, r.dynamic_range
    );
    assert!((peak.f_hz - f_shed).abs() < 1.5, "{}", peak.f_hz);
    assert!((p.peak_v.unwrap().f_hz - f_shed).abs() < 1.5);
    // The bin-mean noise is 20 px/s / √(samples per bin per pulse ≈ 3):
    // the floor estimate must land near it (within a factor 1.5).
    let per_frame: f64 = 400.0 * 256.0 / (256.0 * 128.0);
    let expected = 20.0 / per_frame.sqrt();
    assert!(
        p.noise_rms_u > expected / 1.5 && p.noise_rms_u < expected * 1.5,
        "noise {} vs {expected}",
        p.noise_rms_u
    );
    assert!((r.dynamic_range - 2000.0 / r.noise_rms).abs() < 0.05 * r.dynamic_range);
    // u has no shedding: rms about the moving average is the noise.
    let ma = p.rms_ma_u.unwrap();
    assert!(
        ma > expected / 1.3 && ma < expected * 1.3,
        "moving-average rms {ma} vs {expected}"
    );
}

#[test]
fn premultiplied_spectrum_peaks_on_the_wake_centre_line() {
    let s = wake(35.4, 20.0, 2);
    let pts = line_points((128.0, 8.0), (128.0, 120.0), 8);
    let r = point_spectra(&s, &pts, &options()).unwrap();
    let k = r.points[0]
        .psd_v
        .f_hz
        .iter()
        .position(|&f| f >= 35.4)
        .unwrap();
    let fe: Vec<f64> = r
        .points
        .iter()
        .map(|p| p.psd_v.premultiplied()[k - 1].max(p.psd_v.premultiplied()[k]))
        .collect();
    let best = fe
        .iter()
        .enumerate()
        .max_by(|a, b| a.1.total_cmp(b.1))
        .unwrap()
        .0;
    eprintln!("f·E(f) at the shedding frequency along y: {fe:?}");
    assert!(
        (r.points[best].bin_y - 64.0).abs() <= 16.0,
        "peak at y {}",
        r.points[best].bin_y
    );
    assert!(fe[best] > 10.0 * fe[0]);
}

#[test]
fn bad_points_are_rejected() {
    let s = wake(35.4, 5.0, 3);
    assert!(point_spectra(&s, &[(5000.0, 10.0)], &options()).is_err());
    assert!(point_spectra(&s, &[], &options()).is_err());
}

/// Absurd run options are refused by name before any table is read: a
/// line of 10^8 points aborted on its allocation, and an empty or NaN peak
/// band reported "no significant peak".
#[test]
fn absurd_spectra_options_are_refused_by_name() {
    let ok = RunOptions {
        points: vec![(128.0, 64.0)],
        line: Some((128.0, 8.0, 128.0, 120.0)),
        ..RunOptions::default()
    };
    ok.validate().unwrap();
    type Change = fn(&mut RunOptions);
    let cases: [(Change, &str); 5] = [
        (|o| o.line_points = 100_000_000, "line-points"),
        (|o| o.every = 0, "every"),
        (|o| o.f_min = f64::NAN, "f-min"),
        (|o| o.f_max = 0.5, "f-max"),
        (|o| o.f_max = f64::NAN, "f-max"),
    ];
    for (change, name) in cases {
        let mut o = ok.clone();
        change(&mut o);
        let e = o.validate().unwrap_err().to_string();
        assert!(e.contains(name), "{name}: {e}");
    }
}

#[test]
fn spectra_command_writes_peak_hz() {
    let s = wake_sized(35.4, 10.0, 4, 2048, 200);
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let mut t = String::from("track_id,pulse,t_us,x,y,u,v\n");
    for p in &s {
        t.push_str(&format!(
            "{},{},{},{:.3},{:.3},{:.2},{:.2}\n",
            p.track_id,
            (p.t_us / 500.0) as i64,
            p.t_us,
            p.x,
            p.y,
            p.u,
            p.v
        ));
    }
    std::fs::write(d.join("tracks.csv"), t).unwrap();
    let out = d.join("sp");
    let o = std::process::Command::new(env!("CARGO_BIN_EXE_ebptv"))
        .args([
            "spectra",
            d.join("tracks.csv").to_str().unwrap(),
            "--point",
            "128,64",
            "--line",
            "128,8,128,120",
            "--line-points",
            "5",
        ])
        .args([
            "--nperseg",
            "512",
            "--moving-average",
            "9",
            "--out",
            out.to_str().unwrap(),
        ])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let j: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("spectrum.json")).unwrap()).unwrap();
    let peak = j["peak_hz"].as_f64().unwrap();
    assert!((peak - 35.4).abs() < 1.5, "{peak}");
    assert_eq!(j["peak_significant"], true);
    assert!(j["peak_false_alarm"].as_f64().unwrap() < 0.01);
    assert_eq!(j["false_alarm_level"], 0.01);
    assert!(j["dynamic_range"].as_f64().unwrap() > 10.0);
    assert!((j["fs_hz"].as_f64().unwrap() - 2000.0).abs() < 1e-6);
    let csv = std::fs::read_to_string(out.join("spectra.csv")).unwrap();
    assert!(csv.starts_with("f_hz,psd_u_0,psd_v_0\n"));
    assert_eq!(csv.lines().count(), 1 + 257);
    assert!(out.join("premultiplied_line.csv").exists() && out.join("spectrum_p0.png").exists());
}
