//! Pulse timing and diagnostics on the project's physical simulator
//! (`crate::sim`), streamed through its `EventSource`.

use ebptv::pulses::{analyze, split_pulses, PulseOptions, PulseSource};
use ebptv::sim::{presets::preset, Simulator};

fn nearest_error(start: f64, truth: &[f64]) -> f64 {
    truth
        .iter()
        .map(|t| start - t)
        .min_by(|a, b| a.abs().total_cmp(&b.abs()))
        .unwrap()
}

#[test]
fn simulator_with_and_without_triggers() {
    for name in ["demo", "roi_burst"] {
        let mut sc = preset(name).unwrap();
        sc.duration_s = sc.duration_s.min(0.05);
        sc.triggers.enabled = true;
        let mut sim = Simulator::new(&sc, 3).unwrap();
        let trig = analyze(&mut sim, &PulseOptions::default()).unwrap();
        let truth = sim.pulse_starts_us().to_vec();
        let p_true = sc.period_us();
        assert_eq!(trig.timing.source, PulseSource::Trigger);
        assert!(
            (trig.timing.period_us - p_true).abs() < 0.01,
            "{name}: {} vs {p_true}",
            trig.timing.period_us
        );
        let e0 = trig.timing.pulse_start(0) - truth[0];
        assert!(
            e0.abs() < 1.0,
            "{name}: pulse 0 at {} vs {}",
            trig.timing.pulse_start(0),
            truth[0]
        );
        eprintln!(
            "{name}: trigger: peak {:.1} µs fwhm {:.1} µs contrast {:.1} random {:.3} ppp {:.4} size {:.2} epp {:.2} sat {}",
            trig.latency_peak_us,
            trig.latency_fwhm_us,
            trig.burst_contrast,
            trig.random_event_fraction,
            trig.particles.ppp,
            trig.particles.mean_image_size_px,
            trig.particles.events_per_particle,
            trig.saturated
        );
        assert!(
            !trig.saturated,
            "{name}: {:?} groups {:?}",
            trig.saturation.windows,
            &trig.saturation.group_sizes[..8]
        );

        // Without triggers: period and pulse start from the events alone.
        let onset = trig.latency.window95_us.0;
        let mut sim = Simulator::new(&sc, 4).unwrap();
        let opts = PulseOptions {
            pulse_hz: Some(sc.light.pulse_hz),
            ignore_triggers: true,
            ..Default::default()
        };
        let est = analyze(&mut sim, &opts).unwrap();
        assert_eq!(est.timing.source, PulseSource::Estimated);
        let dp = est.timing.period_us - p_true;
        eprintln!(
            "{name}: trig period {:.5} truth {:.5} est {:.5}",
            trig.timing.period_us,
            (truth[truth.len() - 1] - truth[0]) / (truth.len() - 1) as f64,
            est.timing.period_us
        );
        let e = nearest_error(est.timing.pulse_start(10), &truth);
        eprintln!("{name}: estimated: period err {dp:.5} µs, start err {e:.2} µs (onset window {onset:.1})");
        assert!(dp.abs() < 0.01, "{name}: period error {dp}");
        // The target: pulse start within 5 µs, no user help.
        assert!(e.abs() < 5.0, "{name}: start error {e}");
        // split_pulses hands over every pulse in order.
        let mut sim = Simulator::new(&sc, 3).unwrap();
        let mut next = 0;
        let mut events = 0u64;
        let un = split_pulses(&mut sim, &trig.timing, &mut |p| {
            assert_eq!(p.index, next);
            next += 1;
            events += p.events.len() as u64;
            Ok(())
        })
        .unwrap();
        assert_eq!(events + un, trig.events);
        assert!(next as usize >= truth.len() - 1);
    }
}

/// Pulse start without triggers and without a user-given latency, on
/// several presets and seeds: the target is an error < 5 µs.
#[test]
fn estimated_pulse_start_within_5us_on_presets() {
    let mut worst: f64 = 0.0;
    for (name, seed) in [
        ("roi_burst", 11u64),
        ("laminar_bl", 12),
        ("turbulent_bl", 13),
        ("rib_wake", 14),
        ("water_jet_2khz", 15),
        ("water_jet_10khz", 16),
    ] {
        let mut sc = preset(name).unwrap();
        sc.duration_s = 0.02;
        let mut sim = Simulator::new(&sc, seed).unwrap();
        let opts = PulseOptions {
            pulse_hz: Some(sc.light.pulse_hz),
            ignore_triggers: true,
            ..Default::default()
        };
        let est = analyze(&mut sim, &opts).unwrap();
        assert_eq!(est.timing.source, PulseSource::Estimated);
        let truth = sim.pulse_starts_us().to_vec();
        let e = nearest_error(est.timing.pulse_start(5), &truth);
        let dp = est.timing.period_us - sc.period_us();
        eprintln!("{name}/{seed}: start error {e:.2} µs, period error {dp:.5} µs");
        assert!(e.abs() < 5.0, "{name}/{seed}: start error {e}");
        worst = worst.max(e.abs());
    }
    eprintln!("worst start error {worst:.2} µs");
}
