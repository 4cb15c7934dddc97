//! Clustering + tracking on the full simulator (`ebptv::sim`, preset
//! "demo": Lamb–Oseen vortex, 0.01 ppp, 5 kHz, camera latency, readout and
//! noise effects). Events go to the pulse whose start precedes them (the
//! simulator's true pulse starts; the pulses stage is tested on its own),
//! detections are attributed to the nearest truth particle within 1.5 px.

use ebptv::cluster::{cluster_pulses, ClusterParams};
use ebptv::events::EventChunk;
use ebptv::pulses::PulseEvents;
use ebptv::track::synth::{attribute_nearest, score};
use ebptv::track::{TrackParams, Tracker};

#[test]
fn demo_scenario_tracks_against_truth() {
    let mut sc = ebptv::sim::presets::preset("demo").unwrap();
    sc.duration_s = 0.02;
    let sim = ebptv::sim::simulate(&sc, 7).unwrap();
    let starts = &sim.pulse_starts_us;
    assert!(starts.len() > 50);
    let mut pulses: Vec<PulseEvents> = starts
        .iter()
        .enumerate()
        .map(|(k, &s)| PulseEvents {
            index: k as i64,
            start_us: s,
            events: EventChunk::default(),
        })
        .collect();
    let ev = &sim.events;
    for i in 0..ev.len() {
        let t = ev.t[i] as f64;
        let k = starts.partition_point(|&s| s <= t);
        if k > 0 {
            pulses[k - 1]
                .events
                .push(ev.t[i], ev.x[i], ev.y[i], ev.p[i]);
        }
    }
    let parts = cluster_pulses(&pulses, &ClusterParams::default()).unwrap();
    let all: Vec<_> = parts.iter().flatten().copied().collect();
    let mut tracker = Tracker::new(TrackParams::default()).unwrap();
    let mut tracks = Vec::new();
    for (pe, ps) in pulses.iter().zip(&parts) {
        tracks.extend(tracker.push_linked(pe.index, pe.start_us, ps).unwrap());
    }
    tracks.extend(tracker.finish().0);
    let det_truth = attribute_nearest(&all, &sim.truth, 1.5);
    let det_pulse: Vec<i64> = all.iter().map(|p| p.pulse).collect();
    let period = starts[1] - starts[0];
    let s = score(&tracks, &det_truth, &det_pulse, &sim.truth, period, 5);
    let attributed = det_truth.iter().filter(|d| d.is_some()).count() as f64 / all.len() as f64;
    let truth_per_pulse = sim.truth.len() as f64 / starts.len() as f64;
    println!(
        "{} events, {} pulses, {:.0} truth particles/pulse, {:.0} detections/pulse ({:.1} % near a truth particle), {} tracks, {s:?}",
        ev.len(),
        starts.len(),
        truth_per_pulse,
        all.len() as f64 / starts.len() as f64,
        100.0 * attributed,
        tracks.len()
    );
    assert!(s.truth_links > 5_000, "{s:?}");
    // Issue targets: recall >= 0.95 and velocity rms <= 0.05 px/pulse are
    // met; precision reaches ~0.984 (target 0.99; see BENCHMARKS.md; 0.972
    // before wide clusters were split).
    assert!(s.precision >= 0.975, "precision {}", s.precision);
    assert!(s.recall >= 0.95, "recall {}", s.recall);
    // 0.027 with the adaptive output fit (a fixed 11-point fit: 0.036; target 0.05).
    assert!(
        s.velocity_rms_px_per_pulse <= 0.035,
        "velocity rms {}",
        s.velocity_rms_px_per_pulse
    );
}
