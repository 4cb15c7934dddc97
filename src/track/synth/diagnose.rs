//! Diagnosis of a run's links against truth (`diagnose`,
//! `diagnose_detail`): where wrong and missed links come from.

use super::*;

/// Where wrong links and missed truth links come from (see `diagnose`).
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
#[ebptv_macros::testkit]
pub(crate) struct LinkDiagnosis {
    pub links: u64,
    pub wrong_links: u64,
    /// Wrong links with a merged image (events of two sources, particles
    /// or noise) at one end.
    pub wrong_merged: u64,
    /// Wrong links with a pure noise detection at one end.
    pub wrong_noise: u64,
    /// Wrong links between two clean images of different particles.
    pub wrong_swap: u64,
    /// ... of which the two truth particles were < 2 px apart at the
    /// second pulse (co-moving neighbours).
    pub wrong_swap_close: u64,
    /// Wrong links that are a track's first link (initialisation).
    pub wrong_first: u64,
    /// Wrong links that are a track's last link (the tail).
    pub wrong_last: u64,
    /// Wrong links across a bridged gap.
    pub wrong_gap: u64,
    pub truth_links: u64,
    pub missed: u64,
    /// Missed truth links whose first detection is on no kept track.
    pub missed_a_off_track: u64,
    /// ... whose second detection is on no kept track.
    pub missed_b_off_track: u64,
    /// ... both on tracks (different ones, or not consecutive).
    pub missed_both_on_tracks: u64,
    /// ... with a merged image at either end.
    pub missed_merged: u64,
    /// The tracker's position noise estimate at the end (px per axis).
    pub position_sigma: f64,
}

/// Classify every wrong link and every missed truth link of `tracks`
/// (detections numbered as in [`score`]; `det_mixed[serial]` tells merged
/// images, `det_xy` the detection positions, `truth` the truth samples).
pub(crate) fn diagnose(
    tracks: &[LinkedTrack],
    det_truth: &[Option<u64>],
    det_mixed: &[bool],
    det_pulse: &[i64],
    truth: &[TruthSample],
) -> LinkDiagnosis {
    let mut d = LinkDiagnosis::default();
    let pos: HashMap<(i64, u64), (f64, f64)> = truth
        .iter()
        .map(|t| ((t.pulse, t.particle_id), (t.x, t.y)))
        .collect();
    let mut on_track = vec![false; det_truth.len()];
    let mut found: HashSet<(i64, u64)> = HashSet::new();
    for t in tracks {
        let serials: Vec<u64> = t.detections.iter().flatten().copied().collect();
        for &s in &serials {
            on_track[s as usize] = true;
        }
        let n = serials.len();
        for (i, w) in serials.windows(2).enumerate() {
            d.links += 1;
            let (a, b) = (w[0] as usize, w[1] as usize);
            let (ia, ib) = (det_truth[a], det_truth[b]);
            if let Some(id) = ia.filter(|_| ia == ib) {
                if det_pulse[b] == det_pulse[a] + 1 {
                    found.insert((det_pulse[a], id));
                }
                continue;
            }
            d.wrong_links += 1;
            if i == 0 {
                d.wrong_first += 1;
            }
            if i + 2 == n {
                d.wrong_last += 1;
            }
            if det_pulse[b] != det_pulse[a] + 1 {
                d.wrong_gap += 1;
            }
            if det_mixed[a] || det_mixed[b] {
                d.wrong_merged += 1;
            } else if ia.is_none() || ib.is_none() {
                d.wrong_noise += 1;
            } else {
                d.wrong_swap += 1;
                let k = det_pulse[b];
                if let (Some(pa), Some(pb)) =
                    (pos.get(&(k, ia.unwrap())), pos.get(&(k, ib.unwrap())))
                {
                    if (pa.0 - pb.0).hypot(pa.1 - pb.1) < 2.0 {
                        d.wrong_swap_close += 1;
                    }
                }
            }
        }
    }
    let mut det_of: HashMap<(i64, u64), usize> = HashMap::new();
    for (s, (id, &k)) in det_truth.iter().zip(det_pulse).enumerate() {
        if let Some(id) = id {
            det_of.entry((k, *id)).or_insert(s);
        }
    }
    for (&(k, id), &a) in &det_of {
        let Some(&b) = det_of.get(&(k + 1, id)) else {
            continue;
        };
        d.truth_links += 1;
        if found.contains(&(k, id)) {
            continue;
        }
        d.missed += 1;
        if det_mixed[a] || det_mixed[b] {
            d.missed_merged += 1;
        }
        match (on_track[a], on_track[b]) {
            (false, _) => d.missed_a_off_track += 1,
            (true, false) => d.missed_b_off_track += 1,
            (true, true) => d.missed_both_on_tracks += 1,
        }
    }
    d
}

/// Cluster, track and `diagnose` a scene.
#[ebptv_macros::testkit]
pub(crate) fn run_and_diagnose(
    scene: &[SynthPulse],
    cparams: &ClusterParams,
    tparams: &crate::track::TrackParams,
) -> crate::Result<LinkDiagnosis> {
    let run = run_scene(scene, cparams, tparams)?;
    let mut d = diagnose(
        &run.tracks,
        &run.det_truth,
        &run.det_mixed,
        &run.det_pulse,
        &run.truth,
    );
    d.position_sigma = run.position_sigma;
    Ok(d)
}

/// A finer breakdown than `diagnose`, by cause, for the accuracy work:
/// counts under self-explaining keys. Missed truth links (particle `id`
/// detected at `k` and `k + 1`, the pair not a link of one track):
/// - `missed/never_tracked/run<4`: no detection of the particle is on a
///   kept track and it never has 4 consecutive detections (a new track
///   needs 4; a physical limit of four-frame initialisation);
/// - `missed/never_tracked/run>=4`: never tracked although it could be;
/// - `missed/before_start`: before the first tracked detection of the
///   particle (late initialisation);
/// - `missed/after_end`: after the last tracked detection (early end);
/// - `missed/between`: between tracked detections (a broken track, a
///   swap, a detection taken by another track);
///
/// Wrong links (`wrong/...`): `merged_consistent` (both ends hold events
/// of one particle) split into `.../owner_on_other_track` (the merged
/// image's owner has its own images within 2 pulses on another track: two
/// tracks, and the wrong one took it) and `.../pair_on_one_track` (one
/// track follows two particles whose images stay merged, and the
/// attribution flips with the event majority: no tracker can tell them
/// apart),
/// `noise`, `swap/first|last|gap|interior` (clean images of two
/// particles, by position in the track).
pub(crate) fn diagnose_detail(
    tracks: &[LinkedTrack],
    det_truth: &[Option<u64>],
    det_sources: &[Vec<u64>],
    det_pulse: &[i64],
) -> std::collections::BTreeMap<String, u64> {
    let mut out: std::collections::BTreeMap<String, u64> = Default::default();
    let mut bump = |k: &str| *out.entry(k.to_string()).or_default() += 1;
    let n_det = det_truth.len();
    let mut on_track = vec![false; n_det];
    let mut track_of = vec![usize::MAX; n_det];
    let mut found: HashSet<(i64, u64)> = HashSet::new();
    for (ti, t) in tracks.iter().enumerate() {
        for s in t.detections.iter().flatten() {
            on_track[*s as usize] = true;
            track_of[*s as usize] = ti;
        }
    }
    // Per particle: detected pulses (the detection attributed to it) and
    // the pulses where a detection of it is on a track.
    let mut det_of: HashMap<(i64, u64), usize> = HashMap::new();
    for (s, (id, &k)) in det_truth.iter().zip(det_pulse).enumerate() {
        if let Some(id) = id {
            det_of.entry((k, *id)).or_insert(s);
        }
    }
    let mut detected_pulses: HashMap<u64, Vec<i64>> = HashMap::new();
    let mut tracked_range: HashMap<u64, (i64, i64)> = HashMap::new();
    for (&(k, id), &s) in &det_of {
        detected_pulses.entry(id).or_default().push(k);
        if on_track[s] {
            let e = tracked_range.entry(id).or_insert((k, k));
            e.0 = e.0.min(k);
            e.1 = e.1.max(k);
        }
    }
    let mut longest_run: HashMap<u64, usize> = HashMap::new();
    for (id, ks) in &mut detected_pulses {
        ks.sort_unstable();
        let (mut best, mut run) = (1, 1);
        for w in ks.windows(2) {
            run = if w[1] == w[0] + 1 { run + 1 } else { 1 };
            best = best.max(run);
        }
        longest_run.insert(*id, best);
    }
    for (ti, t) in tracks.iter().enumerate() {
        let serials: Vec<usize> = t.detections.iter().flatten().map(|&s| s as usize).collect();
        let n = serials.len();
        for (i, w) in serials.windows(2).enumerate() {
            let (a, b) = (w[0], w[1]);
            let (ia, ib) = (det_truth[a], det_truth[b]);
            if let Some(id) = ia.filter(|_| ia == ib) {
                if det_pulse[b] == det_pulse[a] + 1 {
                    found.insert((det_pulse[a], id));
                }
                continue;
            }
            bump("wrong");
            let (sa, sb) = (&det_sources[a], &det_sources[b]);
            if sa.iter().any(|id| sb.binary_search(id).is_ok()) {
                // The end that is not its track's particle's own image.
                let merged_end = if sa.len() > 1 { a } else { b };
                let owner = det_truth[merged_end];
                let k = det_pulse[merged_end];
                // The owner's own images nearby on another track: two
                // tracks, and the wrong one took the merged image.
                let owner_elsewhere = owner.is_some_and(|o| {
                    (k - 2..=k + 2).any(|kk| {
                        det_of
                            .get(&(kk, o))
                            .is_some_and(|&s| on_track[s] && track_of[s] != ti)
                    })
                });
                bump(if owner_elsewhere {
                    "wrong/merged_consistent/owner_on_other_track"
                } else {
                    "wrong/merged_consistent/pair_on_one_track"
                });
            } else if ia.is_none() || ib.is_none() {
                bump("wrong/noise");
            } else if i == 0 {
                bump("wrong/swap/first");
            } else if i + 2 == n {
                bump("wrong/swap/last");
            } else if det_pulse[b] != det_pulse[a] + 1 {
                bump("wrong/swap/gap");
            } else {
                bump("wrong/swap/interior");
            }
        }
    }
    for (&(k, id), &a) in &det_of {
        let Some(&b) = det_of.get(&(k + 1, id)) else {
            continue;
        };
        bump("truth_links");
        if found.contains(&(k, id)) {
            continue;
        }
        bump("missed");
        match tracked_range.get(&id) {
            None if longest_run[&id] < INIT_FRAMES_SYNTH => bump("missed/never_tracked/run<4"),
            None => bump("missed/never_tracked/run>=4"),
            Some(&(lo, _)) if k < lo => bump("missed/before_start"),
            Some(&(_, hi)) if k + 1 > hi => bump("missed/after_end"),
            Some(_) => bump(match (on_track[a], on_track[b]) {
                (true, true) if track_of[a] == track_of[b] => "missed/between/same_track",
                (true, true) => "missed/between/two_tracks",
                (false, _) => "missed/between/a_off",
                (true, false) => "missed/between/b_off",
            }),
        }
    }
    out
}

pub(super) const INIT_FRAMES_SYNTH: usize = crate::track::INIT_FRAMES;

/// Cluster, track and `diagnose_detail` a scene.
#[ebptv_macros::testkit]
pub(crate) fn run_and_diagnose_detail(
    scene: &[SynthPulse],
    cparams: &ClusterParams,
    tparams: &crate::track::TrackParams,
) -> crate::Result<std::collections::BTreeMap<String, u64>> {
    let run = run_scene(scene, cparams, tparams)?;
    Ok(diagnose_detail(
        &run.tracks,
        &run.det_truth,
        &run.det_sources,
        &run.det_pulse,
    ))
}
