//! One API for the output fit's local polynomial: [`LocalPolyFit`], its
//! backends and the chain the tracker uses ([`OutputFit`]).
//!
//! Every backend computes the same thing — the adaptive-window fit of
//! [`fit_adaptive`] at one sample of a track — and differs only in which
//! samples it can take and how fast:
//!
//! | backend | samples it takes | cost |
//! |---|---|---|
//! | [`PlainFit`] ([`fit_adaptive`]) | all | sums over the pilot window, a solve per candidate |
//! | [`TabulatedFit`] ([`fit_adaptive_grid`]) | at a detection, pilot window gap-free on the pulse grid | two filters, tabulated solves |
//! | [`RunningFit`] ([`GridRunFit`]) | as tabulated, on tracks longer than the pilot | running moments, O(1) per sample |
//! | [`GapFit`] | pilot window on the pulse grid, gaps allowed, at a detection or a missing pulse | running pilot moments, one pass over the largest candidate, a 3×3 solve per candidate |
//!
//! [`PlainFit`] is the test oracle: the other backends are tested against
//! it on random tracks with gaps (to rounding, the same window chosen).

use super::*;

/// A track's detections as the local fit reads them: times τ (in mean
/// pulse periods from the first detection), positions, and where each
/// detection sits on the pulse grid.
#[derive(Debug, Clone, Default)]
pub(crate) struct TrackSamples {
    pub(crate) tau: Vec<f64>,
    pub(crate) xs: Vec<f64>,
    pub(crate) ys: Vec<f64>,
    pub(crate) xy: Vec<[f64; 2]>,
    /// Pulse offset of each detection from the first.
    pub(crate) offset: Vec<i64>,
    /// Distance within which a τ counts as on the grid ([`grid_tolerance`]).
    pub(crate) tol: f64,
    /// First detection of the gap-free, on-grid run holding each one.
    pub(crate) run_start: Vec<usize>,
    /// First detection of the on-grid run (gaps allowed) holding each one.
    pub(crate) grid_start: Vec<usize>,
}

impl TrackSamples {
    /// The samples of detections at `pulses` (increasing) with times
    /// `tau`; `tol` as [`grid_tolerance`].
    pub(crate) fn new(tau: Vec<f64>, xs: Vec<f64>, ys: Vec<f64>, pulses: &[i64], tol: f64) -> Self {
        let n = tau.len();
        let first = pulses.first().copied().unwrap_or(0);
        let offset: Vec<i64> = pulses.iter().map(|p| p - first).collect();
        let on_grid = |i: usize| (tau[i] - offset[i] as f64).abs() <= tol;
        let (mut run_start, mut grid_start) = (Vec::with_capacity(n), Vec::with_capacity(n));
        for i in 0..n {
            let both = i > 0 && on_grid(i) && on_grid(i - 1);
            let joined = both && offset[i] == offset[i - 1] + 1;
            run_start.push(if joined { run_start[i - 1] } else { i });
            grid_start.push(if both { grid_start[i - 1] } else { i });
        }
        let xy = xs.iter().zip(&ys).map(|(&x, &y)| [x, y]).collect();
        TrackSamples {
            tau,
            xs,
            ys,
            xy,
            offset,
            tol,
            run_start,
            grid_start,
        }
    }

    pub(crate) fn len(&self) -> usize {
        self.tau.len()
    }
}

/// Where one output sample is evaluated: at τ `tau`, pulse offset
/// `offset` (from the track's first detection), the window centred on
/// detection `centre` (the sample's own detection, or at a missing pulse
/// the next one).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct At {
    pub(crate) centre: usize,
    pub(crate) tau: f64,
    pub(crate) offset: i64,
}

impl At {
    /// Whether the sample is at its own detection.
    fn at_detection(&self, s: &TrackSamples) -> bool {
        s.offset[self.centre] == self.offset
    }
}

/// The output fit's local polynomial at one sample of a track: the
/// adaptive window of [`fit_adaptive`] (its rule fixed per backend).
pub(crate) trait LocalPolyFit {
    /// Whether this backend takes the sample.
    fn serves(&self, s: &TrackSamples, at: At) -> bool;
    /// The fit and its window (detections); `None` when no window can be
    /// fitted. Only for samples the backend [`serves`](Self::serves).
    /// `rms_residual` may be NaN (not computed).
    fn fit(&mut self, s: &TrackSamples, at: At) -> Option<(FitState, usize)>;
}

/// [`fit_adaptive`] itself: the plain sums, every sample; the oracle.
#[derive(Debug, Clone)]
pub(crate) struct PlainFit {
    pub(crate) rule: WindowRule,
    /// Compute `rms_residual` (a second pass with the curvature prior).
    pub(crate) residual: bool,
}

impl LocalPolyFit for PlainFit {
    fn serves(&self, _: &TrackSamples, _: At) -> bool {
        true
    }

    fn fit(&mut self, s: &TrackSamples, at: At) -> Option<(FitState, usize)> {
        fit_adaptive_with(
            &s.tau,
            &s.xs,
            &s.ys,
            at.centre,
            at.tau,
            &self.rule,
            self.residual,
        )
    }
}

/// [`fit_adaptive_grid`]: samples at a detection whose pilot window is
/// gap-free on the pulse grid.
#[derive(Debug, Clone)]
pub(crate) struct TabulatedFit<'t> {
    pub(crate) tables: &'t GridTables,
    pub(crate) rule: WindowRule,
}

impl LocalPolyFit for TabulatedFit<'_> {
    fn serves(&self, s: &TrackSamples, at: At) -> bool {
        let span = adaptive_span(s.len(), at.centre, &self.rule);
        self.tables.serves(&self.rule)
            && at.at_detection(s)
            && !span.is_empty()
            && s.run_start[span.end - 1] <= span.start
    }

    fn fit(&mut self, s: &TrackSamples, at: At) -> Option<(FitState, usize)> {
        fit_adaptive_grid_with(self.tables, &s.xy, at.centre, &self.rule, false)
    }
}

/// [`GridRunFit`]: the tabulated fit's samples on tracks longer than the
/// pilot window, consecutive samples by running moments.
#[derive(Debug, Clone)]
pub(crate) struct RunningFit<'t> {
    tabulated: TabulatedFit<'t>,
    run: GridRunFit<'t>,
}

impl<'t> RunningFit<'t> {
    /// `None` where the running path does not apply ([`GridRunFit::new`]).
    pub(crate) fn new(tables: &'t GridTables, rule: &WindowRule) -> Option<Self> {
        Some(RunningFit {
            tabulated: TabulatedFit {
                tables,
                rule: *rule,
            },
            run: GridRunFit::new(tables, rule)?,
        })
    }
}

impl LocalPolyFit for RunningFit<'_> {
    fn serves(&self, s: &TrackSamples, at: At) -> bool {
        self.run.serves_track(s.len()) && self.tabulated.serves(s, at)
    }

    fn fit(&mut self, s: &TrackSamples, at: At) -> Option<(FitState, usize)> {
        self.run.fit(&s.xy, at.centre)
    }
}

/// One candidate window of [`GapFit`]: its length, time moments `Σ sᵏ`
/// (k = 0..=5) and data moments `Σ sᵃ·d` (a = 0..=2, per axis).
#[derive(Debug, Clone, Copy)]
struct GapCandidate {
    w: usize,
    t: [f64; 6],
    d: [[f64; 2]; 3],
}

/// The pilot window's moments of [`GapFit`], kept along a track: `Σ sᵏ`
/// (k = 0..=6, exact integers) and `Σ sᵃ·(d − origin)` (a = 0..=3, per
/// axis), `s` the pulse offset from the sample.
#[derive(Debug, Clone, Copy)]
struct GapPilot {
    /// The track (its points' address and count), the sample's pulse
    /// offset, the pilot's detections `span.0..span.1`, the reference
    /// point, the steps since the moments were summed afresh.
    of: (usize, usize),
    offset: i64,
    span: (usize, usize),
    origin: [f64; 2],
    steps: usize,
    t: [f64; 8],
    d: [[f64; 2]; 4],
}

impl GapPilot {
    const NONE: GapPilot = GapPilot {
        of: (0, 0),
        offset: 0,
        span: (0, 0),
        origin: [0.0; 2],
        steps: 0,
        t: [0.0; 8],
        d: [[0.0; 2]; 4],
    };

    /// Adds (`sign` 1) or removes (−1) detection `i` at pulse offset `si`
    /// from the sample.
    #[inline(always)]
    fn add(&mut self, s: &TrackSamples, i: usize, si: i64, sign: f64) {
        let pw = powers_of(si);
        let q = [
            sign * (s.xy[i][0] - self.origin[0]),
            sign * (s.xy[i][1] - self.origin[1]),
        ];
        for (tk, pk) in self.t.iter_mut().zip(&pw) {
            *tk += sign * pk;
        }
        for (dk, pk) in self.d.iter_mut().zip(&pw) {
            dk[0] += pk * q[0];
            dk[1] += pk * q[1];
        }
    }

    /// Summed afresh over `span` about pulse offset `offset`, positions
    /// from `origin`.
    fn fresh(s: &TrackSamples, span: (usize, usize), offset: i64, origin: [f64; 2]) -> Self {
        let mut p = GapPilot {
            of: (s.xy.as_ptr() as usize, s.len()),
            offset,
            span,
            origin,
            ..GapPilot::NONE
        };
        for i in span.0..span.1 {
            p.add(s, i, s.offset[i] - offset, 1.0);
        }
        p
    }

    /// From the sample at `self.offset` to the one a pulse later, the
    /// pilot now at `span` (both ends at or after the old ones, the
    /// windows overlapping): the offsets shift by one (binomial: exact
    /// for the integer moments), the detections that left are taken out
    /// and those that entered added.
    fn step(&mut self, s: &TrackSamples, span: (usize, usize)) {
        self.offset += 1;
        let o = self.t;
        let t = &mut self.t;
        // Σ (s − 1)ᵏ = Σ_j C(k, j)(−1)^(k−j) Σ sʲ.
        t[1] = o[1] - o[0];
        t[2] = o[2] - 2.0 * o[1] + o[0];
        t[3] = o[3] - 3.0 * o[2] + 3.0 * o[1] - o[0];
        t[4] = o[4] - 4.0 * o[3] + 6.0 * o[2] - 4.0 * o[1] + o[0];
        t[5] = o[5] - 5.0 * o[4] + 10.0 * o[3] - 10.0 * o[2] + 5.0 * o[1] - o[0];
        t[6] = o[6] - 6.0 * o[5] + 15.0 * o[4] - 20.0 * o[3] + 15.0 * o[2] - 6.0 * o[1] + o[0];
        for a in 0..2 {
            let c: [f64; 4] = std::array::from_fn(|k| self.d[k][a]);
            let d = &mut self.d;
            d[1][a] = c[1] - c[0];
            d[2][a] = c[2] - 2.0 * c[1] + c[0];
            d[3][a] = c[3] - 3.0 * c[2] + 3.0 * c[1] - c[0];
        }
        for i in self.span.0..span.0 {
            self.add(s, i, s.offset[i] - self.offset, -1.0);
        }
        for i in self.span.1..span.1 {
            self.add(s, i, s.offset[i] - self.offset, 1.0);
        }
        self.span = span;
        self.steps += 1;
    }
}

/// [`fit_adaptive`] for samples whose pilot window lies on the pulse
/// grid (τ = pulse offset to rounding) but may hold gaps, at a detection
/// or at a missing pulse: the offsets `s` from the sample are exact
/// integers. The pilot window's moments are kept along the track
/// ([`GapPilot`]): from one sample to the next (a pulse later) they shift
/// by the binomial expansion and take the detections entering and
/// leaving the window, summed afresh every [`RUN_RESTART`] samples (the
/// integer moments `Σ sᵏ` stay exact, the data moments pick up rounding
/// only). The candidates' moments come from one pass over the largest
/// candidate window (they are nested, positions taken from the sample's
/// detection, for conditioning), and a candidate costs the cofactors of
/// its 3×3 system; nothing is copied per candidate and the chosen fit is
/// solved from the moments already summed. Quadratic, adaptive rules
/// only (others: [`PlainFit`]). Equal to [`fit_adaptive`] to rounding
/// (tested): the reference's τ, computed from µs times, are off the
/// integers by ~1e-11.
#[derive(Debug, Clone)]
pub(crate) struct GapFit {
    rule: WindowRule,
    cands: Vec<GapCandidate>,
    pilot: GapPilot,
}

impl GapFit {
    /// `None` for a rule this path does not take (order ≠ 2, a fixed
    /// window).
    pub(crate) fn new(rule: &WindowRule) -> Option<Self> {
        let wmax = rule.max_window.max(1);
        (rule.order == 2 && rule.min_window.clamp(1, wmax) < wmax).then(|| GapFit {
            rule: *rule,
            cands: Vec::with_capacity(MAX_CANDIDATES),
            pilot: GapPilot::NONE,
        })
    }

    /// The pilot's moments at sample `at` (centre `c`) over `span`: moved
    /// from the previous sample's where it was a pulse earlier on the same
    /// track, else summed afresh. Offsets beyond the power table's reach
    /// are summed afresh every time.
    fn pilot_moments(&mut self, s: &TrackSamples, at: At, c: usize, span: (usize, usize)) {
        let reach = POWER_RANGE - 1;
        let near =
            s.offset[span.0] - at.offset >= -reach && s.offset[span.1 - 1] - at.offset <= reach;
        let p = &mut self.pilot;
        let same = p.of == (s.xy.as_ptr() as usize, s.len());
        if near && same && p.offset == at.offset && p.span == span {
            return;
        }
        if near
            && same
            && p.offset + 1 == at.offset
            && p.steps < RUN_RESTART
            && span.0 >= p.span.0
            && span.1 >= p.span.1
            && span.0 <= p.span.1
        {
            p.step(s, span);
            return;
        }
        *p = GapPilot::fresh(s, span, at.offset, s.xy[c]);
        if !near {
            p.of = (0, 0);
        }
    }
}

impl LocalPolyFit for GapFit {
    fn serves(&self, s: &TrackSamples, at: At) -> bool {
        let span = adaptive_span(s.len(), at.centre, &self.rule);
        !span.is_empty()
            && s.grid_start[span.end - 1] <= span.start
            && (at.tau - at.offset as f64).abs() <= s.tol
    }

    fn fit(&mut self, s: &TrackSamples, at: At) -> Option<(FitState, usize)> {
        let rule = self.rule;
        let n = s.len();
        if n == 0 {
            return None;
        }
        let wmax = rule.max_window.clamp(1, n);
        let wmin = rule.min_window.clamp(1, wmax);
        let c = at.centre.min(n - 1);
        let pilot = (2 * wmax + 1).min(n);
        let p0 = s.xy[c];
        let (xy, off) = (&s.xy, &s.offset);
        // The candidates' moments, nested windows in one pass.
        let add = |i: usize, t: &mut [f64; 8], d: &mut [[f64; 2]; 4]| {
            let pw = powers_of(off[i] - at.offset);
            let q = [xy[i][0] - p0[0], xy[i][1] - p0[1]];
            for (tk, pk) in t.iter_mut().zip(&pw) {
                *tk += pk;
            }
            for (dk, pk) in d.iter_mut().zip(&pw).take(3) {
                dk[0] += pk * q[0];
                dk[1] += pk * q[1];
            }
        };
        let mut t = [0.0f64; 8];
        let mut d = [[0.0f64; 2]; 4];
        self.cands.clear();
        let (mut lo, mut hi) = (usize::MAX, 0usize);
        let mut w = wmin;
        loop {
            let start = c.saturating_sub(w / 2).min(n - w);
            if lo == usize::MAX {
                (lo, hi) = (start, start);
            }
            while lo > start {
                lo -= 1;
                add(lo, &mut t, &mut d);
            }
            while hi < start + w {
                add(hi, &mut t, &mut d);
                hi += 1;
            }
            if self.cands.len() < MAX_CANDIDATES {
                self.cands.push(GapCandidate {
                    w,
                    t: [t[0], t[1], t[2], t[3], t[4], t[5]],
                    d: [d[0], d[1], d[2]],
                });
            }
            if w >= wmax {
                break;
            }
            w = (w + 2).min(wmax);
        }
        // The pilot cubic (as Sums::pilot): its cubic and quadratic
        // coefficients and their variance factors.
        let s2 = rule.sigma * rule.sigma;
        let mut ridge = rule.ridge();
        let mut c3sq = 0.0;
        // A track no longer than the smallest window has one candidate:
        // the reference fits it as a fixed window, with the prior as it
        // is (no pilot, no widening).
        if pilot >= 5 && wmin < wmax {
            let start = c.saturating_sub(pilot / 2).min(n - pilot);
            self.pilot_moments(s, at, c, (start, start + pilot));
            let (t, d) = (&self.pilot.t, &self.pilot.d);
            if let Some((c3, c2, v33, v22)) = pilot_cubic(t, d) {
                c3sq = (c3[0] * c3[0] + c3[1] * c3[1] - 2.0 * s2 * v33).max(0.0);
                let c2sq = (c2[0] * c2[0] + c2[1] * c2[1] - WIDEN_NOISE * 2.0 * s2 * v22).max(0.0);
                ridge = widened_ridge(ridge, rule.sigma, c2sq);
            }
        }
        // The candidates' criterion; the least wins, on a tie the larger
        // window (candidates come in increasing size). Only the factors
        // the criterion reads; the winner's inverse afterwards.
        let mut best: Option<(f64, usize)> = None;
        for (k, cand) in self.cands.iter().enumerate() {
            let Some((v, b)) = gap_criterion_factors(cand, ridge) else {
                continue;
            };
            let q = rule.bias_weight * c3sq * b * b + 2.0 * s2 * v;
            if best.is_none_or(|x| q.total_cmp(&x.0).is_le()) {
                best = Some((q, k));
            }
        }
        let cand = &self.cands[best?.1];
        let (inv, p) = gap_inverse(cand, ridge)?;
        let w = cand.w;
        let (mut cx, mut cy) = ([0.0f64; 3], [0.0f64; 3]);
        for a in 0..p {
            for b in 0..p {
                cx[a] += inv[a][b] * cand.d[b][0];
                cy[a] += inv[a][b] * cand.d[b][1];
            }
        }
        Some((
            FitState {
                x: cx[0] + p0[0],
                y: cy[0] + p0[1],
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

/// The pilot cubic from its moments `t` (`Σ sᵏ`) and `d` (`Σ sᵃ·x`):
/// the cubic and quadratic coefficients (per axis) and their variance
/// factors `inv₃₃`, `inv₂₂`, by the Schur complement of the quadratic
/// block (cofactors of the 3×3, as [`invert_sym3`]) instead of the whole
/// 4×4 inverse; `None` where the system is (numerically) singular.
#[inline]
fn pilot_cubic(t: &[f64; 8], d: &[[f64; 2]; 4]) -> Option<([f64; 2], [f64; 2], f64, f64)> {
    let b = invert_sym3(&[
        [t[0], t[1], t[2], 0.0],
        [t[1], t[2], t[3], 0.0],
        [t[2], t[3], t[4], 0.0],
        [0.0; 4],
    ])?;
    // u = B⁻¹·(t₃, t₄, t₅); the Schur complement t₆ − (t₃, t₄, t₅)·u.
    let u: [f64; 3] = std::array::from_fn(|a| b[a][0] * t[3] + b[a][1] * t[4] + b[a][2] * t[5]);
    let schur = t[6] - (t[3] * u[0] + t[4] * u[1] + t[5] * u[2]);
    if !schur.is_finite() || schur <= 1e-12 * t[6].abs() {
        return None;
    }
    let r = 1.0 / schur;
    let (mut c3, mut c2) = ([0.0f64; 2], [0.0f64; 2]);
    for k in 0..2 {
        c3[k] = (d[3][k] - (u[0] * d[0][k] + u[1] * d[1][k] + u[2] * d[2][k])) * r;
        c2[k] = b[2][0] * d[0][k] + b[2][1] * d[1][k] + b[2][2] * d[2][k] - u[2] * c3[k];
    }
    Some((c3, c2, r, b[2][2] + u[2] * u[2] * r))
}

/// The powers `sᵏ` of offset `s` ([`power_row`]): from the table within
/// its range, else computed.
#[inline(always)]
fn powers_of(s: i64) -> [f64; 8] {
    match offset_powers().get((s + POWER_RANGE) as usize) {
        Some(pw) => *pw,
        None => power_row(s as f64),
    }
}

/// Offsets whose powers [`offset_powers`] tabulates: −`POWER_RANGE` ..
/// `POWER_RANGE` (a pilot window of 43 detections spans fewer pulses
/// unless it holds long gaps; beyond, the powers are computed).
const POWER_RANGE: i64 = 127;

/// `sᵏ` for k = 0..=6 (and 0 in the last place): exact integers for
/// |s| ≤ [`POWER_RANGE`] (127⁶ < 2⁵³), computed by the same products as
/// the reference's `sk *= s`.
fn power_row(s: f64) -> [f64; 8] {
    let mut row = [0.0f64; 8];
    let mut sk = 1.0;
    for v in row.iter_mut().take(7) {
        *v = sk;
        sk *= s;
    }
    row
}

/// [`power_row`] of every offset −`POWER_RANGE`..=`POWER_RANGE`, at
/// `s + POWER_RANGE`.
fn offset_powers() -> &'static [[f64; 8]] {
    static TABLE: std::sync::OnceLock<Vec<[f64; 8]>> = std::sync::OnceLock::new();
    TABLE.get_or_init(|| {
        (-POWER_RANGE..=POWER_RANGE)
            .map(|s| power_row(s as f64))
            .collect()
    })
}

/// The criterion's factors of a [`GapFit`] candidate under `ridge`: the
/// velocity variance factor `inv₁₁` and the cubic bias factor
/// `Σ_b inv₁ᵦ·t_(b+3)`, bit for bit what [`gap_inverse`]'s inverse gives
/// (the same cofactors for a quadratic; `None` where it has none).
#[inline]
fn gap_criterion_factors(c: &GapCandidate, ridge: f64) -> Option<(f64, f64)> {
    if c.w < 3 {
        let (inv, p) = gap_inverse(c, ridge)?;
        return Some(if p < 2 {
            (0.0, 0.0)
        } else {
            (
                inv[1][1],
                (0..p).map(|b| inv[1][b] * c.t[b + 3]).sum::<f64>(),
            )
        });
    }
    let t = &c.t;
    // invert_sym3's cofactors of [[t0, t1, t2], [t1, t2, t3], [t2, t3, t4 + ridge]].
    let (a, b, cc) = (t[0], t[1], t[2]);
    let (d, e, f) = (t[2], t[3], t[4] + ridge);
    let (ca, cb, c_c) = (d * f - e * e, cc * e - b * f, b * e - cc * d);
    let (cd, ce) = (a * f - cc * cc, b * cc - a * e);
    let det = a * ca + b * cb + cc * c_c;
    if !det.is_finite() || det <= 1e-12 * (a * d * f).abs() {
        return None;
    }
    let r = 1.0 / det;
    let (i10, i11, i12) = (cb * r, cd * r, ce * r);
    Some((i11, 0.0 + i10 * t[3] + i11 * t[4] + i12 * t[5]))
}

/// A [`GapFit`] candidate's inverse normal matrix (quadratic, lowered to
/// what its samples allow; `ridge` on the quadratic coefficient) and size.
fn gap_inverse(c: &GapCandidate, ridge: f64) -> Option<([[f64; 4]; 4], usize)> {
    let p = 2.min(c.w - 1) + 1;
    let mut ata = [[0.0f64; 4]; 4];
    for (a, row) in ata.iter_mut().enumerate().take(p) {
        for (b, v) in row.iter_mut().enumerate().take(p) {
            *v = c.t[a + b];
        }
    }
    if p == 3 {
        ata[2][2] += ridge;
        invert_sym3(&ata).map(|inv| (inv, 3))
    } else {
        invert(&ata, p).map(|inv| (inv, p))
    }
}

/// Which backends [`OutputFit`] may take besides [`PlainFit`].
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum FitPath {
    /// [`PlainFit`] everywhere (with `rms_residual`).
    Plain,
    /// [`RunningFit`] and [`TabulatedFit`] on gap-free windows (the
    /// tests compare the paths with and without [`GapFit`]).
    #[cfg_attr(not(feature = "testkit"), allow(dead_code))]
    Tabulated,
    /// As `Tabulated`, and [`GapFit`] on windows with gaps.
    Fast,
}

/// The output fit: per sample the fastest backend that takes it —
/// [`RunningFit`], [`TabulatedFit`], [`GapFit`] (as `path` allows) — and
/// [`PlainFit`] for the rest (irregular times, other rules).
pub(crate) struct OutputFit<'t> {
    running: Option<RunningFit<'t>>,
    tabulated: Option<TabulatedFit<'t>>,
    gaps: Option<GapFit>,
    plain: PlainFit,
    /// Samples taken by the tabulated backends (running included) and by
    /// [`GapFit`].
    pub(crate) tabulated_fits: usize,
    pub(crate) gap_fits: usize,
}

impl<'t> OutputFit<'t> {
    pub(crate) fn new(rule: &WindowRule, tables: &'t GridTables, path: FitPath) -> Self {
        let grid = path != FitPath::Plain;
        OutputFit {
            running: grid.then(|| RunningFit::new(tables, rule)).flatten(),
            tabulated: grid.then_some(TabulatedFit {
                tables,
                rule: *rule,
            }),
            gaps: (path == FitPath::Fast).then(|| GapFit::new(rule)).flatten(),
            plain: PlainFit {
                rule: *rule,
                residual: !grid,
            },
            tabulated_fits: 0,
            gap_fits: 0,
        }
    }
}

impl LocalPolyFit for OutputFit<'_> {
    fn serves(&self, _: &TrackSamples, _: At) -> bool {
        true
    }

    fn fit(&mut self, s: &TrackSamples, at: At) -> Option<(FitState, usize)> {
        if let Some(t) = &mut self.tabulated {
            if t.serves(s, at) {
                self.tabulated_fits += 1;
                return match &mut self.running {
                    Some(r) if r.serves(s, at) => r.fit(s, at),
                    _ => t.fit(s, at),
                };
            }
        }
        if let Some(g) = &mut self.gaps {
            if g.serves(s, at) {
                self.gap_fits += 1;
                return g.fit(s, at);
            }
        }
        self.plain.fit(s, at)
    }
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// A random track on the pulse grid: `n` detections, gaps of 1–4
    /// pulses with probability `gap`, a path turning at a random rate.
    /// The tracker's default window rule (21-detection windows, order 2)
    /// with a curvature prior.
    fn tracker_rule() -> WindowRule {
        WindowRule {
            min_window: 5,
            max_window: 21,
            order: 2,
            sigma: 0.3,
            bias_weight: 4.0,
            accel_rms: 0.1,
        }
    }

    fn random_track(rng: &mut rand_pcg::Pcg64, n: usize, gap: f64, sigma: f64) -> TrackSamples {
        let turn = rng.gen_range(0.0..0.4);
        let (u, v) = (rng.gen_range(-8.0..8.0), rng.gen_range(-8.0..8.0));
        let mut pulses = Vec::with_capacity(n);
        let mut p = rng.gen_range(0..1000i64);
        for _ in 0..n {
            pulses.push(p);
            p += 1;
            if rng.gen_range(0.0..1.0) < gap {
                p += rng.gen_range(1..=4);
            }
        }
        let first = pulses[0];
        let tau: Vec<f64> = pulses.iter().map(|&p| (p - first) as f64).collect();
        let xs = tau
            .iter()
            .map(|&t| 700.0 + u * t + 30.0 * (turn * t).sin() + rng.gen_range(-sigma..=sigma))
            .collect();
        let ys = tau
            .iter()
            .map(|&t| 300.0 + v * t + 30.0 * (turn * t).cos() + rng.gen_range(-sigma..=sigma))
            .collect();
        TrackSamples::new(tau, xs, ys, &pulses, grid_tolerance(1e6, 200.0))
    }

    #[ebptv_macros::unit_test]
    fn every_backend_matches_the_plain_fit_on_tracks_with_gaps() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(25);
        // (min, max window, bias weight, prior): the default rule among them.
        let rules = [
            (5, 21, 4.0, 0.0),
            (5, 21, 4.0, 0.1),
            (5, 21, 1.0, 0.5),
            (3, 10, 4.0, 0.05),
            (2, 7, 1.0, 0.0),
        ];
        // Samples compared per backend: tabulated, running, gaps (at a
        // detection, at a missing pulse), the chain.
        let mut served = [0usize; 5];
        for (case, &(min_window, max_window, bias_weight, accel_rms)) in rules.iter().enumerate() {
            for track in 0..72 {
                // Lengths at and just above the smallest windows (one
                // candidate: a fixed window) as well as long tracks.
                let n = [4, 5, 6, 7, 9, 30, 45, 80, 200][track % 9];
                let gap = [0.0, 0.02, 0.1, 0.3][(track / 9) % 4];
                let sigma = [0.05, 0.3, 1.0][(case + track) % 3];
                let rule = WindowRule {
                    min_window,
                    max_window,
                    order: 2,
                    sigma,
                    bias_weight,
                    accel_rms,
                };
                let s = random_track(&mut rng, n, gap, sigma);
                let tables = GridTables::cached(&rule);
                let mut plain = PlainFit {
                    rule,
                    residual: false,
                };
                let mut tabulated = TabulatedFit {
                    tables: &tables,
                    rule,
                };
                let mut running = RunningFit::new(&tables, &rule).expect("running path");
                let mut gaps = GapFit::new(&rule).expect("gap path");
                let mut chain = OutputFit::new(&rule, &tables, FitPath::Fast);
                let mut j = 0;
                for offset in 0..=s.offset[n - 1] {
                    while s.offset[j] < offset {
                        j += 1;
                    }
                    let at = At {
                        centre: j,
                        tau: offset as f64,
                        offset,
                    };
                    let what = format!("rule {case} track {track} offset {offset}");
                    let (r, rw) = plain.fit(&s, at).expect(&what);
                    let here = s.offset[j] == offset;
                    let backends: [(usize, &mut dyn LocalPolyFit); 4] = [
                        (0, &mut tabulated),
                        (1, &mut running),
                        (if here { 2 } else { 3 }, &mut gaps),
                        (4, &mut chain),
                    ];
                    for (k, b) in backends {
                        if b.serves(&s, at) {
                            let (f, fw) = b.fit(&s, at).expect(&what);
                            assert_eq!(fw, rw, "{what}: backend {k} window");
                            crate::track::fit::tests::assert_close_with(
                                &f,
                                &r,
                                &format!("{what}: backend {k}"),
                                false,
                            );
                            served[k] += 1;
                        }
                    }
                }
            }
        }
        println!("{served:?}");
        assert!(served.iter().all(|&k| k > 500), "{served:?}");
    }

    #[ebptv_macros::unit_test]
    fn the_gap_path_matches_the_plain_fit_across_long_gaps() {
        // Gaps longer than the power table reaches: the powers computed.
        let mut rng = rand_pcg::Pcg64::seed_from_u64(29);
        let rule = tracker_rule();
        let (mut direct, mut tabled) = (0, 0);
        for gap in [3i64, 90, 150, 400] {
            let s = random_track(&mut rng, 70, 0.1, 0.3);
            let pulses: Vec<i64> = (0..70)
                .map(|k| s.offset[k] + gap * (k >= 35) as i64)
                .collect();
            let tau = pulses.iter().map(|&p| p as f64).collect();
            let s = TrackSamples::new(tau, s.xs, s.ys, &pulses, s.tol);
            let mut gaps = GapFit::new(&rule).unwrap();
            let mut plain = PlainFit {
                rule,
                residual: false,
            };
            let mut j = 0;
            for offset in 0..=s.offset[69] {
                while s.offset[j] < offset {
                    j += 1;
                }
                let at = At {
                    centre: j,
                    tau: offset as f64,
                    offset,
                };
                assert!(gaps.serves(&s, at));
                let what = format!("gap {gap} offset {offset}");
                let (f, fw) = gaps.fit(&s, at).expect(&what);
                let (r, rw) = plain.fit(&s, at).expect(&what);
                assert_eq!(fw, rw, "{what}: window");
                crate::track::fit::tests::assert_close_with(&f, &r, &what, false);
                let span = adaptive_span(70, j, &rule);
                let reach = (s.offset[span.start] - offset)
                    .abs()
                    .max(s.offset[span.end - 1] - offset);
                if reach >= POWER_RANGE {
                    direct += 1;
                } else {
                    tabled += 1;
                }
            }
        }
        assert!(direct > 100 && tabled > 100, "{direct} {tabled}");
    }

    #[ebptv_macros::unit_test]
    fn the_running_gap_path_matches_the_plain_and_the_fresh_fit() {
        // Tracks shorter than the pilot and longer, gaps at the first and
        // last detections (track ends), gaps entering and leaving the
        // pilot's edges at every offset, runs longer than RUN_RESTART;
        // the running moments against the plain fit and against a GapFit
        // summed afresh at every sample.
        let mut rng = rand_pcg::Pcg64::seed_from_u64(31);
        let rule = tracker_rule();
        let mut stepped = 0;
        for (track, n) in [6usize, 12, 30, 43, 44, 60, 150, 300]
            .into_iter()
            .enumerate()
        {
            for gap in [0.05, 0.3] {
                let s = random_track(&mut rng, n, gap, 0.3);
                // A gap after the first detection and before the last.
                let pulses: Vec<i64> = (0..n)
                    .map(|k| s.offset[k] + 3 * (k >= 1) as i64 + 2 * (k + 1 == n) as i64)
                    .collect();
                let tau = pulses.iter().map(|&p| p as f64).collect();
                let s = TrackSamples::new(tau, s.xs, s.ys, &pulses, s.tol);
                let mut running = GapFit::new(&rule).unwrap();
                let mut plain = PlainFit {
                    rule,
                    residual: false,
                };
                let mut j = 0;
                for offset in 0..=s.offset[n - 1] {
                    while s.offset[j] < offset {
                        j += 1;
                    }
                    let at = At {
                        centre: j,
                        tau: offset as f64,
                        offset,
                    };
                    assert!(running.serves(&s, at));
                    let what = format!("track {track} gap {gap} offset {offset}");
                    let (f, fw) = running.fit(&s, at).expect(&what);
                    let (r, rw) = plain.fit(&s, at).expect(&what);
                    assert_eq!(fw, rw, "{what}: window");
                    crate::track::fit::tests::assert_close_with(&f, &r, &what, false);
                    let (g, gw) = GapFit::new(&rule).unwrap().fit(&s, at).expect(&what);
                    assert_eq!(fw, gw, "{what}: window (fresh)");
                    crate::track::fit::tests::assert_close_with(&f, &g, &what, false);
                    // The integer moments are exact, running or fresh.
                    let fresh = GapPilot::fresh(&s, running.pilot.span, offset, s.xy[j]);
                    if n >= 5 {
                        assert_eq!(running.pilot.t, fresh.t, "{what}");
                    }
                    stepped += (running.pilot.steps > 0) as usize;
                }
            }
        }
        assert!(stepped > 1000, "{stepped}");
    }

    #[ebptv_macros::unit_test]
    fn the_chain_serves_every_sample_and_the_gap_path_takes_gaps() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(27);
        let rule = tracker_rule();
        let tables = GridTables::cached(&rule);
        // One gap of two pulses in the middle of a gap-free track.
        let s = random_track(&mut rng, 200, 0.0, 0.3);
        let pulses: Vec<i64> = (0..200).map(|k| k + 2 * (k >= 100) as i64).collect();
        let tau = pulses.iter().map(|&p| p as f64).collect();
        let s = TrackSamples::new(tau, s.xs, s.ys, &pulses, s.tol);
        let mut fast = OutputFit::new(&rule, &tables, FitPath::Fast);
        let mut tab = OutputFit::new(&rule, &tables, FitPath::Tabulated);
        let mut plain = OutputFit::new(&rule, &tables, FitPath::Plain);
        for (j, &offset) in s.offset.iter().enumerate() {
            let at = At {
                centre: j,
                tau: offset as f64,
                offset,
            };
            assert!(fast.fit(&s, at).is_some());
            assert!(tab.fit(&s, at).is_some());
            assert!(plain.fit(&s, at).is_some());
        }
        // Off the grid (jittered times) only the plain backend.
        let mut jittered = s.clone();
        jittered.tau[60] += 0.01;
        let jittered = TrackSamples::new(
            jittered.tau,
            jittered.xs,
            jittered.ys,
            &jittered.offset,
            s.tol,
        );
        let at = At {
            centre: 60,
            tau: jittered.tau[60],
            offset: jittered.offset[60],
        };
        assert!(!GapFit::new(&rule).unwrap().serves(&jittered, at));
        // The pilot windows (43 detections) holding the gap.
        assert_eq!(fast.gap_fits, 42);
        assert_eq!(fast.gap_fits + fast.tabulated_fits, s.len());
        assert_eq!((plain.gap_fits, plain.tabulated_fits), (0, 0));
        assert_eq!(tab.gap_fits, 0);
        // Fixed windows and lower orders are not the gap path's.
        assert!(GapFit::new(&WindowRule {
            min_window: 21,
            ..rule
        })
        .is_none());
        assert!(GapFit::new(&WindowRule { order: 1, ..rule }).is_none());
    }
}
