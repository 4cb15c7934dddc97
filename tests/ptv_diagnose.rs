//! Where the wrong and missed links of the synthetic scene come from
//! (`ebptv::track::synth::diagnose`). Ignored by default:
//! `cargo test --release --test ptv_diagnose -- --ignored --nocapture`

use ebptv::cluster::ClusterParams;
use ebptv::track::synth::{cluster_with_truth_mixed, generate, run_and_diagnose, SynthParams};
use ebptv::track::TrackParams;

#[test]
#[ignore]
fn breakdown_of_link_errors() {
    for (ppp, disp, noise) in [(0.01, 8.0, 0.01), (0.02, 12.0, 0.05)] {
        let sp = SynthParams {
            ppp,
            max_disp: disp,
            noise_fraction: noise,
            width: 384,
            height: 384,
            ..Default::default()
        };
        let scene = generate(&sp);
        // Knobs for experiments without rebuilding: PTV_<PARAM>=value.
        let env = |k: &str| std::env::var(k).ok().and_then(|v| v.parse::<f64>().ok());
        let d = TrackParams::default();
        let tp = TrackParams {
            max_disp: (disp * 1.25).max(10.0),
            predict_window: env("PTV_PREDICT_WINDOW").map_or(d.predict_window, |v| v as usize),
            fit_window: env("PTV_FIT_WINDOW").map_or(d.fit_window, |v| v as usize),
            max_gap: env("PTV_MAX_GAP").map_or(d.max_gap, |v| v as u32),
            n_sigma: env("PTV_N_SIGMA").unwrap_or(d.n_sigma),
            min_search_radius: env("PTV_MIN_SEARCH").unwrap_or(d.min_search_radius),
            min_length: env("PTV_MIN_LENGTH").map_or(d.min_length, |v| v as usize),
            outlier_sigma: env("PTV_OUTLIER_SIGMA").unwrap_or(d.outlier_sigma),
            confirm_after_gap: env("PTV_CONFIRM").map_or(d.confirm_after_gap, |v| v as usize),
            stitch_gap: env("PTV_STITCH_GAP").map_or(d.stitch_gap, |v| v as u32),
            back_extend: env("PTV_BACK_EXTEND").map_or(d.back_extend, |v| v as usize),
            repair_lag: env("PTV_REPAIR_LAG").map_or(d.repair_lag, |v| v as usize),
            init_gap: env("PTV_INIT_GAP").map_or(d.init_gap, |v| v != 0.0),
            sigma_ceiling: env("PTV_SIGMA_CEILING").unwrap_or(d.sigma_ceiling),
            ..d
        };
        let s = ebptv::track::synth::run_and_score(
            &scene,
            &ClusterParams::default(),
            &tp,
            sp.period_us,
        )
        .unwrap()
        .1;
        println!(
            "precision {:.4} recall {:.4} vel {:.3} interior {:.3}",
            s.precision,
            s.recall,
            s.velocity_rms_px_per_pulse,
            s.velocity_rms_interior_px_per_pulse
        );
        // Merged images by size: does extent or event count single them out?
        let mut table = std::collections::BTreeMap::new();
        for sp in &scene {
            let (parts, _, mixed) = cluster_with_truth_mixed(sp, &ClusterParams::default());
            for (p, m) in parts.iter().zip(mixed) {
                let key = (p.extent_x.max(p.extent_y) as u32, p.n_events.min(6));
                let e = table.entry(key).or_insert((0u32, 0u32));
                if m {
                    e.1 += 1;
                } else {
                    e.0 += 1;
                }
            }
        }
        if std::env::var("PTV_TABLE").is_ok() {
            println!("(max extent, events): (clean, merged) {table:?}");
        }
        let d = run_and_diagnose(&scene, &ClusterParams::default(), &tp).unwrap();
        println!("ppp {ppp} disp {disp} noise {noise}: {d:#?}");
        let detail =
            ebptv::track::synth::run_and_diagnose_detail(&scene, &ClusterParams::default(), &tp)
                .unwrap();
        println!("{detail:#?}");
    }
}

/// Linking cost (for callgrind: `valgrind --tool=callgrind
/// --toggle-collect='*link_linked*' target/release/deps/ptv_diagnose-* --ignored linking_cost`).
/// Back extension and the delayed repair switched by PTV_BACK_EXTEND /
/// PTV_REPAIR_LAG.
#[test]
#[ignore]
fn linking_cost() {
    let sp = SynthParams {
        width: 384,
        height: 384,
        ..Default::default()
    };
    let scene = generate(&sp);
    let mut parts = Vec::new();
    for s in &scene {
        parts.extend(cluster_with_truth_mixed(s, &ClusterParams::default()).0);
    }
    let env = |k: &str| std::env::var(k).ok().and_then(|v| v.parse::<usize>().ok());
    let d = TrackParams::default();
    let tp = TrackParams {
        back_extend: env("PTV_BACK_EXTEND").unwrap_or(d.back_extend),
        repair_lag: env("PTV_REPAIR_LAG").unwrap_or(d.repair_lag),
        init_gap: env("PTV_INIT_GAP").map_or(d.init_gap, |v| v != 0),
        ..d
    };
    let cpu = || {
        // Process CPU time (all threads: the fits run on rayon's).
        let mut ru: libc::rusage = unsafe { std::mem::zeroed() };
        // SAFETY: getrusage writes into the struct it is given.
        unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut ru) };
        let t = |v: libc::timeval| v.tv_sec as f64 + v.tv_usec as f64 * 1e-6;
        t(ru.ru_utime) + t(ru.ru_stime)
    };
    let mut best = f64::MAX;
    for _ in 0..5 {
        let c0 = cpu();
        let (tracks, _, stats) = ebptv::track::link_linked(&parts, &tp).unwrap();
        best = best.min(cpu() - c0);
        if best == cpu() - c0 {
            println!(
                "{} particles, {} tracks, {stats:?}",
                parts.len(),
                tracks.len()
            );
        }
    }
    println!("linking: {:.3} CPU-s (best of 5)", best);
}
