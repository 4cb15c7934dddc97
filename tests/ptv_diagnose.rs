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
    }
}
