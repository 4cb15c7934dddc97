//! Link scores against truth ([`LinkScore`], [`score`],
//! [`score_with_sources`]) and the identity scoring of tracks
//! ([`identity_labels`]), as defined in the module doc.

use super::*;

/// Link scores against truth (see the module docs for the definitions).
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
#[ebptv_macros::testkit]
pub(crate) struct LinkScore {
    pub links: u64,
    pub correct_links: u64,
    /// Wrong links whose two detections both hold events of one truth
    /// particle: the track follows that particle through an image merged
    /// with another's (known only with event-level truth; 0 otherwise).
    pub merged_consistent_links: u64,
    /// (correct + merged-consistent links) / links: precision when a link
    /// through an unresolvable merged image of the track's own particle is
    /// not counted as a tracking error.
    pub precision_merged_ok: f64,
    pub truth_links: u64,
    pub found_truth_links: u64,
    pub precision: f64,
    pub recall: f64,
    /// Truth particles present in the sheet at k and k+1, detected or not
    /// (the truth links of `crate::evaluate`).
    pub truth_links_present: u64,
    /// Found truth links / present truth links: recall including the
    /// detection losses (what `crate::evaluate::score_tracks` reports).
    pub recall_present: f64,
    /// Rms of each velocity component's error (px per pulse interval).
    pub velocity_rms_px_per_pulse: f64,
    pub velocity_samples: u64,
    /// The same over track points at least `interior_margin` points from
    /// both ends of their track, where the sliding fit window is centred.
    pub velocity_rms_interior_px_per_pulse: f64,
    pub velocity_samples_interior: u64,
    /// Identity scoring (module docs, "Identity scoring"; needs the event
    /// sources, 0 without them): links whose two ends carry different
    /// labels in the track's optimal labelling, or touch a detection
    /// without particle events.
    #[serde(default)]
    pub identity_wrong_links: u64,
    /// (links − identity-wrong links) / links.
    #[serde(default)]
    pub precision_identity: f64,
    /// Set-valued truth links: (k, p) with a detection at k and one at
    /// k + 1 both holding events of particle p.
    #[serde(default)]
    pub truth_links_set: u64,
    /// ... found: one output track holds two such detections
    /// consecutively, both labelled p.
    #[serde(default)]
    pub found_truth_links_set: u64,
    #[serde(default)]
    pub recall_set: f64,
    /// Rms velocity error per component (px per pulse interval) against
    /// the labelled particle's true velocity, every labelled detection.
    #[serde(default)]
    pub velocity_rms_identity_px_per_pulse: f64,
    #[serde(default)]
    pub velocity_samples_identity: u64,
    /// ... interior points only (`interior_margin`, as above).
    #[serde(default)]
    pub velocity_rms_identity_interior_px_per_pulse: f64,
    #[serde(default)]
    pub velocity_samples_identity_interior: u64,
}

/// Squared velocity errors over a track's points, all and interior (≥
/// `margin` points from both ends), for an rms per component.
pub(super) struct VelocityErrors {
    pub(super) margin: usize,
    pub(super) sq: f64,
    pub(super) n: u64,
    pub(super) sq_interior: f64,
    pub(super) n_interior: u64,
}

impl VelocityErrors {
    pub(super) fn new(margin: usize) -> Self {
        VelocityErrors {
            margin,
            sq: 0.0,
            n: 0,
            sq_interior: 0.0,
            n_interior: 0,
        }
    }

    /// The fitted velocity `(u, v)` of point `i` of a track of `len`
    /// points against the truth `(tu, tv)`, px/s; `k` = period in s.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn add(&mut self, i: usize, len: usize, u: f64, v: f64, tu: f64, tv: f64, k: f64) {
        let e2 = ((u - tu) * k).powi(2) + ((v - tv) * k).powi(2);
        self.sq += e2;
        self.n += 1;
        if i >= self.margin && len - 1 - i >= self.margin {
            self.sq_interior += e2;
            self.n_interior += 1;
        }
    }

    /// (rms all, samples, rms interior, samples), px per pulse per component.
    pub(super) fn rms(&self) -> (f64, u64, f64, u64) {
        let rms = |sq: f64, n: u64| {
            if n > 0 {
                (sq / (2 * n) as f64).sqrt()
            } else {
                0.0
            }
        };
        (
            rms(self.sq, self.n),
            self.n,
            rms(self.sq_interior, self.n_interior),
            self.n_interior,
        )
    }
}

/// Score linked tracks. `det_truth[serial]` is the truth id of each
/// detection (serials as the tracker numbered them), `det_pulse[serial]`
/// its pulse; `truth` the truth samples of all pulses.
#[ebptv_macros::testkit]
pub(crate) fn score(
    tracks: &[LinkedTrack],
    det_truth: &[Option<u64>],
    det_pulse: &[i64],
    truth: &[TruthSample],
    period_us: f64,
    interior_margin: usize,
) -> LinkScore {
    score_with_sources(
        tracks,
        det_truth,
        &[],
        det_pulse,
        truth,
        period_us,
        interior_margin,
    )
}

/// [`score`] with, per detection, every truth particle that made one of
/// its events (`det_sources[serial]`, sorted; empty slice when unknown),
/// which tells the merged-consistent links.
#[ebptv_macros::testkit]
pub(crate) fn score_with_sources(
    tracks: &[LinkedTrack],
    det_truth: &[Option<u64>],
    det_sources: &[Vec<u64>],
    det_pulse: &[i64],
    truth: &[TruthSample],
    period_us: f64,
    interior_margin: usize,
) -> LinkScore {
    let mut s = LinkScore::default();
    // Truth links: (pulse k, id) detected at k and k+1.
    let detected: HashSet<(i64, u64)> = det_truth
        .iter()
        .zip(det_pulse)
        .filter_map(|(id, &k)| id.map(|id| (k, id)))
        .collect();
    s.truth_links = detected
        .iter()
        .filter(|&&(k, id)| detected.contains(&(k + 1, id)))
        .count() as u64;
    let present: HashSet<(i64, u64)> = truth.iter().map(|t| (t.pulse, t.particle_id)).collect();
    s.truth_links_present = present
        .iter()
        .filter(|&&(k, id)| present.contains(&(k + 1, id)))
        .count() as u64;
    let truth_vel: HashMap<(i64, u64), (f64, f64)> = truth
        .iter()
        .map(|t| ((t.pulse, t.particle_id), (t.u, t.v)))
        .collect();
    let mut found: HashSet<(i64, u64)> = HashSet::new();
    let mut vel = VelocityErrors::new(interior_margin);
    for t in tracks {
        let serials: Vec<u64> = t.detections.iter().flatten().copied().collect();
        for w in serials.windows(2) {
            s.links += 1;
            let (a, b) = (w[0] as usize, w[1] as usize);
            let correct = match (det_truth[a], det_truth[b]) {
                (Some(ia), Some(ib)) if ia == ib => {
                    s.correct_links += 1;
                    if det_pulse[b] == det_pulse[a] + 1 {
                        found.insert((det_pulse[a], ia));
                    }
                    true
                }
                _ => false,
            };
            if !correct && !det_sources.is_empty() {
                let (sa, sb) = (&det_sources[a], &det_sources[b]);
                if sa.iter().any(|id| sb.binary_search(id).is_ok()) {
                    s.merged_consistent_links += 1;
                }
            }
        }
        let n = t.track.points.len();
        for (i, (pt, d)) in t.track.points.iter().zip(&t.detections).enumerate() {
            let Some(serial) = d else { continue };
            let Some(id) = det_truth[*serial as usize] else {
                continue;
            };
            if let Some(&(u, v)) = truth_vel.get(&(pt.pulse, id)) {
                vel.add(i, n, pt.u, pt.v, u, v, period_us * 1e-6);
            }
        }
    }
    s.found_truth_links = found.len() as u64;
    if !det_sources.is_empty() {
        score_identity(
            &mut s,
            tracks,
            det_truth,
            det_sources,
            det_pulse,
            &truth_vel,
            period_us,
            interior_margin,
        );
    }
    s.precision = if s.links > 0 {
        s.correct_links as f64 / s.links as f64
    } else {
        0.0
    };
    s.recall = if s.truth_links > 0 {
        s.found_truth_links as f64 / s.truth_links as f64
    } else {
        0.0
    };
    s.precision_merged_ok = if s.links > 0 {
        (s.correct_links + s.merged_consistent_links) as f64 / s.links as f64
    } else {
        0.0
    };
    s.recall_present = if s.truth_links_present > 0 {
        s.found_truth_links as f64 / s.truth_links_present as f64
    } else {
        0.0
    };
    (
        s.velocity_rms_px_per_pulse,
        s.velocity_samples,
        s.velocity_rms_interior_px_per_pulse,
        s.velocity_samples_interior,
    ) = vel.rms();
    s
}

/// The identity part of [`score_with_sources`] (module docs, "Identity
/// scoring"): fills the `identity`/`set` fields of `s` (`s.links` must be
/// counted already).
#[allow(clippy::too_many_arguments)]
pub(super) fn score_identity(
    s: &mut LinkScore,
    tracks: &[LinkedTrack],
    det_truth: &[Option<u64>],
    det_sources: &[Vec<u64>],
    det_pulse: &[i64],
    truth_vel: &HashMap<(i64, u64), (f64, f64)>,
    period_us: f64,
    interior_margin: usize,
) {
    let holds: HashSet<(i64, u64)> = det_sources
        .iter()
        .zip(det_pulse)
        .flat_map(|(src, &k)| src.iter().map(move |&id| (k, id)))
        .collect();
    s.truth_links_set = holds
        .iter()
        .filter(|&&(k, id)| holds.contains(&(k + 1, id)))
        .count() as u64;
    let mut found: HashSet<(i64, u64)> = HashSet::new();
    let mut vel = VelocityErrors::new(interior_margin);
    let k = period_us * 1e-6;
    for t in tracks {
        let serials: Vec<usize> = t.detections.iter().flatten().map(|&d| d as usize).collect();
        let labels = identity_labels(&serials, det_truth, det_sources);
        for (i, w) in serials.windows(2).enumerate() {
            match (labels[i], labels[i + 1]) {
                (Some(a), Some(b)) if a == b => {
                    if det_pulse[w[1]] == det_pulse[w[0]] + 1 {
                        found.insert((det_pulse[w[0]], a));
                    }
                }
                _ => s.identity_wrong_links += 1,
            }
        }
        let n = t.track.points.len();
        let mut j = 0; // index into serials/labels
        for (i, (pt, d)) in t.track.points.iter().zip(&t.detections).enumerate() {
            if d.is_none() {
                continue;
            }
            let label = labels[j];
            j += 1;
            let Some(&(u, v)) = label.and_then(|id| truth_vel.get(&(pt.pulse, id))) else {
                continue;
            };
            vel.add(i, n, pt.u, pt.v, u, v, k);
        }
    }
    s.found_truth_links_set = found.len() as u64;
    let ratio = |a: u64, b: u64| if b > 0 { a as f64 / b as f64 } else { 0.0 };
    s.precision_identity = ratio(s.links - s.identity_wrong_links, s.links);
    s.recall_set = ratio(s.found_truth_links_set, s.truth_links_set);
    (
        s.velocity_rms_identity_px_per_pulse,
        s.velocity_samples_identity,
        s.velocity_rms_identity_interior_px_per_pulse,
        s.velocity_samples_identity_interior,
    ) = vel.rms();
}

/// The optimal labelling of one track (module docs, "Identity scoring"):
/// for the detections `serials` (in track order) one truth particle each
/// from its event sources `det_sources[serial]` (sorted), `None` where
/// the sources are empty (noise only), such that the labels change
/// between consecutive detections as rarely as possible. Among the
/// labellings with fewest changes the one that agrees most often with
/// the strict attribution `det_truth` is taken (so a track through a
/// merged image keeps the particle it follows, and without merged
/// images the labels are `det_truth`), then the smaller particle id
/// (earliest in the track first): one labelling, deterministic.
#[ebptv_macros::testkit]
pub(crate) fn identity_labels(
    serials: &[usize],
    det_truth: &[Option<u64>],
    det_sources: &[Vec<u64>],
) -> Vec<Option<u64>> {
    let mut out = vec![None; serials.len()];
    let mut i = 0;
    while i < serials.len() {
        if det_sources[serials[i]].is_empty() {
            i += 1;
            continue;
        }
        // A detection without sources ends the segment: both its links
        // are wrong whatever the labels, so the segments are labelled
        // independently.
        let mut j = i;
        while j < serials.len() && !det_sources[serials[j]].is_empty() {
            j += 1;
        }
        label_segment(&serials[i..j], det_truth, det_sources, &mut out[i..j]);
        i = j;
    }
    out
}

/// [`identity_labels`] of a run of detections that all have sources:
/// dynamic programming over the track, cost (label changes, disagreements
/// with `det_truth`) compared lexicographically.
pub(super) fn label_segment(
    seg: &[usize],
    det_truth: &[Option<u64>],
    det_sources: &[Vec<u64>],
    out: &mut [Option<u64>],
) {
    // cost[i][c]: least cost of labelling seg[..=i] with label
    // det_sources[seg[i]][c] at i; back[i][c]: the label index at i − 1.
    let mut cost: Vec<Vec<(u32, u32)>> = Vec::with_capacity(seg.len());
    let mut back: Vec<Vec<usize>> = Vec::with_capacity(seg.len());
    for (i, &d) in seg.iter().enumerate() {
        let src = &det_sources[d];
        let mut row = Vec::with_capacity(src.len());
        let mut brow = Vec::with_capacity(src.len());
        for &l in src {
            let disagrees = u32::from(det_truth[d] != Some(l));
            if i == 0 {
                row.push((0, disagrees));
                brow.push(0);
                continue;
            }
            let prev = &det_sources[seg[i - 1]];
            // Least cost; among equals staying on l, else the smallest
            // label (sources are sorted, the first minimum wins).
            let mut best = (u32::MAX, u32::MAX);
            let mut arg = 0;
            for (c, &pl) in prev.iter().enumerate() {
                let pc = cost[i - 1][c];
                let cand = (pc.0 + u32::from(pl != l), pc.1);
                if cand < best || (cand == best && pl == l) {
                    best = cand;
                    arg = c;
                }
            }
            row.push((best.0, best.1 + disagrees));
            brow.push(arg);
        }
        cost.push(row);
        back.push(brow);
    }
    let last = seg.len() - 1;
    let mut c = (0..cost[last].len())
        .min_by_key(|&c| cost[last][c])
        .expect("a segment's detections have sources");
    for i in (0..seg.len()).rev() {
        out[i] = Some(det_sources[seg[i]][c]);
        c = back[i][c];
    }
}
