//! Oracle tracks (`oracle_tracks`: the true links fitted by the
//! tracker's output fit) and the velocity floor they set ([`oracle_report`]).

use super::*;

/// An ideal track (module docs, "Oracle tracks"): one truth particle and
/// the detections holding its events, in pulse order (indices as in
/// [`SceneRun`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub(crate) struct OracleTrack {
    pub particle: u64,
    pub detections: Vec<usize>,
}

/// The tracks a tracker that knew every particle would output (module
/// docs, "Oracle tracks"): per truth particle the detections holding at
/// least one of its events (`det_sources`), one per pulse — where two
/// detections of one pulse hold its events, the one attributed to it
/// (`det_truth`), else the one with fewer sources, else the lower index —
/// cut where more than `max_missed` pulses in a row have none. Tracks of
/// one detection (no link) are left out. Ordered by particle, then time.
pub(crate) fn oracle_tracks(
    det_truth: &[Option<u64>],
    det_sources: &[Vec<u64>],
    det_pulse: &[i64],
    max_missed: u32,
) -> Vec<OracleTrack> {
    let mut of: std::collections::BTreeMap<u64, std::collections::BTreeMap<i64, usize>> =
        Default::default();
    let rank = |d: usize, p: u64| (det_truth[d] != Some(p), det_sources[d].len(), d);
    for (d, src) in det_sources.iter().enumerate() {
        for &p in src {
            of.entry(p)
                .or_default()
                .entry(det_pulse[d])
                .and_modify(|e| {
                    if rank(d, p) < rank(*e, p) {
                        *e = d;
                    }
                })
                .or_insert(d);
        }
    }
    let mut out = Vec::new();
    for (particle, by_pulse) in of {
        let mut cur: Vec<usize> = Vec::new();
        let mut last = i64::MIN;
        for (k, d) in by_pulse {
            if !cur.is_empty() && k - last > max_missed as i64 + 1 {
                if cur.len() >= 2 {
                    out.push(OracleTrack {
                        particle,
                        detections: std::mem::take(&mut cur),
                    });
                }
                cur.clear();
            }
            cur.push(d);
            last = k;
        }
        if cur.len() >= 2 {
            out.push(OracleTrack {
                particle,
                detections: cur,
            });
        }
    }
    out
}

/// What perfect links give on a scene (module docs, "Oracle tracks" and
/// "Velocity floor"); see [`oracle_report`].
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
#[ebptv_macros::testkit]
pub(crate) struct OracleReport {
    /// Oracle tracks (≥ 2 detections).
    pub tracks: u64,
    /// Links that bridge missed pulses.
    pub bridged_links: u64,
    /// Strict, merged-ok and identity scores of all oracle tracks, fitted
    /// by the tracker's output fit. Its velocity fields are against the
    /// majority owner of each detection and cover short tracks too: the
    /// velocity numbers of the oracle are the fields below.
    pub score: LinkScore,
    /// Oracle tracks of at least `min_length` detections (the tracker's
    /// plain length rule): the velocity fields below are over them.
    pub velocity_tracks: u64,
    /// Centroid minus true position of the track's particle, rms per
    /// axis (px), over the detections of those tracks (a merged image
    /// once per particle it holds)...
    pub sigma_all: f64,
    /// ... and over those holding events of that particle alone.
    pub sigma_clean: f64,
    /// The output fit's position noise (the tracker's final estimate on
    /// this scene) and curvature prior (`fit_accel_rms`, else estimated
    /// from those oracle tracks as the finaliser estimates it from kept
    /// tracks), px per axis and px/pulse².
    pub fit_sigma: f64,
    pub fit_accel_rms: f64,
    /// The output fit's velocity minus the particle's true velocity, rms
    /// per component (px per pulse interval), at every detection...
    pub velocity_rms_fit: f64,
    pub velocity_samples: u64,
    /// ... and at interior points (`interior_margin` from both ends).
    pub velocity_rms_fit_interior: f64,
    pub velocity_samples_interior: u64,
    /// Velocity floor with the whole track as one quadratic in time
    /// (module docs), σ = `sigma_all`, same points.
    pub floor_track: f64,
    pub floor_track_interior: f64,
    /// Velocity floor with a quadratic over the `fit_window` detections
    /// nearest the point (the output fit's longest window).
    pub floor_window: f64,
    pub floor_window_interior: f64,
    /// The window floor with the acceleration prior of the output fit
    /// (`fit_accel_rms` per axis, so c₂ ~ N(0, (fit_accel_rms/2)²)): the
    /// Bayesian bound for any estimator, biased or not, of that model.
    pub floor_window_prior: f64,
    pub floor_window_prior_interior: f64,
    /// Strict, merged-ok and identity scores of the oracle tracks of at
    /// least `min_length` detections only.
    pub score_long: LinkScore,
    /// The *exclusive* oracle: as the oracle, but each detection on one
    /// track only (a tracker's constraint), that of the particle among
    /// its sources whose true position is nearest its centroid (what a
    /// tracker with perfect predictions could choose); the other
    /// particle's track misses that pulse (bridged or cut as above).
    pub score_exclusive: LinkScore,
    /// The exclusive oracle choosing by *noisy* positions: each source's
    /// true position plus a Gaussian error of the given σ per axis (px; a
    /// tracker's prediction error), fixed seed: (σ, its scores).
    pub score_exclusive_noisy: Vec<(f64, LinkScore)>,
    /// The oracle without any merged image (events of two or more
    /// particles): their particles' tracks bridge or cut there — what a
    /// tracker that knew which images are merged could do to keep strict
    /// precision, and what it costs in recall.
    pub score_skip_merged: LinkScore,
    /// Position noise per axis (px) of the long tracks' detections by
    /// their event count (1, 2, 3, ≥ 4; the count is observable, so an
    /// estimator may weight by it), and the window floor with the
    /// acceleration prior for that known per-detection noise (weights
    /// 1/σ²(events)): the lowest of the floors.
    pub sigma_by_events: [f64; 4],
    pub floor_window_prior_weighted: f64,
    pub floor_window_prior_weighted_interior: f64,
    /// Not a noise-only floor: the least mean square velocity error of a
    /// sliding least-squares quadratic (as centred on the point as the
    /// track allows, as the output fit's windows are) when its window —
    /// any size from 3 detections to the whole track — is chosen per
    /// point knowing the truth: min over windows of bias² (the fit of the
    /// *true* positions minus the true velocity: the path is not a
    /// quadratic) + σ²·Σ wᵢ² (noise, σ = `sigma_all`), rms per component.
    /// Without and with the acceleration prior (ridge). What the output
    /// fit's window rule could gain at best.
    pub best_window: f64,
    pub best_window_interior: f64,
    pub best_window_prior: f64,
    pub best_window_prior_interior: f64,
}

/// The least mean square velocity error (per component, px²/pulse²) of a
/// least-squares quadratic (ridge `ridge` on the quadratic coefficient)
/// at detection `j` of a track with detections at `taus`, true positions
/// `xy` and true velocity `v` at `j` (px per pulse), noise σ per axis:
/// over the windows of 3 to all detections, each as centred on `j` as the
/// track allows ([`OracleReport::best_window`]).
pub(crate) fn best_window_mse(
    taus: &[f64],
    xy: &[[f64; 2]],
    j: usize,
    v: [f64; 2],
    sigma: f64,
    ridge: f64,
) -> f64 {
    let n = taus.len();
    let at = taus[j];
    let mut best = f64::INFINITY;
    for m in 3..=n {
        let lo = j.saturating_sub(m / 2).min(n - m);
        let mut mm = [[0.0f64; 3]; 3];
        for &t in &taus[lo..lo + m] {
            let b = [1.0, t - at, (t - at) * (t - at)];
            for (r, &br) in mm.iter_mut().zip(&b) {
                for (c, &bc) in r.iter_mut().zip(&b) {
                    *c += br * bc;
                }
            }
        }
        mm[2][2] += ridge;
        let Some(row) = inverse_row_1(&mm) else {
            continue;
        };
        let (mut fx, mut fy, mut w2) = (0.0, 0.0, 0.0);
        for (t, p) in taus[lo..lo + m].iter().zip(&xy[lo..lo + m]) {
            let d = t - at;
            let w = row[0] + row[1] * d + row[2] * d * d;
            fx += w * p[0];
            fy += w * p[1];
            w2 += w * w;
        }
        let mse = 0.5 * ((fx - v[0]).powi(2) + (fy - v[1]).powi(2)) + sigma * sigma * w2;
        best = best.min(mse);
    }
    best
}

/// Row 1 of the inverse of a symmetric 3×3 matrix (`None`: singular).
pub(super) fn inverse_row_1(m: &[[f64; 3]; 3]) -> Option<[f64; 3]> {
    // Cofactors of the column 1 entries (the matrix is symmetric, so the
    // inverse's row 1 is its column 1).
    let c0 = -(m[0][1] * m[2][2] - m[0][2] * m[2][1]);
    let c1 = m[0][0] * m[2][2] - m[0][2] * m[2][0];
    let c2 = -(m[0][0] * m[2][1] - m[0][1] * m[2][0]);
    let det = m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
        - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
        + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]);
    if det.is_nan() || det <= 1e-9 * m[0][0] * m[1][1] * m[2][2] {
        return None;
    }
    Some([c0 / det, c1 / det, c2 / det])
}

/// Per-axis variance factor `(XᵀWX + R)⁻¹₁₁` of the slope at `at` of a
/// weighted least-squares quadratic in τ through samples at `taus` with
/// weights `weights` (empty: all 1), `R` = `ridge` on the quadratic
/// coefficient only. Unit weights, `ridge` 0: σ² times it is the
/// variance of the unbiased velocity estimate, the Cramér–Rao bound of
/// the quadratic model with i.i.d. Gaussian noise σ; `ridge` σ²/var(c₂):
/// the posterior variance when the quadratic coefficient c₂ = a/2 has a
/// zero-mean Gaussian prior (flat priors on position and velocity), the
/// Bayesian (van Trees) bound of that model, which holds for biased
/// estimators too. Weights 1/σᵢ² and `ridge` 1/var(c₂): the same bounds
/// (the variance itself, not a factor) for known per-sample noise σᵢ.
/// `None` when not determined.
pub(crate) fn quadratic_velocity_variance_factor(
    taus: &[f64],
    weights: &[f64],
    at: f64,
    ridge: f64,
) -> Option<f64> {
    let mut m = [0.0f64; 5];
    for (i, &t) in taus.iter().enumerate() {
        let d = t - at;
        let mut p = weights.get(i).copied().unwrap_or(1.0);
        for mk in &mut m {
            *mk += p;
            p *= d;
        }
    }
    let [s0, s1, s2, s3, mut s4] = m;
    s4 += ridge;
    let det = s0 * (s2 * s4 - s3 * s3) - s1 * (s1 * s4 - s2 * s3) + s2 * (s1 * s3 - s2 * s2);
    // Relative to the scale of the products: a singular system (≤ 2
    // distinct times) leaves rounding noise only.
    if det.is_nan() || det <= 1e-9 * s0 * s2 * s4 {
        return None;
    }
    Some((s0 * s4 - s2 * s2) / det)
}

/// Build the oracle tracks of a scene run (`oracle_tracks`, gaps of up
/// to `tparams.stitch.stitch_gap` missed pulses bridged — the longest the
/// tracker bridges, by stitching — longer ones cut), fit each with the
/// tracker's output fit (`fit_detections`) and score them: links
/// (strict, merged-ok, identity; all, long, exclusive), the velocity
/// error with perfect links, and the floors (module docs).
#[ebptv_macros::testkit]
pub(crate) fn oracle_report(
    run: &SceneRun,
    tparams: &crate::track::TrackParams,
    period_us: f64,
    interior_margin: usize,
) -> OracleReport {
    let mut r = OracleReport::default();
    let truth: HashMap<(i64, u64), &TruthSample> = run
        .truth
        .iter()
        .map(|t| ((t.pulse, t.particle_id), t))
        .collect();
    let oracle = oracle_tracks(
        &run.det_truth,
        &run.det_sources,
        &run.det_pulse,
        tparams.stitch.stitch_gap,
    );
    r.tracks = oracle.len() as u64;
    r.bridged_links = oracle
        .iter()
        .flat_map(|t| t.detections.windows(2))
        .filter(|w| run.det_pulse[w[1]] != run.det_pulse[w[0]] + 1)
        .count() as u64;
    let long = |t: &OracleTrack| t.detections.len() >= tparams.min_length;
    // The fit's inputs as the tracker would have them at the end of the
    // run: its noise estimate, and the curvature prior from the kept
    // (here: long oracle) tracks.
    let mut prior = crate::track::fit::AccelPrior::default();
    for t in oracle.iter().filter(|t| long(t)) {
        let pulses: Vec<i64> = t.detections.iter().map(|&d| run.det_pulse[d]).collect();
        let xy: Vec<[f64; 2]> = t.detections.iter().map(|&d| run.det_xy[d]).collect();
        prior.add_track(&pulses, &xy);
    }
    r.fit_sigma = run.position_sigma;
    r.fit_accel_rms = tparams
        .fit
        .fit_accel_rms
        .unwrap_or_else(|| prior.accel_rms(r.fit_sigma));
    let fitted = fit_oracle(run, &oracle, tparams, r.fit_sigma, r.fit_accel_rms);
    let score = |tracks: &[LinkedTrack]| {
        score_with_sources(
            tracks,
            &run.det_truth,
            &run.det_sources,
            &run.det_pulse,
            &run.truth,
            period_us,
            interior_margin,
        )
    };
    r.score = score(&fitted);
    // The other oracles: tracks built from another choice of each
    // detection's particles, fitted like the first, scored.
    let (fit_sigma, fit_accel_rms) = (r.fit_sigma, r.fit_accel_rms);
    let score_oracle = |sources: &[Vec<u64>]| {
        let tracks = oracle_tracks(
            &run.det_truth,
            sources,
            &run.det_pulse,
            tparams.stitch.stitch_gap,
        );
        score(&fit_oracle(run, &tracks, tparams, fit_sigma, fit_accel_rms))
    };
    let long_fitted: Vec<LinkedTrack> = oracle
        .iter()
        .zip(&fitted)
        .filter(|(t, _)| long(t))
        .map(|(_, lt)| lt.clone())
        .collect();
    r.score_long = score(&long_fitted);
    // Exclusive: each detection kept only in the track of its source
    // nearest to it in truth.
    let nearest: Vec<Vec<u64>> = run
        .det_sources
        .iter()
        .enumerate()
        .map(|(d, src)| {
            let dist = |p: u64| {
                let t = truth[&(run.det_pulse[d], p)];
                (t.x - run.det_xy[d][0]).hypot(t.y - run.det_xy[d][1])
            };
            src.iter()
                .copied()
                .min_by(|&a, &b| dist(a).total_cmp(&dist(b)).then(a.cmp(&b)))
                .into_iter()
                .collect()
        })
        .collect();
    r.score_exclusive = score_oracle(&nearest);
    let single: Vec<Vec<u64>> = run
        .det_sources
        .iter()
        .map(|src| {
            if src.len() == 1 {
                src.clone()
            } else {
                Vec::new()
            }
        })
        .collect();
    r.score_skip_merged = score_oracle(&single);
    for (i, sigma_p) in [0.1, 0.2, 0.3].into_iter().enumerate() {
        let mut rng = Pcg64::seed_from_u64(0x5eed_0000 + i as u64);
        let err = Normal::new(0.0, sigma_p).expect("finite sigma");
        let chosen: Vec<Vec<u64>> = run
            .det_sources
            .iter()
            .enumerate()
            .map(|(d, src)| {
                if src.len() < 2 {
                    return src.clone();
                }
                let mut best = (f64::MAX, 0);
                for &p in src {
                    let t = truth[&(run.det_pulse[d], p)];
                    let dx = t.x + err.sample(&mut rng) - run.det_xy[d][0];
                    let dy = t.y + err.sample(&mut rng) - run.det_xy[d][1];
                    let dist = dx.hypot(dy);
                    if dist < best.0 {
                        best = (dist, p);
                    }
                }
                vec![best.1]
            })
            .collect();
        r.score_exclusive_noisy
            .push((sigma_p, score_oracle(&chosen)));
    }
    // Position noise of the detections of the long tracks against their
    // particle (first: the floors need it).
    let (mut pos_sq, mut pos_n, mut clean_sq, mut clean_n) = (0.0, 0u64, 0.0, 0u64);
    let event_class = |d: usize| (run.det_events[d].clamp(1, 4) - 1) as usize;
    let mut by_events = [(0.0f64, 0u64); 4];
    for t in oracle.iter().filter(|t| long(t)) {
        for &d in &t.detections {
            let ts = truth[&(run.det_pulse[d], t.particle)];
            let e2 = (run.det_xy[d][0] - ts.x).powi(2) + (run.det_xy[d][1] - ts.y).powi(2);
            pos_sq += e2;
            pos_n += 1;
            let c = &mut by_events[event_class(d)];
            c.0 += e2;
            c.1 += 1;
            if run.det_sources[d].len() == 1 {
                clean_sq += e2;
                clean_n += 1;
            }
        }
    }
    let per_axis = |sq: f64, n: u64| {
        if n > 0 {
            (sq / (2 * n) as f64).sqrt()
        } else {
            0.0
        }
    };
    r.sigma_all = per_axis(pos_sq, pos_n);
    r.sigma_clean = per_axis(clean_sq, clean_n);
    for (s, &(sq, n)) in r.sigma_by_events.iter_mut().zip(&by_events) {
        *s = per_axis(sq, n);
    }
    // Prior precision 1/var(c₂) of the weighted floor.
    let prior_precision = if r.fit_accel_rms > 0.0 {
        (2.0 / r.fit_accel_rms).powi(2)
    } else {
        0.0
    };
    // The fit's ridge σ²/var(c₂), c₂ = a/2, at the measured noise.
    let ridge = if r.fit_accel_rms > 0.0 {
        (2.0 * r.sigma_all / r.fit_accel_rms).powi(2)
    } else {
        0.0
    };
    let k = period_us * 1e-6;
    // Sums, all points and interior: fit error² (both components), floor
    // factors (track, window, window with the prior; per axis).
    let mut all = [0.0f64; 7];
    let mut inner = [0.0f64; 7];
    for (t, lt) in oracle.iter().zip(&fitted).filter(|(t, _)| long(t)) {
        r.velocity_tracks += 1;
        let taus: Vec<f64> = t
            .detections
            .iter()
            .map(|&d| run.det_pulse[d] as f64)
            .collect();
        let n = taus.len();
        let n_points = lt.track.points.len();
        let first = lt.track.points[0].pulse;
        let w = tparams.fit.fit_window.min(n);
        let weights: Vec<f64> = t
            .detections
            .iter()
            .map(|&d| r.sigma_by_events[event_class(d)].powi(-2))
            .collect();
        let true_xy: Vec<[f64; 2]> = t
            .detections
            .iter()
            .map(|&d| {
                let ts = truth[&(run.det_pulse[d], t.particle)];
                [ts.x, ts.y]
            })
            .collect();
        for (j, &d) in t.detections.iter().enumerate() {
            let pulse = run.det_pulse[d];
            let ts = truth[&(pulse, t.particle)];
            let i = (pulse - first) as usize;
            let pt = &lt.track.points[i];
            debug_assert_eq!(pt.pulse, pulse);
            let at = pulse as f64;
            let lo = j.saturating_sub(w / 2).min(n - w);
            let win = &taus[lo..lo + w];
            let factor = |taus: &[f64], weights: &[f64], ridge: f64| {
                quadratic_velocity_variance_factor(taus, weights, at, ridge).unwrap_or(f64::NAN)
            };
            let best = |ridge: f64| {
                best_window_mse(&taus, &true_xy, j, [ts.u * k, ts.v * k], r.sigma_all, ridge)
            };
            // The weighted floor and the best windows are variances:
            // divided by σ² here so that all scale with σ below.
            let v = [
                ((pt.u - ts.u) * k).powi(2) + ((pt.v - ts.v) * k).powi(2),
                factor(&taus, &[], 0.0),
                factor(win, &[], 0.0),
                factor(win, &[], ridge),
                factor(win, &weights[lo..lo + w], prior_precision) / r.sigma_all.powi(2),
                best(0.0) / r.sigma_all.powi(2),
                best(ridge) / r.sigma_all.powi(2),
            ];
            for (a, b) in all.iter_mut().zip(v) {
                *a += b;
            }
            r.velocity_samples += 1;
            if i >= interior_margin && n_points - 1 - i >= interior_margin {
                for (a, b) in inner.iter_mut().zip(v) {
                    *a += b;
                }
                r.velocity_samples_interior += 1;
            }
        }
    }
    let (n, n_in) = (r.velocity_samples, r.velocity_samples_interior);
    r.velocity_rms_fit = per_axis(all[0], n);
    r.velocity_rms_fit_interior = per_axis(inner[0], n_in);
    // Per component: σ times the root of the mean factor (per axis).
    let floor = |f: f64, n: u64| {
        if n > 0 {
            r.sigma_all * (f / n as f64).sqrt()
        } else {
            0.0
        }
    };
    r.floor_track = floor(all[1], n);
    r.floor_track_interior = floor(inner[1], n_in);
    r.floor_window = floor(all[2], n);
    r.floor_window_interior = floor(inner[2], n_in);
    r.floor_window_prior = floor(all[3], n);
    r.floor_window_prior_interior = floor(inner[3], n_in);
    r.floor_window_prior_weighted = floor(all[4], n);
    r.floor_window_prior_weighted_interior = floor(inner[4], n_in);
    r.best_window = floor(all[5], n);
    r.best_window_interior = floor(inner[5], n_in);
    r.best_window_prior = floor(all[6], n);
    r.best_window_prior_interior = floor(inner[6], n_in);
    r
}

/// Fit oracle tracks with the tracker's output fit (in parallel; the
/// result is in input order and independent of the thread count).
pub(super) fn fit_oracle(
    run: &SceneRun,
    oracle: &[OracleTrack],
    tparams: &crate::track::TrackParams,
    sigma: f64,
    accel_rms: f64,
) -> Vec<LinkedTrack> {
    use rayon::prelude::*;
    oracle
        .par_iter()
        .map(|t| {
            let input: Vec<crate::track::FitInput> = t
                .detections
                .iter()
                .map(|&d| crate::track::FitInput {
                    serial: d as u64,
                    pulse: run.det_pulse[d],
                    t_us: run.det_t_us[d],
                    x: run.det_xy[d][0],
                    y: run.det_xy[d][1],
                })
                .collect();
            crate::track::fit_detections(&input, tparams, sigma, accel_rms)
        })
        .collect()
}
