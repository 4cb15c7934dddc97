//! One scene run end to end ([`run_scene`]: cluster with truth, track,
//! attribute) and its score ([`run_and_score`]).

use super::*;

/// Track points at least this many detections from both ends of their
/// track count as interior in [`run_and_score`] (the half-width of the
/// 11-point fixed output window, kept so numbers compare across fits).
#[ebptv_macros::testkit]
pub(crate) const INTERIOR_MARGIN: usize = 5;

/// A scene clustered and tracked, with the truth of every detection
/// (indexed by detection: the serials of [`crate::track::Tracker`]).
#[derive(Debug, Clone)]
#[ebptv_macros::testkit]
pub(crate) struct SceneRun {
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
}

/// Cluster every pulse, track, and attribute every detection with the
/// rule of [`cluster_with_truth`].
#[ebptv_macros::testkit]
pub(crate) fn run_scene(
    scene: &[SynthPulse],
    cparams: &ClusterParams,
    tparams: &crate::track::TrackParams,
) -> crate::Result<SceneRun> {
    let mut tracker = crate::track::Tracker::new(tparams.clone())?;
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
    };
    for sp in scene {
        let (parts, ids, mixed, sources) = cluster_with_truth_sources(sp, cparams);
        run.det_pulse
            .extend(std::iter::repeat_n(sp.pulse.index, parts.len()));
        run.det_truth.extend(ids);
        run.det_events.extend(parts.iter().map(|p| p.n_events));
        run.det_xy.extend(parts.iter().map(|p| [p.x, p.y]));
        run.det_t_us
            .extend(std::iter::repeat_n(sp.pulse.start_us, parts.len()));
        run.det_mixed.extend(mixed);
        run.det_sources.extend(sources);
        run.tracks
            .extend(tracker.push_linked(sp.pulse.index, sp.pulse.start_us, &parts)?);
        run.truth.extend_from_slice(&sp.truth);
    }
    run.position_sigma = tracker.position_sigma();
    let (rest, stats) = tracker.finish();
    run.tracks.extend(rest);
    run.stats = stats;
    Ok(run)
}

/// Run the whole PTV stage on a scene: cluster every pulse, track, score
/// ([`run_scene`]; detections of the returned tracks numbered as there).
#[ebptv_macros::testkit]
pub(crate) fn run_and_score(
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
