//! The baseline model built from a measurement (no `--model`): pulse
//! timing, seeding, brightness, latency and the flow from ebptv's own
//! tracks, replayed by the simulator as a gridded field. Checked against
//! the truth of a simulated vortex-in-shear recording.

use crate::events::{Edge, Geometry};
use crate::modelcheck::baseline::{baseline_from_measurement, BaselineOptions, PulseTrain};
use crate::modelcheck::scene::{particles_of, timing_of};
use crate::sim::flow::Flow;
use crate::sim::scenario::{FlowSpec, Scenario, Sensor};

fn truth_scene() -> Scenario {
    let mut s = Scenario {
        name: "baseline-truth".into(),
        duration_s: 0.04,
        sensor: Sensor {
            width: 320,
            height: 240,
            roi: None,
        },
        // A vortex on a uniform stream: shear and curvature a coarse grid
        // must follow.
        flow: FlowSpec::LambOseen {
            x0: 160.0,
            y0: 120.0,
            circulation: 2.0e6,
            core_radius: 45.0,
            u: 4000.0,
            v: 0.0,
        },
        ..Scenario::default()
    };
    s.seeding.ppp = 0.008;
    s.light.energy = crate::sim::presets::WATER_ENERGY;
    s.light.first_pulse_us = 37.0;
    s.pixel.latency_us = 20.0;
    s
}

#[ebptv_macros::unit_test]
fn baseline_replays_the_measured_vortex_and_matches_pulses_seeding_brightness() {
    let truth = truth_scene();
    let out = crate::sim::simulate(&truth, 4242).unwrap();
    let rising: Vec<i64> = out
        .triggers
        .iter()
        .filter(|t| t.edge == Edge::Rising)
        .map(|t| t.t)
        .collect();
    let dir = tempfile::tempdir().unwrap();
    let csv = dir.path().join("flow_baseline.csv");
    let opts = BaselineOptions {
        bin_px: 32.0,
        ..BaselineOptions::default()
    };
    let train = PulseTrain::from_triggers(&rising).unwrap();
    let b = baseline_from_measurement(&out.events, &train, Geometry::new(320, 240), &csv, &opts)
        .unwrap();
    for n in &b.notes {
        println!("{n}");
    }
    let sc = &b.scenario;

    // Pulse timing: exact period, phase within a microsecond (trigger
    // times are integer µs).
    assert!((sc.light.pulse_hz - truth.light.pulse_hz).abs() < 1e-6 * truth.light.pulse_hz);
    assert!((sc.light.first_pulse_us - truth.light.first_pulse_us).abs() <= 1.0);

    // Seeding: detected particles per pulse per pixel; the truth counts
    // particles in the sheet, of which some are too dim or overlap.
    let rel = sc.seeding.ppp / truth.seeding.ppp;
    assert!(
        (0.7..=1.3).contains(&rel),
        "ppp {} vs {}",
        sc.seeding.ppp,
        truth.seeding.ppp
    );

    // Brightness and latency: the baseline's clusters look like the
    // measured ones (events per particle within 10 %, median first-event
    // latency within 2 µs; the baseline matched the median of all events),
    // on a fresh seed.
    let replay = {
        let mut r = sc.clone();
        r.duration_s = 0.02;
        crate::sim::simulate(&r, 99).unwrap()
    };
    let cluster = crate::cluster::ClusterParams {
        radius: crate::cluster::ClusterParams::radius_for_image_diameter(1.3),
        ..Default::default()
    };
    let pm = particles_of(&out.events, &timing_of(&truth), &cluster).unwrap();
    let ps = particles_of(&replay.events, &timing_of(sc), &cluster).unwrap();
    let mean = |p: &[crate::cluster::Particle]| {
        p.iter().map(|q| q.n_events as f64).sum::<f64>() / p.len() as f64
    };
    let median = |p: &[crate::cluster::Particle]| {
        let mut l: Vec<f64> = p.iter().map(|q| q.first_latency_us as f64).collect();
        l.sort_by(f64::total_cmp);
        l[l.len() / 2]
    };
    println!(
        "events/particle {:.3} vs {:.3}; median latency {:.1} vs {:.1} us",
        mean(&ps),
        mean(&pm),
        median(&ps),
        median(&pm)
    );
    assert!((mean(&ps) / mean(&pm) - 1.0).abs() < 0.10);
    assert!((median(&ps) - median(&pm)).abs() <= 2.0);

    // Flow: the replayed field (the simulator's own interpolant of the
    // written grid) against the truth, over the interior away from the
    // core, where a 32 px bin can resolve the field.
    let FlowSpec::Gridded { path, .. } = &sc.flow else {
        panic!("baseline flow is not gridded: {:?}", sc.flow);
    };
    assert_eq!(path, &csv);
    let replayed = Flow::build(&sc.flow).unwrap();
    let exact = Flow::build(&truth.flow).unwrap();
    let (mut se, mut ss, mut n) = (0.0, 0.0, 0.0);
    let mut worst = 0.0f64;
    for y in (24..=216).step_by(8) {
        for x in (24..=296).step_by(8) {
            let (x, y) = (x as f64, y as f64);
            let r = ((x - 160.0).powi(2) + (y - 120.0).powi(2)).sqrt();
            if r < 50.0 {
                continue;
            }
            let (ut, vt) = exact.velocity(x, y, 0.0);
            let (ur, vr) = replayed.velocity(x, y, 0.0);
            let e2 = (ur - ut).powi(2) + (vr - vt).powi(2);
            se += e2;
            ss += ut * ut + vt * vt;
            n += 1.0;
            worst = worst.max(e2.sqrt());
        }
    }
    let rel_rms = (se / ss).sqrt();
    println!(
        "flow: relative rms error {:.3} over {} points, worst {:.0} px/s",
        rel_rms, n, worst
    );
    assert!(rel_rms < 0.08, "relative rms error {rel_rms}");

    // The baseline is a complete scenario the simulator accepts.
    let text = sc.to_toml_string().unwrap();
    let back = Scenario::from_toml_str(&text).unwrap();
    assert_eq!(&back, sc);
}

#[ebptv_macros::unit_test]
fn baseline_refuses_a_recording_without_triggers() {
    let out = crate::sim::simulate(
        &Scenario {
            duration_s: 0.004,
            sensor: Sensor {
                width: 64,
                height: 48,
                roi: None,
            },
            ..Scenario::default()
        },
        1,
    )
    .unwrap();
    let dir = tempfile::tempdir().unwrap();
    let err = PulseTrain::from_triggers(&[])
        .and_then(|train| {
            baseline_from_measurement(
                &out.events,
                &train,
                Geometry::new(64, 48),
                &dir.path().join("f.csv"),
                &BaselineOptions::default(),
            )
        })
        .unwrap_err();
    assert!(err.to_string().contains("trigger"), "{err}");
    assert!(!dir.path().join("f.csv").exists());
}
