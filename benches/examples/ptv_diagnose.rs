//! Where the wrong and missed links of the synthetic scene come from
//! (`ebptv::track::synth::diagnose`), what linking costs, and which merged
//! images could be split:
//! `cargo run --release -p ebptv-benches --example ptv_diagnose -- links|cost|merged`

use std::collections::{BTreeMap, HashMap};

use ebptv::cluster::{pixel_labels_with, pulse_pixels, split_wide_clusters, ClusterParams};
use ebptv::track::synth::{cluster_with_truth_mixed, generate, run_and_diagnose, SynthParams};
use ebptv::track::TrackParams;

fn breakdown_of_link_errors() {
    for (ppp, disp, noise) in [(0.01, 8.0, 0.01), (0.02, 12.0, 0.05)] {
        if std::env::var("PTV_ONLY_PAPER").is_ok() && ppp > 0.01 {
            continue;
        }
        let seed = std::env::var("PTV_SEED")
            .ok()
            .and_then(|v| v.parse().ok())
            .unwrap_or(SynthParams::default().seed);
        let sp = SynthParams::conditions(ppp, disp, noise, seed);
        let scene = generate(&sp);
        // Knobs for experiments without rebuilding: PTV_<PARAM>=value.
        let env = |k: &str| std::env::var(k).ok().and_then(|v| v.parse::<f64>().ok());
        let d = TrackParams::default();
        let tp = TrackParams {
            max_disp: sp.search_reach(),
            max_gap: env("PTV_MAX_GAP").map_or(d.max_gap, |v| v as u32),
            min_length: env("PTV_MIN_LENGTH").map_or(d.min_length, |v| v as usize),
            gates: ebptv::track::GateParams {
                predict_window: env("PTV_PREDICT_WINDOW")
                    .map_or(d.gates.predict_window, |v| v as usize),
                n_sigma: env("PTV_N_SIGMA").unwrap_or(d.gates.n_sigma),
                min_search_radius: env("PTV_MIN_SEARCH").unwrap_or(d.gates.min_search_radius),
                repair_lag: env("PTV_REPAIR_LAG").map_or(d.gates.repair_lag, |v| v as usize),
                sigma_ceiling: env("PTV_SIGMA_CEILING").unwrap_or(d.gates.sigma_ceiling),
                ..d.gates
            },
            fit: ebptv::track::FitParams {
                fit_window: env("PTV_FIT_WINDOW").map_or(d.fit.fit_window, |v| v as usize),
                outlier_sigma: env("PTV_OUTLIER_SIGMA").unwrap_or(d.fit.outlier_sigma),
                ..d.fit
            },
            stitch: ebptv::track::StitchParams {
                confirm_after_gap: env("PTV_CONFIRM")
                    .map_or(d.stitch.confirm_after_gap, |v| v as usize),
                stitch_gap: env("PTV_STITCH_GAP").map_or(d.stitch.stitch_gap, |v| v as u32),
                step_split: env("PTV_STEP").unwrap_or(d.stitch.step_split),
                ..d.stitch
            },
            init: ebptv::track::InitParams {
                back_extend: env("PTV_BACK_EXTEND").map_or(d.init.back_extend, |v| v as usize),
                init_gap: env("PTV_INIT_GAP").map_or(d.init.init_gap, |v| v != 0.0),
                ghost_check_length: env("PTV_GHOST_LEN")
                    .map_or(d.init.ghost_check_length, |v| v as usize),
                ghost_sigma: env("PTV_GHOST_SIGMA").unwrap_or(d.init.ghost_sigma),
                ghost_check_init: env("PTV_GHOST_INIT")
                    .map_or(d.init.ghost_check_init, |v| v != 0.0),
                gap_first_step: env("PTV_GAP_FIRST").map_or(d.init.gap_first_step, |v| v != 0.0),
                ..d.init
            },
            ..d
        };
        let run = ebptv::track::synth::run_scene(&scene, &ClusterParams::default(), &tp).unwrap();
        let s = ebptv::track::synth::score_with_sources(
            &run.tracks,
            &run.det_truth,
            &run.det_sources,
            &run.det_pulse,
            &run.truth,
            sp.period_us,
            ebptv::track::synth::INTERIOR_MARGIN,
        );
        println!(
            "precision {:.4} (merged ok {:.4}, identity {:.4}) recall {:.4} ({} of {} truth links; \
             present {:.4}; set {:.4}) vel {:.3} interior {:.3}; {} links",
            s.precision,
            s.precision_merged_ok,
            s.precision_identity,
            s.recall,
            s.found_truth_links,
            s.truth_links,
            s.recall_present,
            s.recall_set,
            s.velocity_rms_px_per_pulse,
            s.velocity_rms_interior_px_per_pulse,
            s.links,
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
/// --toggle-collect='*link_linked*' target/release/examples/ptv_diagnose cost`).
/// Back extension and the delayed repair switched by PTV_BACK_EXTEND /
/// PTV_REPAIR_LAG, the ghost test by PTV_GHOST_LEN (0 = off, with
/// PTV_INIT_GAP=0 the linking without ghost test and gapped chains).
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
        init: ebptv::track::InitParams {
            back_extend: env("PTV_BACK_EXTEND").unwrap_or(d.init.back_extend),
            init_gap: env("PTV_INIT_GAP").map_or(d.init.init_gap, |v| v != 0),
            ghost_check_length: env("PTV_GHOST_LEN").unwrap_or(d.init.ghost_check_length),
            ghost_check_init: env("PTV_GHOST_LEN").map_or(d.init.ghost_check_init, |v| v != 0),
            gap_first_step: env("PTV_GAP_FIRST").map_or(d.init.gap_first_step, |v| v != 0),
            ..d.init
        },
        gates: ebptv::track::GateParams {
            repair_lag: env("PTV_REPAIR_LAG").unwrap_or(d.gates.repair_lag),
            ..d.gates
        },
        stitch: ebptv::track::StitchParams {
            step_split: env("PTV_STEP").map_or(d.stitch.step_split, |v| v as f64),
            ..d.stitch
        },
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

/// Merged images of two particles on the paper-like scene, by the
/// particles' true distance (0.25 px bins), whether a pixel holds events of
/// both, and the image's pixel count: which of them could be split at all,
/// given to which two tracks they belong (~3 800 of 83 200
/// images; most are 1–2.5 px pairs on disjoint pixels, 2–3 pixels).
fn merged_image_geometry() {
    let sp = SynthParams {
        width: 384,
        height: 384,
        ..Default::default()
    };
    let cp = ClusterParams::default();
    let mut hist: BTreeMap<(u32, bool, usize), u32> = BTreeMap::new();
    let mut images = 0;
    for s in &generate(&sp) {
        let pixels = pulse_pixels(&s.pulse, &cp);
        let mut labels = pixel_labels_with(&pixels, &cp);
        split_wide_clusters(&pixels, &mut labels, cp.split_extent);
        let index: HashMap<(u16, u16), usize> = pixels
            .iter()
            .enumerate()
            .map(|(i, p)| ((p.x, p.y), i))
            .collect();
        // Truth particles of each pixel's events (noise: none).
        let mut sources: Vec<Vec<u64>> = vec![Vec::new(); pixels.len()];
        let ev = &s.pulse.events;
        for i in 0..ev.len() {
            if let Some(id) = s.event_truth[i] {
                let v = &mut sources[index[&(ev.x[i], ev.y[i])]];
                if !v.contains(&id) {
                    v.push(id);
                }
            }
        }
        let n_labels = labels.iter().map(|&l| l as usize + 1).max().unwrap_or(0);
        images += n_labels;
        let mut members: Vec<Vec<usize>> = vec![Vec::new(); n_labels];
        for (i, &l) in labels.iter().enumerate() {
            members[l as usize].push(i);
        }
        let pos: HashMap<u64, (f64, f64)> = s
            .truth
            .iter()
            .map(|t| (t.particle_id, (t.x, t.y)))
            .collect();
        for m in &members {
            let mut ids: Vec<u64> = m.iter().flat_map(|&j| sources[j].clone()).collect();
            ids.sort_unstable();
            ids.dedup();
            if ids.len() != 2 {
                continue;
            }
            let (a, b) = (pos[&ids[0]], pos[&ids[1]]);
            let d = (a.0 - b.0).hypot(a.1 - b.1);
            let shared = m.iter().any(|&j| sources[j].len() > 1);
            *hist
                .entry(((d * 4.0) as u32, shared, m.len().min(4)))
                .or_default() += 1;
        }
    }
    println!("{images} images; merged pairs (distance from, shared pixel, pixels): count");
    for ((d, shared, n), c) in hist {
        println!("{:.2} px  shared {shared:5}  {n} px: {c}", d as f64 / 4.0);
    }
}

fn main() {
    match std::env::args().nth(1).as_deref() {
        Some("links") => breakdown_of_link_errors(),
        Some("cost") => linking_cost(),
        Some("merged") => merged_image_geometry(),
        _ => {
            eprintln!("usage: ptv_diagnose links|cost|merged");
            std::process::exit(2);
        }
    }
}
