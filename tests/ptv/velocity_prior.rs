//! The output fit's velocity prior from the local flow
//! (`TrackParams::velocity_prior`): the velocity error of the
//! paper-like synthetic scene (issue #5's target 0.05 px/pulse), and, on
//! a turbulent simulated scene, that it does not shrink the fluctuations
//! the grid stage turns into Reynolds stresses.
use crate::chain_common;

use ebptv::cluster::ClusterParams;
use ebptv::events::Chunk;
use ebptv::io::StreamInfo;
use ebptv::track::synth::{generate, run_and_score, LinkScore, SynthParams};
use ebptv::track::TrackParams;

fn paper_like(seed: u64, tp: &TrackParams) -> LinkScore {
    let sp = SynthParams {
        width: 384,
        height: 384,
        seed,
        ..Default::default()
    };
    let scene = generate(&sp);
    let (_, s) = run_and_score(&scene, &ClusterParams::default(), tp, sp.period_us).unwrap();
    println!("seed {seed}, prior {}: {s:?}", tp.velocity_prior);
    s
}

fn without_prior() -> TrackParams {
    TrackParams::default()
}

fn with_prior() -> TrackParams {
    TrackParams {
        velocity_prior: 1.0,
        ..Default::default()
    }
}

fn two_pass(mean: bool) -> TrackParams {
    TrackParams {
        velocity_prior_two_pass: true,
        velocity_prior_mean: mean,
        ..with_prior()
    }
}

/// The two-pass prior (`TrackParams::velocity_prior_two_pass`,
/// the flow from the first pass's fitted velocities over the whole run)
/// with the posterior mean on the paper-like scene, seed 1 (the scene its
/// radius and window were chosen on): issue #5's 0.05 px/pulse, 0.0494
/// measured (one-pass 0.0696, no prior 0.1299); held-out seeds 2 and 3
/// give 0.059 and 0.066 (BENCHMARKS.md). Links unchanged.
#[test]
fn two_pass_prior_at_paper_like_conditions() {
    let on = paper_like(1, &two_pass(true));
    let off = paper_like(1, &without_prior());
    assert_eq!((on.correct_links, on.links), (off.correct_links, off.links));
    assert!(
        on.velocity_rms_px_per_pulse <= 0.05,
        "velocity rms {}",
        on.velocity_rms_px_per_pulse
    );
    assert!(
        on.velocity_rms_interior_px_per_pulse <= 0.6 * off.velocity_rms_interior_px_per_pulse,
        "interior {} vs {} without",
        on.velocity_rms_interior_px_per_pulse,
        off.velocity_rms_interior_px_per_pulse
    );
}

/// The turbulent scene's stresses with the two-pass prior (numbers for
/// BENCHMARKS.md; ignored: `cargo test --release --test
/// ptv_velocity_prior turbulent_two_pass -- --ignored --nocapture`).
#[test]
#[ignore]
fn turbulent_two_pass_numbers() {
    let sc = chain_common::turbulent_roi_scenario();
    let chain_common::Recorded {
        chunks, info, flow, ..
    } = chain_common::record(&sc, 6);
    for (label, tp) in [
        ("off", without_prior()),
        ("two-pass variance-matching", two_pass(false)),
        ("two-pass posterior mean", two_pass(true)),
    ] {
        let t = turbulent(&chunks, &info, &flow, sc.light.pulse_hz, tp);
        println!("{label}: {t:?}");
    }
}

/// Paper-like 384² scene (seed 1, the scene the design was tried on, and
/// seed 2, held out): the prior takes the velocity rms from 0.130 /
/// 0.133 px/pulse to 0.100 / 0.103; the links are the same
/// (the prior only changes the output velocities).
#[test]
fn flow_prior_cuts_the_velocity_error_at_paper_like_conditions() {
    for seed in [1, 2] {
        let on = paper_like(seed, &with_prior());
        let off = paper_like(seed, &without_prior());
        assert!(
            on.velocity_rms_px_per_pulse <= 0.11,
            "seed {seed}: velocity rms {}",
            on.velocity_rms_px_per_pulse
        );
        assert!(
            on.velocity_rms_px_per_pulse <= 0.85 * off.velocity_rms_px_per_pulse,
            "seed {seed}: {} vs {} without",
            on.velocity_rms_px_per_pulse,
            off.velocity_rms_px_per_pulse
        );
        assert!(
            on.velocity_rms_interior_px_per_pulse <= off.velocity_rms_interior_px_per_pulse,
            "seed {seed}: interior {} vs {} without",
            on.velocity_rms_interior_px_per_pulse,
            off.velocity_rms_interior_px_per_pulse
        );
        assert_eq!((on.correct_links, on.links), (off.correct_links, off.links));
        // The posterior mean, least error per point (0.074 / 0.072).
        let mean = paper_like(
            seed,
            &TrackParams {
                velocity_prior_mean: true,
                ..with_prior()
            },
        );
        assert!(
            mean.velocity_rms_px_per_pulse <= 0.085,
            "seed {seed}: posterior mean {}",
            mean.velocity_rms_px_per_pulse
        );
    }
}

fn percentile(mut v: Vec<f64>, q: f64) -> f64 {
    v.sort_by(|a, b| a.total_cmp(b));
    v[((v.len() - 1) as f64 * q).round() as usize]
}

/// What the turbulent scene gives with one tracker setting.
#[derive(Debug)]
struct Turbulence {
    samples: usize,
    /// Rms error of the track samples' velocity against the flow at their
    /// position and time (px/pulse per axis).
    velocity_rms: f64,
    /// Median over bins of |measured − truth| / truth (uv: / |uv| of the
    /// modes) of uu, vv, uv.
    median_abs: [f64; 3],
    /// Median over bins of (measured − truth) / truth: the bias.
    median_signed: [f64; 3],
}

/// The preset `turbulent_bl` (random Fourier modes on a mean shear,
/// 10 kHz, ~2.5 px/pulse) in a 256 × 128 ROI for 0.1 s through the whole
/// chain; stresses of 16 px bins (linear fit, noise correction from the
/// pair estimator) against the same statistics of the analytic velocity
/// at the samples (as `tests/grid_sim.rs`).
fn turbulent(
    chunks: &[Chunk],
    info: &StreamInfo,
    flow: &ebptv::sim::Flow,
    pulse_hz: f64,
    tp: TrackParams,
) -> Turbulence {
    let samples = chain_common::track_samples(info, chunks, tp);
    let period_s = 1.0 / pulse_hz;
    let grids = chain_common::turbulent_roi_grids(&samples, flow);
    let sq: f64 = samples
        .iter()
        .zip(&grids.at_samples)
        .map(|(m, t)| (m.u - t.u).powi(2) + (m.v - t.v).powi(2))
        .sum();
    let velocity_rms = (sq / (2 * samples.len()) as f64).sqrt() * period_s;
    let (gm, gt) = (grids.measured, grids.truth);
    let (_, _, uv) = flow.known_stresses().unwrap();
    let mut abs: [Vec<f64>; 3] = Default::default();
    let mut signed: [Vec<f64>; 3] = Default::default();
    for (m, t) in gm.bins.iter().zip(&gt.bins) {
        if m.count >= 50 && m.uu.is_finite() && t.uu.is_finite() {
            for (k, (e, scale)) in [
                (m.uu - t.uu, t.uu),
                (m.vv - t.vv, t.vv),
                (m.uv - t.uv, uv.abs()),
            ]
            .into_iter()
            .enumerate()
            {
                abs[k].push(e.abs() / scale);
                signed[k].push(e / scale);
            }
        }
    }
    assert!(abs[0].len() >= 100, "{} bins", abs[0].len());
    Turbulence {
        samples: samples.len(),
        velocity_rms,
        median_abs: abs.map(|v| percentile(v, 0.5)),
        median_signed: signed.map(|v| percentile(v, 0.5)),
    }
}

/// The prior on a turbulent scene: the local flow's spread is large
/// there, so the prior weakens by itself. It must neither bias the
/// grid's Reynolds stresses low (shrinking the fluctuations towards the
/// local mean) nor raise the stress errors or the samples' velocity
/// error (see BENCHMARKS.md, "Tracking accuracy", for the numbers).
#[test]
fn flow_prior_does_not_shrink_turbulent_stresses() {
    let sc = chain_common::turbulent_roi_scenario();
    let chain_common::Recorded {
        chunks, info, flow, ..
    } = chain_common::record(&sc, 6);
    let on = turbulent(&chunks, &info, &flow, sc.light.pulse_hz, with_prior());
    let off = turbulent(&chunks, &info, &flow, sc.light.pulse_hz, without_prior());
    println!("with the prior {on:?}\nwithout {off:?}");
    assert_eq!(on.samples, off.samples);
    assert!(on.velocity_rms <= off.velocity_rms, "{on:?} vs {off:?}");
    for k in 0..3 {
        assert!(
            on.median_abs[k] <= off.median_abs[k] + 0.015,
            "stress {k}: {on:?} vs {off:?}"
        );
        // Not pulled below the truth: the posterior mean (least error per
        // point) took the stresses 3.5–5.5 % low here.
        assert!(
            on.median_signed[k] >= off.median_signed[k].min(0.0) - 0.02,
            "stress {k}: {on:?} vs {off:?}"
        );
    }
}

/// The numbers of BENCHMARKS.md ("Tracking accuracy"): seeds 1–3 of the paper-like
/// scene and the harsh one (ppp 0.02, 12 px/pulse, 5 % noise), prior off,
/// variance-matching, posterior mean. Ignored: `cargo test --release
/// --test ptv_velocity_prior -- --ignored --nocapture`.
#[test]
#[ignore]
fn velocity_prior_numbers() {
    let harsh = SynthParams {
        width: 384,
        height: 384,
        ppp: 0.02,
        max_disp: 12.0,
        noise_fraction: 0.05,
        ..Default::default()
    };
    let scenes: Vec<(String, SynthParams)> = (1..=3)
        .map(|seed| {
            (
                format!("paper-like seed {seed}"),
                SynthParams {
                    width: 384,
                    height: 384,
                    seed,
                    ..Default::default()
                },
            )
        })
        .chain(std::iter::once(("harsh seed 1".to_string(), harsh)))
        .collect();
    for (name, sp) in scenes {
        let scene = generate(&sp);
        for (label, tp) in [
            ("off", without_prior()),
            ("variance-matching", with_prior()),
            (
                "posterior mean",
                TrackParams {
                    velocity_prior_mean: true,
                    ..with_prior()
                },
            ),
            ("two-pass variance-matching", two_pass(false)),
            ("two-pass posterior mean", two_pass(true)),
        ] {
            let (_, s) =
                run_and_score(&scene, &ClusterParams::default(), &tp, sp.period_us).unwrap();
            println!(
                "{name}, {label}: velocity rms {:.4} (interior {:.4}), precision {:.4}, recall {:.4}",
                s.velocity_rms_px_per_pulse,
                s.velocity_rms_interior_px_per_pulse,
                s.precision,
                s.recall
            );
        }
    }
}

/// Score a `tracks.csv` against a simulated recording's truth as `ebptv
/// demo` does (for the demo row of BENCHMARKS.md with `ebptv track
/// --velocity-prior 1 --velocity-prior-two-pass`): `PV_SIM` the simulator's
/// output directory, `PV_TRACKS` the tracks. Ignored.
#[test]
#[ignore]
fn score_tracks_csv() {
    let (Ok(sim), Ok(tracks)) = (std::env::var("PV_SIM"), std::env::var("PV_TRACKS")) else {
        println!("PV_SIM / PV_TRACKS not set: skipped");
        return;
    };
    let sim = std::path::Path::new(&sim);
    let scenario =
        ebptv::sim::scenario::Scenario::from_toml_file(sim.join("scenario.toml")).unwrap();
    let truth = ebptv::evaluate::Truth::read(&sim.join("truth_particles.csv")).unwrap();
    let s = ebptv::evaluate::score_tracks(
        std::path::Path::new(&tracks),
        &truth,
        scenario.period_us(),
        1.0,
    )
    .unwrap();
    println!(
        "link precision {:.4}, recall {:.4}, velocity rms {:.4} px/pulse",
        s.link_precision, s.link_recall, s.velocity_rms_px_per_pulse
    );
}
