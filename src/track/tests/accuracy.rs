//! Clustering + tracking against exact ground truth on synthetic scenes
//! (`crate::track::synth`; definitions of precision, recall and velocity
//! error in its module docs). Thresholds are what the implementation
//! reaches with a margin; BENCHMARKS.md compares them with the issue's
//! targets (precision 0.99, recall 0.95, 0.05 px/pulse), which are not met
//! at ppp 0.01 — close particle pairs whose images merge (closer than
//! ~1 px, beyond what splitting wide clusters can separate) set the limit.

use crate::cluster::ClusterParams;
use crate::track::synth::{generate, run_and_score, SynthParams};
use crate::track::TrackParams;

fn run(sp: &SynthParams) -> crate::track::synth::LinkScore {
    let scene = generate(sp);
    let (tracks, s) = run_and_score(
        &scene,
        &ClusterParams::default(),
        &TrackParams::default(),
        sp.period_us,
    )
    .unwrap();
    println!("{} tracks, {s:?}", tracks.len());
    assert!(
        s.truth_links > 10_000,
        "scene too small to mean anything: {s:?}"
    );
    s
}

#[ebptv_macros::unit_test]
fn paper_like_conditions() {
    // ppp 0.01, 1.3-2 events per firing particle, 95 % firing, 1 % noise
    // events, up to 8 px/pulse, particles leaving/entering the sheet.
    let s = run(&SynthParams::default());
    assert!(s.precision >= 0.94, "precision {}", s.precision);
    // Counting a link through an unresolvable merged image of the track's
    // own particle as correct (`precision_merged_ok`): 0.988 here, 0.991
    // on the 384² scene of BENCHMARKS.md (issue target 0.99).
    assert!(
        s.precision_merged_ok >= 0.985,
        "precision (merged ok) {}",
        s.precision_merged_ok
    );
    // 0.921 with the backward extension of new tracks and the fixed-lag
    // repair (they take the 384² scene from 0.922 to 0.940).
    assert!(s.recall >= 0.91, "recall {}", s.recall);
    assert!(
        s.velocity_rms_interior_px_per_pulse <= 0.10,
        "interior velocity rms {}",
        s.velocity_rms_interior_px_per_pulse
    );
    assert!(
        s.velocity_rms_px_per_pulse <= 0.30,
        "velocity rms {}",
        s.velocity_rms_px_per_pulse
    );
}

#[ebptv_macros::unit_test]
fn sparse_seeding_meets_the_issue_targets_on_links() {
    // At ppp 0.002 close pairs are rare and linking is nearly perfect.
    let s = run(&SynthParams {
        ppp: 0.002,
        width: 512,
        height: 512,
        ..Default::default()
    });
    assert!(s.precision >= 0.98, "precision {}", s.precision);
    assert!(s.recall >= 0.95, "recall {}", s.recall);
}

#[ebptv_macros::unit_test]
fn dense_noisy_fast_conditions() {
    // The hardest row of BENCHMARKS.md: ppp 0.02, up to 12 px/pulse, 5 %
    // noise events (384², 60 pulses). Without the position-noise ceiling
    // and the ghost test: precision 0.754, recall 0.651, velocity rms 3.44
    // px/pulse; with the ceiling at 0.45 px: 0.800, 0.678, 2.86; with the
    // ghost test against the local flow too: 0.860, 0.821, 0.658.
    let sp = SynthParams {
        ppp: 0.02,
        max_disp: 12.0,
        noise_fraction: 0.05,
        width: 384,
        height: 384,
        ..Default::default()
    };
    let scene = generate(&sp);
    let tp = TrackParams {
        max_disp: 15.0,
        ..Default::default()
    };
    let (_, s) = run_and_score(&scene, &ClusterParams::default(), &tp, sp.period_us).unwrap();
    println!("{s:?}");
    assert!(s.truth_links > 100_000, "{s:?}");
    assert!(s.precision >= 0.85, "precision {}", s.precision);
    assert!(s.recall >= 0.80, "recall {}", s.recall);
    assert!(
        s.velocity_rms_px_per_pulse <= 1.0,
        "velocity rms {}",
        s.velocity_rms_px_per_pulse
    );
}

#[ebptv_macros::unit_test]
fn ghost_test_keeps_short_tracks_at_paper_like_conditions() {
    // The 384² paper-like scene of BENCHMARKS.md. No ghost test,
    // `min_length` 5: precision 0.9628, recall 0.9395, velocity rms
    // 0.1337 px/pulse; with `min_length` 4 alone recall 0.9501 but
    // velocity 0.244 (four-detection ghosts). With short tracks and
    // new chains checked against the local flow of the established tracks
    // (`TrackParams::ghost_check_length`, `ghost_check_init`) and chains
    // with one missed pulse (`init_gap`): 0.9632 / 0.9529 / 0.1313.
    let run = paper_like_384_runner();
    let s = run(&TrackParams::default());
    assert!(s.truth_links > 60_000, "{s:?}");
    assert!(s.recall >= 0.95, "recall {}", s.recall);
    assert!(s.precision >= 0.9628, "precision {}", s.precision);
    // The turning-path predictor (`TrackParams::turn_model`,
    // `young_turn_sigma`) keeps some noisy young tracks alive here:
    // 0.1317 → 0.1340 (BENCHMARKS.md, "Tracking accuracy on independent
    // recordings").
    assert!(
        s.velocity_rms_px_per_pulse <= 0.1345,
        "velocity rms {}",
        s.velocity_rms_px_per_pulse
    );
    // The ghost test is what makes four-detection tracks affordable:
    // without it, the same short tracks cost velocity.
    let without = run(&TrackParams {
        min_length: 4,
        init: crate::track::InitParams {
            ghost_check_length: 0,
            ghost_check_init: false,
            ..Default::default()
        },
        ..Default::default()
    });
    assert!(
        without.velocity_rms_px_per_pulse > s.velocity_rms_px_per_pulse + 0.05,
        "without the ghost test {} vs {}",
        without.velocity_rms_px_per_pulse,
        s.velocity_rms_px_per_pulse
    );
}

#[ebptv_macros::unit_test]
fn cutting_tracks_at_steps_removes_swaps() {
    // A track whose particle is missed while an untracked
    // neighbour 1–4 px away lies in its gate goes on with the neighbour
    // (`benches/examples/ptv_swaps.rs`); ended tracks are cut where their positions
    // jump (`TrackParams::step_split`). Paper-like 384² scene, without the cut:
    // precision 0.9632, recall 0.9529, interior velocity rms 0.064.
    let run = paper_like_384_runner();
    let on = run(&TrackParams::default());
    let off = run(&TrackParams {
        stitch: crate::track::StitchParams {
            step_split: 0.0,
            ..Default::default()
        },
        ..Default::default()
    });
    assert!(on.precision >= 0.9645, "precision {}", on.precision);
    assert!(on.precision >= off.precision + 0.0015, "{on:?} vs {off:?}");
    assert!(on.recall >= 0.95, "recall {}", on.recall);
    assert!(
        on.velocity_rms_interior_px_per_pulse <= 0.058,
        "interior velocity rms {}",
        on.velocity_rms_interior_px_per_pulse
    );
    assert!(
        on.velocity_rms_px_per_pulse <= off.velocity_rms_px_per_pulse,
        "velocity rms {} vs {}",
        on.velocity_rms_px_per_pulse,
        off.velocity_rms_px_per_pulse
    );
}

#[ebptv_macros::unit_test]
fn gapped_chains_search_only_along_the_flow() {
    // Chains that skip a pulse look for their second particle
    // only where the local flow leads (`TrackParams::gap_first_step`):
    // far fewer first steps expanded, the same links to within a few.
    use crate::track::synth::cluster_with_truth;
    use crate::track::Tracker;
    let sp = SynthParams {
        width: 256,
        height: 256,
        ..Default::default()
    };
    let scene = generate(&sp);
    let run = |gap_first_step: bool| {
        let mut tracker = Tracker::new(TrackParams {
            init: crate::track::InitParams {
                gap_first_step,
                ..Default::default()
            },
            ..Default::default()
        })
        .unwrap();
        let mut links = 0usize;
        for s in &scene {
            let (parts, _) = cluster_with_truth(s, &ClusterParams::default());
            for t in tracker
                .push_linked(s.pulse.index, s.pulse.start_us, &parts)
                .unwrap()
            {
                links += t.track.points.len() - 1;
            }
        }
        let expanded = tracker.chains_enumerated();
        let (rest, _) = tracker.finish();
        links += rest.iter().map(|t| t.track.points.len() - 1).sum::<usize>();
        (expanded, links)
    };
    let (fast, fast_links) = run(true);
    let (full, full_links) = run(false);
    println!("first steps {fast} vs {full}; links {fast_links} vs {full_links}");
    assert!(fast * 10 < full * 7, "first steps {fast} vs {full}");
    let diff = (fast_links as f64 - full_links as f64).abs();
    assert!(
        diff <= 0.002 * full_links as f64,
        "links {fast_links} vs {full_links}"
    );
}

/// The 384² paper-like scene of BENCHMARKS.md ("Accuracy vs conditions"),
/// generated once, and a function that tracks it with the given
/// parameters and scores the links against its truth (printed).
fn paper_like_384_runner() -> impl Fn(&TrackParams) -> crate::track::synth::LinkScore {
    let sp = SynthParams {
        width: 384,
        height: 384,
        ..Default::default()
    };
    let scene = generate(&sp);
    move |tp: &TrackParams| {
        let (_, s) = run_and_score(&scene, &ClusterParams::default(), tp, sp.period_us).unwrap();
        println!("{s:?}");
        s
    }
}
