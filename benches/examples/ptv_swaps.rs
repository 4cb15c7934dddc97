//! Swaps: links of one track between clean images of two different
//! particles. Where are they, and what happened to the other particle?
//! Prints counts against the truth, paper-like 384²:
//! `cargo run --release -p ebptv-benches --example ptv_swaps`
//! (`PTV_SEED` picks the scene; parameters as `ptv_diagnose links`'s knobs).

use std::collections::{BTreeMap, HashMap};

use ebptv::cluster::ClusterParams;
use ebptv::track::synth::{generate, run_scene, SynthParams};
use ebptv::track::TrackParams;

fn main() {
    let env = |k: &str| std::env::var(k).ok().and_then(|v| v.parse::<f64>().ok());
    let sp = SynthParams {
        width: 384,
        height: 384,
        seed: env("PTV_SEED").map_or(SynthParams::default().seed, |v| v as u64),
        ..Default::default()
    };
    let scene = generate(&sp);
    let d = TrackParams::default();
    let tp = TrackParams {
        max_disp: 10.0,
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
    let run = run_scene(&scene, &ClusterParams::default(), &tp).unwrap();
    println!("{:?}", run.stats);
    let n_det = run.det_truth.len();
    let mut track_of = vec![usize::MAX; n_det];
    let mut pos_in = vec![usize::MAX; n_det];
    let tracks: Vec<Vec<usize>> = run
        .tracks
        .iter()
        .map(|t| t.detections.iter().flatten().map(|&d| d as usize).collect())
        .collect();
    for (ti, t) in tracks.iter().enumerate() {
        for (i, &d) in t.iter().enumerate() {
            track_of[d] = ti;
            pos_in[d] = i;
        }
    }
    let mut det_of: HashMap<(i64, u64), usize> = HashMap::new();
    for (s, (id, &k)) in run.det_truth.iter().zip(&run.det_pulse).enumerate() {
        if let Some(id) = id {
            det_of.entry((k, *id)).or_insert(s);
        }
    }
    let truth_xy: HashMap<(i64, u64), (f64, f64)> = run
        .truth
        .iter()
        .map(|t| ((t.pulse, t.particle_id), (t.x, t.y)))
        .collect();
    let mut counts: BTreeMap<String, u32> = BTreeMap::new();
    let mut bump = |k: String| *counts.entry(k).or_default() += 1;
    for (ti, t) in tracks.iter().enumerate() {
        let n = t.len();
        for i in 0..n.saturating_sub(1) {
            let (a, b) = (t[i], t[i + 1]);
            let (Some(p), Some(q)) = (run.det_truth[a], run.det_truth[b]) else {
                continue;
            };
            if p == q {
                continue;
            }
            let (sa, sb) = (&run.det_sources[a], &run.det_sources[b]);
            if sa.iter().any(|id| sb.binary_search(id).is_ok()) {
                continue; // merged images: not a swap
            }
            let (ka, kb) = (run.det_pulse[a], run.det_pulse[b]);
            let place = if i == 0 {
                "first"
            } else if i + 2 == n {
                "last"
            } else if kb != ka + 1 {
                "gap"
            } else {
                "interior"
            };
            // After the wrong link: back to p (an excursion through q's
            // image), on with q (an exchange), or something else.
            let next = t.get(i + 2).and_then(|&c| run.det_truth[c]);
            let pattern = match next {
                Some(x) if x == p => "excursion",
                Some(x) if x == q => "exchange",
                None if i + 2 == n => "end",
                _ => "other",
            };
            // The other particle: where was q's image at ka, and p's at kb?
            let q_before = det_of.get(&(ka, q)).copied();
            let p_after = det_of.get(&(kb, p)).copied();
            let partner = match (q_before, p_after) {
                (Some(qa), Some(pb))
                    if track_of[qa] != usize::MAX && track_of[qa] == track_of[pb] =>
                {
                    "mutual (q's track took p)"
                }
                (Some(qa), _) if track_of[qa] != usize::MAX && track_of[qa] != ti => {
                    "q's track took other/none"
                }
                (_, Some(pb)) if track_of[pb] == usize::MAX => "q untracked, p's image left free",
                (_, Some(_)) => "q untracked, p's image on a track",
                (_, None) => "q untracked, p not detected",
            };
            let dist = match (truth_xy.get(&(kb, p)), truth_xy.get(&(kb, q))) {
                (Some(a), Some(b)) => ((a.0 - b.0).powi(2) + (a.1 - b.1).powi(2)).sqrt(),
                _ => f64::NAN,
            };
            let dbin = if dist.is_nan() {
                "p gone"
            } else if dist < 1.0 {
                "<1"
            } else if dist < 2.0 {
                "1-2"
            } else if dist < 4.0 {
                "2-4"
            } else {
                ">=4"
            };
            let len_bin = match n {
                0..=9 => "len<10",
                10..=19 => "len10-19",
                _ => "len>=20",
            };
            bump(place.to_string());
            bump(format!("{place}/{pattern}"));
            bump(format!("{place}/partner: {partner}"));
            bump(format!("{place}/dist {dbin}"));
            bump(format!("{place}/{len_bin}"));
            if place == "interior" {
                bump(format!("interior/{pattern}/{partner}"));
                let _ = pos_in[b];
            }
        }
    }
    println!("{counts:#?}");
}
