//! The parallel slice-and-stitch tracker (`crate::track::slice`) against
//! the sequential `Tracker` on simulator truth (paper-like synthetic
//! scenes, scored as in `tests/ptv_accuracy.rs`), and its determinism
//! across thread counts.
//!
//! The slices here are short (40 pulses) so that a scene of a few hundred
//! pulses crosses many seams: what the seams cost shows up clearly.

use crate::cluster::{ClusterParams, Particle};
use crate::sim::TruthSample;
use crate::track::slice::SliceTracker;
use crate::track::synth::{
    cluster_with_truth_sources, generate, score_with_sources, LinkScore, SynthParams, SynthPulse,
    INTERIOR_MARGIN,
};
use crate::track::{LinkedTrack, SliceParams, TrackParams, Tracker};

struct Clustered {
    pulses: Vec<(i64, f64, Vec<Particle>)>,
    det_truth: Vec<Option<u64>>,
    det_sources: Vec<Vec<u64>>,
    det_pulse: Vec<i64>,
    truth: Vec<TruthSample>,
}

fn cluster(scene: &[SynthPulse]) -> Clustered {
    let params = ClusterParams::default();
    let mut c = Clustered {
        pulses: Vec::new(),
        det_truth: Vec::new(),
        det_sources: Vec::new(),
        det_pulse: Vec::new(),
        truth: Vec::new(),
    };
    for sp in scene {
        let (parts, ids, _, sources) = cluster_with_truth_sources(sp, &params);
        c.det_pulse
            .extend(std::iter::repeat_n(sp.pulse.index, parts.len()));
        c.det_truth.extend(ids);
        c.det_sources.extend(sources);
        c.truth.extend_from_slice(&sp.truth);
        c.pulses.push((sp.pulse.index, sp.pulse.start_us, parts));
    }
    c
}

fn sequential(c: &Clustered, tp: &TrackParams) -> Vec<LinkedTrack> {
    let mut tracker = Tracker::new(tp.clone()).unwrap();
    let mut out = Vec::new();
    for (k, t, ps) in &c.pulses {
        out.extend(tracker.push_linked(*k, *t, ps).unwrap());
    }
    out.extend(tracker.finish().0);
    out
}

fn sliced(c: &Clustered, tp: &TrackParams, sp: SliceParams) -> Vec<LinkedTrack> {
    let mut st = SliceTracker::new(tp.clone(), sp).unwrap();
    let mut out = Vec::new();
    for (k, t, ps) in &c.pulses {
        out.extend(st.push(*k, *t, ps.clone()).unwrap());
    }
    out.extend(st.finish().unwrap().0);
    out
}

fn score(c: &Clustered, tracks: &[LinkedTrack], period_us: f64) -> LinkScore {
    score_with_sources(
        tracks,
        &c.det_truth,
        &c.det_sources,
        &c.det_pulse,
        &c.truth,
        period_us,
        INTERIOR_MARGIN,
    )
}

/// Short slices with the default overlap.
fn short_slices() -> SliceParams {
    SliceParams {
        slice_pulses: 40,
        ..Default::default()
    }
}

/// Sliced tracking scores like sequential tracking: link precision and
/// recall within 0.002, velocity errors at most 3 % larger, with seams
/// 4–6× denser than the default 256-pulse slices.
fn compare(sp: &SynthParams, slicing: SliceParams) {
    let scene = generate(sp);
    let c = cluster(&scene);
    // As benches/examples/ptv_conditions.rs: the search reaches 25 % past the largest
    // displacement.
    let tp = TrackParams {
        max_disp: (sp.max_disp * 1.25).max(10.0),
        ..Default::default()
    };
    let seq = score(&c, &sequential(&c, &tp), sp.period_us);
    let sli = score(&c, &sliced(&c, &tp, slicing), sp.period_us);
    println!("sequential {seq:?}\nsliced     {sli:?}");
    assert!(seq.truth_links > 20_000, "scene too small: {seq:?}");
    assert!(
        sli.precision >= seq.precision - 0.002,
        "precision {} vs {}",
        sli.precision,
        seq.precision
    );
    assert!(
        sli.recall >= seq.recall - 0.002,
        "recall {} vs {}",
        sli.recall,
        seq.recall
    );
    assert!(
        sli.velocity_rms_interior_px_per_pulse <= 1.03 * seq.velocity_rms_interior_px_per_pulse,
        "interior velocity rms {} vs {}",
        sli.velocity_rms_interior_px_per_pulse,
        seq.velocity_rms_interior_px_per_pulse
    );
    assert!(
        sli.velocity_rms_px_per_pulse <= 1.03 * seq.velocity_rms_px_per_pulse,
        "velocity rms {} vs {}",
        sli.velocity_rms_px_per_pulse,
        seq.velocity_rms_px_per_pulse
    );
}

#[ebptv_macros::unit_test]
fn sliced_matches_sequential_at_paper_conditions() {
    compare(
        &SynthParams {
            pulses: 320,
            ..Default::default()
        },
        short_slices(),
    );
}

#[ebptv_macros::unit_test]
fn sliced_matches_sequential_when_harder() {
    // ppp 0.02 (with 12 px/pulse and 5 % noise on top the sequential
    // tracker itself fails: precision ~0.3, nothing to compare).
    compare(
        &SynthParams {
            ppp: 0.02,
            pulses: 200,
            seed: 7,
            ..Default::default()
        },
        SliceParams {
            slice_pulses: 64,
            ..Default::default()
        },
    );
}

/// Same tracks (ids, points, detections) with 1, 2 and 3 threads and any
/// number of slices in flight.
#[ebptv_macros::unit_test]
fn sliced_output_is_identical_for_any_thread_count() {
    let scene = generate(&SynthParams {
        width: 160,
        height: 160,
        pulses: 200,
        seed: 3,
        ..Default::default()
    });
    let c = cluster(&scene);
    let tp = TrackParams {
        gates: crate::track::GateParams {
            max_track_length: 60,
            ..Default::default()
        },
        ..Default::default()
    };
    let run = |threads: usize, in_flight: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| {
                sliced(
                    &c,
                    &tp,
                    SliceParams {
                        in_flight,
                        ..short_slices()
                    },
                )
            })
    };
    let reference = run(1, 1);
    assert!(reference.len() > 100, "{}", reference.len());
    // Segments of at most max_track_length points, detections used once.
    let mut used = std::collections::HashSet::new();
    for t in &reference {
        assert!(t.track.points.len() <= 60 + 40);
        for d in t.detections.iter().flatten() {
            assert!(used.insert(*d), "detection {d} on two tracks");
        }
    }
    for (threads, in_flight) in [(2, 0), (2, 3), (3, 0)] {
        let r = run(threads, in_flight);
        assert!(
            r == reference,
            "{threads} threads, {in_flight} in flight: tracks differ"
        );
    }
}

/// What the overlap costs in accuracy (printed; BENCHMARKS.md): run with
/// `cargo test --release --test integration -- --ignored --nocapture track::tests::slice`.
#[ebptv_macros::unit_test]
#[ignore]
fn overlap_sweep() {
    let sp = SynthParams {
        pulses: 320,
        ..Default::default()
    };
    let c = cluster(&generate(&sp));
    let tp = TrackParams::default();
    let s = score(&c, &sequential(&c, &tp), sp.period_us);
    println!(
        "| sequential | {:.4} | {:.4} | {:.4} | {:.4} |",
        s.precision, s.recall, s.velocity_rms_px_per_pulse, s.velocity_rms_interior_px_per_pulse
    );
    for overlap in [4, 8, 12, 16, 24] {
        let sl = SliceParams {
            slice_pulses: 40,
            overlap,
            in_flight: 0,
        };
        let s = score(&c, &sliced(&c, &tp, sl), sp.period_us);
        println!(
            "| sliced 40, overlap {overlap} | {:.4} | {:.4} | {:.4} | {:.4} |",
            s.precision,
            s.recall,
            s.velocity_rms_px_per_pulse,
            s.velocity_rms_interior_px_per_pulse
        );
    }
}
