//! The truth is consistent with the events and with the flow.

use std::collections::BTreeMap;

use ebptv::sim::scenario::*;
use ebptv::sim::{presets, simulate, Flow, SimOutput};

/// For every event: distance to the nearest lit particle of its pulse.
fn event_distances(o: &SimOutput, period: f64) -> Vec<f64> {
    let first = o.pulse_starts_us[0];
    let mut grid: BTreeMap<(i64, i32, i32), Vec<(f64, f64)>> = BTreeMap::new();
    for t in &o.truth {
        grid.entry((
            t.pulse,
            (t.x / 8.0).floor() as i32,
            (t.y / 8.0).floor() as i32,
        ))
        .or_default()
        .push((t.x, t.y));
    }
    o.events
        .iter()
        .map(|e| {
            let k = ((e.t as f64 - first) / period).floor() as i64;
            let (ex, ey) = (e.x as f64, e.y as f64);
            let (cx, cy) = ((ex / 8.0).floor() as i32, (ey / 8.0).floor() as i32);
            let mut best = f64::INFINITY;
            for dx in -1..=1 {
                for dy in -1..=1 {
                    if let Some(v) = grid.get(&(k, cx + dx, cy + dy)) {
                        for p in v {
                            best = best.min(((ex - p.0).powi(2) + (ey - p.1).powi(2)).sqrt());
                        }
                    }
                }
            }
            best
        })
        .collect()
}

#[test]
fn every_event_sits_on_a_particle_image_of_its_pulse() {
    // The demo preset with its camera effects, minus the noise sources.
    let mut s = presets::preset("demo").unwrap();
    s.duration_s = 0.01;
    s.noise.background_noise = None;
    let o = simulate(&s, 9).unwrap();
    assert!(o.events.len() > 10_000);
    // Events at the ROI border may come from particles centred just
    // outside it (not in the truth, which lists image centres in the ROI).
    let d: Vec<f64> = event_distances(&o, s.period_us())
        .into_iter()
        .zip(o.events.iter())
        .filter(|(_, e)| e.x >= 2 && e.y >= 2 && e.x < 638 && e.y < 358)
        .map(|(d, _)| d)
        .collect();
    // Image e⁻² radius 0.75 px plus pixel quantisation (≤ 0.71 px) plus a
    // streak: every event lies within 1.6 px of its particle.
    let far = d.iter().filter(|&&x| x > 1.6).count();
    assert_eq!(
        far,
        0,
        "{far} of {} events are off every particle image",
        d.len()
    );
    let mean = d.iter().sum::<f64>() / d.len() as f64;
    assert!(mean < 0.7, "mean distance {mean}");
    // And most lit particles fire: ~2 events per particle per pulse.
    let mut fired: BTreeMap<(i64, u64), bool> = BTreeMap::new();
    for t in &o.truth {
        fired.insert((t.pulse, t.particle_id), false);
    }
    let first = o.pulse_starts_us[0];
    let mut by_pulse: BTreeMap<i64, Vec<&ebptv::sim::TruthSample>> = BTreeMap::new();
    for t in &o.truth {
        by_pulse.entry(t.pulse).or_default().push(t);
    }
    for e in o.events.iter() {
        let k = ((e.t as f64 - first) / s.period_us()).floor() as i64;
        if let Some(v) = by_pulse.get(&k) {
            for t in v {
                if (t.x - e.x as f64).abs() <= 1.0 && (t.y - e.y as f64).abs() <= 1.0 {
                    fired.insert((k, t.particle_id), true);
                }
            }
        }
    }
    let frac = fired.values().filter(|&&f| f).count() as f64 / fired.len() as f64;
    assert!(frac > 0.8, "only {frac:.2} of lit particles fired");
}

#[test]
fn truth_velocity_is_the_field_and_pathlines_are_accurate() {
    let s = presets::preset("demo").unwrap();
    let mut s = s.without_effects();
    s.duration_s = 0.02;
    s.seeding.out_of_plane_rms = 0.0; // particles stay: long pathlines
    let o = simulate(&s, 2).unwrap();
    let flow = Flow::build(&s.flow).unwrap();
    let (x0, y0) = (320.0, 180.0);
    let mut by_id: BTreeMap<u64, Vec<&ebptv::sim::TruthSample>> = BTreeMap::new();
    for t in &o.truth {
        let (u, v) = flow.velocity(t.x, t.y, t.t_us * 1e-6);
        assert!((u - t.u).abs() < 1e-9 && (v - t.v).abs() < 1e-9);
        by_id.entry(t.particle_id).or_default().push(t);
    }
    // Lamb–Oseen pathlines are circles: the radius is conserved.
    let mut checked = 0;
    for v in by_id.values().filter(|v| v.len() >= 50) {
        let r = |t: &ebptv::sim::TruthSample| ((t.x - x0).powi(2) + (t.y - y0).powi(2)).sqrt();
        let (a, b) = (r(v[0]), r(v[v.len() - 1]));
        assert!((a - b).abs() < 1e-3, "radius drifted {a} -> {b}");
        // Consecutive pulses: the displacement matches the trapezoid of the
        // truth velocities to second order.
        for w in v.windows(2) {
            if w[1].pulse != w[0].pulse + 1 {
                continue;
            }
            let dt = (w[1].t_us - w[0].t_us) * 1e-6;
            let ex = 0.5 * (w[0].u + w[1].u) * dt;
            let ey = 0.5 * (w[0].v + w[1].v) * dt;
            let err = ((w[1].x - w[0].x - ex).powi(2) + (w[1].y - w[0].y - ey).powi(2)).sqrt();
            let speed = (w[0].u.powi(2) + w[0].v.powi(2)).sqrt() * dt;
            assert!(
                err < 0.02 * speed.max(0.5),
                "step error {err} px for a {speed} px step"
            );
        }
        checked += 1;
    }
    assert!(checked > 100, "{checked}");
}

#[test]
fn particles_leave_and_enter_the_sheet_and_recycle() {
    let mut s = Scenario::default();
    s.sensor = Sensor {
        width: 200,
        height: 100,
        roi: None,
    };
    s.duration_s = 0.02;
    s.flow = FlowSpec::Uniform {
        u: 20_000.0,
        v: 0.0,
    };
    s.seeding.ppp = 0.02;
    s.seeding.out_of_plane_rms = 2000.0;
    let o = simulate(&s, 1).unwrap();
    let pulses = o.pulse_starts_us.len() as f64;
    // The lit count per pulse stays at ppp · area despite the churn.
    let per_pulse = o.truth.len() as f64 / pulses;
    let expect = 0.02 * 200.0 * 100.0;
    assert!(
        (per_pulse - expect).abs() < 0.1 * expect,
        "{per_pulse} lit per pulse, expected {expect}"
    );
    // Many identities are created: particles leave (out of plane or
    // downstream) and new ones enter.
    let ids: std::collections::BTreeSet<u64> = o.truth.iter().map(|t| t.particle_id).collect();
    assert!(
        ids.len() as f64 > 3.0 * expect,
        "{} distinct particles",
        ids.len()
    );
    // One row per particle per pulse.
    let mut seen = std::collections::BTreeSet::new();
    for t in &o.truth {
        assert!(seen.insert((t.pulse, t.particle_id)), "duplicate truth row");
    }
}

#[test]
fn turbulent_truth_has_the_known_stresses() {
    let mut s = Scenario::default();
    s.sensor = Sensor {
        width: 256,
        height: 256,
        roi: None,
    };
    s.duration_s = 0.2;
    s.light.pulse_hz = 1000.0;
    s.seeding.ppp = 0.01;
    s.flow = FlowSpec::Turbulent {
        u_mean: 3000.0,
        v_mean: 0.0,
        shear: 0.0,
        y_ref: 0.0,
        rms: 800.0,
        length_scale: 80.0,
        time_scale_s: 0.01,
        n_modes: 24,
        seed: 5,
    };
    let o = simulate(&s, 3).unwrap();
    let flow = Flow::build(&s.flow).unwrap();
    let (uu, vv, uv) = flow.known_stresses().unwrap();
    let n = o.truth.len() as f64;
    let (mut su, mut sv, mut suv) = (0.0, 0.0, 0.0);
    for t in &o.truth {
        let (um, vm) = flow.mean_velocity(t.x, t.y);
        su += (t.u - um).powi(2);
        sv += (t.v - vm).powi(2);
        suv += (t.u - um) * (t.v - vm);
    }
    let tol = 0.15 * (uu + vv);
    assert!((su / n - uu).abs() < tol, "uu {} vs {uu}", su / n);
    assert!((sv / n - vv).abs() < tol, "vv {} vs {vv}", sv / n);
    assert!((suv / n - uv).abs() < tol, "uv {} vs {uv}", suv / n);
}

#[test]
fn shedding_frequency_follows_the_strouhal_number() {
    let s = presets::preset("rib_wake").unwrap();
    let f = Flow::build(&s.flow)
        .unwrap()
        .shedding_frequency_hz()
        .unwrap();
    assert!((f - 35.4).abs() < 0.05, "{f} Hz");
    // The cross-stream velocity on the wake axis oscillates at f.
    let flow = Flow::build(&s.flow).unwrap();
    let n = 4096;
    let dt = 1.0 / 2000.0;
    let v: Vec<f64> = (0..n)
        .map(|k| flow.velocity(640.0, 360.0, k as f64 * dt).1)
        .collect();
    let best = (1..200)
        .map(|fi| {
            let fr = fi as f64 * 0.5;
            let (mut c, mut sn) = (0.0, 0.0);
            for (k, x) in v.iter().enumerate() {
                let ph = std::f64::consts::TAU * fr * k as f64 * dt;
                c += x * ph.cos();
                sn += x * ph.sin();
            }
            (c * c + sn * sn, fr)
        })
        .max_by(|a, b| a.0.total_cmp(&b.0))
        .unwrap()
        .1;
    assert!((best - 35.4).abs() <= 0.5, "spectral peak at {best} Hz");
}
