//! Calibrated defaults against the paper's figures (Willert 2023).

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

struct Burst {
    peak_us: f64,
    fwhm_us: f64,
    frac_before_150: f64,
    frac_before_200: f64,
    flatness: f64,
}

fn burst(out: &SimOutput, period: f64) -> Burst {
    let h = folded(out, period);
    // 5 µs moving average for a stable peak.
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
    let tot: f64 = h.iter().sum();
    let before = |t: usize| h[..t.min(n)].iter().sum::<f64>() / tot;
    let mean = tot / n as f64;
    let mn = sm.iter().cloned().fold(f64::INFINITY, f64::min);
    Burst {
        peak_us: ip as f64,
        fwhm_us: fwhm,
        frac_before_150: before(150),
        frac_before_200: before(200),
        flatness: mn / mean.max(1e-9) * (mean / mx),
    }
}

fn short(mut s: Scenario, secs: f64) -> Scenario {
    s.duration_s = secs;
    s
}

#[test]
#[ignore]
fn explore() {
    for name in [
        "demo",
        "water_jet_5khz",
        "water_jet_2khz",
        "roi_burst",
        "laminar_bl",
        "rib_wake",
    ] {
        let s = short(presets::preset(name).unwrap(), 0.02);
        let t = std::time::Instant::now();
        let out = simulate(&s, 1).unwrap();
        let el = t.elapsed().as_secs_f64();
        let b = burst(&out, s.period_us());
        let epp = out.events.len() as f64 / out.truth.len() as f64;
        println!(
            "{name}: {} ev in {el:.2}s ({:.1} Mev/s sim), rate {:.1} Mev/s, ev/particle {epp:.2}, peak {} fwhm {} <150 {:.2} <200 {:.2} flat {:.2}",
            out.events.len(),
            out.events.len() as f64 / el / 1e6,
            out.events.len() as f64 / s.duration_s / 1e6,
            b.peak_us,
            b.fwhm_us,
            b.frac_before_150,
            b.frac_before_200,
            b.flatness
        );
    }
}
