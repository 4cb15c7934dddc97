//! Where the velocity error of the synthetic scene comes from: rms by
//! distance from the track end and by track length:
//! `cargo run --release -p ebptv-benches --example ptv_velocity_breakdown`

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
        fit: ebptv::track::FitParams {
            fit_window: env("PTV_FIT_WINDOW").map_or(d.fit.fit_window, |v| v as usize),
            fit_min_window: env("PTV_FIT_MIN_WINDOW").map_or(d.fit.fit_min_window, |v| v as usize),
            fit_accel_rms: env("PTV_FIT_ACCEL").map_or(d.fit.fit_accel_rms, Some),
            ..d.fit
        },
        ..d
    };
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
    println!(
        "sigma {:.3}, prior acceleration {:.4} px/pulse²",
        tracker.position_sigma(),
        tracker.fit_accel_rms()
    );
    tracks.extend(tracker.finish().0);
    let k = sp.period_us * 1e-6;
    // Optional dump for prototyping fits elsewhere: one row per output
    // point (detections with their centroid, event count and truth).
    if let Ok(path) = std::env::var("PTV_DUMP") {
        use std::fmt::Write as _;
        let mut out = String::from("track,pulse,det,x,y,n_events,truth,tu,tv,u,v\n");
        for (ti, t) in tracks.iter().enumerate() {
            for (pt, d) in t.track.points.iter().zip(&t.detections) {
                let (x, y, n, id) = match d {
                    Some(s) => {
                        let p = &all_parts[*s as usize];
                        (p.x, p.y, p.n_events, det_truth[*s as usize])
                    }
                    None => (f64::NAN, f64::NAN, 0, None),
                };
                let (tu, tv) = id
                    .and_then(|id| truth.get(&(pt.pulse, id)))
                    .map_or((f64::NAN, f64::NAN), |&(u, v)| (u * k, v * k));
                writeln!(
                    out,
                    "{ti},{},{},{x},{y},{n},{},{tu},{tv},{},{}",
                    pt.pulse,
                    d.is_some() as u8,
                    id.map_or(-1, |i| i as i64),
                    pt.u * k,
                    pt.v * k
                )
                .unwrap();
            }
        }
        std::fs::write(path, out).unwrap();
    }
    let mut by_end: BTreeMap<usize, (f64, usize)> = BTreeMap::new();
    let mut by_len: BTreeMap<usize, (f64, usize)> = BTreeMap::new();
    let mut clean = (0.0, 0usize);
    let mut by_end_clean: BTreeMap<usize, (f64, usize)> = BTreeMap::new();
    let mut all = (0.0, 0usize);
    // Squared error by (short track?, start or end side, distance).
    let mut by_side: BTreeMap<(bool, bool, char, usize), (f64, usize)> = BTreeMap::new();
    let mut wrong = (0.0, 0usize);
    for t in &tracks {
        let n = t.track.points.len();
        let ids: Vec<Option<u64>> = t
            .detections
            .iter()
            .map(|d| d.and_then(|s| det_truth[s as usize]))
            .collect();
        let first = ids.iter().flatten().next().copied();
        let pure = ids.iter().all(|i| i.is_none() || *i == first);
        // Tracks from the recording's first pulses: no flow known yet.
        let early = t.track.points[0].pulse < 8;
        for (i, (pt, id)) in t.track.points.iter().zip(&ids).enumerate() {
            let Some(id) = id else { continue };
            let Some(&(u, v)) = truth.get(&(pt.pulse, *id)) else {
                continue;
            };
            let e2 = ((pt.u - u) * k).powi(2) + ((pt.v - v) * k).powi(2);
            let e = by_end.entry(i.min(n - 1 - i).min(8)).or_default();
            e.0 += e2;
            e.1 += 1;
            let l = by_len.entry((n / 5 * 5).min(40)).or_default();
            l.0 += e2;
            l.1 += 1;
            all.0 += e2;
            all.1 += 1;
            let side = if i <= n - 1 - i { 's' } else { 'e' };
            let b = by_side
                .entry((
                    pure,
                    n < 10,
                    if early {
                        side.to_ascii_uppercase()
                    } else {
                        side
                    },
                    i.min(n - 1 - i).min(4),
                ))
                .or_default();
            b.0 += e2;
            b.1 += 1;
            if !pure {
                wrong.0 += e2;
                wrong.1 += 1;
            }
            if pure {
                clean.0 += e2;
                clean.1 += 1;
                let c = by_end_clean.entry(i.min(n - 1 - i).min(8)).or_default();
                c.0 += e2;
                c.1 += 1;
            }
        }
    }
    let rms = |(s, n): (f64, usize)| (s / (2 * n.max(1)) as f64).sqrt();
    println!(
        "all {:.4} ({}), tracks without a wrong link {:.4} ({})",
        rms(all),
        all.1,
        rms(clean),
        clean.1
    );
    println!(
        "share of the squared error: tracks with a wrong link {:.1} %",
        100.0 * wrong.0 / all.0
    );
    for ((pure, short, side, d), v) in &by_side {
        println!(
            "{} {} side {side} from end {d}: rms {:.4} ({}), share {:.1} %",
            if *pure { "clean" } else { "wrong" },
            if *short { "len<10" } else { "len>=10" },
            rms(*v),
            v.1,
            100.0 * v.0 / all.0
        );
    }
    for (d, v) in by_end {
        println!("from end {d}: {:.4} ({})", rms(v), v.1);
    }
    for (d, v) in by_end_clean {
        println!("clean, from end {d}: {:.4} ({})", rms(v), v.1);
    }
    for (l, v) in by_len {
        println!(
            "length {l}..: {:.4} ({}), share {:.1} %",
            rms(v),
            v.1,
            100.0 * v.0 / all.0
        );
    }
}
