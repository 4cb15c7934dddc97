//! Finishing ended tracks (stage 6 of the module doc): the cuts at steps
//! ([`super::step`]), outlier removal, the length rules and the local-flow
//! ghost test, and the calls of the output fit ([`super::fit`]);
//! [`Finaliser`] holds the fits' sequential state so that they can run off the
//! linking thread. [`fit_detections`] fits given detections directly.

use super::*;
use fit::LocalPolyFit;

/// Window of the outlier check at finalisation (an 11-point fixed window;
/// the output fit itself chooses its window adaptively).
pub(super) const OUTLIER_WINDOW: usize = 11;

impl Tracker {
    /// Fit, validate and number the given ended tracks — here, or, after
    /// [`Tracker::defer_fits`], later by the [`Finaliser`] (with the
    /// outlier gate and noise of this moment either way).
    pub(super) fn finalise(&mut self, ended: Vec<ActiveTrack>) -> Vec<LinkedTrack> {
        if ended.is_empty() {
            // The flow samples wait for the next batch that has tracks.
            return Vec::new();
        }
        let sigma = self.position_sigma();
        let ended = EndedTracks {
            tracks: ended,
            sigma,
            gate: self.params.fit.outlier_sigma * sigma,
            flow_samples: std::mem::take(&mut self.flow_log),
        };
        match &mut self.deferred {
            Some(queue) => {
                if !ended.tracks.is_empty() {
                    queue.push(ended);
                }
                Vec::new()
            }
            None => self.finaliser.finalise(ended, &mut self.stats),
        }
    }
}

/// Cut an ended track at its steps (`TrackParams::step_split`, see
/// [`step::step_cuts`]): the pieces, in order, each to be fitted as a track
/// of its own, and the number of cuts. A pure function of the track, so
/// it runs on the finaliser's parallel workers, not on the linking thread.
pub(super) fn cut_at_steps(t: ActiveTrack, sigma: f64, threshold: f64) -> (u64, Vec<ActiveTrack>) {
    if threshold <= 0.0 {
        return (0, vec![t]);
    }
    let xy: Vec<(i64, f64, f64)> = t.dets.iter().map(|d| (d.pulse, d.x, d.y)).collect();
    // Context detections were handed out with an earlier segment: a cut
    // among them could not change that segment.
    let cuts = step::step_cuts(&xy, sigma, threshold, t.context.max(1));
    if cuts.is_empty() {
        return (0, vec![t]);
    }
    let ActiveTrack { uid, dets, context } = t;
    let mut pieces = Vec::with_capacity(cuts.len() + 1);
    let mut start = 0;
    for (k, &c) in cuts.iter().chain(std::iter::once(&dets.len())).enumerate() {
        pieces.push(ActiveTrack {
            uid: if k == 0 { uid } else { NO_OWNER },
            dets: dets[start..c].to_vec(),
            context: if k == 0 { context } else { 0 },
        });
        start = c;
    }
    (cuts.len() as u64, pieces)
}

/// Tracks that ended together (one call of the tracker's fits), not yet
/// fitted: their detections and the position noise and outlier gate of
/// the moment they ended. [`Finaliser::finalise`] turns them into tracks.
pub(crate) struct EndedTracks {
    pub(super) tracks: Vec<ActiveTrack>,
    pub(super) sigma: f64,
    pub(super) gate: f64,
    /// The tracker's local-flow samples since the previous batch.
    pub(super) flow_samples: Vec<local_flow::FlowSample>,
}

/// The output fits' sequential state: the curvature prior estimated from
/// the tracks kept so far ([`fit::AccelPrior`]) and the next track id.
/// Batches of [`EndedTracks`] must be finalised in the order they ended:
/// each batch's fits use the prior of the batches before it (and run in
/// parallel among themselves), its tracks are numbered after them.
pub(crate) struct Finaliser {
    pub(super) params: TrackParams,
    pub(super) accel_prior: fit::AccelPrior,
    /// A copy of the tracker's local flow, brought up to date from each
    /// batch's `flow_samples` (the ghost test of short tracks).
    pub(super) flow: local_flow::LocalFlow,
    pub(super) next_id: u64,
}

impl Finaliser {
    pub(super) fn new(params: TrackParams) -> Self {
        Finaliser {
            params,
            accel_prior: fit::AccelPrior::default(),
            flow: local_flow::LocalFlow::new(FLOW_CELL, FLOW_MEMORY),
            next_id: 0,
        }
    }

    /// Fit, validate and number one batch of ended tracks; the fits'
    /// counters (`tracks_kept`, `tracks_rejected_*`,
    /// `particles_on_tracks`) are added to `stats`. The fit of each
    /// track depends only on its detections, the parameters, the noise
    /// and gate of the batch and the prior (fixed for the batch), so the
    /// tracks are fitted in parallel (rayon, in the caller's pool) and
    /// counted and numbered afterwards in input order: the result does
    /// not depend on the thread count.
    pub(crate) fn finalise(
        &mut self,
        ended: EndedTracks,
        stats: &mut TrackerStats,
    ) -> Vec<LinkedTrack> {
        use rayon::prelude::*;
        let EndedTracks {
            tracks: ended,
            sigma,
            gate,
            flow_samples,
        } = ended;
        let params = &self.params;
        // The flow as the tracker saw it when these tracks ended.
        for sample in flow_samples {
            self.flow.add_sample(sample);
        }
        // The prior as of the tracks kept before this batch: the same for
        // every track of the batch, whatever the thread count (and so is
        // the local flow).
        let accel = params
            .fit
            .fit_accel_rms
            .unwrap_or_else(|| self.accel_prior.accel_rms(sigma));
        let flow = &self.flow;
        // Step cuts first (each piece is fitted as a track of its own),
        // on the same workers as the fits.
        let cut_and_fit = |t: ActiveTrack| -> (u64, Vec<Finalised>) {
            let (cuts, pieces) = cut_at_steps(t, sigma, params.stitch.step_split);
            let fitted = pieces
                .into_iter()
                .map(|p| finalise_one(p, params, flow, gate, sigma, accel))
                .collect();
            (cuts, fitted)
        };
        let fitted: Vec<(u64, Vec<Finalised>)> = if ended.len() >= 2 {
            ended
                .into_par_iter()
                .with_max_len(1)
                .map(cut_and_fit)
                .collect()
        } else {
            ended.into_iter().map(cut_and_fit).collect()
        };
        let mut out = Vec::new();
        for f in fitted.into_iter().flat_map(|(cuts, pieces)| {
            stats.tracks_cut_at_steps += cuts;
            pieces
        }) {
            match f {
                Finalised::NothingNew => {}
                Finalised::Short => stats.tracks_rejected_short += 1,
                Finalised::Ghost => stats.tracks_rejected_ghost += 1,
                Finalised::Rough => stats.tracks_rejected_rough += 1,
                Finalised::Kept {
                    points,
                    detections,
                    fresh,
                    curvature,
                    by_flow,
                } => {
                    stats.tracks_kept_by_flow += by_flow as u64;
                    self.accel_prior.merge(&curvature);
                    stats.tracks_kept += 1;
                    stats.particles_on_tracks += fresh as u64;
                    out.push(LinkedTrack {
                        track: Track {
                            id: self.next_id,
                            points,
                        },
                        detections,
                    });
                    self.next_id += 1;
                }
            }
        }
        out
    }
}

/// What [`finalise_one`] made of an ended track.
pub(super) enum Finalised {
    /// A continuation segment with nothing after the last handed-out one.
    NothingNew,
    /// Fewer than `min_length` detections.
    Short,
    /// A short track whose velocity disagrees with the local flow.
    Ghost,
    /// Fit residual above `max_fit_residual`.
    Rough,
    /// Kept, with `fresh` detections not handed out before, and their
    /// curvature samples for the output fit's prior.
    Kept {
        points: Vec<TrackPoint>,
        detections: Vec<Option<u64>>,
        fresh: usize,
        curvature: fit::AccelPrior,
        /// Below `min_length`, kept by the local-flow test.
        by_flow: bool,
    },
}

/// Clean (outliers, unconfirmed tail), validate and fit one ended track;
/// `gate` is the outlier gate in px. Pure: the numbering and the counters
/// are [`Tracker::finalise`]'s.
pub(super) fn finalise_one(
    mut t: ActiveTrack,
    params: &TrackParams,
    flow: &local_flow::LocalFlow,
    gate: f64,
    sigma: f64,
    accel_rms: f64,
) -> Finalised {
    // Points up to this pulse went out with an earlier segment.
    let handed_out = (t.context > 0).then(|| t.dets[t.context - 1].pulse);
    // The outlier pass's heading prefix of the detections, while they
    // are the ones it was computed from (the output fit's screen reads
    // the same prefix).
    let mut heading = None;
    if params.fit.outlier_sigma > 0.0 {
        let window = params.fit.fit_window.min(OUTLIER_WINDOW);
        if params.turn_model {
            heading = remove_outliers_turning(&mut t.dets, window, gate, sigma);
        } else {
            remove_outliers(&mut t.dets, window, gate);
        }
    }
    let before_trim = t.dets.len();
    trim_unconfirmed_tail(&mut t.dets, params.stitch.confirm_after_gap);
    if t.dets.len() != before_trim {
        heading = None;
    }
    let fresh = match handed_out {
        None => t.dets.len(),
        Some(h) => t.dets.iter().filter(|d| d.pulse > h).count(),
    };
    if handed_out.is_some() && fresh == 0 {
        return Finalised::NothingNew;
    }
    let mut by_flow = false;
    if handed_out.is_none() {
        match short_track_verdict(&t.dets, params, flow, sigma) {
            Verdict::Short => return Finalised::Short,
            Verdict::Ghost => return Finalised::Ghost,
            Verdict::Keep { by_flow: f } => by_flow = f,
        }
    }
    let (mut points, mut detections, rms) = fit_track_known(
        &t.dets,
        params,
        sigma,
        accel_rms,
        fit::FitPath::Fast,
        &mut (0, 0),
        heading,
    );
    if rms > params.fit.max_fit_residual {
        return Finalised::Rough;
    }
    let mut curvature = fit::AccelPrior::default();
    {
        let new = &t.dets[t.dets.len() - fresh..];
        let pulses: Vec<i64> = new.iter().map(|d| d.pulse).collect();
        let xy: Vec<[f64; 2]> = new.iter().map(|d| [d.x, d.y]).collect();
        curvature.add_track(&pulses, &xy);
    }
    if let Some(h) = handed_out {
        let first = points
            .iter()
            .position(|p| p.pulse > h)
            .unwrap_or(points.len());
        points.drain(..first);
        detections.drain(..first);
    }
    Finalised::Kept {
        points,
        detections,
        fresh,
        curvature,
        by_flow,
    }
}

/// What the length rules and the ghost test say about a whole track.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Verdict {
    Short,
    Ghost,
    Keep { by_flow: bool },
}

/// The length rules with the local-flow ghost test: below
/// `min_length_flow` detections a track is short; below
/// `ghost_check_length` it is tested against the local flow and dropped
/// as a ghost when it disagrees; below `min_length` it needs the flow's
/// approval (an unknown flow makes it short).
pub(super) fn short_track_verdict(
    dets: &[Det],
    params: &TrackParams,
    flow: &local_flow::LocalFlow,
    sigma: f64,
) -> Verdict {
    let n = dets.len();
    let checked = n < params.init.ghost_check_length;
    if n < params.min_length && (!checked || n < params.init.min_length_flow) {
        return Verdict::Short;
    }
    if !checked {
        return Verdict::Keep { by_flow: false };
    }
    let xy: Vec<(i64, f64, f64)> = dets.iter().map(|d| (d.pulse, d.x, d.y)).collect();
    match local_flow::flow_consistent(&xy, flow, sigma, params.init.ghost_sigma) {
        local_flow::FlowCheck::Ghost => Verdict::Ghost,
        local_flow::FlowCheck::Consistent => Verdict::Keep {
            by_flow: n < params.min_length,
        },
        local_flow::FlowCheck::Unknown if n < params.min_length => Verdict::Short,
        local_flow::FlowCheck::Unknown => Verdict::Keep { by_flow: false },
    }
}

/// Remove detections that the rest of the track does not support: each
/// detection is compared with a quadratic fit of its neighbours (the
/// `window` nearest detections, itself excluded), and dropped when it lies
/// further than `gate · √(1 + leverage)` from it. A dropped interior
/// detection becomes a bridged gap. Catches the stray particle a track
/// grabs while its own is missing, and wrong first/last detections.
pub(super) fn remove_outliers(dets: &mut Vec<Det>, window: usize, gate: f64) {
    remove_outliers_with(dets, window, gate, true)
}

/// [`remove_outliers`] where the path turns: a detection whose window's
/// heading changes visibly (the output fit's screen, position noise
/// `sigma`) is predicted by the turning path through the window
/// ([`turn`]) instead of the quadratic, which would take good detections
/// of a vortex core for outliers and the stray one a young track took
/// there for good. Returns the heading prefix ([`turn::heading_prefix`])
/// of the detections it leaves when it computed one and removed none.
pub(super) fn remove_outliers_turning(
    dets: &mut Vec<Det>,
    window: usize,
    gate: f64,
    sigma: f64,
) -> Option<Vec<[f64; 2]>> {
    let n = dets.len();
    if n < 8 || sigma <= 0.0 {
        remove_outliers(dets, window, gate);
        return None;
    }
    let w = window.min(n - 1).max(5);
    let pulses: Vec<i64> = dets.iter().map(|d| d.pulse).collect();
    let xs: Vec<f64> = dets.iter().map(|d| d.x).collect();
    let ys: Vec<f64> = dets.iter().map(|d| d.y).collect();
    let hp = turn::heading_prefix(&pulses, &xs, &ys, sigma);
    // The verdicts of the polynomial pass (detections numbered by their
    // index), replaced by the turning path's where the heading turns.
    let mut marked: Vec<Det> = dets.clone();
    for (k, d) in marked.iter_mut().enumerate() {
        d.serial = k as u64;
    }
    remove_outliers(&mut marked, window, gate);
    let mut keep = vec![false; n];
    for d in &marked {
        keep[d.serial as usize] = true;
    }
    let (mut tau, mut wx, mut wy) = (
        Vec::with_capacity(w),
        Vec::with_capacity(w),
        Vec::with_capacity(w),
    );
    for i in 0..n {
        let mut lo = i.saturating_sub(w / 2);
        if lo + w + 1 > n {
            lo = n - w - 1;
        }
        let hi = lo + w + 1;
        // Heading changes at detections lo+1..hi-1.
        let (dth, var) = (hp[hi - 1][0] - hp[lo + 1][0], hp[hi - 1][1] - hp[lo + 1][1]);
        if !(var > 0.0 && dth * dth > TURN_SCREEN_Z * TURN_SCREEN_Z * var) {
            continue;
        }
        tau.clear();
        wx.clear();
        wy.clear();
        for j in lo..hi {
            if j != i {
                tau.push((pulses[j] - pulses[i]) as f64);
                wx.push(xs[j]);
                wy.push(ys[j]);
            }
        }
        // Only where the window's other detections show the turn: the
        // turning path beats the quadratic by the output fit's margin.
        if let Some((f, gain)) = turn::turn_eval_with_gain(&tau, &wx, &wy, 0.0) {
            if gain > TURN_GAIN_MIN * sigma * sigma {
                let d2 = (f.x - xs[i]).powi(2) + (f.y - ys[i]).powi(2);
                keep[i] = d2 <= gate * gate * (1.0 + f.leverage);
            }
        }
    }
    if keep.iter().all(|&k| k) {
        return Some(hp);
    }
    let mut k = 0;
    dets.retain(|_| {
        k += 1;
        keep[k - 1]
    });
    None
}

/// [`remove_outliers`]; `grid` takes the tabulated predictions
/// ([`fit::LeaveOneOut`]) on gap-free windows, `false` the plain fit
/// everywhere (the reference).
pub(super) fn remove_outliers_with(dets: &mut Vec<Det>, window: usize, gate: f64, grid: bool) {
    let n = dets.len();
    if n < 6 {
        return;
    }
    let w = window.min(n - 1).max(5);
    // Gap-free windows (τ = pulse offsets, exact integers) take the
    // tabulated leave-one-out weights; windows with gaps the plain fit.
    let loo = fit::LeaveOneOut::cached(window.max(5));
    let all_xy: Vec<[f64; 2]> = dets.iter().map(|d| [d.x, d.y]).collect();
    let mut keep = vec![true; n];
    let mut tau = Vec::with_capacity(w);
    let mut xs = Vec::with_capacity(w);
    let mut ys = Vec::with_capacity(w);
    for i in 0..n {
        // The w detections nearest to i, i excluded.
        let mut lo = i.saturating_sub(w / 2);
        if lo + w + 1 > n {
            lo = n - w - 1;
        }
        if grid && dets[lo + w].pulse - dets[lo].pulse == w as i64 {
            if let Some((dx, dy, leverage)) = loo.predict(&all_xy[lo..=lo + w], i - lo) {
                if dx * dx + dy * dy > gate * gate * (1.0 + leverage) {
                    keep[i] = false;
                }
                continue;
            }
        }
        tau.clear();
        xs.clear();
        ys.clear();
        for (j, d) in dets.iter().enumerate().skip(lo).take(w + 1) {
            if j != i {
                tau.push((d.pulse - dets[i].pulse) as f64);
                xs.push(d.x);
                ys.push(d.y);
            }
        }
        if let Some(f) = fit::fit_eval(&tau, &xs, &ys, 2, 0.0) {
            let d2 = (f.x - dets[i].x).powi(2) + (f.y - dets[i].y).powi(2);
            if d2 > gate * gate * (1.0 + f.leverage) {
                keep[i] = false;
            }
        }
    }
    let mut k = 0;
    dets.retain(|_| {
        k += 1;
        keep[k - 1]
    });
}

/// Cut detections after the last gap when fewer than `confirm` follow it.
pub(super) fn trim_unconfirmed_tail(dets: &mut Vec<Det>, confirm: usize) {
    let n = dets.len();
    let Some(last_gap) = (1..n)
        .rev()
        .find(|&i| dets[i].pulse != dets[i - 1].pulse + 1)
    else {
        return;
    };
    if n - last_gap < confirm {
        dets.truncate(last_gap);
    }
}

/// The mean pulse period (s) over a track's detections: the output fit's
/// time unit.
pub(super) fn fit_period_s(dets: &[Det]) -> f64 {
    let n = dets.len();
    ((dets[n - 1].t_us - dets[0].t_us) / (dets[n - 1].pulse - dets[0].pulse).max(1) as f64)
        .max(1e-9)
        * 1e-6
}

/// Sliding-window polynomial fit of a track at every pulse from its first
/// to its last detection, the window chosen per pulse by the adaptive
/// rule of [`fit::fit_adaptive`] for position noise `sigma` (px per
/// axis), through the one fit API ([`fit::OutputFit`]). Returns the
/// points, the detection serials and the rms residual (px per axis) of the
/// detections about the fitted positions.
///
/// `path` names the backends the fit may take besides the plain one
/// ([`fit::FitPath`]); the tests compare them with `FitPath::Plain`.
/// `fits` counts the samples taken by the tabulated and the gap backends.
#[cfg(feature = "testkit")]
pub(super) fn fit_track_with(
    dets: &[Det],
    p: &TrackParams,
    sigma: f64,
    accel_rms: f64,
    path: fit::FitPath,
    fits: &mut (usize, usize),
) -> (Vec<TrackPoint>, Vec<Option<u64>>, f64) {
    fit_track_known(dets, p, sigma, accel_rms, path, fits, None)
}

/// [`fit_track_with`], given the heading prefix of `dets`
/// ([`turn::heading_prefix`] with this `sigma`) when it is known.
fn fit_track_known(
    dets: &[Det],
    p: &TrackParams,
    sigma: f64,
    accel_rms: f64,
    path: fit::FitPath,
    fits: &mut (usize, usize),
    known_heading: Option<Vec<[f64; 2]>>,
) -> (Vec<TrackPoint>, Vec<Option<u64>>, f64) {
    let n = dets.len();
    let first = dets[0].pulse;
    let last = dets[n - 1].pulse;
    let mut points = Vec::with_capacity((last - first + 1) as usize);
    let mut serials = Vec::with_capacity(points.capacity());
    let mut ssr = 0.0;
    // τ in units of the mean period from the first detection.
    let period_s = fit_period_s(dets);
    let tau: Vec<f64> = dets
        .iter()
        .map(|d| (d.t_us - dets[0].t_us) * 1e-6 / period_s)
        .collect();
    let xs: Vec<f64> = dets.iter().map(|d| d.x).collect();
    let ys: Vec<f64> = dets.iter().map(|d| d.y).collect();
    let pulses: Vec<i64> = dets.iter().map(|d| d.pulse).collect();
    let rule = fit::WindowRule {
        min_window: p.fit.fit_min_window,
        max_window: p.fit.fit_window,
        order: p.fit.fit_order,
        sigma,
        bias_weight: p.fit.fit_bias_weight,
        // px/pulse² to px/τ² (τ in mean periods: the same on the grid).
        accel_rms,
    };
    let t_max = dets[0].t_us.abs().max(dets[n - 1].t_us.abs());
    let samples = fit::TrackSamples::new(
        tau,
        xs,
        ys,
        &pulses,
        fit::grid_tolerance(t_max, period_s * 1e6),
    );
    let (tau, xs, ys) = (&samples.tau, &samples.xs, &samples.ys);
    let tables = fit::GridTables::cached(&rule);
    let mut output_fit = fit::OutputFit::new(&rule, &tables, path);
    // Where the path turns, the turning path's fit (`turn_fit_window`).
    let heading =
        (p.turn_model && p.fit.turn_fit_window >= 7 && n >= p.fit.turn_fit_window).then(|| {
            known_heading
                .filter(|h| h.len() == n + 1)
                .unwrap_or_else(|| turn::heading_prefix(&pulses, xs, ys, sigma))
        });
    let mut j = 0; // index of the first detection at or after the pulse
    for pulse in first..=last {
        while dets[j].pulse < pulse {
            j += 1;
        }
        let here = dets[j].pulse == pulse;
        // Pulse time: exact at detections, interpolated on gaps (pulses are
        // regular, so linear in the pulse index).
        let t_us = if here {
            dets[j].t_us
        } else {
            let (a, b) = (&dets[j - 1], &dets[j]);
            a.t_us + (b.t_us - a.t_us) * (pulse - a.pulse) as f64 / (b.pulse - a.pulse) as f64
        };
        let at = (t_us - dets[0].t_us) * 1e-6 / period_s;
        let fitted = output_fit.fit(
            &samples,
            fit::At {
                centre: j,
                tau: at,
                offset: pulse - first,
            },
        );
        let mut f = fitted.map(|(f, _)| f).unwrap_or(fit::FitState {
            x: dets[j].x,
            y: dets[j].y,
            vx: 0.0,
            vy: 0.0,
            ax: 0.0,
            ay: 0.0,
            rms_residual: 0.0,
            leverage: 1.0,
            velocity_variance: 0.0,
        });
        if let Some(hp) = &heading {
            let wt = p.fit.turn_fit_window;
            let a = j.saturating_sub(wt / 2).min(n - wt);
            let b = a + wt;
            // Heading changes at detections a+1..b-1 (inside the window).
            let (dth, var) = (hp[b - 1][0] - hp[a + 1][0], hp[b - 1][1] - hp[a + 1][1]);
            if var > 0.0 && dth * dth > TURN_SCREEN_Z * TURN_SCREEN_Z * var {
                if let Some((t, gain)) =
                    turn::turn_eval_with_gain(&tau[a..b], &xs[a..b], &ys[a..b], at)
                {
                    if gain > TURN_GAIN_MIN * sigma * sigma {
                        f.x = t.x;
                        f.y = t.y;
                        f.vx = t.u;
                        f.vy = t.v;
                        f.ax = t.ax;
                        f.ay = t.ay;
                    }
                }
            }
        }
        if here {
            ssr += (dets[j].x - f.x).powi(2) + (dets[j].y - f.y).powi(2);
        }
        points.push(TrackPoint {
            pulse,
            t_us,
            x: f.x,
            y: f.y,
            u: f.vx / period_s,
            v: f.vy / period_s,
            ax: f.ax / (period_s * period_s),
            ay: f.ay / (period_s * period_s),
            interpolated: !here,
        });
        serials.push(if here { Some(dets[j].serial) } else { None });
    }
    *fits = (output_fit.tabulated_fits, output_fit.gap_fits);
    (points, serials, (ssr / (2 * n) as f64).sqrt())
}

#[cfg(feature = "testkit")]
/// One detection handed to [`fit_detections`]: its serial, pulse, pulse
/// time (µs) and centroid (px).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct FitInput {
    pub serial: u64,
    pub pulse: i64,
    pub t_us: f64,
    pub x: f64,
    pub y: f64,
}

#[cfg(feature = "testkit")]
/// The output fit the tracker gives a finished track (the sliding,
/// adaptive-window polynomial of `fit_order` with the curvature prior
/// `accel_rms`, px/pulse², 0 = none; position noise `sigma`, px per axis;
/// tabulated where the windows are gap-free), applied to detections given
/// from outside: for analysis, e.g. fitting the ideal tracks of a
/// synthetic scene ([`synth::oracle_tracks`]) with exactly the code that
/// fits the tracker's own, so that the two velocity errors differ only in
/// the links. Only the fit: no outlier removal, length rule or step cut
/// (those are link decisions).
/// `dets` must be in increasing pulse order, at least one.
pub(crate) fn fit_detections(
    dets: &[FitInput],
    params: &TrackParams,
    sigma: f64,
    accel_rms: f64,
) -> LinkedTrack {
    let dets: Vec<Det> = dets
        .iter()
        .map(|d| Det {
            serial: d.serial,
            pulse: d.pulse,
            t_us: d.t_us,
            x: d.x,
            y: d.y,
        })
        .collect();
    let (points, detections, _) = fit_track_with(
        &dets,
        params,
        sigma,
        accel_rms,
        fit::FitPath::Fast,
        &mut (0, 0),
    );
    LinkedTrack {
        track: Track { id: 0, points },
        detections,
    }
}
