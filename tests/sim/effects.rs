//! Each sensor/readout effect switches on and off cleanly: off is exactly
//! absent, on changes what it should and nothing else.

use std::collections::BTreeMap;

use ebptv::events::{Event, OFF, ON};
use ebptv::sim::scenario::*;
use ebptv::sim::{simulate, SimOutput, Simulator};

fn base() -> Scenario {
    let mut s = Scenario::default();
    s.name = "effects".into();
    s.sensor = Sensor {
        width: 320,
        height: 160,
        roi: None,
    };
    s.duration_s = 0.01;
    s.flow = FlowSpec::Uniform {
        u: 8000.0,
        v: 1500.0,
    };
    s.seeding.ppp = 0.01;
    s
}

fn run(s: &Scenario) -> SimOutput {
    simulate(s, 42).unwrap()
}

fn sorted(o: &SimOutput) -> Vec<Event> {
    let mut v: Vec<Event> = o.events.iter().collect();
    v.sort();
    v
}

/// Multiset difference a − b; panics if b is not contained in a.
fn minus(a: &[Event], b: &[Event]) -> Vec<Event> {
    let mut count: BTreeMap<Event, i64> = BTreeMap::new();
    for e in a {
        *count.entry(*e).or_default() += 1;
    }
    for e in b {
        let c = count.entry(*e).or_default();
        *c -= 1;
        assert!(*c >= 0, "{e:?} is in the smaller set only");
    }
    count
        .into_iter()
        .flat_map(|(e, c)| std::iter::repeat_n(e, c as usize))
        .collect()
}

fn pixels(v: &[Event]) -> Vec<(u16, u16, u8)> {
    let mut p: Vec<_> = v.iter().map(|e| (e.x, e.y, e.p)).collect();
    p.sort();
    p
}

fn assert_same_pixels(a: &SimOutput, b: &SimOutput) {
    let (pa, pb) = (pixels(&sorted(a)), pixels(&sorted(b)));
    assert_eq!(pa.len(), pb.len(), "event counts differ");
    let diff = pa.iter().zip(&pb).filter(|(x, y)| x != y).count();
    assert_eq!(diff, 0, "{diff} events moved to other pixels or polarities");
}

/// Mean offset (dx, dy) of events from the nearest lit particle of their
/// pulse (within 2 px), assuming latencies shorter than the period.
fn mean_offset(o: &SimOutput, period: f64) -> (f64, f64) {
    let first = o.pulse_starts_us[0];
    let mut by_pulse: BTreeMap<i64, Vec<(f64, f64)>> = BTreeMap::new();
    for t in &o.truth {
        by_pulse.entry(t.pulse).or_default().push((t.x, t.y));
    }
    let (mut sx, mut sy, mut n) = (0.0, 0.0, 0usize);
    for e in o.events.iter() {
        let k = ((e.t as f64 - first) / period).floor() as i64;
        let Some(ps) = by_pulse.get(&k) else { continue };
        let (ex, ey) = (e.x as f64, e.y as f64);
        let best = ps
            .iter()
            .map(|p| ((ex - p.0).powi(2) + (ey - p.1).powi(2), p))
            .min_by(|a, b| a.0.total_cmp(&b.0));
        if let Some((d2, p)) = best {
            if d2 < 4.0 {
                sx += ex - p.0;
                sy += ey - p.1;
                n += 1;
            }
        }
    }
    (sx / n as f64, sy / n as f64)
}

fn assert_same_world(a: &SimOutput, b: &SimOutput) {
    assert_eq!(a.truth, b.truth, "truth must not depend on sensor effects");
    assert_eq!(a.triggers, b.triggers);
    assert_eq!(a.pulse_starts_us, b.pulse_starts_us);
}

fn with(effect: &str, params: &[(&str, f64)]) -> Scenario {
    let mut s = base();
    let m: BTreeMap<String, f64> = params.iter().map(|(k, v)| (k.to_string(), *v)).collect();
    s.set_effect(effect, Some(&m)).unwrap();
    s.validate().unwrap();
    assert_eq!(s.effect_params(effect).unwrap(), Some(m));
    s
}

fn latency_var(o: &SimOutput, period: f64) -> f64 {
    let first = o.pulse_starts_us[0];
    let l: Vec<f64> = o
        .events
        .t
        .iter()
        .map(|&t| (t as f64 - first).rem_euclid(period))
        .collect();
    let m = l.iter().sum::<f64>() / l.len() as f64;
    l.iter().map(|x| (x - m).powi(2)).sum::<f64>() / l.len() as f64
}

#[test]
fn default_scenario_has_no_effects() {
    let s = base();
    assert_eq!(s.without_effects(), s);
    for name in EFFECT_NAMES {
        assert_eq!(s.effect_params(name).unwrap(), None, "{name}");
    }
    assert!(s.effect_params("nonsense").is_err());
}

#[test]
fn hot_pixels_add_on_events_only_at_hot_pixels() {
    let off = run(&base());
    let s = with("hot_pixels", &[("count", 5.0), ("rate_hz", 2000.0)]);
    let on = run(&s);
    assert_same_world(&off, &on);
    let hot = Simulator::new(&s, 42).unwrap().hot_pixels().to_vec();
    assert_eq!(hot.len(), 5);
    let extra = minus(&sorted(&on), &sorted(&off));
    assert!(
        (50..=150).contains(&extra.len()),
        "{} hot events, expected ~100",
        extra.len()
    );
    for e in &extra {
        assert!(
            hot.iter().any(|h| h.0 == e.x && h.1 == e.y),
            "{e:?} not at a hot pixel"
        );
        assert_eq!(e.p, ON);
    }
}

#[test]
fn background_noise_adds_uniform_on_and_off_events() {
    let off = run(&base());
    let on = run(&with("background_noise", &[("rate_hz", 50.0)]));
    assert_same_world(&off, &on);
    let extra = minus(&sorted(&on), &sorted(&off));
    let expect = 50.0 * 320.0 * 160.0 * 0.01;
    assert!(
        (extra.len() as f64 - expect).abs() < 5.0 * expect.sqrt(),
        "{} vs {expect}",
        extra.len()
    );
    let on_frac = extra.iter().filter(|e| e.p == ON).count() as f64 / extra.len() as f64;
    assert!((on_frac - 0.5).abs() < 0.03, "{on_frac}");
    let right = extra.iter().filter(|e| e.x >= 160).count() as f64 / extra.len() as f64;
    assert!((right - 0.5).abs() < 0.03, "spatially uniform: {right}");
}

#[test]
fn latency_jitter_moves_times_only() {
    let s0 = base();
    let off = run(&s0);
    let on = run(&with("latency_jitter", &[("spread_us", 5.0)]));
    assert_same_world(&off, &on);
    assert_same_pixels(&on, &off);
    assert_ne!(on.events.t, off.events.t);
    // Independent Gaussian jitter adds its variance to the latency's
    // (timestamps are truncated to µs in both runs).
    let dv = latency_var(&on, s0.period_us()) - latency_var(&off, s0.period_us());
    assert!(
        (dv - 25.0).abs() < 6.0,
        "variance grew by {dv}, expected 25"
    );
}

#[test]
fn intensity_latency_makes_bright_pixels_faster() {
    // Latency of each pixel's first event in a pulse, split by how many
    // events the pixel fired (a proxy for its brightness).
    fn gap(o: &SimOutput, period: f64) -> f64 {
        let first = o.pulse_starts_us[0];
        let mut by_pixel: BTreeMap<(i64, u16, u16), Vec<f64>> = BTreeMap::new();
        for e in o.events.iter() {
            let rel = e.t as f64 - first;
            let k = (rel / period).floor() as i64;
            by_pixel
                .entry((k, e.x, e.y))
                .or_default()
                .push(rel - k as f64 * period);
        }
        let (mut b, mut nb, mut d, mut nd) = (0.0, 0, 0.0, 0);
        for v in by_pixel.values() {
            let l = v.iter().cloned().fold(f64::INFINITY, f64::min);
            if v.len() >= 3 {
                b += l;
                nb += 1;
            } else if v.len() == 1 {
                d += l;
                nd += 1;
            }
        }
        d / nd as f64 - b / nb as f64
    }
    let s0 = base();
    let off = run(&s0);
    // Exponent 0.5 keeps every latency well inside the period, so no event
    // is pushed past the end of the recording.
    let on = run(&with(
        "intensity_latency",
        &[("exponent", 0.5), ("reference", 3.0)],
    ));
    assert_same_world(&off, &on);
    assert_same_pixels(&on, &off);
    let (g_off, g_on) = (gap(&off, s0.period_us()), gap(&on, s0.period_us()));
    eprintln!("dim-minus-bright latency gap: off {g_off:.2} µs, on {g_on:.2} µs");
    assert!(
        g_on > g_off + 1.0,
        "dim-minus-bright latency gap: off {g_off:.2} µs, on {g_on:.2} µs"
    );
}

#[test]
fn refractory_only_removes_close_repeats() {
    let off = run(&base());
    let on = run(&with("refractory", &[("period_us", 50.0)]));
    assert_same_world(&off, &on);
    let removed = minus(&sorted(&off), &sorted(&on));
    assert!(
        !removed.is_empty(),
        "the base scene has repeats within 50 µs"
    );
    fn min_gap(o: &SimOutput) -> i64 {
        let mut last: BTreeMap<(u16, u16), i64> = BTreeMap::new();
        let mut g = i64::MAX;
        for e in o.events.iter() {
            if let Some(l) = last.insert((e.x, e.y), e.t) {
                g = g.min(e.t - l);
            }
        }
        g
    }
    assert!(min_gap(&off) < 50);
    // Timestamps are truncated to µs: a 50 µs gap can show as 49.
    assert!(min_gap(&on) >= 49, "{}", min_gap(&on));
}

#[test]
fn arbiter_delays_and_groups_events_and_loses_only_blocked_ones() {
    let s0 = base();
    let off = run(&s0);
    // A slow readout so that it saturates in this small scene.
    let s = with(
        "arbiter_saturation",
        &[("row_time_us", 0.2), ("event_time_us", 0.3)],
    );
    let mut sim = Simulator::new(&s, 42).unwrap();
    let on = simulate(&s, 42).unwrap();
    let mut chunk = ebptv::Chunk::default();
    use ebptv::io::EventSource;
    while sim.next_chunk(&mut chunk).unwrap() {}
    let lost = sim.stats().lost_in_readout as usize;
    assert_same_world(&off, &on);
    // Requests still pending at the end of the recording are not events.
    let missing = off.events.len() - on.events.len();
    assert!(missing >= lost);
    let on_px = pixels(&sorted(&on));
    let off_px = pixels(&sorted(&off));
    let mut i = 0;
    for p in &on_px {
        while i < off_px.len() && off_px[i] < *p {
            i += 1;
        }
        assert!(
            i < off_px.len() && off_px[i] == *p,
            "{p:?} appears only with the arbiter"
        );
        i += 1;
    }
    let mean = |o: &SimOutput| o.events.t.iter().sum::<i64>() as f64 / o.events.len() as f64;
    assert!(mean(&on) > mean(&off) + 5.0, "events are delayed");
    // Row grouping: many consecutive events share (t, y).
    let shared = |o: &SimOutput| {
        (1..o.events.len())
            .filter(|&i| o.events.t[i] == o.events.t[i - 1] && o.events.y[i] == o.events.y[i - 1])
            .count()
    };
    assert!(
        shared(&on) > 2 * shared(&off) + 100,
        "shared (t,row): off {} on {}",
        shared(&off),
        shared(&on)
    );
}

#[test]
fn pulse_streaks_shift_images_along_the_motion_only() {
    // No motion: no streak, identical output.
    let mut still = base();
    still.flow = FlowSpec::Uniform { u: 0.0, v: 0.0 };
    let mut still_on = still.clone();
    still_on.light.pulse_streaks = Some(PulseStreaks { scale: 1.0 });
    assert_eq!(run(&still).events, run(&still_on).events);
    // Fast motion along x: events move downstream by u·(pulse centroid).
    let mut fast = base();
    fast.flow = FlowSpec::Uniform {
        u: 40_000.0,
        v: 0.0,
    };
    fast.light.pulse_width_us = 20.0;
    let mut fast_on = fast.clone();
    fast_on.light.pulse_streaks = Some(PulseStreaks { scale: 1.0 });
    let (off, on) = (run(&fast), run(&fast_on));
    assert_same_world(&off, &on);
    let centroid = ebptv::sim::light::PulseShape::new(&fast.light).centroid_us;
    let expect = 40_000.0 * centroid * 1e-6;
    let (dx0, dy0) = mean_offset(&off, fast.period_us());
    let (dx1, dy1) = mean_offset(&on, fast.period_us());
    eprintln!("offsets off ({dx0:.3}, {dy0:.3}) on ({dx1:.3}, {dy1:.3}), expected dx {expect:.3}");
    assert!(
        dx0.abs() < 0.05 && dy0.abs() < 0.05,
        "without streaks events centre on the truth"
    );
    assert!(
        (dx1 - expect).abs() < 0.2 * expect,
        "dx {dx1:.3} px, expected {expect:.3}"
    );
    assert!(dy1.abs() < 0.05, "dy {dy1:.3}");
}

#[test]
fn threshold_mismatch_changes_counts_not_the_world() {
    let off = run(&base());
    let on = run(&with("threshold_mismatch", &[("sigma", 0.2)]));
    assert_same_world(&off, &on);
    assert_ne!(on.events.len(), off.events.len());
    // Pixels are fixed-pattern: some pixels fire consistently more, some less.
    let count = |o: &SimOutput| {
        let mut m: BTreeMap<(u16, u16), i64> = BTreeMap::new();
        for e in o.events.iter() {
            *m.entry((e.x, e.y)).or_default() += 1;
        }
        m
    };
    let (a, b) = (count(&off), count(&on));
    let changed = b.iter().filter(|(k, v)| a.get(k) != Some(v)).count();
    assert!(
        changed > b.len() / 10,
        "{changed} of {} pixels changed",
        b.len()
    );
}

#[test]
fn rate_limiter_drops_excess_per_window_only() {
    let off = run(&base());
    let on = run(&with(
        "rate_limiter",
        &[("max_rate_ev_s", 2e6), ("window_us", 100.0)],
    ));
    assert_same_world(&off, &on);
    let per_window = |o: &SimOutput| {
        let mut m: BTreeMap<i64, usize> = BTreeMap::new();
        for &t in &o.events.t {
            *m.entry(t.div_euclid(100)).or_default() += 1;
        }
        m.values().cloned().max().unwrap()
    };
    assert!(per_window(&off) > 200, "the base scene exceeds the limit");
    assert!(per_window(&on) <= 200);
    // The kept events are a subsequence of the unlimited stream.
    let full: Vec<Event> = off.events.iter().collect();
    let mut j = 0;
    for e in on.events.iter() {
        while j < full.len() && full[j] != e {
            j += 1;
        }
        assert!(j < full.len(), "{e:?} not in the unlimited stream");
        j += 1;
    }
}

#[test]
fn off_events_add_off_polarity_after_the_pulse() {
    let s0 = base();
    let off = run(&s0);
    let on = run(&with("off_events", &[("threshold", 0.3), ("tau_us", 20.0)]));
    assert_same_world(&off, &on);
    let on_sorted = sorted(&on);
    let ons: Vec<Event> = on_sorted.iter().cloned().filter(|e| e.p == ON).collect();
    assert_eq!(ons, sorted(&off), "ON events unchanged");
    let offs: Vec<Event> = on_sorted.iter().cloned().filter(|e| e.p == OFF).collect();
    assert!(
        offs.len() > off.events.len() / 4,
        "{} OFF events",
        offs.len()
    );
    let first = on.pulse_starts_us[0];
    let end = ebptv::sim::light::PulseShape::new(&s0.light).end_us;
    for e in &offs {
        let lat = (e.t as f64 - first).rem_euclid(s0.period_us());
        assert!(
            lat >= end + s0.pixel.latency_us - 1.0,
            "OFF event {lat} µs after the pulse start"
        );
    }
}

#[test]
fn clock_drift_moves_pulses_triggers_and_truth_together() {
    let off = run(&base());
    // Zero drift is exactly no drift.
    let zero = run(&with(
        "clock_drift",
        &[("ppm", 0.0), ("wander_ppm", 0.0), ("wander_period_s", 1.0)],
    ));
    assert_eq!(zero.events, off.events);
    assert_same_world(&zero, &off);
    // 500 ppm slow laser plus a ±300 ppm wander over 4 ms.
    let s = with(
        "clock_drift",
        &[
            ("ppm", 500.0),
            ("wander_ppm", 300.0),
            ("wander_period_s", 0.004),
        ],
    );
    let on = run(&s);
    let period = s.period_us();
    let n = on.pulse_starts_us.len();
    assert_eq!(n as u64, s.pulse_count());
    let mut min_gap = f64::INFINITY;
    let mut max_gap: f64 = 0.0;
    for (k, w) in on.pulse_starts_us.windows(2).enumerate() {
        // The camera-time start follows the drift formula.
        let tau = k as f64 * period;
        let expect = s.light.first_pulse_us
            + tau
            + 1e-6
                * (500.0 * tau
                    + 300.0 * 4000.0 / std::f64::consts::TAU
                        * (1.0 - (std::f64::consts::TAU * tau / 4000.0).cos()));
        assert!(
            (w[0] - expect).abs() < 1e-9,
            "pulse {k}: {} vs {expect}",
            w[0]
        );
        min_gap = min_gap.min(w[1] - w[0]);
        max_gap = max_gap.max(w[1] - w[0]);
    }
    // Spacing = period·(1 + (500 ± 300)·1e-6), within the sampling of the
    // wander by the pulses.
    assert!(
        (min_gap - period * (1.0 + 200e-6)).abs() < 0.005,
        "{min_gap}"
    );
    assert!(
        (max_gap - period * (1.0 + 800e-6)).abs() < 0.005,
        "{max_gap}"
    );
    assert!(on.pulse_starts_us.last().unwrap() - off.pulse_starts_us[n - 1] > 1.0);
    // Triggers (camera clock) mark the drifted pulses.
    let rising: Vec<i64> = on
        .triggers
        .iter()
        .filter(|t| t.edge == ebptv::events::Edge::Rising)
        .map(|t| t.t)
        .collect();
    let expect: Vec<i64> = on
        .pulse_starts_us
        .iter()
        .map(|t| t.floor() as i64)
        .collect();
    assert_eq!(rising, expect);
    // Truth is stamped with the drifted pulse starts.
    for t in &on.truth {
        assert_eq!(t.t_us, on.pulse_starts_us[t.pulse as usize]);
    }
    // Off again restores the original exactly.
    let mut back = s.clone();
    back.set_effect("clock_drift", None).unwrap();
    assert_eq!(back, base());
    assert!(s.without_effects().light.clock_drift.is_none());
}

#[test]
fn clock_drift_is_validated_with_the_field_named() {
    for (field, params) in [
        (
            "light.clock_drift.ppm",
            [
                ("ppm", 5000.0),
                ("wander_ppm", 0.0),
                ("wander_period_s", 1.0),
            ],
        ),
        (
            "light.clock_drift.ppm",
            [
                ("ppm", f64::NAN),
                ("wander_ppm", 0.0),
                ("wander_period_s", 1.0),
            ],
        ),
        (
            "light.clock_drift.wander_ppm",
            [
                ("ppm", 0.0),
                ("wander_ppm", -2000.0),
                ("wander_period_s", 1.0),
            ],
        ),
        (
            "light.clock_drift.wander_period_s",
            [("ppm", 0.0), ("wander_ppm", 10.0), ("wander_period_s", 0.0)],
        ),
    ] {
        let mut s = base();
        let m: BTreeMap<String, f64> = params.iter().map(|(k, v)| (k.to_string(), *v)).collect();
        s.set_effect("clock_drift", Some(&m)).unwrap();
        let e = s.validate().unwrap_err().to_string();
        assert!(e.contains(field), "{e}");
    }
}

/// The pulse stage recovers a drifted laser period from the events alone
/// (no triggers) to the 0.01 µs: the nominal period would miss by
/// 0.08 µs.
#[test]
fn pulse_period_estimation_follows_the_drifted_laser() {
    use ebptv::pulses::{analyze, PulseOptions, PulseSource};
    let mut s = ebptv::sim::presets::preset("demo").unwrap();
    s.duration_s = 0.05;
    s.triggers.enabled = false;
    s.light.clock_drift = Some(ClockDrift {
        ppm: 400.0,
        wander_ppm: 0.0,
        wander_period_s: 1.0,
    });
    s.validate().unwrap();
    let drifted = s.period_us() * (1.0 + 400e-6);
    let mut sim = Simulator::new(&s, 5).unwrap();
    let opts = PulseOptions {
        pulse_hz: Some(s.light.pulse_hz),
        ..Default::default()
    };
    let est = analyze(&mut sim, &opts).unwrap();
    assert_eq!(est.timing.source, PulseSource::Estimated);
    let truth = sim.pulse_starts_us();
    let truth_period = (truth[truth.len() - 1] - truth[0]) / (truth.len() - 1) as f64;
    assert!((truth_period - drifted).abs() < 1e-9);
    let err = est.timing.period_us - drifted;
    eprintln!(
        "drifted period {drifted:.5} µs, estimated {:.5} µs (error {err:.5}), nominal {:.5}",
        est.timing.period_us,
        s.period_us()
    );
    assert!(err.abs() < 0.01, "period error {err} µs");
    assert!((est.timing.period_us - s.period_us()).abs() > 0.05);
}
