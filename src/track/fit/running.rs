//! Running moments along a track ([`GridRunFit`], the output fit's path):
//! the candidate windows' sums are updated from one sample to the next
//! instead of summed afresh, restarted every `RUN_RESTART` steps.

use super::*;

/// Steps of [`GridRunFit`]'s running moments before they are summed
/// afresh: bounds the rounding they pick up (each step's re-centring
/// carries an error of the zeroth moment into the higher ones with
/// powers of the distance travelled).
pub(super) const RUN_RESTART: usize = 32;

/// Running moments `Σ sᵃ·(x − origin)` (a < `A`, per axis) of a window of
/// samples, `s` the offset from the evaluation sample: moved to the next
/// sample in O(1) — the window slides by one (one sample out, one in) or
/// stays (at a track's ends), then the offsets shift by one (binomial).
#[derive(Debug, Clone, Copy)]
pub(super) struct RunningMoments<const A: usize> {
    pub(super) start: usize,
    pub(super) m: [[f64; 2]; A],
}

impl<const A: usize> RunningMoments<A> {
    /// Summed afresh over `start..start + len` about sample `centre`.
    pub(super) fn new(
        xy: &[[f64; 2]],
        origin: [f64; 2],
        start: usize,
        len: usize,
        centre: usize,
    ) -> Self {
        let mut m = [[0.0f64; 2]; A];
        let mut s = start as f64 - centre as f64;
        for q in &xy[start..start + len] {
            let d = [q[0] - origin[0], q[1] - origin[1]];
            let mut sa = 1.0;
            for row in m.iter_mut() {
                row[0] += sa * d[0];
                row[1] += sa * d[1];
                sa *= s;
            }
            s += 1.0;
        }
        RunningMoments { start, m }
    }

    /// From sample `centre` to `centre + 1`, the window now at `start`
    /// (the old start or one more).
    #[inline]
    pub(super) fn step(
        &mut self,
        xy: &[[f64; 2]],
        origin: [f64; 2],
        len: usize,
        centre: usize,
        start: usize,
    ) {
        let m = &mut self.m;
        if start != self.start {
            let (out, inn) = (xy[self.start], xy[self.start + len]);
            let so = self.start as f64 - centre as f64;
            let si = so + len as f64;
            let (mut po, mut pi) = (1.0, 1.0);
            for row in m.iter_mut() {
                for a in 0..2 {
                    row[a] += pi * (inn[a] - origin[a]) - po * (out[a] - origin[a]);
                }
                po *= so;
                pi *= si;
            }
            self.start = start;
        }
        // s → s − 1: Σ (s − 1)ᵃ·d = Σ_b C(a, b)(−1)^(a−b) Σ sᵇ·d.
        for a in 0..2 {
            let c: [f64; 4] = std::array::from_fn(|k| if k < A { m[k][a] } else { 0.0 });
            if A > 1 {
                m[1][a] = c[1] - c[0];
            }
            if A > 2 {
                m[2][a] = c[2] - 2.0 * c[1] + c[0];
            }
            if A > 3 {
                m[3][a] = c[3] - 3.0 * c[2] + 3.0 * c[1] - c[0];
            }
        }
    }
}

/// One candidate window of [`GridRunFit`] at a centred sample: its table
/// entry and its factors and prior-updated inverse under the track's
/// population prior, computed once per track with [`GridWindow`]'s own
/// arithmetic (so bit for bit what [`fit_adaptive_grid`] computes per
/// sample).
#[derive(Debug, Clone, Copy)]
pub(super) struct CentredCandidate {
    pub(super) w: usize,
    pub(super) window: usize,
    pub(super) variance: f64,
    pub(super) bias: f64,
    pub(super) inv: [[f64; 3]; 3],
    pub(super) k: f64,
}

/// [`fit_adaptive_grid`] along a gap-free run of a track of at least
/// `2·max_window + 1` samples, called for consecutive samples: instead of
/// the pilot's two filters over its `2·max_window + 1` samples and the
/// chosen window's sums, it keeps the pilot's moments `Σ sᵃ·x` (a =
/// 0..=3, s the offset from the sample) and the largest candidate
/// window's (a = 0..=2) as running sums, moved per sample in O(1)
/// ([`RunningMoments`]), summed afresh every [`RUN_RESTART`] samples; the
/// pilot's coefficients are its tabulated inverse rows (per offset of the
/// sample in the pilot window) times the moments. The centred candidates'
/// factors under the track's prior are computed once
/// ([`CentredCandidate`]); a sample whose pilot widens the prior, and the
/// samples near a track's ends, compute their own. Positions in the
/// running sums are taken from a reference point (the sample at the last
/// restart), which changes nothing but rounding: the candidates' fits and
/// the pilot's coefficients do not depend on a constant offset (the prior
/// acts on the curvature only). The result equals [`fit_adaptive_grid`]'s
/// to rounding (~1e-13 px; tested against [`fit_adaptive`]), the same
/// window chosen unless two candidates' criteria agree to rounding;
/// `rms_residual` is not computed (NaN).
#[derive(Debug, Clone)]
pub(crate) struct GridRunFit<'t> {
    pub(super) tables: &'t GridTables,
    pub(super) rule: WindowRule,
    pub(super) ridge: f64,
    /// The candidate windows in the order of the search, centred.
    pub(super) centred: std::sync::Arc<[CentredCandidate]>,
    /// The running state: the sample it is centred on, the points it
    /// belongs to (address and length), the steps since the restart, the
    /// reference point, the pilot's and the largest window's moments.
    pub(super) at: Option<usize>,
    pub(super) of: (usize, usize),
    pub(super) steps: usize,
    pub(super) origin: [f64; 2],
    pub(super) pilot: RunningMoments<4>,
    pub(super) largest: RunningMoments<3>,
}

impl<'t> GridRunFit<'t> {
    /// `None` where the running path does not apply (a fixed window, an
    /// order below 2, tables for another rule, more candidates than the
    /// search takes): the caller takes [`fit_adaptive_grid`].
    pub(crate) fn new(tables: &'t GridTables, rule: &WindowRule) -> Option<Self> {
        let wmax = rule.max_window;
        if !tables.serves(rule)
            || rule.order < 2
            || tables.min_window >= wmax
            || wmax != tables.max_window
            || tables.pilot_rows.len() != 2 * wmax + 1
        {
            return None;
        }
        let ridge = rule.ridge();
        // The centred candidates depend on the rule only (the tables are
        // its shape's): the last rule's are kept per thread, as the
        // tracker fits track after track under the same rule.
        type Last = Option<(WindowRule, std::sync::Arc<[CentredCandidate]>)>;
        thread_local! {
            static LAST: std::cell::RefCell<Last> = const { std::cell::RefCell::new(None) };
        }
        let cached = LAST.with_borrow(|last| match last {
            Some((r, c)) if r == rule => Some(c.clone()),
            _ => None,
        });
        let centred = match cached {
            Some(c) => c,
            None => {
                let c: std::sync::Arc<[CentredCandidate]> =
                    Self::centred_candidates(tables, rule, ridge)?.into();
                LAST.set(Some((*rule, c.clone())));
                c
            }
        };
        Some(GridRunFit {
            tables,
            rule: *rule,
            ridge,
            centred,
            at: None,
            of: (0, 0),
            steps: 0,
            origin: [0.0; 2],
            pilot: RunningMoments {
                start: 0,
                m: [[0.0; 2]; 4],
            },
            largest: RunningMoments {
                start: 0,
                m: [[0.0; 2]; 3],
            },
        })
    }

    /// The centred candidate windows of `rule` under the prior `ridge`;
    /// `None` where the running path does not apply.
    fn centred_candidates(
        tables: &GridTables,
        rule: &WindowRule,
        ridge: f64,
    ) -> Option<Vec<CentredCandidate>> {
        let wmax = rule.max_window;
        let centre = wmax; // a sample with max_window samples either side
        let mut centred = Vec::new();
        let mut w = tables.min_window;
        loop {
            let window = grid_index(w, -((w / 2) as isize));
            let g = &tables.windows[window];
            if !g.ok || centred.len() + 1 >= MAX_CANDIDATES {
                return None;
            }
            debug_assert!(std::ptr::eq(g, tables.window(w, centre - w / 2, centre)));
            let (variance, bias) = g.variance_and_bias(ridge);
            let (inv, k) = g.inverse_with_prior(ridge);
            centred.push(CentredCandidate {
                w,
                window,
                variance,
                bias,
                inv,
                k,
            });
            if w >= wmax {
                break;
            }
            w = (w + 2).min(wmax);
        }
        Some(centred)
    }

    /// Whether a track of `n` samples takes the running path (its pilot
    /// window has full length).
    #[inline]
    pub(crate) fn serves_track(&self, n: usize) -> bool {
        n > 2 * self.rule.max_window
    }

    /// The fit at sample `centre` of the track's points `xy` (τ = index;
    /// [`GridRunFit::serves_track`]), whose pilot window
    /// ([`adaptive_span`]) must be gap-free with regular times (the
    /// caller's check, as for [`fit_adaptive_grid`]). Consecutive samples
    /// of the same `xy` move the running sums; anything else starts them
    /// afresh.
    pub(crate) fn fit(&mut self, xy: &[[f64; 2]], centre: usize) -> Option<(FitState, usize)> {
        let n = xy.len();
        let h = self.rule.max_window;
        let (pl, wmax) = (2 * h + 1, h);
        if n < pl || centre >= n {
            return fit_adaptive_grid_with(self.tables, xy, centre, &self.rule, false);
        }
        let pilot_start = centre.saturating_sub(h).min(n - pl);
        let largest_start = centre.saturating_sub(wmax / 2).min(n - wmax);
        let same = self.of == (xy.as_ptr() as usize, n);
        match self.at {
            Some(c) if same && c + 1 == centre && self.steps < RUN_RESTART => {
                self.pilot.step(xy, self.origin, pl, c, pilot_start);
                self.largest.step(xy, self.origin, wmax, c, largest_start);
                self.steps += 1;
            }
            Some(c) if same && c == centre => {}
            _ => {
                self.origin = xy[centre];
                self.pilot = RunningMoments::new(xy, self.origin, pilot_start, pl, centre);
                self.largest = RunningMoments::new(xy, self.origin, largest_start, wmax, centre);
                (self.steps, self.of) = (0, (xy.as_ptr() as usize, n));
            }
        }
        self.at = Some(centre);
        let rule = &self.rule;
        let tables = self.tables;
        let wmin = tables.min_window;
        let s2 = rule.sigma * rule.sigma;
        // The pilot's cubic and quadratic coefficients from its moments.
        let rows = &tables.pilot_rows[centre - pilot_start];
        let pm = &self.pilot.m;
        let (mut c3, mut c2) = ([0.0f64; 2], [0.0f64; 2]);
        for a in 0..2 {
            for (b, m) in pm.iter().enumerate() {
                c3[a] += rows.cubic_row[b] * m[a];
                c2[a] += rows.quadratic_row[b] * m[a];
            }
        }
        let c3sq = (c3[0] * c3[0] + c3[1] * c3[1] - 2.0 * s2 * rows.cubic_var).max(0.0);
        let ridge = if self.ridge > 0.0 {
            let c2sq = (c2[0] * c2[0] + c2[1] * c2[1]
                - WIDEN_NOISE * 2.0 * s2 * rows.quadratic_var)
                .max(0.0);
            widened_ridge(self.ridge, rule.sigma, c2sq)
        } else {
            0.0
        };
        let own = ridge.to_bits() != self.ridge.to_bits();
        let interior = centre >= h && centre + h < n;
        let crit =
            |variance: f64, bias: f64| rule.bias_weight * c3sq * bias * bias + 2.0 * s2 * variance;
        // The window choice of fit_adaptive_grid: (window length, table
        // entry, index into `centred` when centred and cached).
        let (w, window, cached) = if interior
            && ridge == 0.0
            && tables.centred_unimodal
            && (wmax - wmin).div_ceil(2) < MAX_CANDIDATES
        {
            // Down from the largest window to the first rise (the table
            // entries of windows between the candidates too).
            let criterion = |w: usize| {
                let (v, b) =
                    tables.windows[grid_index(w, -((w / 2) as isize))].variance_and_bias(0.0);
                crit(v, b)
            };
            let mut w = wmax;
            let mut best = (criterion(w), w);
            while w > wmin {
                let next = if (w - wmin) % 2 == 1 { w - 1 } else { w - 2 };
                let c = criterion(next);
                if c < best.0 {
                    best = (c, next);
                    w = next;
                } else {
                    break;
                }
            }
            let w = best.1;
            let window = grid_index(w, -((w / 2) as isize));
            (
                w,
                window,
                self.centred.iter().position(|c| c.window == window),
            )
        } else if interior {
            // Every candidate, the least criterion (on a tie the larger).
            let mut best = (f64::INFINITY, 0usize);
            for (i, c) in self.centred.iter().enumerate() {
                let (v, b) = if own {
                    tables.windows[c.window].variance_and_bias(ridge)
                } else {
                    (c.variance, c.bias)
                };
                let q = crit(v, b);
                if i == 0 || q.total_cmp(&best.0).is_le() {
                    best = (q, i);
                }
            }
            let c = &self.centred[best.1];
            (c.w, c.window, Some(best.1))
        } else {
            // Near an end: the candidates as centred as the ends allow.
            let mut best: Option<(f64, usize, usize)> = None;
            for c in self.centred.iter() {
                let start = centre.saturating_sub(c.w / 2).min(n - c.w);
                let window = grid_index(c.w, start as isize - centre as isize);
                let g = &tables.windows[window];
                if g.ok {
                    let (v, b) = g.variance_and_bias(ridge);
                    let q = crit(v, b);
                    if best.is_none_or(|b| q.total_cmp(&b.0).is_le()) {
                        best = Some((q, c.w, window));
                    }
                }
            }
            let (_, w, window) = best?;
            (w, window, None)
        };
        let g = &tables.windows[window];
        if !g.ok {
            return None;
        }
        let (inv, k) = match cached {
            Some(i) if !own => (self.centred[i].inv, self.centred[i].k),
            _ => g.inverse_with_prior(ridge),
        };
        if w != wmax {
            let start = centre.saturating_sub(w / 2).min(n - w);
            return grid_solve_inv(g.p, &inv, k, xy, start, w, centre, ridge, false)
                .map(|f| (f, w));
        }
        // The largest window from its running moments.
        let p = g.p;
        let fm = &self.largest.m;
        let (mut cx, mut cy) = ([0.0f64; 3], [0.0f64; 3]);
        for a in 0..p {
            for b in 0..p {
                cx[a] += inv[a][b] * fm[b][0];
                cy[a] += inv[a][b] * fm[b][1];
            }
        }
        Some((
            FitState {
                x: cx[0] + self.origin[0],
                y: cy[0] + self.origin[1],
                vx: cx[1],
                vy: cy[1],
                ax: 2.0 * cx[2],
                ay: 2.0 * cy[2],
                rms_residual: f64::NAN,
                leverage: inv[0][0],
                velocity_variance: if p > 1 { inv[1][1] } else { 0.0 },
            },
            w,
        ))
    }
}
