//! The tracker's options ([`TrackParams`]): their defaults and their
//! validation.

use super::*;

/// Options of the tracker. Distances in px, counts in pulses/detections.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct TrackParams {
    /// Largest displacement between consecutive pulses (px); bounds the
    /// first step of a new track and every search radius.
    pub max_disp: f64,
    /// Smallest tolerance (px) of the third and fourth frames of a new track
    /// around the constant-velocity prediction (the gate is `n_sigma` times
    /// the prediction's uncertainty, √6 σ per axis).
    pub init_radius: f64,
    /// Smallest search radius of a running track (px).
    pub min_search_radius: f64,
    /// Search radius in units of the predictor's position uncertainty.
    pub n_sigma: f64,
    /// Position noise floor assumed by the predictor (px per axis).
    pub sigma_floor: f64,
    /// Ceiling of the estimated position noise (px per axis). The estimate
    /// comes from the innovations of accepted links; in dense, noisy scenes
    /// wrong links inflate it, wider gates admit more wrong links, and the
    /// tracker runs away (without a ceiling: precision 0.29 at ppp 0.02,
    /// 12 px/pulse, 5 % noise). A centroid of 1–4 events of a 1–1.5 px image errs by
    /// at most ~0.45 px per axis (a single event: √(σ_image² + 1/12)
    /// with σ_image ≈ 0.35 px), which is the default: what the innovations
    /// show beyond it is predictor bias at high speeds and wrong links, and
    /// gates widened for it admit more wrong links than they recover
    /// (ppp 0.02, 12 px/pulse, 5 % noise: ceiling 1 → 0.45 px,
    /// estimate 0.54 → 0.45, precision 0.754 → 0.800, recall 0.651 →
    /// 0.678; the paper-like scene, σ ≈ 0.415, is unchanged). Raise it for
    /// larger particle images.
    #[serde(default = "default_sigma_ceiling")]
    pub sigma_ceiling: f64,
    /// Pulses a track may miss and still continue.
    pub max_gap: u32,
    /// Relative growth of the search radius per missed pulse.
    pub gap_growth: f64,
    /// Detections the predictor fits.
    pub predict_window: usize,
    /// Polynomial order of the predictor (≤ 2).
    pub predict_order: usize,
    /// Largest window (detections) of the output fit.
    pub fit_window: usize,
    /// Smallest window of the output fit: per sample the window between
    /// `fit_min_window` and `fit_window` of least predicted velocity error
    /// (noise from the position noise, bias from the path's cubic term) is
    /// taken ([`fit::fit_adaptive`]): long on straight stretches (less
    /// noise), short on sharp turns (less curvature bias).
    /// `fit_min_window ≥ fit_window` gives the fixed window `fit_window`.
    #[serde(default = "default_fit_min_window")]
    pub fit_min_window: usize,
    /// Weight of the squared bias against the noise variance in the choice
    /// of the window (1: least error of one sample; more: shorter windows,
    /// for Eulerian means where noise averages out and bias does not).
    #[serde(default = "default_fit_bias_weight")]
    pub fit_bias_weight: f64,
    /// Polynomial order of the output fit (≤ 2).
    pub fit_order: usize,
    /// Prior rms acceleration per axis (px/pulse²) of the output fit's
    /// quadratics ([`fit::WindowRule::accel_rms`]): `None` (default)
    /// estimates it from the tracks kept so far ([`fit::AccelPrior`]),
    /// `Some(0.0)` fits without a prior.
    #[serde(default)]
    pub fit_accel_rms: Option<f64>,
    /// Fewest detections of a kept track (see also `min_length_flow`).
    pub min_length: usize,
    /// Tracks with fewer detections than this are tested against the
    /// local flow of the established tracks around them
    /// ([`local_flow::flow_consistent`]) and dropped as ghosts (images of
    /// different particles that line up) when their velocity disagrees;
    /// 0 = no test. A track of `min_length_flow..min_length` detections is
    /// kept only when it passes (an unknown flow counts as a fail).
    #[serde(default = "default_ghost_check_length")]
    pub ghost_check_length: usize,
    /// Fewest detections of a track kept because it agrees with the local
    /// flow (`ghost_check_length`); `≥ min_length` keeps no shorter track.
    #[serde(default = "default_min_length_flow")]
    pub min_length_flow: usize,
    /// Tolerance of the ghost test in standard deviations of the velocity
    /// difference (the flow's local variation, the track's and the local
    /// mean's noise).
    #[serde(default = "default_ghost_sigma")]
    pub ghost_sigma: f64,
    /// Also drop new four-frame chains that fail the ghost test before
    /// they start (their particles stay free for other chains).
    #[serde(default = "default_ghost_check_init")]
    pub ghost_check_init: bool,
    /// Largest rms residual (px per axis) of a kept track's fit.
    pub max_fit_residual: f64,
    /// Pulses across which an ended track may be stitched to a new one.
    pub stitch_gap: u32,
    /// Relative growth per gap pulse of the stitching tolerance
    /// (`min_search_radius` at a gap of 0).
    pub stitch_growth: f64,
    /// Detections a track needs after a bridged gap for the detections after
    /// the gap to be kept when the track ends there: a track whose particle
    /// left the sheet tends to grab a stray neighbour or noise before it
    /// ends, and such a tail is cut.
    pub confirm_after_gap: usize,
    /// Detections further than this many position sigmas from the fit of
    /// their neighbours are removed when a track is finalised (0 = off).
    pub outlier_sigma: f64,
    /// Detections a running track holds before its older part is handed
    /// out as a finished segment (a new track id; the continuation keeps
    /// the last few detections as fit context). Bounds memory when
    /// particles stay in view for thousands of pulses.
    #[serde(default = "default_max_track_length")]
    pub max_track_length: usize,
    /// Pulses before its first four frames that a new track is extended
    /// backwards into, through the particles no track took (with the
    /// predictor's gate and up to `max_gap` missed pulses): a particle
    /// whose first pulses could not start a track (a missed detection, a
    /// merged image, a chain conflict) gets its early detections back.
    /// 0 = off.
    #[serde(default = "default_back_extend")]
    pub back_extend: usize,
    /// Pulses after which the links of a pulse are revisited (0 = never):
    /// once `repair_lag` later detections are in, every track that missed
    /// the pulse is fitted on both sides of it, and the particles of that
    /// pulse in its gate are assigned again among it and the tracks that
    /// hold them, with two-sided positions (a fixed-lag smoother): a track
    /// gets back a particle the forward step could not place (outside the
    /// one-sided gate, or taken by a neighbour whose two-sided fit says
    /// it is not its own).
    #[serde(default = "default_repair_lag")]
    pub repair_lag: usize,
    /// Also start tracks from four detections over five pulses that miss
    /// one of the three middle pulses (after the gap-free chains), for
    /// particles that never show four images in a row. On by default;
    /// such a chain must also agree with a known local flow
    /// (`ghost_check_init`): without that check it gained 0.0014
    /// recall for 0.0012 precision on the paper-like scene and started
    /// many wrong tracks in dense, noisy scenes (precision 0.75 → 0.67);
    /// with the ghost test the paper-like recall goes 0.9491 → 0.9529 at
    /// equal precision.
    #[serde(default = "default_init_gap")]
    pub init_gap: bool,
    /// Split merged images between the tracks that predict into them
    /// (needs the pixels of each image: [`Tracker::push_linked_with_pixels`];
    /// without them, e.g. when linking a `particles.csv`, nothing is split).
    /// When two live tracks both have a multi-pixel image in their gates,
    /// its pixels are partitioned by the nearer prediction
    /// ([`split_by_predictions`]) and the two parts (event-weighted
    /// centroids) replace the image when that lowers the two tracks'
    /// assignment cost by more than `split_penalty`: two particles closer
    /// than the join radius (~1–2 px) made one image, and each track gets
    /// its own particle's events instead of one of them taking the
    /// centroid between them and the other missing.
    ///
    /// Off by default: on the paper-like synthetic scene (384²)
    /// it moves precision 0.9628 → 0.9635 and recall 0.9395 → 0.9404 at
    /// equal velocity error, but in the dense, fast, noisy scene (ppp 0.02,
    /// 12 px/pulse, 5 % noise) it costs precision 0.8004 → 0.7977 and
    /// recall 0.6784 → 0.6749: with 1–2 events per particle a one-pixel
    /// part sits ~0.45 px from its particle, about what separates a
    /// merged pair from one particle's two-pixel image whose neighbour
    /// did not fire, so about as many wrong splits as right ones are made
    /// unless `split_penalty` keeps only the clearest. On the full
    /// simulator's demo scene it helps: `ebptv demo`'s recording with
    /// `track --split-merged`, link precision 0.9941 → 0.9950, recall
    /// 0.9607 → 0.9682, velocity rms 0.0236 → 0.0219 px/pulse.
    #[serde(default = "default_split_merged")]
    pub split_merged: bool,
    /// Cost (in units of a missed detection) a split must save, against
    /// the assignment without it, to be made: the prior odds against two
    /// particles in one image. The parts' separation earns a bonus (its
    /// squared length times `na·nb/(na + nb)` events, over (n_σ σ)²: one
    /// particle's image is seldom that wide). 1.3 on the paper-like scene:
    /// 0.3 / 0.6 / 1.0 split 1161 / 837 / 442 images there (at 0.6 as
    /// many one particle's images, 362, as right splits, 362; precision
    /// 0.9586 / 0.9618 / 0.9639, velocity rms 0.200 / 0.177 / 0.169
    /// px/pulse against 0.149 unsplit); 1.3 splits 176, 130 of them (74 %)
    /// between the two tracks' own particles, 27 one particle's image.
    #[serde(default = "default_split_penalty")]
    pub split_penalty: f64,
    /// Cut ended tracks where their detections jump to a close neighbour
    /// and stay with it ([`step::step_cuts`]): the χ² (2 degrees of
    /// freedom, units of the position noise σ²) by which a step in the
    /// positions must improve a quadratic's fit of the detections around
    /// it, and beat a single outlier by half; 0 = off. A track's particle
    /// missed (it left the sheet, did not fire, merged with another) while
    /// an untracked neighbour 1–4 px away lies in the gate is taken over
    /// by the neighbour: smooth, but shifted by their distance, which the
    /// detections on both sides of the jump show. Paper-like
    /// synthetic scene (384², seed 1): 0 / 20 / 16 / 12 / 10 / 8 give
    /// precision 0.9632 / 0.9641 / 0.9644 / 0.9652 / 0.9656 / 0.9662,
    /// recall 0.9529 / 0.9533 / 0.9533 / 0.9523 / 0.9506 / 0.9470,
    /// interior velocity rms 0.064 / 0.059 / 0.058 / 0.055 / 0.054 / 0.052
    /// px/pulse; 12 cuts 246 tracks there.
    #[serde(default = "default_step_split")]
    pub step_split: f64,
    /// The step test's threshold (same units as `step_split`, which must
    /// be on) where the step matches a neighbour: the detection before
    /// the step had another detection beside it, offset by about the
    /// step, or the detection after it had one offset by about minus the
    /// step ([`step::step_cuts_hinted`]). A track that jumped to a close
    /// neighbour had that neighbour beside it one pulse earlier (the two
    /// move alike), and its own particle, when detected, beside it after;
    /// a step of noise or curvature seldom lines up with a neighbour, so
    /// the test can go lower there without cutting many good tracks.
    /// 0 = the plain test everywhere (default).
    ///
    /// Threshold 8 (tuned on seed 1 of the paper-like 384²
    /// synthetic scene): precision 0.9652 → 0.9658 and recall 0.9523 →
    /// 0.9516 there; held-out seeds 2 / 3: 0.9618 → 0.9626 / 0.9635 →
    /// 0.9642, recall 0.9521 → 0.9514 / 0.9519 → 0.9507; harsh scene
    /// (ppp 0.02, 12 px/pulse, 5 % noise) +0.0012…+0.0014 precision,
    /// −0.0018…−0.0024 recall. About one good link is lost per wrong
    /// link removed (a cut piece shorter than `min_length` goes), and on
    /// the Lamb–Oseen vortex of `tests/grid_sim.rs` the core's bins keep
    /// more than 3× the noise floor after the fit (124 k against a limit
    /// of 121 k (px/s)²), so it is off by default.
    #[serde(default = "default_step_split_hinted")]
    pub step_split_hinted: f64,
    /// Chains that skip a pulse (`init_gap`) look for their second
    /// particle only where the local flow from the first one leads (the
    /// flow's tolerance of the ghost test plus three σ of the first
    /// step's noise), instead of in the whole `max_disp` disc, and not at
    /// all where the flow is unknown: such chains must match a known flow
    /// anyway (`ghost_check_init`), and most of the candidates in the disc
    /// would be enumerated into whole chains only to fail that test.
    #[serde(default = "default_gap_first_step")]
    pub gap_first_step: bool,
    /// Strength of the output fit's velocity prior from the local flow
    /// of the established tracks; 0 = off (default), 1 = the prior's
    /// variance as estimated and calibrated from the data (larger values
    /// trust it more). At each point the local linear flow around it at
    /// its pulse ([`local_flow::FlowHistory::prior`]: the plane of the
    /// recent links of long tracks in the 48 px around it, its variance
    /// the links' spread about the plane less their noise — turbulence,
    /// unsteadiness, the field's curvature — plus the plane's own
    /// uncertainty, scaled by how far the prior was actually off at
    /// well-fitted points, [`local_flow::PriorCalibration`]) is combined
    /// with the fitted velocity (noise σ²·
    /// [`fit::FitState::velocity_variance`]): fits noisier than the
    /// typical one — one-sided fits at track ends, few-point fits of
    /// short tracks — are drawn towards the flow so that their noise
    /// falls to the typical level ([`local_flow::combine`]), the rest is
    /// unchanged. Off by default: in a steady curved flow the plane's
    /// error is the same at every visit of a place, and a Lamb–Oseen
    /// vortex bin's mean moved by 3–4 % of v_max (limit 1 %,
    /// `tests/grid_sim.rs`). Needs the local flow (`ghost_check_length`
    /// > 0). Measured effects in `docs/readme/ptv.md`.
    #[serde(default)]
    pub velocity_prior: f64,
    /// With `velocity_prior`: take the posterior mean of fit and prior
    /// ([`local_flow::posterior_mean`], least error per point: 0.130 →
    /// 0.074 px/pulse on the paper-like scene) instead of the
    /// variance-matching combination ([`local_flow::combine`], 0.130 →
    /// 0.100). The posterior mean shrinks every sample's fluctuation
    /// about the local flow: Reynolds stresses of a turbulent scene came
    /// out 3.5–5.5 % low. For Lagrangian per-particle velocities of a
    /// smooth flow, not for statistics.
    #[serde(default)]
    pub velocity_prior_mean: bool,
    /// With `velocity_prior`: take the prior from a first pass over the
    /// whole run instead of the links made so far. Every
    /// kept track is fitted without a prior first; the fitted velocities
    /// of all tracks then give the local flow
    /// ([`local_flow::WholeRunFlow`]: a quadratic in space, linear in
    /// time, from the samples of *other* tracks within 24 px and ±3
    /// pulses), calibrated on all points, and each point's first-pass fit
    /// is combined with it (as the one-pass prior: `velocity_prior_mean`
    /// chooses the form). Track starts in the recording's first pulses
    /// get a prior too, and the quadratic follows a curved flow's mean
    /// where the one-pass plane did not (vortex bins within 0.9 % of
    /// v_max). Paper-like scene with the posterior mean 0.130 → 0.049
    /// px/pulse (seed 1), demo 0.0233 → 0.0124; ~10× the CPU of the
    /// tracker, and neighbours share their prior, so the grid stage's
    /// pair noise estimate comes out low (BENCHMARKS.md, "Tracking
    /// accuracy"). Tracks are held until the end of the run
    /// ([`Tracker::finish`], [`Finaliser::refit_held`]; the streaming
    /// pipeline hands them on before its end): memory grows with the run.
    #[serde(default)]
    pub velocity_prior_two_pass: bool,
    /// Follow turning paths ([`turn`]: a path turning at a constant rate
    /// with a linear speed change, the rate fitted to the window, the
    /// quadratic's count of coefficients): the predictor of tracks whose
    /// window visibly turns, the stitch test, the backward extension, the
    /// step test's rival model, and the outlier pass and output fit where
    /// the heading turns (`turn_fit_window`). `false`: polynomials in time
    /// throughout. On the
    /// independent `ptvdev_vortex` recording velocity rms 0.081 → 0.039
    /// px/pulse, within 1.5 core radii 0.38 → 0.13 (docs/readme/ptv.md).
    #[serde(default = "default_turn_model")]
    pub turn_model: bool,
    /// With `turn_model`: young tracks (predicted by a line) take the
    /// constant-speed turning path's prediction where the line's ± this
    /// many σ misses it (0 = the line alone).
    #[serde(default = "default_young_turn_sigma")]
    pub young_turn_sigma: f64,
    /// With `turn_model`: detections (≥ 7; 0 = off) of the output fit's
    /// turning-path window, taken where the heading visibly turns and the
    /// turning path fits the window better than the quadratic.
    #[serde(default = "default_turn_fit_window")]
    pub turn_fit_window: usize,
    /// Search radius (px) around the prior's prediction for the first step.
    pub prior_radius: f64,
    /// Mean-flow prior for initialisation.
    #[serde(skip)]
    pub prior: Option<FlowPrior>,
}

impl Default for TrackParams {
    fn default() -> Self {
        TrackParams {
            max_disp: 10.0,
            init_radius: 1.5,
            min_search_radius: 1.5,
            n_sigma: 3.5,
            sigma_floor: 0.3,
            sigma_ceiling: default_sigma_ceiling(),
            max_gap: 1,
            gap_growth: 0.0,
            predict_window: 12,
            predict_order: 2,
            fit_window: 21,
            fit_min_window: default_fit_min_window(),
            fit_bias_weight: default_fit_bias_weight(),
            fit_order: 2,
            fit_accel_rms: None,
            min_length: 5,
            ghost_check_length: default_ghost_check_length(),
            min_length_flow: default_min_length_flow(),
            ghost_sigma: default_ghost_sigma(),
            ghost_check_init: default_ghost_check_init(),
            max_fit_residual: 1.5,
            stitch_gap: 3,
            stitch_growth: 0.25,
            confirm_after_gap: 2,
            outlier_sigma: 3.5,
            max_track_length: default_max_track_length(),
            back_extend: default_back_extend(),
            repair_lag: default_repair_lag(),
            init_gap: default_init_gap(),
            split_merged: default_split_merged(),
            split_penalty: default_split_penalty(),
            step_split: default_step_split(),
            step_split_hinted: default_step_split_hinted(),
            gap_first_step: default_gap_first_step(),
            velocity_prior: 0.0,
            velocity_prior_mean: false,
            velocity_prior_two_pass: false,
            turn_model: default_turn_model(),
            young_turn_sigma: default_young_turn_sigma(),
            turn_fit_window: default_turn_fit_window(),
            prior_radius: 3.0,
            prior: None,
        }
    }
}

pub(super) fn default_turn_model() -> bool {
    true
}

pub(super) fn default_young_turn_sigma() -> f64 {
    2.0
}

pub(super) fn default_turn_fit_window() -> usize {
    11
}

pub(super) fn default_max_track_length() -> usize {
    512
}

pub(super) fn default_repair_lag() -> usize {
    1
}

pub(super) fn default_back_extend() -> usize {
    8
}

pub(super) fn default_ghost_check_length() -> usize {
    6
}

pub(super) fn default_min_length_flow() -> usize {
    4
}

pub(super) fn default_ghost_sigma() -> f64 {
    2.25
}

pub(super) fn default_ghost_check_init() -> bool {
    true
}

pub(super) fn default_init_gap() -> bool {
    true
}

pub(super) fn default_split_merged() -> bool {
    false
}

pub(super) fn default_split_penalty() -> f64 {
    1.3
}

pub(super) fn default_step_split() -> f64 {
    12.0
}

pub(super) fn default_step_split_hinted() -> f64 {
    0.0
}

pub(super) fn default_gap_first_step() -> bool {
    true
}

pub(super) fn default_sigma_ceiling() -> f64 {
    0.45
}

pub(super) fn default_fit_min_window() -> usize {
    5
}

pub(super) fn default_fit_bias_weight() -> f64 {
    4.0
}

impl TrackParams {
    /// Fewest detections any kept track may have: `min_length`, or
    /// `min_length_flow` when the ghost test can keep shorter tracks.
    pub fn min_kept_length(&self) -> usize {
        if self.ghost_check_length > 0 {
            self.min_length.min(self.min_length_flow)
        } else {
            self.min_length
        }
    }

    /// Check the parameters; errors name the parameter.
    pub fn validate(&self) -> Result<()> {
        let positive = [
            ("max_disp", self.max_disp),
            ("init_radius", self.init_radius),
            ("min_search_radius", self.min_search_radius),
            ("n_sigma", self.n_sigma),
            ("sigma_floor", self.sigma_floor),
            ("sigma_ceiling", self.sigma_ceiling),
            ("max_fit_residual", self.max_fit_residual),
            ("fit_bias_weight", self.fit_bias_weight),
            ("prior_radius", self.prior_radius),
            ("ghost_sigma", self.ghost_sigma),
        ];
        if !(self.velocity_prior.is_finite() && self.velocity_prior >= 0.0) {
            return Err(Error::param(
                "velocity_prior",
                format!("must be a finite number >= 0, got {}", self.velocity_prior),
            ));
        }
        if !(self.step_split_hinted.is_finite() && self.step_split_hinted >= 0.0) {
            return Err(Error::param(
                "step_split_hinted",
                format!(
                    "must be a finite number >= 0, got {}",
                    self.step_split_hinted
                ),
            ));
        }
        if self.velocity_prior_two_pass && self.velocity_prior <= 0.0 {
            return Err(Error::param(
                "velocity_prior_two_pass",
                "needs velocity_prior > 0 (its strength)".to_string(),
            ));
        }
        if !(self.step_split.is_finite() && self.step_split >= 0.0) {
            return Err(Error::param(
                "step_split",
                format!("must be a finite number >= 0, got {}", self.step_split),
            ));
        }
        if !(self.split_penalty.is_finite() && self.split_penalty >= 0.0) {
            return Err(Error::param(
                "split_penalty",
                format!("must be >= 0, got {}", self.split_penalty),
            ));
        }
        for (name, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return Err(Error::param(
                    name,
                    format!("must be a positive finite number, got {v}"),
                ));
            }
        }
        if let Some(a) = self.fit_accel_rms {
            if !(a.is_finite() && a >= 0.0) {
                return Err(Error::param(
                    "fit_accel_rms",
                    format!("must be a finite number >= 0, got {a}"),
                ));
            }
        }
        if !(self.gap_growth.is_finite() && self.gap_growth >= 0.0) {
            return Err(Error::param(
                "gap_growth",
                format!("must be >= 0, got {}", self.gap_growth),
            ));
        }
        if self.predict_window < 2 {
            return Err(Error::param(
                "predict_window",
                "needs at least 2 detections",
            ));
        }
        if self.predict_order > 2 || self.fit_order > 2 {
            return Err(Error::param(
                "predict_order/fit_order",
                "polynomial order must be 0, 1 or 2",
            ));
        }
        if self.max_track_length < 2 * self.predict_window.max(self.fit_window).max(INIT_FRAMES) {
            return Err(Error::param(
                "max_track_length",
                format!(
                    "must be at least twice the predictor/fit window, got {}",
                    self.max_track_length
                ),
            ));
        }
        if self.fit_window < 2 {
            return Err(Error::param("fit_window", "needs at least 2 detections"));
        }
        if self.fit_min_window < 2 {
            return Err(Error::param(
                "fit_min_window",
                "needs at least 2 detections",
            ));
        }
        if self.min_length < INIT_FRAMES {
            return Err(Error::param(
                "min_length",
                format!("tracks start with {INIT_FRAMES} detections; min_length must be >= {INIT_FRAMES}, got {}", self.min_length),
            ));
        }
        if self.min_length_flow < 3 {
            return Err(Error::param(
                "min_length_flow",
                format!("must be >= 3, got {}", self.min_length_flow),
            ));
        }
        if self.repair_lag >= INIT_FRAMES {
            return Err(Error::param(
                "repair_lag",
                format!("must be below {INIT_FRAMES}, got {}", self.repair_lag),
            ));
        }
        if self.back_extend > 1000 {
            return Err(Error::param("back_extend", "at most 1000 pulses"));
        }
        if self.max_gap > 1000 || self.stitch_gap > 1000 {
            return Err(Error::param("max_gap/stitch_gap", "at most 1000 pulses"));
        }
        Ok(())
    }
}
