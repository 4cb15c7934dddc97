//! The table of BENCHMARKS.md: link scores as conditions get harder.
//! A few seconds per row: `cargo run --release -p ebptv-benches --example ptv_conditions`
//! (`PTV_MIN_LENGTH`, `PTV_FIT_ACCEL`, `PTV_STEP`, `PTV_GAP_FIRST`
//! override those parameters, `PTV_SEED` the scene's seed, `PTV_ROWS=1`
//! runs the paper-like and the all-three rows only).

use ebptv::cluster::ClusterParams;
use ebptv::track::synth::{generate, run_and_score, SynthParams};
use ebptv::track::TrackParams;

fn main() {
    // Overrides for comparisons: PTV_MIN_LENGTH, PTV_FIT_ACCEL (px/pulse²;
    // 0 = the output fit without the curvature prior).
    let env = |k: &str| std::env::var(k).ok().and_then(|v| v.parse::<f64>().ok());
    let rows: [(&str, f64, f64, f64); 6] = [
        ("paper-like", 0.01, 8.0, 0.01),
        ("ppp 0.005", 0.005, 8.0, 0.01),
        ("ppp 0.02", 0.02, 8.0, 0.01),
        ("12 px/pulse", 0.01, 12.0, 0.01),
        ("5 % noise", 0.01, 8.0, 0.05),
        ("all three", 0.02, 12.0, 0.05),
    ];
    println!("| conditions | ppp | px/pulse | noise | precision | precision (merged ok) | precision (identity) | recall | recall (present) | recall (set) | vel rms (px/pulse) | interior vel rms |");
    println!("|---|---|---|---|---|---|---|---|---|---|---|---|");
    for (name, ppp, disp, noise) in rows {
        if env("PTV_ROWS") == Some(1.0) && !matches!(name, "paper-like" | "all three") {
            continue;
        }
        let seed = env("PTV_SEED").map_or(SynthParams::default().seed, |v| v as u64);
        let sp = SynthParams::conditions(ppp, disp, noise, seed);
        let scene = generate(&sp);
        let d = TrackParams::default();
        let tp = TrackParams {
            max_disp: sp.search_reach(),
            min_length: env("PTV_MIN_LENGTH").map_or(d.min_length, |v| v as usize),
            fit: ebptv::track::FitParams {
                fit_accel_rms: env("PTV_FIT_ACCEL").map_or(d.fit.fit_accel_rms, Some),
                ..d.fit
            },
            stitch: ebptv::track::StitchParams {
                step_split: env("PTV_STEP").unwrap_or(d.stitch.step_split),
                ..d.stitch
            },
            init: ebptv::track::InitParams {
                gap_first_step: env("PTV_GAP_FIRST").map_or(d.init.gap_first_step, |v| v != 0.0),
                ..d.init
            },
            ..d
        };
        let (_, s) = run_and_score(&scene, &ClusterParams::default(), &tp, sp.period_us).unwrap();
        println!(
            "| {name} | {ppp} | {disp} | {noise} | {:.4} | {:.4} | {:.4} | {:.4} | {:.4} | {:.4} | {:.3} | {:.3} |",
            s.precision,
            s.precision_merged_ok,
            s.precision_identity,
            s.recall,
            s.recall_present,
            s.recall_set,
            s.velocity_rms_px_per_pulse,
            s.velocity_rms_interior_px_per_pulse
        );
    }
}
