//! Finishing ended tracks (stage 6 of the module doc): the cuts at steps
//! ([`super::step`]), outlier removal, the length rules and the local-flow
//! ghost test, and the calls of the output fit ([`super::fit`]);
//! [`Finaliser`] holds the fits' sequential state so that they can run off the
//! linking thread. [`fit_detections`] fits given detections directly.

use super::*;

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
            gate: self.params.outlier_sigma * sigma,
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
pub(super) fn cut_at_steps(
    t: ActiveTrack,
    sigma: f64,
    threshold: f64,
    hinted_threshold: f64,
) -> (u64, Vec<ActiveTrack>) {
    if threshold <= 0.0 {
        return (0, vec![t]);
    }
    let xy: Vec<(i64, f64, f64)> = t.dets.iter().map(|d| (d.pulse, d.x, d.y)).collect();
    // Context detections were handed out with an earlier segment: a cut
    // among them could not change that segment.
    let cuts = if hinted_threshold > 0.0 {
        let nb: Vec<[f64; 2]> = t
            .dets
            .iter()
            .map(|d| [d.nb[0] as f64, d.nb[1] as f64])
            .collect();
        step::step_cuts_hinted(
            &xy,
            &nb,
            sigma,
            threshold,
            hinted_threshold,
            t.context.max(1),
        )
    } else {
        step::step_cuts(&xy, sigma, threshold, t.context.max(1))
    };
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
pub struct EndedTracks {
    pub(super) tracks: Vec<ActiveTrack>,
    pub(super) sigma: f64,
    pub(super) gate: f64,
    /// The tracker's local-flow samples since the previous batch.
    pub(super) flow_samples: Vec<local_flow::FlowSample>,
}

impl EndedTracks {
    /// Number of ended tracks (kept or not).
    pub fn len(&self) -> usize {
        self.tracks.len()
    }

    pub fn is_empty(&self) -> bool {
        self.tracks.is_empty()
    }
}

/// The output fits' sequential state: the curvature prior estimated from
/// the tracks kept so far ([`fit::AccelPrior`]) and the next track id.
/// Batches of [`EndedTracks`] must be finalised in the order they ended:
/// each batch's fits use the prior of the batches before it (and run in
/// parallel among themselves), its tracks are numbered after them.
pub struct Finaliser {
    pub(super) params: TrackParams,
    pub(super) accel_prior: fit::AccelPrior,
    /// A copy of the tracker's local flow, brought up to date from each
    /// batch's `flow_samples` (the ghost test of short tracks).
    pub(super) flow: local_flow::LocalFlow,
    /// The same samples with their positions: the local linear flow of
    /// the output fit's velocity prior (`TrackParams::velocity_prior`).
    pub(super) linear_flow: local_flow::FlowHistory,
    /// The prior's variance as measured on the tracks kept so far.
    pub(super) prior_calibration: local_flow::PriorCalibration,
    pub(super) next_id: u64,
    /// Numbered tracks waiting for [`Finaliser::refit_held`].
    pub(super) held: Vec<(LinkedTrack, Box<Refit>)>,
}

impl Finaliser {
    pub(super) fn new(params: TrackParams) -> Self {
        Finaliser {
            params,
            accel_prior: fit::AccelPrior::default(),
            flow: local_flow::LocalFlow::new(FLOW_CELL, FLOW_MEMORY),
            linear_flow: local_flow::FlowHistory::new(
                FLOW_CELL,
                FLOW_MEMORY,
                PRIOR_BLOCK,
                PRIOR_KEEP,
            ),
            prior_calibration: local_flow::PriorCalibration::default(),
            next_id: 0,
            held: Vec::new(),
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
    pub fn finalise(&mut self, ended: EndedTracks, stats: &mut TrackerStats) -> Vec<LinkedTrack> {
        use rayon::prelude::*;
        let EndedTracks {
            tracks: ended,
            sigma,
            gate,
            flow_samples,
        } = ended;
        let params = &self.params;
        // The flow as the tracker saw it when these tracks ended (the
        // two-pass prior comes later, from all tracks).
        let with_prior = params.velocity_prior > 0.0 && !params.velocity_prior_two_pass;
        for sample in flow_samples {
            self.flow.add_sample(sample);
            if with_prior {
                self.linear_flow.add_sample(sample);
            }
        }
        // The prior as of the tracks kept before this batch: the same for
        // every track of the batch, whatever the thread count (and so is
        // the local flow).
        let accel = params
            .fit_accel_rms
            .unwrap_or_else(|| self.accel_prior.accel_rms(sigma));
        let flow = &self.flow;
        // The prior applies once its variance is calibrated (as of the
        // batches before this one); before, only the calibration runs.
        let prior = with_prior.then(|| VelocityPriorUse {
            flow: &self.linear_flow,
            scale: self
                .prior_calibration
                .scale()
                .zip(self.prior_calibration.typical_fit_variance()),
            strength: params.velocity_prior,
        });
        // Step cuts first (each piece is fitted as a track of its own),
        // on the same workers as the fits.
        let cut_and_fit = |t: ActiveTrack| -> (u64, Vec<Finalised>) {
            let (cuts, pieces) =
                cut_at_steps(t, sigma, params.step_split, params.step_split_hinted);
            let fitted = pieces
                .into_iter()
                .map(|p| finalise_one(p, params, flow, prior.as_ref(), gate, sigma, accel))
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
                    calibration,
                    by_flow,
                    refit,
                } => {
                    self.prior_calibration.merge(&calibration);
                    stats.tracks_kept_by_flow += by_flow as u64;
                    self.accel_prior.merge(&curvature);
                    stats.tracks_kept += 1;
                    stats.particles_on_tracks += fresh as u64;
                    let linked = LinkedTrack {
                        track: Track {
                            id: self.next_id,
                            points,
                        },
                        detections,
                    };
                    match refit {
                        Some(r) => self.held.push((linked, r)),
                        None => out.push(linked),
                    }
                    self.next_id += 1;
                }
            }
        }
        out
    }

    /// The second pass of `TrackParams::velocity_prior_two_pass`: the
    /// held tracks' first-pass points become the whole run's flow
    /// ([`local_flow::WholeRunFlow`]), the prior's variance is calibrated
    /// on all of them (their first-pass fits, every point), and each
    /// point's fit is combined with its prior as the output fit would
    /// (the fit is the first pass's: links, positions and residuals
    /// stay; only the velocities move). Returns the tracks in id order;
    /// none when nothing is held. Each point's prior depends only on its
    /// track and the (fixed) flow: parallel, independent of the thread
    /// count.
    pub fn refit_held(&mut self) -> Vec<LinkedTrack> {
        use rayon::prelude::*;
        let held = std::mem::take(&mut self.held);
        if held.is_empty() {
            return Vec::new();
        }
        let params = &self.params;
        let mut samples = Vec::new();
        for (lt, r) in &held {
            let period = r.period_s;
            for ((p, d), &fit_var) in lt.track.points.iter().zip(&lt.detections).zip(&r.fit_vars) {
                if let (Some(serial), false) = (d, p.interpolated) {
                    samples.push(local_flow::RunSample {
                        pulse: p.pulse,
                        x: p.x,
                        y: p.y,
                        u: p.u * period,
                        v: p.v * period,
                        fit_var,
                        serial: *serial,
                    });
                }
            }
        }
        let flow = local_flow::WholeRunFlow::new(&samples, RUN_PRIOR_RADIUS, RUN_PRIOR_HALF_WINDOW);
        // Each point's prior, once, and the calibration on the first-pass
        // fits (every point).
        let priors: Vec<(
            Vec<Option<local_flow::VelocityPrior>>,
            local_flow::PriorCalibration,
        )> = held
            .par_iter()
            .with_max_len(1)
            .map(|(lt, r)| {
                let mut cal = local_flow::PriorCalibration::default();
                let priors = lt
                    .track
                    .points
                    .iter()
                    .zip(&r.fit_vars)
                    .map(|(p, &fit_var)| {
                        cal.note_fit_variance(fit_var);
                        let pr = flow.prior(p.pulse, p.x, p.y, &r.own);
                        if let Some(pr) = &pr {
                            cal.add(p.u * r.period_s, p.v * r.period_s, fit_var, pr);
                        }
                        pr
                    })
                    .collect();
                (priors, cal)
            })
            .collect();
        let mut calibration = local_flow::PriorCalibration::default();
        for (_, c) in &priors {
            calibration.merge(c);
        }
        let Some((scale, typical)) = calibration.scale().zip(calibration.typical_fit_variance())
        else {
            return held.into_iter().map(|(lt, _)| lt).collect();
        };
        // The output fit with this prior (`fit_track_with`'s combination;
        // the fit itself is the first pass's).
        let strength = params.velocity_prior;
        held.into_iter()
            .zip(priors)
            .map(|((mut lt, r), (priors, _))| {
                for ((p, &fit_var), pr) in lt.track.points.iter_mut().zip(&r.fit_vars).zip(priors) {
                    let apply = fit_var > typical || (params.velocity_prior_mean && fit_var > 0.0);
                    let Some(mut pr) = pr.filter(|_| apply) else {
                        continue;
                    };
                    pr.variance *= scale;
                    let (vx, vy) = (p.u * r.period_s, p.v * r.period_s);
                    let (vx, vy) = if params.velocity_prior_mean {
                        local_flow::posterior_mean(vx, vy, fit_var, &pr, strength)
                    } else {
                        local_flow::combine(vx, vy, fit_var, &pr, strength, typical)
                    };
                    p.u = vx / r.period_s;
                    p.v = vy / r.period_s;
                }
                lt
            })
            .collect()
    }
}

/// Radius (px) of [`local_flow::WholeRunFlow`]'s neighbourhood: a few
/// particle spacings at ppp 0.01 (half the one-pass prior's 48 px).
/// Paper-like seed 1, posterior mean: 16 px 0.067 px/pulse (too few
/// samples for the quadratic), 24 px 0.049, 32 px 0.052.
pub(super) const RUN_PRIOR_RADIUS: f64 = 24.0;

/// Its half window (pulses): 2 gave 0.055, 3 0.049, 5 0.047 px/pulse at
/// twice the cost of the queries.
pub(super) const RUN_PRIOR_HALF_WINDOW: i64 = 3;

/// What [`finalise_one`] made of an ended track.
#[allow(clippy::large_enum_variant)]
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
        /// Its points' check of the velocity prior's variance.
        calibration: local_flow::PriorCalibration,
        /// Below `min_length`, kept by the local-flow test.
        by_flow: bool,
        /// What the second pass of `velocity_prior_two_pass` refits.
        refit: Option<Box<Refit>>,
    },
}

/// What the second pass of `TrackParams::velocity_prior_two_pass` needs
/// of a kept track besides its points: the serials of its cleaned
/// detections (sorted; left out of its own prior), its mean pulse period
/// (s; the fit's velocity unit is px per mean period) and each point's
/// fit noise variance per axis (px²/pulse²).
pub(super) struct Refit {
    pub(super) own: Vec<u64>,
    pub(super) period_s: f64,
    pub(super) fit_vars: Vec<f64>,
}

/// Clean (outliers, unconfirmed tail), validate and fit one ended track;
/// `gate` is the outlier gate in px. Pure: the numbering and the counters
/// are [`Tracker::finalise`]'s.
pub(super) fn finalise_one(
    mut t: ActiveTrack,
    params: &TrackParams,
    flow: &local_flow::LocalFlow,
    prior: Option<&VelocityPriorUse>,
    gate: f64,
    sigma: f64,
    accel_rms: f64,
) -> Finalised {
    // Points up to this pulse went out with an earlier segment.
    let handed_out = (t.context > 0).then(|| t.dets[t.context - 1].pulse);
    if params.outlier_sigma > 0.0 {
        let window = params.fit_window.min(OUTLIER_WINDOW);
        if params.turn_model {
            remove_outliers_turning(&mut t.dets, window, gate, sigma);
        } else {
            remove_outliers(&mut t.dets, window, gate);
        }
    }
    trim_unconfirmed_tail(&mut t.dets, params.confirm_after_gap);
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
    let mut calibration = local_flow::PriorCalibration::default();
    let hold = params.velocity_prior > 0.0 && params.velocity_prior_two_pass;
    let mut fit_vars = Vec::new();
    let (mut points, mut detections, rms) = fit_track_with(
        &t.dets,
        params,
        sigma,
        accel_rms,
        prior,
        &mut calibration,
        true,
        &mut 0,
        hold.then_some(&mut fit_vars),
    );
    if rms > params.max_fit_residual {
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
        if hold {
            fit_vars.drain(..first);
        }
    }
    let refit = hold.then(|| {
        let mut own: Vec<u64> = t.dets.iter().map(|d| d.serial).collect();
        own.sort_unstable();
        Box::new(Refit {
            own,
            period_s: fit_period_s(&t.dets),
            fit_vars,
        })
    });
    Finalised::Kept {
        points,
        detections,
        fresh,
        curvature,
        calibration,
        by_flow,
        refit,
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
    let checked = n < params.ghost_check_length;
    if n < params.min_length && (!checked || n < params.min_length_flow) {
        return Verdict::Short;
    }
    if !checked {
        return Verdict::Keep { by_flow: false };
    }
    let xy: Vec<(i64, f64, f64)> = dets.iter().map(|d| (d.pulse, d.x, d.y)).collect();
    match local_flow::flow_consistent(&xy, flow, sigma, params.ghost_sigma) {
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
/// there for good.
pub(super) fn remove_outliers_turning(dets: &mut Vec<Det>, window: usize, gate: f64, sigma: f64) {
    let n = dets.len();
    if n < 8 || sigma <= 0.0 {
        return remove_outliers(dets, window, gate);
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
    let mut k = 0;
    dets.retain(|_| {
        k += 1;
        keep[k - 1]
    });
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

/// The output fit's velocity prior as one batch of the finaliser uses it:
/// the flow, the calibration's variance factor (`None`: not calibrated
/// yet, the prior is only checked) with the fits' typical noise variance,
/// and `TrackParams::velocity_prior`.
pub(super) struct VelocityPriorUse<'a> {
    pub(super) flow: &'a local_flow::FlowHistory,
    pub(super) scale: Option<(f64, f64)>,
    pub(super) strength: f64,
}

/// Sliding-window polynomial fit of a track at every pulse from its first
/// to its last detection, the window chosen per pulse by
/// [`fit::fit_adaptive`] for position noise `sigma` (px per axis). Returns
/// the points, the detection serials and the rms residual (px per axis) of
/// the detections about the fitted positions.
///
/// `grid` takes [`fit::fit_adaptive_grid`] (tabulated
/// windows) at the detections whose fit windows are gap-free with regular
/// times, `false` runs [`fit::fit_adaptive`] everywhere (the reference the
/// tests compare with); `grid_fits` counts the tabulated fits; `fit_vars`
/// receives each point's fit noise variance per axis (px²/pulse²).
#[allow(clippy::too_many_arguments)]
pub(super) fn fit_track_with(
    dets: &[Det],
    p: &TrackParams,
    sigma: f64,
    accel_rms: f64,
    prior: Option<&VelocityPriorUse>,
    calibration: &mut local_flow::PriorCalibration,
    grid: bool,
    grid_fits: &mut usize,
    mut fit_vars: Option<&mut Vec<f64>>,
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
    let rule = fit::WindowRule {
        min_window: p.fit_min_window,
        max_window: p.fit_window,
        order: p.fit_order,
        sigma,
        bias_weight: p.fit_bias_weight,
        // px/pulse² to px/τ² (τ in mean periods: the same on the grid).
        accel_rms,
    };
    // The tabulated fit needs τ = pulse offset: `run_start[i]` is the
    // first detection of the gap-free, regularly timed run holding i.
    let tables = grid.then(|| fit::GridTables::cached(&rule));
    let mut run_start = Vec::new();
    let mut xy = Vec::new();
    if grid {
        xy.extend(dets.iter().map(|d| [d.x, d.y]));
        let t_max = dets[0].t_us.abs().max(dets[n - 1].t_us.abs());
        let tol = fit::grid_tolerance(t_max, period_s * 1e6);
        let on_grid = |i: usize| (tau[i] - (dets[i].pulse - first) as f64).abs() <= tol;
        run_start.reserve(n);
        for i in 0..n {
            let joined =
                i > 0 && dets[i].pulse == dets[i - 1].pulse + 1 && on_grid(i) && on_grid(i - 1);
            run_start.push(if joined { run_start[i - 1] } else { i });
        }
    }
    // Where the path turns, the turning path's fit (`turn_fit_window`).
    let heading = (p.turn_model && p.turn_fit_window >= 7 && n >= p.turn_fit_window).then(|| {
        let pulses: Vec<i64> = dets.iter().map(|d| d.pulse).collect();
        turn::heading_prefix(&pulses, &xs, &ys, sigma)
    });
    // Samples whose pilot window is centred take running moments.
    let mut run_fit = tables
        .as_deref()
        .and_then(|t| fit::GridRunFit::new(t, &rule));
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
        let span = fit::adaptive_span(n, j, &rule);
        let fitted = match &tables {
            Some(t) if here && run_start[span.end - 1] <= span.start => {
                *grid_fits += 1;
                match &mut run_fit {
                    Some(r) if r.serves_track(n) => r.fit(&xy, j),
                    _ => fit::fit_adaptive_grid_with(t, &xy, j, &rule, false),
                }
            }
            _ => fit::fit_adaptive_with(&tau, &xs, &ys, j, at, &rule, !grid),
        };
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
            let wt = p.turn_fit_window;
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
        // The velocity prior from the local flow (px per pulse = px/τ on
        // the grid; τ is in mean periods), after the residual: the
        // validation sees the track's own fit.
        let (mut vx, mut vy) = (f.vx, f.vy);
        if let Some(v) = fit_vars.as_deref_mut() {
            v.push(sigma * sigma * f.velocity_variance);
        }
        if let Some(use_) = prior {
            let fit_var = sigma * sigma * f.velocity_variance;
            calibration.note_fit_variance(fit_var);
            let check = pulse.rem_euclid(local_flow::CALIBRATION_STRIDE) == 0;
            let apply = use_.scale.is_some_and(|(_, typical)| {
                fit_var > typical || (p.velocity_prior_mean && fit_var > 0.0)
            });
            let pr = if check || apply {
                use_.flow.prior(pulse, f.x, f.y, sigma)
            } else {
                None
            };
            if let Some(mut pr) = pr {
                if check {
                    calibration.add(vx, vy, fit_var, &pr);
                }
                if let (true, Some((scale, typical))) = (apply, use_.scale) {
                    pr.variance *= scale;
                    (vx, vy) = if p.velocity_prior_mean {
                        local_flow::posterior_mean(vx, vy, fit_var, &pr, use_.strength)
                    } else {
                        local_flow::combine(vx, vy, fit_var, &pr, use_.strength, typical)
                    };
                }
            }
        }
        points.push(TrackPoint {
            pulse,
            t_us,
            x: f.x,
            y: f.y,
            u: vx / period_s,
            v: vy / period_s,
            ax: f.ax / (period_s * period_s),
            ay: f.ay / (period_s * period_s),
            interpolated: !here,
        });
        serials.push(if here { Some(dets[j].serial) } else { None });
    }
    (points, serials, (ssr / (2 * n) as f64).sqrt())
}

/// One detection handed to [`fit_detections`]: its serial, pulse, pulse
/// time (µs) and centroid (px).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FitInput {
    pub serial: u64,
    pub pulse: i64,
    pub t_us: f64,
    pub x: f64,
    pub y: f64,
}

/// The output fit the tracker gives a finished track (the sliding,
/// adaptive-window polynomial of `fit_order` with the curvature prior
/// `accel_rms`, px/pulse², 0 = none; position noise `sigma`, px per axis;
/// tabulated where the windows are gap-free), applied to detections given
/// from outside: for analysis, e.g. fitting the ideal tracks of a
/// synthetic scene ([`synth::oracle_tracks`]) with exactly the code that
/// fits the tracker's own, so that the two velocity errors differ only in
/// the links. Only the fit: no outlier removal, length rule, step cut or
/// velocity prior (those are link decisions or use other tracks).
/// `dets` must be in increasing pulse order, at least one.
pub fn fit_detections(
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
            nb: NO_NEIGHBOUR,
        })
        .collect();
    let (points, detections, _) = fit_track_with(
        &dets,
        params,
        sigma,
        accel_rms,
        None,
        &mut local_flow::PriorCalibration::default(),
        true,
        &mut 0,
        None,
    );
    LinkedTrack {
        track: Track { id: 0, points },
        detections,
    }
}
