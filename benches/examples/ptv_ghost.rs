//! Ghost tracks: short tracks made of detections of different particles
//! that happen to line up. Which rule tells them from real short tracks?
//! Prints counts against the truth:
//! `cargo run --release -p ebptv-benches --example ptv_ghost`

use std::collections::{BTreeMap, HashMap};

use ebptv::cluster::ClusterParams;
use ebptv::track::synth::{cluster_with_truth, generate, SynthParams};
use ebptv::track::{TrackParams, Tracker};

fn main() {
    let env = |k: &str| std::env::var(k).ok().and_then(|v| v.parse::<f64>().ok());
    let sp = SynthParams {
        width: 384,
        height: 384,
        ..Default::default()
    };
    let scene = generate(&sp);
    let d = TrackParams::default();
    let tp = TrackParams {
        min_length: env("PTV_MIN_LENGTH").map_or(d.min_length, |v| v as usize),
        init: ebptv::track::InitParams {
            ghost_check_length: env("PTV_GHOST_LEN")
                .map_or(d.init.ghost_check_length, |v| v as usize),
            min_length_flow: env("PTV_MIN_FLOW").map_or(d.init.min_length_flow, |v| v as usize),
            ghost_sigma: env("PTV_GHOST_SIGMA").unwrap_or(d.init.ghost_sigma),
            ghost_check_init: env("PTV_GHOST_INIT").map_or(d.init.ghost_check_init, |v| v != 0.0),
            init_gap: env("PTV_INIT_GAP").map_or(d.init.init_gap, |v| v != 0.0),
            ..d.init
        },
        ..d
    };
    let (_, s) =
        ebptv::track::synth::run_and_score(&scene, &ClusterParams::default(), &tp, sp.period_us)
            .unwrap();
    println!(
        "precision {:.4} (merged ok {:.4}) recall {:.4} vel {:.4} interior {:.4}",
        s.precision,
        s.precision_merged_ok,
        s.recall,
        s.velocity_rms_px_per_pulse,
        s.velocity_rms_interior_px_per_pulse
    );
    let mut tracker = Tracker::new(tp).unwrap();
    let (mut det_truth, mut tracks, mut truth) = (Vec::new(), Vec::new(), HashMap::new());
    let mut all_parts = Vec::new();
    for s in &scene {
        let (parts, ids) = cluster_with_truth(s, &ClusterParams::default());
        det_truth.extend(ids);
        all_parts.extend(parts.iter().copied());
        tracks.extend(
            tracker
                .push_linked(s.pulse.index, s.pulse.start_us, &parts)
                .unwrap(),
        );
        for t in &s.truth {
            truth.insert((t.pulse, t.particle_id), (t.u, t.v));
        }
    }
    let sigma = tracker.position_sigma();
    let (rest, stats) = tracker.finish();
    println!("{stats:?}");
    tracks.extend(rest);
    let k = sp.period_us * 1e-6;
    // Reference flow: fitted points of long tracks, by pulse, in 16 px cells.
    let cell = 16.0;
    let mut flow: HashMap<(i64, i32, i32), (f64, f64, f64)> = HashMap::new();
    for t in &tracks {
        if t.detections.iter().flatten().count() < 10 {
            continue;
        }
        for p in &t.track.points {
            let key = (p.pulse, (p.x / cell) as i32, (p.y / cell) as i32);
            let e = flow.entry(key).or_default();
            e.0 += p.u * k;
            e.1 += p.v * k;
            e.2 += 1.0;
        }
    }
    let local = |pulse: i64, x: f64, y: f64| -> Option<(f64, f64)> {
        let (cx, cy) = ((x / cell) as i32, (y / cell) as i32);
        let mut s = (0.0, 0.0, 0.0);
        for dx in -1..=1 {
            for dy in -1..=1 {
                if let Some(e) = flow.get(&(pulse, cx + dx, cy + dy)) {
                    s.0 += e.0;
                    s.1 += e.1;
                    s.2 += e.2;
                }
            }
        }
        (s.2 > 0.0).then(|| (s.0 / s.2, s.1 / s.2))
    };
    // Per short track: class, features, squared velocity error of its points.
    #[derive(Default, Debug)]
    struct Acc {
        tracks: u32,
        links: u32,
        good_links: u32,
        e2: f64,
        pts: u32,
    }
    let mut by: BTreeMap<(usize, &str, u32, u32), Acc> = BTreeMap::new();
    let mut totals: BTreeMap<(usize, &str), Acc> = BTreeMap::new();
    for t in &tracks {
        let dets: Vec<u64> = t.detections.iter().flatten().copied().collect();
        let n = dets.len();
        if n > 6 {
            continue;
        }
        let ids: Vec<Option<u64>> = dets.iter().map(|&s| det_truth[s as usize]).collect();
        let wrong = ids
            .windows(2)
            .filter(|w| w[0].is_none() || w[0] != w[1])
            .count();
        let class = match wrong {
            0 => "clean",
            1 => "one wrong",
            _ => "ghost",
        };
        // Linear fit of the detections (τ = pulse).
        let ps: Vec<&ebptv::cluster::Particle> =
            dets.iter().map(|&s| &all_parts[s as usize]).collect();
        let tau: Vec<f64> = ps.iter().map(|p| p.pulse as f64).collect();
        let tm = tau.iter().sum::<f64>() / n as f64;
        let stt: f64 = tau.iter().map(|t| (t - tm).powi(2)).sum();
        let lin = |v: &dyn Fn(&ebptv::cluster::Particle) -> f64| {
            let m = ps.iter().map(|p| v(p)).sum::<f64>() / n as f64;
            let b = ps
                .iter()
                .zip(&tau)
                .map(|(p, t)| (v(p) - m) * (t - tm))
                .sum::<f64>()
                / stt;
            let r2: f64 = ps
                .iter()
                .zip(&tau)
                .map(|(p, t)| (v(p) - m - b * (t - tm)).powi(2))
                .sum();
            (m, b, r2)
        };
        let (mx, bx, rx) = lin(&|p| p.x);
        let (my, by_, ry) = lin(&|p| p.y);
        let chi2 = (rx + ry) / (sigma * sigma * (2 * n - 4) as f64);
        let pulse_mid = ps[n / 2].pulse;
        let dv = local(pulse_mid, mx, my).map(|(u, v)| (bx - u).hypot(by_ - v));
        let dv_bin = dv.map_or(99, |d| (d * 2.0).min(20.0) as u32);
        let chi_bin = (chi2 * 2.0).min(10.0) as u32;
        let mut e2 = 0.0;
        let mut pts = 0;
        for (pt, id) in t.track.points.iter().filter(|p| !p.interpolated).zip(&ids) {
            let Some(id) = id else { continue };
            let Some(&(u, v)) = truth.get(&(pt.pulse, *id)) else {
                continue;
            };
            e2 += ((pt.u - u) * k).powi(2) + ((pt.v - v) * k).powi(2);
            pts += 1;
        }
        for acc in [
            by.entry((n, class, dv_bin, chi_bin)).or_default(),
            totals.entry((n, class)).or_default(),
        ] {
            acc.tracks += 1;
            acc.links += (n - 1) as u32;
            acc.good_links += (n - 1 - wrong) as u32;
            acc.e2 += e2;
            acc.pts += pts;
        }
    }
    println!("sigma {sigma:.3}");
    for (k, a) in &totals {
        println!("{k:?}: {a:?}");
    }
    // Marginals: by dv bin (0.5 px/pulse) and by chi² bin (0.5).
    let mut dvm: BTreeMap<(usize, u32, &str), (u32, u32, f64)> = BTreeMap::new();
    let mut chim: BTreeMap<(usize, u32, &str), (u32, u32, f64)> = BTreeMap::new();
    for ((n, c, dv, chi), a) in &by {
        let e = dvm.entry((*n, *dv, c)).or_default();
        e.0 += a.tracks;
        e.1 += a.good_links;
        e.2 += a.e2;
        let e = chim.entry((*n, *chi, c)).or_default();
        e.0 += a.tracks;
        e.1 += a.good_links;
        e.2 += a.e2;
    }
    println!("(n, dv bin /0.5 px/pulse, class): (tracks, good links, sq vel err)");
    for (k, v) in &dvm {
        println!("{k:?}: {v:?}");
    }
    println!("(n, chi2 bin /0.5, class): (tracks, good links, sq vel err)");
    for (k, v) in &chim {
        println!("{k:?}: {v:?}");
    }
}
