//! The tracker's options ([`TrackParams`]): their defaults and their
//! validation.
//!
//! # A budget of knobs
//! A user sets at most a handful: [`TrackParams::max_disp`] (the largest
//! displacement between pulses), [`TrackParams::max_gap`] (missed pulses a
//! track bridges), [`TrackParams::min_length`] (the shortest track kept),
//! [`TrackParams::turn_model`] (follow turning paths) and a mean-flow
//! [`TrackParams::prior`]. Everything else sits in four named parts with
//! defaults that suit particle images of 1–2 px at 1–12 px per pulse:
//!
//! - [`GateParams`] (`gates`): how far a running track looks for its next
//!   particle (prediction, search radius, noise estimate, the delayed
//!   repair);
//! - [`InitParams`] (`init`): how new tracks start (the four-frame chains,
//!   the mean-flow prior's radius, the backward extension) and the
//!   local-flow ghost test of young and short tracks;
//! - [`StitchParams`] (`stitch`): how ended tracks are joined across
//!   longer gaps and cut where they jumped to a neighbour;
//! - [`FitParams`] (`fit`): the output fit (positions, velocities,
//!   accelerations) and the outlier and residual rules of kept tracks.
//!
//! Some defaults follow the top-level knobs: every search radius is capped
//! by `max_disp` (a gap of `g` pulses by `(g + 1)·max_disp`), the stitch
//! search reaches `(gap + 1)·max_disp` plus its tolerance, and a track of
//! `init.min_length_flow..min_length` detections is kept only when the
//! ghost test approves it. In a TOML file (`ebptv track --params`) each
//! part is a table (`[gates]`, `[init]`, `[stitch]`, `[fit]`) and any key
//! left out takes its default.

use super::*;

/// Options of the tracker. Distances in px, counts in pulses/detections.
/// The top-level fields are the ones a user is expected to set; the parts
/// hold the rest (module doc of `params`, and each part's doc).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrackParams {
    /// Largest particle displacement between consecutive pulses (px): a
    /// new track's first step is searched within it and no search radius
    /// exceeds it. Set it a little above the fastest particle's motion per
    /// pulse; larger values cost time and admit more wrong links.
    pub max_disp: f64,
    /// Pulses in a row a track may miss (no detection) and still continue;
    /// the missed pulses are filled in by the fit and marked
    /// `interpolated`. Longer gaps end the track (and may be bridged by
    /// stitching, [`StitchParams::stitch_gap`]).
    pub max_gap: u32,
    /// Fewest detections of a kept track (at least 4, the chain that
    /// starts a track). Shorter tracks that agree with the local flow may
    /// still be kept ([`InitParams::min_length_flow`]).
    pub min_length: usize,
    /// Follow turning paths (`turn`): where a track's recent detections
    /// visibly turn, it is predicted, stitched, step-tested and fitted by a
    /// path turning at a constant rate instead of a polynomial in time.
    /// Keep it on for vortices and curved flows; `false` uses polynomials
    /// throughout.
    pub turn_model: bool,
    /// Mean-flow prior for starting tracks: where the flow is fast, a new
    /// track's first step is looked for around `p0 + u(p0)·Δt` within
    /// [`InitParams::prior_radius`] instead of the whole `max_disp` disc
    /// (`ebptv track --prior U,V`; not part of a TOML file).
    #[serde(skip)]
    pub prior: Option<FlowPrior>,
    /// Regions that are not flow (walls, models, reflections): an ended
    /// track is not stitched to a new one across them (`ebptv track
    /// --mask`, `run.mask`; not part of the `[track]` table).
    #[serde(skip)]
    pub mask: Option<std::sync::Arc<crate::calib::PixelMask>>,
    /// Prediction and gating of running tracks.
    pub gates: GateParams,
    /// Starting tracks and the ghost test.
    pub init: InitParams,
    /// Stitching ended tracks and cutting them at jumps.
    pub stitch: StitchParams,
    /// The output fit and the rules a kept track must pass.
    pub fit: FitParams,
}

/// Prediction and gating of running tracks (stages 1–3 of the module doc
/// of `track`).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GateParams {
    /// Width of a running track's search disc in standard deviations of
    /// its predicted position: larger keeps more tracks through noisy
    /// detections, smaller confuses fewer neighbours.
    pub n_sigma: f64,
    /// Smallest search radius of a running track (px), whatever the
    /// predictor's uncertainty.
    pub min_search_radius: f64,
    /// Smallest position noise (px per axis) the predictor assumes; the
    /// tracker estimates the noise from its links and never goes below it.
    pub sigma_floor: f64,
    /// Largest position noise (px per axis) the tracker's estimate may
    /// reach. The estimate comes from the links' innovations, which wrong
    /// links inflate; wider gates would then admit more wrong links. The
    /// default suits centroids of 1–4 events of a 1–1.5 px image; raise it
    /// for larger particle images.
    pub sigma_ceiling: f64,
    /// Relative growth of the search radius per missed pulse.
    pub gap_growth: f64,
    /// Detections the predictor fits (the most recent ones).
    pub predict_window: usize,
    /// Polynomial order of the predictor (≤ 2).
    pub predict_order: usize,
    /// With `turn_model`: a young track (predicted by a line) takes the
    /// constant-speed turning path's prediction where the line's
    /// ± this many σ misses it (0 = the line alone).
    pub young_turn_sigma: f64,
    /// Pulses after which a pulse's links are revisited with the
    /// detections on both sides (a fixed-lag smoother: a track gets back a
    /// particle the one-sided gate missed or a neighbour took); 0 = never,
    /// at most 3.
    pub repair_lag: usize,
    /// Detections a running track holds before its older part is handed
    /// out as a finished segment (a new track id; the continuation keeps
    /// its last detections as fit context): bounds memory when particles
    /// stay in view for thousands of pulses.
    pub max_track_length: usize,
}

/// Starting tracks (stage 4 of the module doc of `track`) and the
/// local-flow ghost test of young and short tracks.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct InitParams {
    /// Smallest tolerance (px) of the third and fourth detections of a new
    /// track around the constant-velocity prediction (the tolerance grows
    /// with the predicted position's uncertainty, `gates.n_sigma` σ).
    pub init_radius: f64,
    /// Search radius (px) of a new track's first step around the mean-flow
    /// prior's prediction (with [`TrackParams::prior`]).
    pub prior_radius: f64,
    /// Also start tracks from four detections over five pulses (one of the
    /// three middle pulses missed), for particles never seen four times in
    /// a row. Such chains must agree with a known local flow (needs
    /// `ghost_check_init`).
    pub init_gap: bool,
    /// Chains that skip a pulse look for their second particle only where
    /// the local flow leads (not in the whole `max_disp` disc): faster,
    /// and such chains must match the flow anyway.
    pub gap_first_step: bool,
    /// Pulses before its first four detections that a new track is
    /// extended backwards into, through particles no track took: a
    /// particle whose first pulses could not start a track gets its early
    /// detections back. 0 = off.
    pub back_extend: usize,
    /// Tracks with fewer detections than this are compared with the local
    /// flow of the established tracks around them and dropped as ghosts
    /// (images of different particles that happen to line up) when their
    /// velocity disagrees. 0 = no ghost test; then set `ghost_check_init`
    /// and `init_gap` off too (`track_to_dir` does).
    pub ghost_check_length: usize,
    /// Fewest detections of a track kept because it agrees with the local
    /// flow (below `min_length`; needs `ghost_check_length`); a value
    /// `≥ min_length` keeps no shorter track. At least 3.
    pub min_length_flow: usize,
    /// Tolerance of the ghost test in standard deviations of the velocity
    /// difference (the flow's local variation and the noise of both
    /// velocities): larger keeps more short tracks, ghosts included.
    pub ghost_sigma: f64,
    /// Also test new four-detection chains against the local flow before
    /// they start (their particles stay free for other chains).
    pub ghost_check_init: bool,
}

/// Stitching and step cuts (stages 5–6 of the module doc of `track`).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct StitchParams {
    /// Pulses across which an ended track may be joined to a new one
    /// (a particle lost for longer than `max_gap`).
    pub stitch_gap: u32,
    /// Relative growth per gap pulse of the stitching tolerance
    /// (`gates.min_search_radius` at a gap of 0).
    pub stitch_growth: f64,
    /// Detections a track needs after a bridged gap for them to be kept
    /// when the track ends there: a track whose particle left the sheet
    /// tends to grab a stray neighbour before it ends, and such a tail is
    /// cut.
    pub confirm_after_gap: usize,
    /// Cut ended tracks where their positions jump to a close neighbour
    /// and stay with it (the track's particle was missed and an untracked
    /// neighbour in the gate took its place): the χ² gain (units of the
    /// position noise) a step must bring over a smooth path and over a
    /// single outlier. Lower cuts more (wrong links and good tracks
    /// alike); 0 = off (about 10 % less CPU).
    pub step_split: f64,
}

/// The output fit and the rules a kept track must pass (stage 6 of the
/// module doc of `track`).
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FitParams {
    /// Largest window (detections) of the output fit: longer windows give
    /// less noisy velocities on straight stretches.
    pub fit_window: usize,
    /// Smallest window of the output fit. Per sample the window between
    /// `fit_min_window` and `fit_window` of least predicted velocity error
    /// is taken (`fit::fit_adaptive`): long where the path is straight,
    /// short on sharp turns. `fit_min_window ≥ fit_window` gives a fixed
    /// window.
    pub fit_min_window: usize,
    /// Weight of the squared bias against the noise in the choice of the
    /// window (1: least error of one sample; more: shorter windows, for
    /// Eulerian means where noise averages out and bias does not).
    pub fit_bias_weight: f64,
    /// Polynomial order of the output fit (≤ 2; 2 gives accelerations).
    pub fit_order: usize,
    /// Typical particle acceleration (px/pulse², rms per axis) of the
    /// output fit's curvature prior: unset = estimated from the tracks
    /// kept so far, 0 = a plain least-squares fit.
    pub fit_accel_rms: Option<f64>,
    /// With `turn_model`: detections (≥ 7; 0 = off) of the turning-path
    /// fit used where the heading visibly turns and that path fits better
    /// than the polynomial.
    pub turn_fit_window: usize,
    /// Detections further than this many position σ from the fit of their
    /// neighbours are removed when a track ends (a stray particle a track
    /// grabbed; the pulse becomes a bridged gap). 0 = off.
    pub outlier_sigma: f64,
    /// Largest rms residual (px per axis) of a kept track's fit; rougher
    /// tracks are dropped.
    pub max_fit_residual: f64,
}

impl Default for TrackParams {
    fn default() -> Self {
        TrackParams {
            max_disp: 10.0,
            max_gap: 1,
            min_length: 5,
            turn_model: true,
            prior: None,
            mask: None,
            gates: GateParams::default(),
            init: InitParams::default(),
            stitch: StitchParams::default(),
            fit: FitParams::default(),
        }
    }
}

impl Default for GateParams {
    fn default() -> Self {
        GateParams {
            n_sigma: 3.5,
            min_search_radius: 1.5,
            sigma_floor: 0.3,
            sigma_ceiling: 0.45,
            gap_growth: 0.0,
            predict_window: 12,
            predict_order: 2,
            young_turn_sigma: 2.0,
            repair_lag: 1,
            max_track_length: 512,
        }
    }
}

impl Default for InitParams {
    fn default() -> Self {
        InitParams {
            init_radius: 1.5,
            prior_radius: 3.0,
            init_gap: true,
            gap_first_step: true,
            back_extend: 8,
            ghost_check_length: 6,
            min_length_flow: 4,
            ghost_sigma: 2.25,
            ghost_check_init: true,
        }
    }
}

impl Default for StitchParams {
    fn default() -> Self {
        StitchParams {
            stitch_gap: 3,
            stitch_growth: 0.25,
            confirm_after_gap: 2,
            step_split: 12.0,
        }
    }
}

impl Default for FitParams {
    fn default() -> Self {
        FitParams {
            fit_window: 21,
            fit_min_window: 5,
            fit_bias_weight: 4.0,
            fit_order: 2,
            fit_accel_rms: None,
            turn_fit_window: 11,
            outlier_sigma: 3.5,
            max_fit_residual: 1.5,
        }
    }
}

/// Largest `max_disp` accepted (px per pulse): wider than any event
/// sensor, so a larger value can only be a mistake.
const MAX_DISP_PX: f64 = 4096.0;
/// Largest `min_length` accepted (detections).
const MAX_MIN_LENGTH: usize = 1_000_000;

impl TrackParams {
    /// Fewest detections any kept track may have: `min_length`, or
    /// `init.min_length_flow` when the ghost test can keep shorter tracks.
    pub(crate) fn min_kept_length(&self) -> usize {
        if self.init.ghost_check_length > 0 {
            self.min_length.min(self.init.min_length_flow)
        } else {
            self.min_length
        }
    }

    /// Check the parameters; errors name the parameter (as `part.key`
    /// for the parts).
    pub(crate) fn validate(&self) -> Result<()> {
        let (g, i, s, f) = (&self.gates, &self.init, &self.stitch, &self.fit);
        let positive = [
            ("max_disp", self.max_disp),
            ("init.init_radius", i.init_radius),
            ("gates.min_search_radius", g.min_search_radius),
            ("gates.n_sigma", g.n_sigma),
            ("gates.sigma_floor", g.sigma_floor),
            ("gates.sigma_ceiling", g.sigma_ceiling),
            ("fit.max_fit_residual", f.max_fit_residual),
            ("fit.fit_bias_weight", f.fit_bias_weight),
            ("init.prior_radius", i.prior_radius),
            ("init.ghost_sigma", i.ghost_sigma),
        ];
        let non_negative = [
            ("stitch.step_split", s.step_split),
            ("gates.gap_growth", g.gap_growth),
            ("stitch.stitch_growth", s.stitch_growth),
            ("gates.young_turn_sigma", g.young_turn_sigma),
            ("fit.outlier_sigma", f.outlier_sigma),
        ];
        for (name, v) in non_negative {
            if !(v.is_finite() && v >= 0.0) {
                return Err(Error::param(
                    name,
                    format!("must be a finite number >= 0, got {v}"),
                ));
            }
        }
        for (name, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return Err(Error::param(
                    name,
                    format!("must be a positive finite number, got {v}"),
                ));
            }
        }
        if let Some(a) = f.fit_accel_rms {
            if !(a.is_finite() && a >= 0.0) {
                return Err(Error::param(
                    "fit.fit_accel_rms",
                    format!("must be a finite number >= 0, got {a}"),
                ));
            }
        }
        if g.predict_window < 2 {
            return Err(Error::param(
                "gates.predict_window",
                "needs at least 2 detections",
            ));
        }
        if g.predict_order > 2 || f.fit_order > 2 {
            return Err(Error::param(
                "gates.predict_order/fit.fit_order",
                "polynomial order must be 0, 1 or 2",
            ));
        }
        if g.max_track_length < 2 * g.predict_window.max(f.fit_window).max(INIT_FRAMES) {
            return Err(Error::param(
                "gates.max_track_length",
                format!(
                    "must be at least twice the predictor/fit window, got {}",
                    g.max_track_length
                ),
            ));
        }
        if f.fit_window < 2 {
            return Err(Error::param(
                "fit.fit_window",
                "needs at least 2 detections",
            ));
        }
        if f.fit_min_window < 2 {
            return Err(Error::param(
                "fit.fit_min_window",
                "needs at least 2 detections",
            ));
        }
        if self.min_length < INIT_FRAMES {
            return Err(Error::param(
                "min_length",
                format!("tracks start with {INIT_FRAMES} detections; min_length must be >= {INIT_FRAMES}, got {}", self.min_length),
            ));
        }
        if i.min_length_flow < 3 {
            return Err(Error::param(
                "init.min_length_flow",
                format!("must be >= 3, got {}", i.min_length_flow),
            ));
        }
        if g.repair_lag >= INIT_FRAMES {
            return Err(Error::param(
                "gates.repair_lag",
                format!("must be below {INIT_FRAMES}, got {}", g.repair_lag),
            ));
        }
        if i.back_extend > 1000 {
            return Err(Error::param("init.back_extend", "at most 1000 pulses"));
        }
        if self.max_disp > MAX_DISP_PX {
            return Err(Error::param(
                "max_disp",
                format!(
                    "{} px per pulse is wider than any sensor (at most {MAX_DISP_PX} px)",
                    self.max_disp
                ),
            ));
        }
        if self.min_length > MAX_MIN_LENGTH {
            return Err(Error::param(
                "min_length",
                format!(
                    "at most {MAX_MIN_LENGTH} detections (50 s of pulses at 20 kHz), got {}",
                    self.min_length
                ),
            ));
        }
        if self.max_gap > 1000 || s.stitch_gap > 1000 {
            return Err(Error::param(
                "max_gap/stitch.stitch_gap",
                "at most 1000 pulses",
            ));
        }
        Ok(())
    }
}
