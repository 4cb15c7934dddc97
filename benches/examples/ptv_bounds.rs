//! What the synthetic scene allows at best: the tracker's links under the
//! strict, merged-ok and identity scorings, the same for the oracle tracks
//! (a tracker that knew every particle), and the velocity error of the
//! tracker, of the tracker's own output fit on the oracle tracks, and the
//! quadratic floors (definitions in `ebptv::track::synth`'s module docs).
//! ~6 s for the four scenes after the build:
//! `cargo run --release -p ebptv-benches --example ptv_bounds`
//! (`PTV_SCENES=paper` runs the three paper-like seeds only;
//! `PTV_FIT_MIN_WINDOW`, `PTV_FIT_BIAS_WEIGHT`, `PTV_FIT_ACCEL` override
//! the output fit's parameters, for the tracker and the oracle alike).

use ebptv::cluster::ClusterParams;
use ebptv::track::synth::{
    generate, identity_labels, oracle_report, run_scene, score_with_sources, SynthParams,
    INTERIOR_MARGIN,
};
use ebptv::track::TrackParams;

fn main() {
    let paper_only = std::env::var("PTV_SCENES").is_ok_and(|v| v == "paper");
    // (name, ppp, px/pulse, noise, seed): the 384² scenes of BENCHMARKS.md.
    let scenes = [
        ("paper-like seed 1", 0.01, 8.0, 0.01, 1),
        ("paper-like seed 2", 0.01, 8.0, 0.01, 2),
        ("paper-like seed 3", 0.01, 8.0, 0.01, 3),
        ("harsh seed 1", 0.02, 12.0, 0.05, 1),
    ];
    let mut links = String::from(
        "| scene | tracker strict | merged-ok | identity | recall strict | recall set | \
         oracle strict | merged-ok | identity | oracle recall strict | set | \
         long oracle strict | exclusive oracle strict | its recall strict / set | \
         exclusive, prediction σ 0.1 / 0.2 / 0.3 px: strict | \
         oracle skipping merged images: strict / its recall strict |\n\
         |---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    let mut vel = String::from(
        "| scene | tracker strict | tracker identity | oracle, our fit | floor, window quadratic | \
         floor, track quadratic | floor, window with accel prior | \
         floor, same, noise by event count | best window (noise + bias) | same with accel prior | \
         σ all / clean (fit σ, accel) |\n\
         |---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    for (name, ppp, disp, noise, seed) in scenes {
        if paper_only && ppp > 0.01 {
            continue;
        }
        let sp = SynthParams::conditions(ppp, disp, noise, seed);
        // As `tests/ptv_conditions.rs`: the search reaches 1.25× the
        // largest displacement (the default 10 px below 8 px/pulse).
        // Output-fit overrides for comparisons (PTV_FIT_MIN_WINDOW,
        // PTV_FIT_BIAS_WEIGHT, PTV_FIT_ACCEL: px/pulse², 0 = no prior).
        let env = |k: &str| std::env::var(k).ok().and_then(|v| v.parse::<f64>().ok());
        let d = TrackParams::default();
        let tp = TrackParams {
            max_disp: sp.search_reach(),
            fit: ebptv::track::FitParams {
                fit_min_window: env("PTV_FIT_MIN_WINDOW")
                    .map_or(d.fit.fit_min_window, |v| v as usize),
                fit_bias_weight: env("PTV_FIT_BIAS_WEIGHT").unwrap_or(d.fit.fit_bias_weight),
                fit_accel_rms: env("PTV_FIT_ACCEL").map_or(d.fit.fit_accel_rms, Some),
                ..d.fit
            },
            ..d
        };
        let run = run_scene(&generate(&sp), &ClusterParams::default(), &tp).unwrap();
        let s = score_with_sources(
            &run.tracks,
            &run.det_truth,
            &run.det_sources,
            &run.det_pulse,
            &run.truth,
            sp.period_us,
            INTERIOR_MARGIN,
        );
        let o = oracle_report(&run, &tp, sp.period_us, INTERIOR_MARGIN);
        // The tracker's identity-wrong links by kind: through a merged
        // image (the track changes particle where the two met), at a
        // noise-only detection, or between clean images (a swap).
        let (mut merged, mut noise, mut clean) = (0u64, 0u64, 0u64);
        for t in &run.tracks {
            let serials: Vec<usize> = t.detections.iter().flatten().map(|&d| d as usize).collect();
            let labels = identity_labels(&serials, &run.det_truth, &run.det_sources);
            for (w, l) in serials.windows(2).zip(labels.windows(2)) {
                if l[0].is_some() && l[0] == l[1] {
                    continue;
                }
                let src = |d: usize| run.det_sources[d].len();
                if src(w[0]) == 0 || src(w[1]) == 0 {
                    noise += 1;
                } else if src(w[0]) > 1 || src(w[1]) > 1 {
                    merged += 1;
                } else {
                    clean += 1;
                }
            }
        }
        assert_eq!(merged + noise + clean, s.identity_wrong_links);
        println!(
            "{name}: identity-wrong links {} = {merged} through a merged image + {noise} at noise + {clean} swaps between clean images",
            s.identity_wrong_links
        );
        println!("{name}: tracker {s:?}\noracle {o:?}");
        // The identity count lies between strict and merged-ok by
        // construction; a table that broke it would be scoring nonsense.
        for sc in [&s, &o.score] {
            assert!(sc.precision <= sc.precision_identity + 1e-12, "{sc:?}");
            assert!(
                sc.precision_identity <= sc.precision_merged_ok + 1e-12,
                "{sc:?}"
            );
        }
        links.push_str(&format!(
            "| {name} | {:.4} | {:.4} | {:.4} | {:.4} | {:.4} | {:.4} | {:.4} | {:.4} | {:.4} | {:.4} | {:.4} | {:.4} | {:.4} / {:.4} | {} | {:.4} / {:.4} |\n",
            s.precision,
            s.precision_merged_ok,
            s.precision_identity,
            s.recall,
            s.recall_set,
            o.score.precision,
            o.score.precision_merged_ok,
            o.score.precision_identity,
            o.score.recall,
            o.score.recall_set,
            o.score_long.precision,
            o.score_exclusive.precision,
            o.score_exclusive.recall,
            o.score_exclusive.recall_set,
            o.score_exclusive_noisy
                .iter()
                .map(|(_, e)| format!("{:.4}", e.precision))
                .collect::<Vec<_>>()
                .join(" / "),
            o.score_skip_merged.precision,
            o.score_skip_merged.recall,
        ));
        vel.push_str(&format!(
            "| {name} | {:.3} ({:.3}) | {:.3} ({:.3}) | {:.3} ({:.3}) | {:.3} ({:.3}) | {:.3} ({:.3}) | {:.3} ({:.3}) | {:.3} ({:.3}) | {:.3} ({:.3}) | {:.3} ({:.3}) | {:.3} / {:.3} ({:.3}, {:.4}) |\n",
            s.velocity_rms_px_per_pulse,
            s.velocity_rms_interior_px_per_pulse,
            s.velocity_rms_identity_px_per_pulse,
            s.velocity_rms_identity_interior_px_per_pulse,
            o.velocity_rms_fit,
            o.velocity_rms_fit_interior,
            o.floor_window,
            o.floor_window_interior,
            o.floor_track,
            o.floor_track_interior,
            o.floor_window_prior,
            o.floor_window_prior_interior,
            o.floor_window_prior_weighted,
            o.floor_window_prior_weighted_interior,
            o.best_window,
            o.best_window_interior,
            o.best_window_prior,
            o.best_window_prior_interior,
            o.sigma_all,
            o.sigma_clean,
            o.fit_sigma,
            o.fit_accel_rms,
        ));
    }
    println!("\nLinks (precision, recall):\n{links}\nVelocity rms, px/pulse, all points (interior):\n{vel}");
}
