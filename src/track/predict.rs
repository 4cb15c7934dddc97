//! Prediction (stage 1 of the module doc): where each active track is
//! expected at the next pulse and how far around it to search — the
//! polynomial predictor with cached weights, the turning path ([`super::turn`])
//! and the young tracks' choice between line and turning path.

use super::*;

/// Innovations beyond this many σ do not update the noise estimate.
pub(super) const CLIP_K: f64 = 2.5;

/// E[r²] / (2σ²) of a 2-D Gaussian truncated at r ≤ kσ.
pub(super) fn clipped_second_moment(k: f64) -> f64 {
    let e = (-0.5 * k * k).exp();
    (1.0 - (1.0 + 0.5 * k * k) * e) / (1.0 - e)
}

/// The predictor takes the turning path where the heading of a window's
/// second half differs from its first half's by this many standard
/// deviations of its noise.
pub(super) const PREDICT_TURN_Z: f64 = 2.0;

/// Whether the angle θ = atan2(`cross`, `dot`) between two headings has
/// θ² > `t2`, as computing θ would decide, mostly without computing it: for
/// `dot` > 0, sin²θ ≤ θ² ≤ tan²θ bound it by ratios, and only a turn
/// between the bounds (within ~θ⁴ of the threshold) or an unusual input
/// takes the arctangent. The margins (1e-9 relative) are far wider than
/// the arctangent's rounding, so the answer is the arctangent's (tested).
/// The screen runs for every mature track at every pulse.
fn turned_beyond(cross: f64, dot: f64, t2: f64) -> bool {
    if dot > 0.0 && t2.is_finite() && t2 > 0.0 {
        let r = cross / dot;
        if r * r < t2 * (1.0 - 1e-9) {
            return false;
        }
        let (c2, d2) = (cross * cross, dot * dot);
        if c2 / (c2 + d2) > t2 * (1.0 + 1e-9) {
            return true;
        }
    }
    turned_beyond_exact(cross, dot, t2)
}

/// [`turned_beyond`] by the arctangent: the definition it is tested against.
fn turned_beyond_exact(cross: f64, dot: f64, t2: f64) -> bool {
    let turned = cross.atan2(dot);
    turned * turned > t2
}

/// The output fit's turning path is tried where the heading change over
/// its window is this many standard deviations of its noise ...
pub(super) const TURN_SCREEN_Z: f64 = 1.5;

/// ... and taken where it fits the window better than the quadratic by
/// this χ² (units of σ²; one coefficient more, the rate of turn).
pub(super) const TURN_GAIN_MIN: f64 = 4.0;

/// The line through `(tau, xs, ys)` evaluated at `at`, or, where the
/// line's ±`k` σ misses the constant-speed turning path's ([`turn`]), the
/// turning path's: a young track's prediction (`young_turn_sigma`). The
/// line's leverage comes along (the gate stays the line's).
pub(super) fn young_prediction(
    tau: &[f64],
    xs: &[f64],
    ys: &[f64],
    at: f64,
    sigma: f64,
    k: f64,
) -> Option<(f64, f64, f64)> {
    let line = fit::fit_eval(tau, xs, ys, 1, at)?;
    if k > 0.0 {
        if let Some(f) = turn::turn_eval(tau, xs, ys, at, false) {
            let preds = [(f.x, f.y, f.leverage), (line.x, line.y, line.leverage)];
            let c = ici_choice(&preds, sigma, k);
            return Some((preds[c].0, preds[c].1, line.leverage));
        }
    }
    Some((line.x, line.y, line.leverage))
}

/// Index of the prediction kept among `(x, y, leverage)` ordered from
/// the least biased to the least noisy: the last one whose
/// ±`k`·σ·√leverage box overlaps every earlier one's (intersection of
/// confidence intervals).
pub(super) fn ici_choice(preds: &[(f64, f64, f64)], sigma: f64, k: f64) -> usize {
    let (mut lo, mut hi) = ([f64::NEG_INFINITY; 2], [f64::INFINITY; 2]);
    let mut chosen = 0;
    for (i, &(x, y, lev)) in preds.iter().enumerate() {
        let h = k * sigma * lev.sqrt();
        for (a, v) in [x, y].into_iter().enumerate() {
            lo[a] = lo[a].max(v - h);
            hi[a] = hi[a].min(v + h);
        }
        if lo[0] > hi[0] || lo[1] > hi[1] {
            break;
        }
        chosen = i;
    }
    chosen
}

/// The predictor of a track whose last `window` detections are on
/// consecutive pulses is a fixed linear combination of their positions (the
/// least-squares polynomial is linear in the data): `x̂ = Σ c_i x_i`, with
/// the same leverage for every track. Computed once per (window, order,
/// steps ahead) from [`fit::fit_eval`] itself, they make the common case a
/// dot product instead of a fit.
#[derive(Debug, Clone)]
pub(super) struct PredictWeights {
    pub(super) window: usize,
    pub(super) order: usize,
    pub(super) ahead: i64,
    pub(super) c: Vec<f64>,
    pub(super) leverage: f64,
}

impl PredictWeights {
    pub(super) fn new(window: usize, order: usize, ahead: i64) -> Option<Self> {
        let tau: Vec<f64> = (0..window)
            .map(|i| i as f64 - (window - 1) as f64)
            .collect();
        let mut unit = vec![0.0; window];
        let zeros = vec![0.0; window];
        let mut c = Vec::with_capacity(window);
        let mut leverage = 1.0;
        for i in 0..window {
            unit[i] = 1.0;
            let f = fit::fit_eval(&tau, &unit, &zeros, order, ahead as f64)?;
            unit[i] = 0.0;
            c.push(f.x);
            leverage = f.leverage;
        }
        Some(PredictWeights {
            window,
            order,
            ahead,
            c,
            leverage,
        })
    }
}

impl Tracker {
    /// Predicted position, search radius and fit leverage of a track at
    /// pulse `pulse`: [`Tracker::predict_plain`], with cached weights
    /// when the window has no gap (the common case).
    pub(super) fn predict(&mut self, ti: usize, pulse: i64) -> (f64, f64, f64, f64) {
        let p = &self.params;
        let track = &self.active[ti];
        let n = track.dets.len();
        let w = p.gates.predict_window.min(n);
        let win = &track.dets[n - w..];
        let last = track.last();
        if p.turn_model {
            if let Some(r) = self.predict_turn(track, pulse) {
                return r;
            }
        }
        if win[0].pulse + w as i64 - 1 != last.pulse {
            return self.predict_plain(track, pulse);
        }
        let order = self.predict_order(n);
        let ahead = pulse - last.pulse;
        let Some(k) = self.weights_index(w, order, ahead) else {
            return self.predict_plain(&self.active[ti], pulse);
        };
        let c = &self.weights[k];
        let win = &self.active[ti].dets[n - w..];
        let (mut x, mut y) = (0.0, 0.0);
        for (ci, d) in c.c.iter().zip(win) {
            x += ci * d.x;
            y += ci * d.y;
        }
        let (r, lev) = self.search_radius(c.leverage, ahead);
        (x, y, r, lev)
    }

    /// The turning-path predictor ([`turn`]): mature tracks by the
    /// constant-turn-rate path with a linear speed change over the window,
    /// young ones by the line, or (`young_turn_sigma`) by the
    /// constant-speed turning path where the line's prediction is
    /// visibly off it. `None`: too few detections for the model.
    pub(super) fn predict_turn(
        &self,
        track: &ActiveTrack,
        pulse: i64,
    ) -> Option<(f64, f64, f64, f64)> {
        let p = &self.params;
        let n = track.dets.len();
        let w = p.gates.predict_window.min(n).min(64);
        let win = &track.dets[n - w..];
        let last = track.last();
        // The window as time, x and y columns (filled only where a model
        // reads them: most mature tracks stop at the screen below).
        let columns = || {
            let (mut tau, mut xs, mut ys) = ([0.0; 64], [0.0; 64], [0.0; 64]);
            for (i, d) in win.iter().enumerate() {
                tau[i] = (d.pulse - last.pulse) as f64;
                xs[i] = d.x;
                ys[i] = d.y;
            }
            (tau, xs, ys)
        };
        let at = (pulse - last.pulse) as f64;
        let order = self.predict_order(n);
        let (x, y, lev) = if order >= 2 {
            // Cheap screen first: the heading of the window's second half
            // against its first half's, in units of its noise; where it
            // does not visibly turn the quadratic (the cached fast path)
            // serves as well at a tenth of the cost.
            let h = w / 2;
            let (a, b) = (&win[..h], &win[h..]);
            let (la, lb) = (
                (a[h - 1].pulse - a[0].pulse) as f64,
                (b[b.len() - 1].pulse - b[0].pulse) as f64,
            );
            if la < 1.0 || lb < 1.0 {
                return None;
            }
            let (ux, uy) = ((a[h - 1].x - a[0].x) / la, (a[h - 1].y - a[0].y) / la);
            let (vx, vy) = (
                (b[b.len() - 1].x - b[0].x) / lb,
                (b[b.len() - 1].y - b[0].y) / lb,
            );
            let speed2 = (ux * ux + uy * uy).min(vx * vx + vy * vy);
            // Each half's heading: σ√2 per end over its span.
            let sigma = self.position_sigma();
            let var = 2.0 * sigma * sigma / speed2 * (1.0 / (la * la) + 1.0 / (lb * lb));
            let (cross, dot) = (ux * vy - uy * vx, ux * vx + uy * vy);
            if !turned_beyond(cross, dot, PREDICT_TURN_Z * PREDICT_TURN_Z * var) {
                return None;
            }
            let (tau, xs, ys) = columns();
            let f = turn::turn_eval(&tau[..w], &xs[..w], &ys[..w], at, true)?;
            (f.x, f.y, f.leverage)
        } else {
            let (tau, xs, ys) = columns();
            young_prediction(
                &tau[..w],
                &xs[..w],
                &ys[..w],
                at,
                self.position_sigma(),
                p.gates.young_turn_sigma,
            )?
        };
        let (r, lev) = self.search_radius(lev, pulse - last.pulse);
        Some((x, y, r, lev))
    }

    /// Cached predictor weights of a gap-free window.
    pub(super) fn weights_index(&mut self, w: usize, order: usize, ahead: i64) -> Option<usize> {
        // Most tracks use the same weights as the previous one: try those
        // first (the list holds a dozen or more combinations).
        let hint = self.weights_hint;
        let same = |c: &PredictWeights| c.window == w && c.order == order && c.ahead == ahead;
        let found = match self.weights.get(hint) {
            Some(c) if same(c) => Some(hint),
            _ => self.weights.iter().position(same),
        };
        let k = match found {
            Some(k) => k,
            None => {
                self.weights.push(PredictWeights::new(w, order, ahead)?);
                self.weights.len() - 1
            }
        };
        self.weights_hint = k;
        Some(k)
    }

    pub(super) fn predict_order(&self, n: usize) -> usize {
        let p = &self.params;
        if n >= p.gates.predict_order * 3 {
            p.gates.predict_order
        } else {
            p.gates.predict_order.min(1)
        }
    }

    /// Search radius for a prediction of the given leverage `ahead` pulses
    /// after the last detection.
    pub(super) fn search_radius(&self, leverage: f64, ahead: i64) -> (f64, f64) {
        let p = &self.params;
        let gap = (ahead - 1).max(0) as f64;
        let sigma = self.position_sigma() * (1.0 + leverage).sqrt();
        // (`max_disp` wins over the floor when a slow flow sets it lower.)
        let r = (p.gates.n_sigma * sigma)
            .max(p.gates.min_search_radius)
            .min(p.max_disp)
            * (1.0 + p.gates.gap_growth * gap);
        (r.min(p.max_disp * (1.0 + gap)), leverage)
    }

    /// The predictor as a plain least-squares fit over the window: the
    /// path for windows with gaps, and what the cached weights of
    /// [`Tracker::predict`] reproduce on gap-free windows.
    pub(super) fn predict_plain(&self, track: &ActiveTrack, pulse: i64) -> (f64, f64, f64, f64) {
        let p = &self.params;
        let n = track.dets.len();
        let w = p.gates.predict_window.min(n);
        let win = &track.dets[n - w..];
        let last = track.last();
        // τ in pulse periods (by pulse index), conditioning-friendly; the
        // columns on the stack for the usual windows.
        let (mut tau, mut xs, mut ys) = ([0.0; 32], [0.0; 32], [0.0; 32]);
        let heap: (Vec<f64>, Vec<f64>, Vec<f64>);
        let (tau, xs, ys): (&[f64], &[f64], &[f64]) = if w <= 32 {
            for (i, d) in win.iter().enumerate() {
                tau[i] = (d.pulse - last.pulse) as f64;
                xs[i] = d.x;
                ys[i] = d.y;
            }
            (&tau[..w], &xs[..w], &ys[..w])
        } else {
            heap = (
                win.iter().map(|d| (d.pulse - last.pulse) as f64).collect(),
                win.iter().map(|d| d.x).collect(),
                win.iter().map(|d| d.y).collect(),
            );
            (&heap.0, &heap.1, &heap.2)
        };
        let at = (pulse - last.pulse) as f64;
        let order = self.predict_order(n);
        let Some(f) = fit::fit_eval(tau, xs, ys, order, at) else {
            return (last.x, last.y, p.max_disp, 1.0);
        };
        let (r, lev) = self.search_radius(f.leverage, pulse - last.pulse);
        (f.x, f.y, r, lev)
    }
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// The bounded screen decides as the arctangent does: headings at all
    /// angles, thresholds at random and within a hair (1e-15 … 1e-6
    /// relative) of the angle itself on either side, and the odd inputs
    /// (opposite, perpendicular and equal headings, zero, infinite and NaN
    /// thresholds).
    #[ebptv_macros::unit_test]
    fn turn_screen_matches_the_arctangent() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(11);
        let mut cases = vec![
            (0.0, 1.0, 0.0),
            (0.0, -1.0, 1.0),
            (1.0, 0.0, 2.0),
            (-1.0, 0.0, 2.0),
            (1e-300, 1.0, 1e-300),
            (0.3, 1.0, f64::INFINITY),
            (0.3, 1.0, f64::NAN),
            (f64::NAN, 1.0, 0.1),
            (1e200, 1e-200, 1.0),
        ];
        for _ in 0..200_000 {
            let scale = 10f64.powi(rng.gen_range(-3..4));
            let a: f64 = rng.gen_range(-std::f64::consts::PI..std::f64::consts::PI)
                * if rng.gen_bool(0.5) { 1e-3 } else { 1.0 };
            let (cross, dot) = (scale * a.sin(), scale * a.cos());
            let theta2 = cross.atan2(dot).powi(2);
            let t2 = match rng.gen_range(0..3) {
                0 => rng.gen_range(0.0..4.0),
                _ => {
                    let rel = 10f64.powi(rng.gen_range(-15..-5)) * rng.gen_range(-1.0..1.0);
                    theta2 * (1.0 + rel)
                }
            };
            cases.push((cross, dot, t2));
            cases.push((cross, dot, theta2));
        }
        for (c, d, t2) in cases {
            assert_eq!(
                turned_beyond(c, d, t2),
                turned_beyond_exact(c, d, t2),
                "cross {c}, dot {d}, t2 {t2}"
            );
        }
    }
}
