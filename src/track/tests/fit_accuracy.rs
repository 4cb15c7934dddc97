//! The output fit's curvature prior on the paper-like synthetic scene
//! (`crate::track::synth`, the test size of tests/ptv_accuracy.rs): the
//! velocity error over all scored points, against the same tracks fitted
//! without the prior (`fit_accel_rms: Some(0.0)`, a plain least-squares fit). The
//! links are the same either way; only the fitted velocities change.

use crate::cluster::ClusterParams;
use crate::track::synth::{generate, run_and_score, LinkScore, SynthParams};
use crate::track::TrackParams;

fn score(sp: &SynthParams, tp: &TrackParams) -> LinkScore {
    let scene = generate(sp);
    let (_, s) = run_and_score(&scene, &ClusterParams::default(), tp, sp.period_us).unwrap();
    println!("{s:?}");
    s
}

#[ebptv_macros::unit_test]
fn curvature_prior_lowers_the_velocity_error_on_the_paper_like_scene() {
    let sp = SynthParams::default();
    let plain = score(
        &sp,
        &TrackParams {
            fit: crate::track::FitParams {
                fit_accel_rms: Some(0.0),
                ..Default::default()
            },
            ..Default::default()
        },
    );
    let prior = score(&sp, &TrackParams::default());
    assert!(prior.truth_links > 10_000, "{prior:?}");
    assert_eq!(
        (prior.precision, prior.recall),
        (plain.precision, plain.recall),
        "the fit does not change links"
    );
    println!(
        "velocity rms {:.4} -> {:.4}, interior {:.4} -> {:.4} px/pulse",
        plain.velocity_rms_px_per_pulse,
        prior.velocity_rms_px_per_pulse,
        plain.velocity_rms_interior_px_per_pulse,
        prior.velocity_rms_interior_px_per_pulse
    );
    // No prior: 0.213 over all points; the prior 0.193. The
    // error is the ends of short tracks (benches/examples/ptv_velocity_breakdown.rs).
    assert!(
        prior.velocity_rms_px_per_pulse <= 0.20,
        "velocity rms {}",
        prior.velocity_rms_px_per_pulse
    );
    assert!(
        prior.velocity_rms_px_per_pulse <= 0.95 * plain.velocity_rms_px_per_pulse,
        "{} -> {}",
        plain.velocity_rms_px_per_pulse,
        prior.velocity_rms_px_per_pulse
    );
    // The interior keeps its windows (their curvature is measured).
    assert!(
        prior.velocity_rms_interior_px_per_pulse <= 1.02 * plain.velocity_rms_interior_px_per_pulse,
        "interior {} -> {}",
        plain.velocity_rms_interior_px_per_pulse,
        prior.velocity_rms_interior_px_per_pulse
    );
}
