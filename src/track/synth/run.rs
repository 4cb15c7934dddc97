//! One scene run end to end ([`run_scene`]: cluster with truth, track,
//! attribute) and its score ([`run_and_score`]).

use super::*;

/// Track points at least this many detections from both ends of their
/// track count as interior in [`run_and_score`] (the half-width of the
/// 11-point fixed output window, kept so numbers compare across fits).
pub const INTERIOR_MARGIN: usize = 5;

/// A scene clustered and tracked, with the truth of every detection
/// (indexed by detection: the serials of [`crate::track::Tracker`], with the parts
/// of split images renumbered after all pushed particles).
#[derive(Debug, Clone)]
pub struct SceneRun {
    pub tracks: Vec<LinkedTrack>,
    pub det_truth: Vec<Option<u64>>,
    pub det_sources: Vec<Vec<u64>>,
    pub det_mixed: Vec<bool>,
    pub det_pulse: Vec<i64>,
    /// Centroid (px) of each detection.
    pub det_xy: Vec<[f64; 2]>,
    /// Pulse start (µs) of each detection: the time the tracker gave it.
    pub det_t_us: Vec<f64>,
    /// Events of each detection.
    pub det_events: Vec<u32>,
    pub truth: Vec<TruthSample>,
    /// The tracker's position noise estimate at the end (px per axis).
    pub position_sigma: f64,
    pub stats: crate::track::TrackerStats,
    /// Per part of a split image: (its detection index, the image's index,
    /// whether the image held events of more than one source).
    pub split_parts: Vec<(usize, usize, bool)>,
}

/// Cluster every pulse (with the pixel table, so that the tracker can
/// split merged images when `tparams.split_merged`), track, and attribute
/// every detection — also the parts of split images, by the events on
/// their pixels, with the rule of [`cluster_with_truth`]. A split image
/// is replaced by its parts: it keeps no truth (it is on no track, and a
/// particle it was attributed to is detected by the part with its events).
pub fn run_scene(
    scene: &[SynthPulse],
    cparams: &ClusterParams,
    tparams: &crate::track::TrackParams,
) -> crate::Result<SceneRun> {
    let mut tracker = crate::track::Tracker::new(tparams.clone())?;
    tracker.record_splits(true);
    let mut run = SceneRun {
        tracks: Vec::new(),
        det_truth: Vec::new(),
        det_sources: Vec::new(),
        det_mixed: Vec::new(),
        det_pulse: Vec::new(),
        det_xy: Vec::new(),
        det_t_us: Vec::new(),
        det_events: Vec::new(),
        truth: Vec::new(),
        position_sigma: 0.0,
        stats: Default::default(),
        split_parts: Vec::new(),
    };
    // Split parts: (serial, truth, sources, mixed, pulse, parent serial,
    // events, centroid).
    type Part = (u64, Option<u64>, Vec<u64>, bool, i64, u64, u32, [f64; 2]);
    let mut parts_of_splits: Vec<Part> = Vec::new();
    for sp in scene {
        let ((parts, ids, mixed, sources), table) = cluster_with_truth_pixels(sp, cparams);
        run.det_pulse
            .extend(std::iter::repeat_n(sp.pulse.index, parts.len()));
        run.det_truth.extend(ids);
        run.det_events.extend(parts.iter().map(|p| p.n_events));
        run.det_xy.extend(parts.iter().map(|p| [p.x, p.y]));
        run.det_t_us
            .extend(std::iter::repeat_n(sp.pulse.start_us, parts.len()));
        run.det_mixed.extend(mixed);
        run.det_sources.extend(sources);
        run.tracks.extend(tracker.push_linked_with_pixels(
            sp.pulse.index,
            sp.pulse.start_us,
            &parts,
            Some(&table),
        )?);
        run.truth.extend_from_slice(&sp.truth);
        let splits = tracker.take_splits();
        if splits.is_empty() {
            continue;
        }
        let mut at_pixel: HashMap<(u16, u16), Vec<Option<u64>>> = HashMap::new();
        let ev = &sp.pulse.events;
        for i in 0..ev.len() {
            if !(cparams.on_only && ev.p[i] != ON) {
                at_pixel
                    .entry((ev.x[i], ev.y[i]))
                    .or_default()
                    .push(sp.event_truth[i]);
            }
        }
        let truth_xy: HashMap<u64, (f64, f64)> = sp
            .truth
            .iter()
            .map(|t| (t.particle_id, (t.x, t.y)))
            .collect();
        for d in splits {
            let mut votes: HashMap<Option<u64>, u32> = HashMap::new();
            for p in &d.pixels {
                for id in at_pixel.get(&(p.x, p.y)).into_iter().flatten() {
                    *votes.entry(*id).or_default() += 1;
                }
            }
            let mut src: Vec<u64> = votes.keys().flatten().copied().collect();
            src.sort_unstable();
            let id = attribute_votes(&votes, (d.x, d.y), &truth_xy);
            let n: u32 = d.pixels.iter().map(|p| p.count).sum();
            parts_of_splits.push((
                d.serial,
                id,
                src,
                votes.len() > 1,
                d.pulse,
                d.parent,
                n,
                [d.x, d.y],
            ));
        }
    }
    run.position_sigma = tracker.position_sigma();
    let (rest, stats) = tracker.finish();
    run.tracks.extend(rest);
    run.stats = stats;
    if !parts_of_splits.is_empty() {
        let base = run.det_truth.len() as u64;
        let index: HashMap<u64, u64> = parts_of_splits
            .iter()
            .enumerate()
            .map(|(k, p)| (p.0, base + k as u64))
            .collect();
        for (_, id, src, mixed, pulse, parent, n, xy) in parts_of_splits {
            run.det_events.push(n);
            let parent = parent as usize;
            run.det_xy.push(xy);
            run.det_t_us.push(run.det_t_us[parent]);
            let was_mixed = run.det_mixed[parent] || run.det_sources[parent].len() > 1;
            run.split_parts
                .push((run.det_truth.len(), parent, was_mixed));
            run.det_truth[parent] = None;
            run.det_sources[parent].clear();
            run.det_mixed[parent] = false;
            run.det_truth.push(id);
            run.det_sources.push(src);
            run.det_mixed.push(mixed);
            run.det_pulse.push(pulse);
        }
        for t in &mut run.tracks {
            for d in t.detections.iter_mut().flatten() {
                if *d & crate::track::SPLIT_SERIAL_BIT != 0 {
                    *d = index[d];
                }
            }
        }
    }
    Ok(run)
}

/// Run the whole PTV stage on a scene: cluster every pulse, track, score
/// ([`run_scene`]; detections of the returned tracks numbered as there).
pub fn run_and_score(
    scene: &[SynthPulse],
    cparams: &ClusterParams,
    tparams: &crate::track::TrackParams,
    period_us: f64,
) -> crate::Result<(Vec<LinkedTrack>, LinkScore)> {
    let run = run_scene(scene, cparams, tparams)?;
    let s = score_with_sources(
        &run.tracks,
        &run.det_truth,
        &run.det_sources,
        &run.det_pulse,
        &run.truth,
        period_us,
        INTERIOR_MARGIN,
    );
    Ok((run.tracks, s))
}
