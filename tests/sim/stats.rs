//! Seed-to-seed statistics of the calibrated presets: the table that a
//! change of the random stream is judged by (BENCHMARKS.md "## Simulator").
//! Not a test (no assertion; the calibration tests hold the
//! thresholds): `cargo test --release --test integration -- --ignored sim::stats::
//! --nocapture` prints one line `STAT <name> <seed> <value>` per statistic
//! and seed, to be compared between two builds (mean and seed-to-seed
//! standard deviation per statistic).

use ebptv::events::{OFF, ON};
use ebptv::sim::scenario::OffEvents;
use ebptv::sim::{presets, simulate, Scenario, SimOutput};

/// Folded histogram of event time after the latest pulse start, 1 µs bins.
fn folded(out: &SimOutput, period: f64) -> Vec<f64> {
    let first = out.pulse_starts_us[0];
    let n = period.ceil() as usize;
    let mut h = vec![0.0; n];
    for &t in &out.events.t {
        let rel = t as f64 + 0.5 - first;
        if rel < 0.0 {
            continue;
        }
        let ph = rel - (rel / period).floor() * period;
        h[(ph as usize).min(n - 1)] += 1.0;
    }
    h
}

/// (peak, FWHM, flatness) of the folded histogram, 5 µs moving average
/// (as tests/sim_calibration.rs).
fn burst(out: &SimOutput, period: f64) -> (f64, f64, f64) {
    let h = folded(out, period);
    let n = h.len();
    let sm: Vec<f64> = (0..n)
        .map(|i| {
            (i.saturating_sub(2)..(i + 3).min(n))
                .map(|j| h[j])
                .sum::<f64>()
                / 5.0
        })
        .collect();
    let (ip, &mx) = sm
        .iter()
        .enumerate()
        .max_by(|a, b| a.1.total_cmp(b.1))
        .unwrap();
    let above: Vec<usize> = (0..n).filter(|&i| sm[i] >= mx / 2.0).collect();
    let fwhm = (above.last().unwrap() - above.first().unwrap() + 1) as f64;
    let mn = sm.iter().cloned().fold(f64::INFINITY, f64::min);
    (ip as f64, fwhm, mn / mx)
}

/// Mean, standard deviation and skewness of the event delay after the
/// latest pulse start (µs), events of polarity `p` only.
fn delay_moments(out: &SimOutput, period: f64, p: u8) -> (f64, f64, f64) {
    let first = out.pulse_starts_us[0];
    let d: Vec<f64> = out
        .events
        .iter()
        .filter(|e| e.p == p)
        .map(|e| e.t as f64 + 0.5 - first)
        .filter(|&r| r >= 0.0)
        .map(|r| r - (r / period).floor() * period)
        .collect();
    let n = d.len() as f64;
    let m = d.iter().sum::<f64>() / n;
    let v = d.iter().map(|x| (x - m).powi(2)).sum::<f64>() / n;
    let s3 = d.iter().map(|x| (x - m).powi(3)).sum::<f64>() / n;
    (m, v.sqrt(), s3 / v.powf(1.5))
}

fn short(name: &str, secs: f64) -> Scenario {
    let mut s = presets::preset(name).unwrap();
    s.duration_s = secs;
    s
}

fn stat(name: &str, seed: u64, v: f64) {
    println!("STAT {name} {seed} {v:.6}");
}

#[test]
#[ignore]
fn seed_to_seed_statistics() {
    for seed in 1..=6u64 {
        for name in ["demo", "water_jet_5khz", "laminar_bl", "rib_wake"] {
            let s = short(name, 0.005);
            let out = simulate(&s, seed).unwrap();
            stat(
                &format!("ev_per_particle_{name}"),
                seed,
                out.events.len() as f64 / out.truth.len() as f64,
            );
        }
        // Full frame and 1280x160 ROI bursts, saturated and not.
        let s = short("water_jet_5khz", 0.01);
        let out = simulate(&s, seed).unwrap();
        let (peak, fwhm, flat) = burst(&out, s.period_us());
        stat("full_peak_us", seed, peak);
        stat("full_fwhm_us", seed, fwhm);
        stat("full_flatness", seed, flat);
        stat(
            "full_rate_mev_s",
            seed,
            out.events.len() as f64 / s.duration_s / 1e6,
        );
        let s = short("roi_burst", 0.01);
        let out = simulate(&s, seed).unwrap();
        let (peak, fwhm, _) = burst(&out, s.period_us());
        stat("roi_peak_us", seed, peak);
        stat("roi_fwhm_us", seed, fwhm);
        let (m, sd, sk) = delay_moments(&out, s.period_us(), ON);
        stat("roi_delay_mean_us", seed, m);
        stat("roi_delay_sd_us", seed, sd);
        stat("roi_delay_skew", seed, sk);
        // Beyond saturation: the readout's output rate.
        let mut s = short("water_jet_5khz", 0.008);
        s.seeding.ppp = 0.009;
        let out = simulate(&s, seed).unwrap();
        stat(
            "saturated_rate_mev_s",
            seed,
            out.events.len() as f64 / s.duration_s / 1e6,
        );
        // Unsaturated latency distribution and ON/OFF counts: the demo
        // scene with OFF events.
        let mut s = short("demo", 0.01);
        s.pixel.off_events = Some(OffEvents {
            threshold: 0.3,
            tau_us: 20.0,
        });
        let out = simulate(&s, seed).unwrap();
        let pulses = out.pulse_starts_us.len() as f64;
        let on = out.events.p.iter().filter(|&&p| p == ON).count() as f64;
        let off = out.events.p.iter().filter(|&&p| p == OFF).count() as f64;
        stat("demo_off_on_per_pulse", seed, on / pulses);
        stat("demo_off_off_per_pulse", seed, off / pulses);
        for (p, tag) in [(ON, "on"), (OFF, "off")] {
            let (m, sd, sk) = delay_moments(&out, s.period_us(), p);
            stat(&format!("demo_{tag}_delay_mean_us"), seed, m);
            stat(&format!("demo_{tag}_delay_sd_us"), seed, sd);
            stat(&format!("demo_{tag}_delay_skew"), seed, sk);
        }
        // The pixel's own latency distribution (jitter included): no
        // arbiter queueing.
        s.readout.arbiter_saturation = None;
        let out = simulate(&s, seed).unwrap();
        for (p, tag) in [(ON, "on"), (OFF, "off")] {
            let (m, sd, sk) = delay_moments(&out, s.period_us(), p);
            stat(&format!("pixel_{tag}_delay_mean_us"), seed, m);
            stat(&format!("pixel_{tag}_delay_sd_us"), seed, sd);
            stat(&format!("pixel_{tag}_delay_skew"), seed, sk);
        }
    }
}
