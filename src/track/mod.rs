//! Multi-frame predictor tracking of particles across pulses.
//!
//! # Why multi-frame
//! With 1–2 events per particle the centroid of a particle image is only
//! known to ~0.4 px, and at 0.01 particles per pixel a disc of 8 px (the
//! largest displacement per pulse) holds two particles on average: two-frame
//! nearest-neighbour linking is ambiguous. Tracks are therefore started only
//! from four-frame chains that move smoothly, and once started they are
//! extended with a polynomial predictor whose uncertainty is small.
//!
//! # Algorithm (streaming, one pulse at a time: [`Tracker::push`])
//! 1. **Predict** every active track at the new pulse time: a polynomial fit
//!    (order ≤ 2) over its last `predict_window` detections, extrapolated;
//!    where the window visibly turns, a path turning at a constant rate
//!    ([`turn`], `turn_model`), and for young tracks the line unless it
//!    misses the constant-speed turning path by `young_turn_sigma`.
//!    The search radius is `n_sigma` times the predictor's position
//!    uncertainty (residual rms, floored, times the fit's leverage at the
//!    extrapolation point), clamped to `[min_search_radius, max_disp]` and
//!    grown by `gap_growth` per missed pulse.
//! 2. **Assign** globally: candidates inside each track's radius come from a
//!    k-d tree over the pulse's particles; the cost of a pair is
//!    `(d / radius)²`, the cost of a miss 1. A minimum-total-cost assignment
//!    ([`lap`], Hungarian on the connected components of the sparse
//!    candidate graph) resolves conflicts — no first-come order.
//! 3. **Bridge gaps**: a track without a match keeps predicting for up to
//!    `max_gap` pulses with a growing radius; then it ends.
//! 4. **Initialise** (four-frame best estimate, as MyPTV/OpenPTV and
//!    Shake-The-Box's initialisation): particles left unassigned in the last
//!    four pulses are chained p0→p1 (within `max_disp`, or around
//!    `p0 + u(p0)·Δt` within `prior_radius` when a mean-flow prior is given),
//!    →p2 and →p3 (within `init_radius` of the constant-velocity
//!    prediction). A chain's cost is the sum of its squared velocity changes;
//!    chains are accepted best-first without sharing particles, except
//!    those whose velocity disagrees with the local flow of the
//!    established tracks ([`local_flow`], `ghost_check_init`). Chains of
//!    four detections over five pulses (`init_gap`) follow, for particles
//!    missed once early; they need a known local flow that they match.
//! 5. **Stitch**: a new chain may be the continuation of a track that ended
//!    in the last `stitch_gap` pulses (lost through a longer gap or a missed
//!    detection streak). Ends and starts are matched by the same assignment
//!    solver on the cost of extrapolating each across the gap, and a matched
//!    pair becomes one track.
//! 6. **Finish and validate**: a track whose stitch window has passed is
//!    first cut where its positions jump to a close neighbour and stay
//!    there ([`step`], `step_split`: its particle was missed and an
//!    untracked neighbour in the gate took its place); each piece is
//!    fitted (local polynomial of order `fit_order` over a sliding window of
//!    `fit_min_window`..=`fit_window` detections around each pulse, chosen
//!    per pulse from the position noise by [`fit::fit_adaptive`]: position,
//!    velocity in px/s from the pulse times, acceleration in px/s²), and
//!    kept when it has at
//!    least `min_length` detections and the rms fit residual is at most
//!    `max_fit_residual`. Tracks of fewer than `ghost_check_length`
//!    detections are tested against the local flow and dropped as ghosts
//!    (images of different particles in a line) when they disagree; those
//!    of `min_length_flow..min_length` detections are kept when they agree.
//!
//! Memory is bounded by the active tracks, the last four pulses of
//! unassigned particles and the stitch pool; finished tracks are handed out
//! as soon as they can no longer change.

pub mod fit;
pub mod grid_index;
pub mod io;
pub mod lap;
pub mod local_flow;
pub mod slice;
pub mod step;
pub mod stream;
pub mod synth;
pub mod turn;

use std::collections::VecDeque;
use std::sync::Arc;

use serde::{Deserialize, Serialize};

use crate::cluster::{ImagePixel, Particle, ParticlePixels};
use crate::error::{Error, Result};
use grid_index::GridIndex;

pub use io::{
    read_particles_csv, read_tracks_csv, write_particles_csv, write_summary_json, write_tracks_csv,
    write_tracks_npy, ParticlesCsvWriter, Summary, SummaryAcc, TracksCsvWriter, TracksNpyWriter,
};
pub use slice::{SliceParams, SliceTracker};
pub use stream::{track_recording, PtvSink, PtvStream};

/// One point of a track: the track's fitted state at one pulse.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TrackPoint {
    pub pulse: i64,
    pub t_us: f64,
    /// Fitted position (px).
    pub x: f64,
    pub y: f64,
    /// Fitted velocity (px/s).
    pub u: f64,
    pub v: f64,
    /// Fitted acceleration (px/s²).
    pub ax: f64,
    pub ay: f64,
    /// True where the point bridges a gap (no detection at this pulse).
    pub interpolated: bool,
}

/// A Lagrangian track.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Track {
    pub id: u64,
    pub points: Vec<TrackPoint>,
}

/// A track with, for each point, the serial number of the detection it was
/// built from (`None` on bridged gaps). Serial numbers count the particles
/// in the order they were pushed, from 0 — for [`link`] the index into its
/// (pulse-sorted) input. Used to score links against ground truth.
#[derive(Debug, Clone, PartialEq)]
pub struct LinkedTrack {
    pub track: Track,
    pub detections: Vec<Option<u64>>,
}

/// A mean-flow prior for track initialisation: velocity (px/s) at a
/// position (px). Build one from a closure, a uniform flow or a grid.
#[derive(Clone)]
pub struct FlowPrior(pub Arc<dyn Fn(f64, f64) -> (f64, f64) + Send + Sync>);

impl std::fmt::Debug for FlowPrior {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("FlowPrior(..)")
    }
}

impl FlowPrior {
    pub fn from_fn(f: impl Fn(f64, f64) -> (f64, f64) + Send + Sync + 'static) -> Self {
        FlowPrior(Arc::new(f))
    }
    pub fn uniform(u: f64, v: f64) -> Self {
        Self::from_fn(move |_, _| (u, v))
    }
    /// A gridded field: node `(i, j)` at `(x0 + i·dx, y0 + j·dy)`, row-major
    /// `u[j·nx + i]`; bilinear inside, clamped to the border outside.
    #[allow(clippy::too_many_arguments)]
    pub fn grid(
        x0: f64,
        y0: f64,
        dx: f64,
        dy: f64,
        nx: usize,
        ny: usize,
        u: Vec<f64>,
        v: Vec<f64>,
    ) -> Result<Self> {
        if nx == 0 || ny == 0 || u.len() != nx * ny || v.len() != nx * ny || !(dx > 0.0 && dy > 0.0)
        {
            return Err(Error::param(
                "prior",
                "grid needs nx·ny values per component and positive spacing",
            ));
        }
        if u.iter().chain(&v).any(|a| !a.is_finite()) {
            return Err(Error::param("prior", "grid velocities must be finite"));
        }
        Ok(Self::from_fn(move |x, y| {
            let fi = ((x - x0) / dx).clamp(0.0, (nx - 1) as f64);
            let fj = ((y - y0) / dy).clamp(0.0, (ny - 1) as f64);
            let (i0, j0) = (fi.floor() as usize, fj.floor() as usize);
            let (i1, j1) = ((i0 + 1).min(nx - 1), (j0 + 1).min(ny - 1));
            let (a, b) = (fi - i0 as f64, fj - j0 as f64);
            let bil = |f: &Vec<f64>| {
                (1.0 - a) * (1.0 - b) * f[j0 * nx + i0]
                    + a * (1.0 - b) * f[j0 * nx + i1]
                    + (1.0 - a) * b * f[j1 * nx + i0]
                    + a * b * f[j1 * nx + i1]
            };
            (bil(&u), bil(&v))
        }))
    }
}

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

/// Innovations beyond this many σ do not update the noise estimate.
const CLIP_K: f64 = 2.5;

/// E[r²] / (2σ²) of a 2-D Gaussian truncated at r ≤ kσ.
fn clipped_second_moment(k: f64) -> f64 {
    let e = (-0.5 * k * k).exp();
    (1.0 - (1.0 + 0.5 * k * k) * e) / (1.0 - e)
}

fn default_turn_model() -> bool {
    true
}

fn default_young_turn_sigma() -> f64 {
    2.0
}

fn default_turn_fit_window() -> usize {
    11
}

/// The predictor takes the turning path where the heading of a window's
/// second half differs from its first half's by this many standard
/// deviations of its noise.
const PREDICT_TURN_Z: f64 = 2.0;

/// The output fit's turning path is tried where the heading change over
/// its window is this many standard deviations of its noise ...
const TURN_SCREEN_Z: f64 = 1.5;

/// ... and taken where it fits the window better than the quadratic by
/// this χ² (units of σ²; one coefficient more, the rate of turn).
const TURN_GAIN_MIN: f64 = 4.0;

/// The line through `(tau, xs, ys)` evaluated at `at`, or, where the
/// line's ±`k` σ misses the constant-speed turning path's ([`turn`]), the
/// turning path's: a young track's prediction (`young_turn_sigma`). The
/// line's leverage comes along (the gate stays the line's).
fn young_prediction(
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
fn ici_choice(preds: &[(f64, f64, f64)], sigma: f64, k: f64) -> usize {
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

fn default_max_track_length() -> usize {
    512
}

fn default_repair_lag() -> usize {
    1
}

fn default_back_extend() -> usize {
    8
}

fn default_ghost_check_length() -> usize {
    6
}

fn default_min_length_flow() -> usize {
    4
}

fn default_ghost_sigma() -> f64 {
    2.25
}

fn default_ghost_check_init() -> bool {
    true
}

fn default_init_gap() -> bool {
    true
}

fn default_split_merged() -> bool {
    false
}

fn default_split_penalty() -> f64 {
    1.3
}

fn default_step_split() -> f64 {
    12.0
}

fn default_step_split_hinted() -> f64 {
    0.0
}

fn default_gap_first_step() -> bool {
    true
}

fn default_sigma_ceiling() -> f64 {
    0.45
}

fn default_fit_min_window() -> usize {
    5
}

fn default_fit_bias_weight() -> f64 {
    4.0
}

/// Window of the outlier check at finalisation (an 11-point fixed window;
/// the output fit itself chooses its window adaptively).
const OUTLIER_WINDOW: usize = 11;

/// Cell size (px) of the local flow grid of the ghost test: the flow is
/// averaged over 3 × 3 cells (48 px), a few particle spacings at ppp 0.01.
const FLOW_CELL: f64 = 16.0;

/// Time constant (pulses) of the local flow's memory.
const FLOW_MEMORY: f64 = 8.0;

/// The velocity prior's flow keeps a copy of its grid every this many
/// pulses ([`local_flow::FlowHistory`]) ...
const PRIOR_BLOCK: i64 = 4;

/// ... the last this many: the starts of tracks up to ~128 pulses long
/// see the flow of their moment; before that the prior fades (the
/// grid's forgetting, symmetric in time).
const PRIOR_KEEP: usize = 32;

/// Detections a track must hold before its links feed the local flow
/// (longer than any track the ghost test judges).
const FLOW_MIN_DETECTIONS: usize = 6;

/// Detections a new track has room for before its first reallocation.
const NEW_TRACK_CAPACITY: usize = 64;

/// Frames (pulses) a new track's initialisation chain spans.
pub const INIT_FRAMES: usize = 4;

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

#[derive(Debug, Clone, Copy)]
struct Det {
    serial: u64,
    pulse: i64,
    t_us: f64,
    x: f64,
    y: f64,
    /// Offset (px) from this detection to the nearest other detection of
    /// its pulse within [`NEIGHBOUR_RADIUS`], recorded when a running
    /// track takes it (NaN: none, or not looked for). A track that jumps
    /// to a close neighbour q at pulse k had q beside it at k − 1: the
    /// step test ([`step::step_cuts_hinted`]) trusts a smaller step where
    /// the step matches such a neighbour.
    nb: [f32; 2],
}

/// Neighbours further than this (px) are not recorded in [`Det::nb`]:
/// the swaps the step test misses are 1–2 px jumps (`tests/ptv_swaps.rs`), and
/// neighbours 4 px away are outside every gate at σ ≈ 0.4 px.
const NEIGHBOUR_RADIUS: f64 = 4.0;

/// No neighbour recorded ([`Det::nb`]).
const NO_NEIGHBOUR: [f32; 2] = [f32::NAN, f32::NAN];

#[derive(Debug, Clone)]
struct ActiveTrack {
    /// Identity for the frames' owner lists (kept through stitching and
    /// cuts; `NO_OWNER` for handed-out segments).
    uid: u64,
    dets: Vec<Det>,
    /// Leading detections that only give context (the predictor and the
    /// fit) because an earlier segment of the track already handed them
    /// out (see `TrackParams::max_track_length`).
    context: usize,
}

impl ActiveTrack {
    fn last(&self) -> &Det {
        self.dets.last().expect("tracks are never empty")
    }
}

/// Owner of a particle no track took.
const NO_OWNER: u64 = u64::MAX;

/// Detections on each side of the repaired pulse that its two-sided fit
/// uses at most (before it; after it there are `repair_lag`).
const REPAIR_WINDOW: i64 = 8;

/// Most detections the backward extension fits (its predictor window).
const BACK_FIT_WINDOW: usize = 16;

/// What [`Tracker::extend_active`] did with the particles of a pulse.
struct FrameLinks {
    used: Vec<bool>,
    owner: Vec<u64>,
    hungry: Vec<u64>,
    /// The scratch grid does not hold this pulse's particles.
    grid_stale: bool,
}

/// Particles of one recent pulse with their "already used" flags.
struct Frame {
    pulse: i64,
    t_us: f64,
    /// Serial of the pulse's first particle (the next serial if none).
    first_serial: u64,
    /// Particles pushed (`dets` holds them, then the split parts).
    n_pushed: usize,
    /// Serial of the first split part of this pulse.
    first_split: u64,
    /// The track (uid) each particle went to (`NO_OWNER`: none).
    owner: Vec<u64>,
    /// Tracks (uids) that found no particle at this pulse.
    hungry: Vec<u64>,
    /// Grid over `dets` (for the delayed repair).
    grid: GridIndex,
    dets: Vec<Det>,
    used: Vec<bool>,
}

impl Frame {
    /// Index in `dets` of the detection with this serial.
    fn index_of(&self, serial: u64) -> Option<usize> {
        let i = if serial & SPLIT_SERIAL_BIT == 0 {
            serial.checked_sub(self.first_serial)? as usize
        } else {
            self.n_pushed + serial.checked_sub(self.first_split)? as usize
        };
        (i < self.dets.len()).then_some(i)
    }
}

/// Serials of the parts of split images have this bit set (the pushed
/// particles keep serials counted from 0, so that a serial still indexes
/// the input of [`link_linked`]); the rest counts the parts from 0.
pub const SPLIT_SERIAL_BIT: u64 = 1 << 63;

/// A part of a merged image split by the tracker (see
/// `TrackParams::split_merged`): a detection that was not in the input.
#[derive(Debug, Clone, PartialEq)]
pub struct SplitDetection {
    /// Its serial (with [`SPLIT_SERIAL_BIT`] set).
    pub serial: u64,
    /// Serial of the image it was split from.
    pub parent: u64,
    pub pulse: i64,
    /// Event-weighted centroid of its pixels (px).
    pub x: f64,
    pub y: f64,
    pub pixels: Vec<ImagePixel>,
}

/// Counters of what the tracker did (for `summary.json`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct TrackerStats {
    pub pulses: u64,
    pub particles: u64,
    pub tracks_started: u64,
    pub tracks_stitched: u64,
    pub tracks_kept: u64,
    pub tracks_rejected_short: u64,
    pub tracks_rejected_rough: u64,
    /// Detections on kept tracks.
    pub particles_on_tracks: u64,
    /// Merged images split between two tracks (`TrackParams::split_merged`).
    #[serde(default)]
    pub images_split: u64,
    /// Short tracks dropped as ghosts by the local-flow test
    /// (`TrackParams::ghost_check_length`).
    #[serde(default)]
    pub tracks_rejected_ghost: u64,
    /// Tracks below `min_length` kept because they agree with the local flow.
    #[serde(default)]
    pub tracks_kept_by_flow: u64,
    /// Ended tracks cut at a step (`TrackParams::step_split`), per cut.
    #[serde(default)]
    pub tracks_cut_at_steps: u64,
}

impl TrackerStats {
    /// Add the counters that [`Finaliser::finalise`] keeps (the fits'
    /// verdicts: kept, short, ghost, rough, kept by flow, particles on
    /// tracks, step cuts) from `fits`; the linking counters stay this one's.
    pub fn add_fit_counters(&mut self, fits: &TrackerStats) {
        self.tracks_kept += fits.tracks_kept;
        self.tracks_rejected_short += fits.tracks_rejected_short;
        self.tracks_rejected_ghost += fits.tracks_rejected_ghost;
        self.tracks_rejected_rough += fits.tracks_rejected_rough;
        self.tracks_kept_by_flow += fits.tracks_kept_by_flow;
        self.particles_on_tracks += fits.particles_on_tracks;
        self.tracks_cut_at_steps += fits.tracks_cut_at_steps;
    }
}

/// Streaming multi-frame tracker: feed pulses in increasing order with
/// [`Tracker::push`], collect finished tracks as they come out, and call
/// [`Tracker::finish`] at the end.
pub struct Tracker {
    params: TrackParams,
    active: Vec<ActiveTrack>,
    frames: VecDeque<Frame>,
    /// The `back_extend` pulses before `frames` (oldest first), for the
    /// backward extension of new tracks.
    back_frames: VecDeque<Frame>,
    /// Ended tracks waiting for a possible stitch.
    pool: Vec<ActiveTrack>,
    next_serial: u64,
    /// Split parts made so far (their serials count from
    /// [`SPLIT_SERIAL_BIT`]).
    next_split: u64,
    /// Keep a [`SplitDetection`] of every split part (for scoring).
    record_splits: bool,
    splits: Vec<SplitDetection>,
    next_uid: u64,
    /// Sum and count of squared normalised innovations (px², per axis),
    /// seeded with `sigma_floor` as a prior worth a few dozen links.
    innov_sum: f64,
    innov_n: f64,
    last_pulse: Option<i64>,
    stats: TrackerStats,
    /// Predictor weights for gap-free windows (see [`PredictWeights`]).
    weights: Vec<PredictWeights>,
    /// Index in `weights` of the last used entry.
    weights_hint: usize,
    /// Fits, validates and numbers ended tracks (the output fit's
    /// curvature prior, its copy of the local flow and the track ids live
    /// there).
    finaliser: Finaliser,
    /// Ended tracks waiting for [`Tracker::take_ended`] instead of being
    /// fitted here ([`Tracker::defer_fits`]).
    deferred: Option<Vec<EndedTracks>>,
    /// Displacements of the established tracks' links, for the ghost test
    /// of new chains (and, replayed, of short ended tracks).
    flow: local_flow::LocalFlow,
    /// The samples added to `flow` since the last batch of ended tracks:
    /// they travel with the next batch, and the [`Finaliser`] replays them
    /// into its own copy of the flow, so that a deferred fit sees the flow
    /// exactly as it was when its tracks ended.
    flow_log: Vec<local_flow::FlowSample>,
    /// Reused buffers of [`Tracker::extend_active`] and
    /// [`Tracker::initialise`] (no allocation per pulse in steady state).
    scratch: Scratch,
    /// First steps (p0→p1 pairs) the initialisation has expanded.
    chains_enumerated: u64,
}

#[derive(Default)]
struct Scratch {
    grid: GridIndex,
    init_grids: [GridIndex; INIT_FRAMES - 1],
    init_idx: [Vec<usize>; INIT_FRAMES - 1],
    near: Vec<(u32, f64)>,
    near2: Vec<(u32, f64)>,
    near3: Vec<(u32, f64)>,
    /// (track, detection, normalised cost) candidate pairs, grouped by track.
    edges: Vec<(usize, usize, f64)>,
    edge_d2: Vec<f64>,
    row_start: Vec<usize>,
    leverage: Vec<f64>,
    miss: Vec<f64>,
    /// Each active track's prediction (x, y, search radius).
    pred: Vec<(f64, f64, f64)>,
    /// (detection, track, cost) candidate pairs of multi-pixel images.
    multi: Vec<(usize, usize, f64)>,
}

/// The predictor of a track whose last `window` detections are on
/// consecutive pulses is a fixed linear combination of their positions (the
/// least-squares polynomial is linear in the data): `x̂ = Σ c_i x_i`, with
/// the same leverage for every track. Computed once per (window, order,
/// steps ahead) from [`fit::fit_eval`] itself, they make the common case a
/// dot product instead of a fit.
#[derive(Debug, Clone)]
struct PredictWeights {
    window: usize,
    order: usize,
    ahead: i64,
    c: Vec<f64>,
    leverage: f64,
}

impl PredictWeights {
    fn new(window: usize, order: usize, ahead: i64) -> Option<Self> {
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
    pub fn new(params: TrackParams) -> Result<Self> {
        params.validate()?;
        let floor2 = params.sigma_floor.powi(2);
        Ok(Tracker {
            params: params.clone(),
            active: Vec::new(),
            frames: VecDeque::new(),
            back_frames: VecDeque::new(),
            pool: Vec::new(),
            next_serial: 0,
            next_split: 0,
            record_splits: false,
            splits: Vec::new(),
            next_uid: 0,
            innov_sum: floor2 * 30.0,
            innov_n: 30.0,
            last_pulse: None,
            stats: TrackerStats::default(),
            weights: Vec::new(),
            weights_hint: 0,
            finaliser: Finaliser::new(params.clone()),
            deferred: None,
            flow: local_flow::LocalFlow::new(FLOW_CELL, FLOW_MEMORY),
            flow_log: Vec::new(),
            scratch: Scratch::default(),
            chains_enumerated: 0,
        })
    }

    pub fn stats(&self) -> &TrackerStats {
        &self.stats
    }

    /// The options the tracker runs with.
    pub fn params(&self) -> &TrackParams {
        &self.params
    }

    /// Number of tracks currently being extended.
    pub fn active_tracks(&self) -> usize {
        self.active.len()
    }

    /// Feed the particles of one pulse; returns the tracks that finished.
    pub fn push(&mut self, pulse: i64, t_us: f64, particles: &[Particle]) -> Result<Vec<Track>> {
        Ok(self
            .push_linked(pulse, t_us, particles)?
            .into_iter()
            .map(|t| t.track)
            .collect())
    }

    /// Keep a record of every split part (see [`Tracker::take_splits`]);
    /// off by default (the records grow with the run).
    pub fn record_splits(&mut self, on: bool) {
        self.record_splits = on;
    }

    /// The split parts recorded since the last call.
    pub fn take_splits(&mut self) -> Vec<SplitDetection> {
        std::mem::take(&mut self.splits)
    }

    /// [`Tracker::push`], keeping the detection serial numbers.
    pub fn push_linked(
        &mut self,
        pulse: i64,
        t_us: f64,
        particles: &[Particle],
    ) -> Result<Vec<LinkedTrack>> {
        self.push_linked_with_pixels(pulse, t_us, particles, None)
    }

    /// [`Tracker::push`] with the pixels of each particle (from
    /// [`crate::cluster::cluster_pulse_with_pixels`]), which lets the
    /// tracker split merged images (`TrackParams::split_merged`).
    pub fn push_with_pixels(
        &mut self,
        pulse: i64,
        t_us: f64,
        particles: &[Particle],
        pixels: &ParticlePixels,
    ) -> Result<Vec<Track>> {
        Ok(self
            .push_linked_with_pixels(pulse, t_us, particles, Some(pixels))?
            .into_iter()
            .map(|t| t.track)
            .collect())
    }

    /// [`Tracker::push_linked`] with the pixels of each particle (or none).
    /// Parts of split images get serials with [`SPLIT_SERIAL_BIT`] set.
    pub fn push_linked_with_pixels(
        &mut self,
        pulse: i64,
        t_us: f64,
        particles: &[Particle],
        pixels: Option<&ParticlePixels>,
    ) -> Result<Vec<LinkedTrack>> {
        if let Some(px) = pixels {
            if px.len() != particles.len()
                || px.start.last().map(|&e| e as usize) != Some(px.pixels.len())
            {
                return Err(Error::param(
                    "pixels",
                    format!(
                        "pulse {pulse}: pixel table of {} particles for {} particles",
                        px.len(),
                        particles.len()
                    ),
                ));
            }
        }
        if let Some(last) = self.last_pulse {
            if pulse <= last {
                return Err(Error::param(
                    "pulse",
                    format!("pulses must increase: got {pulse} after {last}"),
                ));
            }
        }
        if !t_us.is_finite() {
            return Err(Error::param(
                "t_us",
                format!("pulse {pulse}: time is not finite"),
            ));
        }
        if let Some(bad) = particles
            .iter()
            .find(|p| !(p.x.is_finite() && p.y.is_finite()))
        {
            return Err(Error::param(
                "particles",
                format!("pulse {pulse}: non-finite position ({}, {})", bad.x, bad.y),
            ));
        }
        self.last_pulse = Some(pulse);
        self.stats.pulses += 1;
        self.stats.particles += particles.len() as u64;
        let first_serial = self.next_serial;
        let first_split = self.next_split;
        let mut dets: Vec<Det> = particles
            .iter()
            .map(|p| {
                let d = Det {
                    serial: self.next_serial,
                    pulse,
                    t_us,
                    x: p.x,
                    y: p.y,
                    nb: NO_NEIGHBOUR,
                };
                self.next_serial += 1;
                d
            })
            .collect();

        // Tracks that missed too many pulses end (and wait for a stitch).
        // Removal keeps the order: active tracks stay sorted by uid (new
        // tracks get the next uids, revived ones are inserted in place), so
        // the order is deterministic and the delayed repair finds tracks
        // by binary search.
        let max_gap = self.params.max_gap as i64;
        let mut kept = 0;
        for i in 0..self.active.len() {
            // A short loop body: the misses need more lead than in
            // `extend_active`.
            if let Some(ahead) = self.active.get(i + 4 * PREFETCH_AHEAD) {
                prefetch_window(&ahead.dets, 1);
            }
            if pulse - self.active[i].last().pulse - 1 > max_gap {
                let t = std::mem::replace(
                    &mut self.active[i],
                    ActiveTrack {
                        uid: NO_OWNER,
                        dets: Vec::new(),
                        context: 0,
                    },
                );
                self.pool.push(t);
            } else {
                self.active.swap(kept, i);
                kept += 1;
            }
        }
        self.active.truncate(kept);
        debug_assert!(self.active.windows(2).all(|w| w[0].uid < w[1].uid));

        let n_pushed = dets.len();
        let links = self.extend_active(&mut dets, pixels, pulse);
        let segments = self.cut_long_tracks();
        let mut grid = std::mem::take(&mut self.scratch.grid);
        if links.grid_stale {
            grid.rebuild(dets.iter().map(|d| (d.x, d.y)));
        }
        self.frames.push_back(Frame {
            pulse,
            t_us,
            first_serial,
            n_pushed,
            first_split,
            dets,
            used: links.used,
            owner: links.owner,
            hungry: links.hungry,
            grid,
        });
        if self.params.repair_lag > 0 {
            self.repair(pulse - self.params.repair_lag as i64);
        }
        let kept_frames = INIT_FRAMES + self.params.init_gap as usize;
        while self.frames.len() > kept_frames {
            let mut old = self.frames.pop_front().expect("more frames than kept");
            // The grid goes back to the scratch for reuse.
            self.scratch.grid = std::mem::take(&mut old.grid);
            if self.params.back_extend > 0 {
                self.back_frames.push_back(old);
            }
        }
        while self.back_frames.len() > self.params.back_extend {
            self.back_frames.pop_front();
        }
        self.initialise();

        // Pool entries no new chain can reach any more are final.
        let horizon = pulse - (INIT_FRAMES as i64 - 1) - self.params.stitch_gap as i64 - 1;
        let (done, keep): (Vec<_>, Vec<_>) = std::mem::take(&mut self.pool)
            .into_iter()
            .partition(|t| t.last().pulse < horizon);
        self.pool = keep;
        let mut out = self.finalise(segments);
        out.extend(self.finalise(done));
        Ok(out)
    }

    /// Hand out the detections of tracks that reached `max_track_length`
    /// as a finished segment and continue each such track with its last
    /// few detections as context, so that memory does not grow with the
    /// life of a particle that stays in view.
    fn cut_long_tracks(&mut self) -> Vec<ActiveTrack> {
        let max = self.params.max_track_length;
        let keep = self.params.predict_window.max(self.params.fit_window);
        let mut segments = Vec::new();
        for t in &mut self.active {
            if t.dets.len() >= max {
                let tail = t.dets[t.dets.len() - keep..].to_vec();
                let seg = std::mem::replace(&mut t.dets, tail);
                segments.push(ActiveTrack {
                    uid: NO_OWNER,
                    dets: seg,
                    context: t.context,
                });
                t.context = keep;
            }
        }
        segments
    }

    /// End every track and return the rest.
    pub fn finish(mut self) -> (Vec<LinkedTrack>, TrackerStats) {
        let mut all = std::mem::take(&mut self.pool);
        all.append(&mut self.active);
        all.sort_unstable_by_key(|t| t.dets[0].serial);
        let mut out = self.finalise(all);
        // The second pass of `velocity_prior_two_pass` (no tracks held
        // otherwise): every track so far, in id order.
        out.extend(self.finaliser.refit_held());
        (out, self.stats)
    }

    /// First steps (pairs of a first and a second particle) the four-frame
    /// initialisation has expanded into chains so far: its work, for
    /// comparing search strategies (`TrackParams::gap_first_step`).
    pub fn chains_enumerated(&self) -> u64 {
        self.chains_enumerated
    }

    /// Position noise per axis (px) estimated from the innovations of all
    /// accepted links so far (a few per-track residuals are too noisy to
    /// set a gate), within `[sigma_floor, sigma_ceiling]`.
    pub fn position_sigma(&self) -> f64 {
        (self.innov_sum / self.innov_n)
            .sqrt()
            .min(self.params.sigma_ceiling)
            .max(self.params.sigma_floor)
    }

    /// The output fit's prior rms acceleration per axis (px/pulse²) for
    /// the next tracks: `fit_accel_rms` if set, else the estimate from the
    /// tracks kept so far (0 until there are enough; after
    /// [`Tracker::defer_fits`] the estimate lives in the [`Finaliser`]).
    pub fn fit_accel_rms(&self) -> f64 {
        self.params
            .fit_accel_rms
            .unwrap_or_else(|| self.finaliser.accel_prior.accel_rms(self.position_sigma()))
    }

    /// From now on, tracks that end are not fitted on this thread: they
    /// wait, unfitted, for [`Tracker::take_ended`] (and `push*` return no
    /// tracks), and the returned [`Finaliser`] — the fits' state so far:
    /// curvature prior, track numbering — fits them elsewhere, in the
    /// order they are taken. Outputs are those of the synchronous path
    /// (`stream::parallel_stream_equals_sequential_tracking`); only the
    /// counters of the fits ([`TrackerStats::add_fit_counters`]) are then
    /// the finaliser's, not [`Tracker::stats`]'s.
    pub fn defer_fits(&mut self) -> Finaliser {
        self.deferred.get_or_insert_with(Vec::new);
        std::mem::replace(&mut self.finaliser, Finaliser::new(self.params.clone()))
    }

    /// The ended tracks waiting since the last call (after
    /// [`Tracker::defer_fits`]), one entry per batch the tracker would
    /// have fitted at once, in order.
    pub fn take_ended(&mut self) -> Vec<EndedTracks> {
        self.deferred
            .as_mut()
            .map(std::mem::take)
            .unwrap_or_default()
    }

    /// [`Tracker::finish`] for a tracker that defers its fits (after
    /// [`Tracker::defer_fits`]): end every track and return all that wait
    /// unfitted.
    pub fn finish_unfitted(mut self) -> (Vec<EndedTracks>, TrackerStats) {
        self.deferred.get_or_insert_with(Vec::new);
        let mut all = std::mem::take(&mut self.pool);
        all.append(&mut self.active);
        all.sort_unstable_by_key(|t| t.dets[0].serial);
        self.finalise(all);
        (self.take_ended(), self.stats)
    }

    /// Predicted position, search radius and fit leverage of a track at
    /// pulse `pulse`: [`Tracker::predict_reference`], with cached weights
    /// when the window has no gap (the common case).
    fn predict(&mut self, ti: usize, pulse: i64) -> (f64, f64, f64, f64) {
        let p = &self.params;
        let track = &self.active[ti];
        let n = track.dets.len();
        let w = p.predict_window.min(n);
        let win = &track.dets[n - w..];
        let last = track.last();
        if p.turn_model {
            if let Some(r) = self.predict_turn(track, pulse) {
                return r;
            }
        }
        if win[0].pulse + w as i64 - 1 != last.pulse {
            return self.predict_reference(track, pulse);
        }
        let order = self.predict_order(n);
        let ahead = pulse - last.pulse;
        let Some(k) = self.weights_index(w, order, ahead) else {
            return self.predict_reference(&self.active[ti], pulse);
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
    fn predict_turn(&self, track: &ActiveTrack, pulse: i64) -> Option<(f64, f64, f64, f64)> {
        let p = &self.params;
        let n = track.dets.len();
        let w = p.predict_window.min(n).min(64);
        let win = &track.dets[n - w..];
        let last = track.last();
        let (mut tau, mut xs, mut ys) = ([0.0; 64], [0.0; 64], [0.0; 64]);
        for (i, d) in win.iter().enumerate() {
            tau[i] = (d.pulse - last.pulse) as f64;
            xs[i] = d.x;
            ys[i] = d.y;
        }
        let (tau, xs, ys) = (&tau[..w], &xs[..w], &ys[..w]);
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
            let turned = (ux * vy - uy * vx).atan2(ux * vx + uy * vy);
            let speed2 = (ux * ux + uy * uy).min(vx * vx + vy * vy);
            // Each half's heading: σ√2 per end over its span.
            let sigma = self.position_sigma();
            let var = 2.0 * sigma * sigma / speed2 * (1.0 / (la * la) + 1.0 / (lb * lb));
            if !(turned * turned > PREDICT_TURN_Z * PREDICT_TURN_Z * var) {
                return None;
            }
            let f = turn::turn_eval(tau, xs, ys, at, true)?;
            (f.x, f.y, f.leverage)
        } else {
            young_prediction(tau, xs, ys, at, self.position_sigma(), p.young_turn_sigma)?
        };
        let (r, lev) = self.search_radius(lev, pulse - last.pulse);
        Some((x, y, r, lev))
    }

    /// Cached predictor weights of a gap-free window.
    fn weights_index(&mut self, w: usize, order: usize, ahead: i64) -> Option<usize> {
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

    fn predict_order(&self, n: usize) -> usize {
        let p = &self.params;
        if n >= p.predict_order * 3 {
            p.predict_order
        } else {
            p.predict_order.min(1)
        }
    }

    /// Search radius for a prediction of the given leverage `ahead` pulses
    /// after the last detection.
    fn search_radius(&self, leverage: f64, ahead: i64) -> (f64, f64) {
        let p = &self.params;
        let gap = (ahead - 1).max(0) as f64;
        let sigma = self.position_sigma() * (1.0 + leverage).sqrt();
        let r =
            (p.n_sigma * sigma).clamp(p.min_search_radius, p.max_disp) * (1.0 + p.gap_growth * gap);
        (r.min(p.max_disp * (1.0 + gap)), leverage)
    }

    /// The predictor as a plain least-squares fit over the window (the
    /// reference of [`Tracker::predict`]).
    fn predict_reference(&self, track: &ActiveTrack, pulse: i64) -> (f64, f64, f64, f64) {
        let p = &self.params;
        let n = track.dets.len();
        let w = p.predict_window.min(n);
        let win = &track.dets[n - w..];
        let last = track.last();
        // τ in pulse periods (by pulse index), conditioning-friendly.
        let tau: Vec<f64> = win.iter().map(|d| (d.pulse - last.pulse) as f64).collect();
        let xs: Vec<f64> = win.iter().map(|d| d.x).collect();
        let ys: Vec<f64> = win.iter().map(|d| d.y).collect();
        let at = (pulse - last.pulse) as f64;
        let order = self.predict_order(n);
        let Some(f) = fit::fit_eval(&tau, &xs, &ys, order, at) else {
            return (last.x, last.y, p.max_disp, 1.0);
        };
        let (r, lev) = self.search_radius(f.leverage, pulse - last.pulse);
        (f.x, f.y, r, lev)
    }

    /// Extend active tracks with this pulse's detections (global
    /// assignment); returns the used flags of the detections.
    fn extend_active(
        &mut self,
        dets: &mut Vec<Det>,
        pixels: Option<&ParticlePixels>,
        pulse: i64,
    ) -> FrameLinks {
        let mut links = FrameLinks {
            used: vec![false; dets.len()],
            owner: vec![NO_OWNER; dets.len()],
            hungry: Vec::new(),
            grid_stale: true,
        };
        if self.active.is_empty() || dets.is_empty() {
            links.hungry.extend(self.active.iter().map(|t| t.uid));
            return links;
        }
        links.grid_stale = false;
        let mut sc = std::mem::take(&mut self.scratch);
        sc.grid.rebuild(dets.iter().map(|d| (d.x, d.y)));
        sc.edges.clear();
        sc.edge_d2.clear();
        sc.row_start.clear();
        sc.leverage.clear();
        sc.pred.clear();
        for ti in 0..self.active.len() {
            if let Some(ahead) = self.active.get(ti + PREFETCH_AHEAD) {
                prefetch_window(&ahead.dets, self.params.predict_window);
            }
            let (px, py, r, l) = self.predict(ti, pulse);
            sc.leverage.push(l);
            sc.pred.push((px, py, r));
            sc.row_start.push(sc.edges.len());
            sc.near.clear();
            sc.grid.within(px, py, r, &mut sc.near);
            for &(j, d2) in &sc.near {
                sc.edges.push((ti, j as usize, d2 / (r * r)));
                sc.edge_d2.push(d2);
            }
        }
        sc.row_start.push(sc.edges.len());
        let sigma = self.position_sigma();
        sc.miss.clear();
        sc.miss.resize(self.active.len(), 1.0);
        let mut sol = lap::assign_sparse(dets.len(), &sc.edges, &sc.miss);
        if let (true, Some(px)) = (self.params.split_merged, pixels) {
            let parents = self.split_merged_images(dets, px, &mut sc, &mut sol);
            if !parents.is_empty() {
                links.used.resize(dets.len(), false);
                links.owner.resize(dets.len(), NO_OWNER);
                // The split images are replaced by their parts: nobody's,
                // and not free for new tracks either.
                for j in parents {
                    links.used[j] = true;
                }
                links.grid_stale = true;
            }
        }
        let flow_on = self.params.ghost_check_length > 0;
        for (ti, c) in sol.into_iter().enumerate() {
            let Some(c) = c else {
                links.hungry.push(self.active[ti].uid);
                continue;
            };
            {
                if flow_on && self.active[ti].dets.len() >= FLOW_MIN_DETECTIONS {
                    let (a, b) = (self.active[ti].last(), &dets[c]);
                    let gap = (b.pulse - a.pulse) as f64;
                    let sample = local_flow::FlowSample {
                        pulse: b.pulse,
                        x: 0.5 * (a.x + b.x),
                        y: 0.5 * (a.y + b.y),
                        u: (b.x - a.x) / gap,
                        v: (b.y - a.y) / gap,
                    };
                    self.flow.add_sample(sample);
                    self.flow_log.push(sample);
                }
                let mut det = dets[c];
                if self.params.step_split_hinted > 0.0 && !links.grid_stale {
                    det.nb = nearest_neighbour(&sc.grid, dets, c, &mut sc.near);
                }
                self.active[ti].dets.push(det);
                links.used[c] = true;
                links.owner[c] = self.active[ti].uid;
                let row = sc.row_start[ti]..sc.row_start[ti + 1];
                if let Some(k) = row.clone().find(|&k| sc.edges[k].1 == c) {
                    // Squared innovation per axis, normalised by the
                    // predictor's variance factor. Only innovations within
                    // CLIP_K σ count (wrong links, whose innovations are
                    // large, would otherwise inflate σ, widen the gates and
                    // let in more wrong links: a runaway in dense, noisy
                    // scenes); dividing by the truncated Gaussian's second
                    // moment keeps the estimate unbiased.
                    let z2 = sc.edge_d2[k] / (1.0 + sc.leverage[ti]);
                    if z2 <= (CLIP_K * sigma).powi(2) {
                        self.innov_sum += z2 / (2.0 * clipped_second_moment(CLIP_K));
                        self.innov_n += 1.0;
                    }
                }
            }
        }
        self.scratch = sc;
        links
    }

    /// Split multi-pixel images that two tracks predict into (see
    /// `TrackParams::split_merged`), after the assignment `sol` of the
    /// whole images: for each such image and pair of its candidate tracks
    /// (the image taken by one of them or by none), the pixels go to the
    /// nearer prediction; when both parts lie in their track's gate and
    /// their costs plus `split_penalty` are below what the two tracks pay
    /// now (their assigned candidates, or a miss), the best pair gets the
    /// parts (appended to `dets`, `sol` updated). A track takes part in at
    /// most one split per pulse. Returns the indices of the split images.
    /// Only images in two gates are looked at: the per-pulse cost is a
    /// pass over the candidate pairs.
    fn split_merged_images(
        &mut self,
        dets: &mut Vec<Det>,
        px: &ParticlePixels,
        sc: &mut Scratch,
        sol: &mut [Option<usize>],
    ) -> Vec<usize> {
        let mut parents = Vec::new();
        sc.multi.clear();
        for &(ti, j, c) in &sc.edges {
            if px.start[j + 1] - px.start[j] >= 2 {
                sc.multi.push((j, ti, c));
            }
        }
        if sc.multi.len() < 2 {
            return parents;
        }
        sc.multi
            .sort_unstable_by(|a, b| (a.0, a.1).cmp(&(b.0, b.1)));
        // What a track pays now: its assigned candidate's cost, or a miss.
        let cost_now = |sc: &Scratch, sol: &[Option<usize>], ti: usize| match sol[ti] {
            None => sc.miss[ti],
            Some(c) => sc.edges[sc.row_start[ti]..sc.row_start[ti + 1]]
                .iter()
                .find(|e| e.1 == c)
                .map_or(sc.miss[ti], |e| e.2),
        };
        let mut locked: Vec<usize> = Vec::new();
        let mut side = Vec::new();
        let penalty = self.params.split_penalty;
        let sep_weight = 1.0 / (self.params.n_sigma * self.position_sigma()).powi(2);
        let mut g = 0;
        while g < sc.multi.len() {
            let j = sc.multi[g].0;
            let mut e = g + 1;
            while e < sc.multi.len() && sc.multi[e].0 == j {
                e += 1;
            }
            let group = g..e;
            g = e;
            if group.len() < 2 {
                continue;
            }
            let taker = group
                .clone()
                .map(|k| sc.multi[k].1)
                .find(|&t| sol[t] == Some(j));
            let image = px.of(j);
            // (gain, a, b, parts)
            let mut best: Option<(f64, usize, usize, SplitParts)> = None;
            for ia in group.clone() {
                for ib in ia + 1..group.end {
                    let (a, b) = (sc.multi[ia].1, sc.multi[ib].1);
                    if locked.contains(&a)
                        || locked.contains(&b)
                        || taker.is_some_and(|t| t != a && t != b)
                    {
                        continue;
                    }
                    let (pa, pb) = (sc.pred[a], sc.pred[b]);
                    let Some((cost, parts)) = split_by_predictions(image, pa, pb, &mut side) else {
                        continue;
                    };
                    // Each part inside its track's gate.
                    let inside = |q: (f64, f64, u32), p: Prediction| {
                        (q.0 - p.0).powi(2) + (q.1 - p.1).powi(2) <= p.2 * p.2
                    };
                    if !(inside(parts[0], pa) && inside(parts[1], pb)) {
                        continue;
                    }
                    // Two images in one: the parts' separation, which one
                    // particle's image seldom shows, in the assignment's
                    // units (squared distance over n_σ² σ²).
                    let (na, nb) = (parts[0].2 as f64, parts[1].2 as f64);
                    let sep2 =
                        (parts[0].0 - parts[1].0).powi(2) + (parts[0].1 - parts[1].1).powi(2);
                    let bonus = sep_weight * na * nb / (na + nb) * sep2;
                    let gain =
                        cost_now(sc, sol, a) + cost_now(sc, sol, b) - (cost + penalty - bonus);
                    if gain > 0.0 && best.as_ref().map_or(true, |x| gain > x.0) {
                        best = Some((gain, a, b, parts));
                    }
                }
            }
            let Some((_, a, b, parts)) = best else {
                continue;
            };
            locked.extend([a, b]);
            parents.push(j);
            self.stats.images_split += 1;
            if self.record_splits {
                // `side` belongs to the last pair tried: partition again.
                split_by_predictions(image, sc.pred[a], sc.pred[b], &mut side);
            }
            let parent = dets[j];
            for (k, (ti, part)) in [(a, parts[0]), (b, parts[1])].into_iter().enumerate() {
                let serial = SPLIT_SERIAL_BIT | self.next_split;
                self.next_split += 1;
                dets.push(Det {
                    serial,
                    x: part.0,
                    y: part.1,
                    nb: NO_NEIGHBOUR,
                    ..parent
                });
                sol[ti] = Some(dets.len() - 1);
                if self.record_splits {
                    self.splits.push(SplitDetection {
                        serial,
                        parent: parent.serial,
                        pulse: parent.pulse,
                        x: part.0,
                        y: part.1,
                        pixels: image
                            .iter()
                            .zip(&side)
                            .filter(|(_, &s)| s == (k == 1))
                            .map(|(p, _)| *p)
                            .collect(),
                    });
                }
            }
        }
        parents
    }

    /// Four-frame initialisation over the unused particles of the last
    /// [`INIT_FRAMES`] pulses (and, with `init_gap`, chains of four
    /// detections over the last five pulses that skip one of the three
    /// middle pulses), then backward extension and stitching of the new
    /// chains to ended tracks.
    fn initialise(&mut self) {
        let n = self.frames.len();
        if n < INIT_FRAMES {
            return;
        }
        let consecutive = |frames: &VecDeque<Frame>, from: usize| {
            (from + 1..n).all(|k| frames[k].pulse == frames[k - 1].pulse + 1)
        };
        let mut new_tracks: Vec<ActiveTrack> = Vec::new();
        let last: [usize; INIT_FRAMES] = std::array::from_fn(|k| n - INIT_FRAMES + k);
        if consecutive(&self.frames, n - INIT_FRAMES) {
            self.start_chains(last, &mut new_tracks);
        }
        if self.params.init_gap && n == INIT_FRAMES + 1 && consecutive(&self.frames, 0) {
            // A particle missed once in its first pulses (5 % of the
            // images are lost, and merged ones are taken by a neighbour)
            // starts here instead of waiting for four clean pulses in a row.
            for skip in 1..INIT_FRAMES {
                let idx: Vec<usize> = (0..=INIT_FRAMES).filter(|&k| k != skip).collect();
                self.start_chains([idx[0], idx[1], idx[2], idx[3]], &mut new_tracks);
            }
        }
        self.stats.tracks_started += new_tracks.len() as u64;
        self.next_uid += new_tracks.len() as u64;
        self.extend_backward(&mut new_tracks);
        let new_tracks = self.stitch(new_tracks);
        for t in &new_tracks {
            self.set_owner(t);
        }
        self.active.extend(new_tracks);
    }

    /// Chains of unused particles through the frames `idx` (indices into
    /// `frames`, increasing pulses, any spacing): p0→p1 within `max_disp`
    /// per pulse (or around the prior's prediction), →p2 and →p3 within
    /// the gate of the constant-velocity prediction from the previous two.
    /// A chain's cost is the sum of its two prediction errors, each
    /// divided by its variance factor (6 on consecutive pulses: a
    /// prediction from two noisy positions errs by √6 σ per axis); chains
    /// are accepted best-first without sharing particles and appended to
    /// `out` (uids after `next_uid + out.len()`), their particles marked used.
    fn start_chains(&mut self, idx: [usize; INIT_FRAMES], out: &mut Vec<ActiveTrack>) {
        let f = &self.frames;
        let p = &self.params;
        let sigma = self.position_sigma();
        let dt = |a: usize, b: usize| f[idx[b]].t_us - f[idx[a]].t_us;
        let span = |a: usize, b: usize| (f[idx[b]].pulse - f[idx[a]].pulse) as f64;
        // Variance factor of the prediction of frame k from frames k-2, k-1.
        let var = |k: usize| {
            let a = span(k - 1, k) / span(k - 2, k - 1);
            (1.0 + a).powi(2) + a * a + 1.0
        };
        let (var2, var3) = (var(2), var(3));
        let gate = |v: f64| (p.n_sigma * sigma * v.sqrt()).clamp(p.init_radius, p.max_disp);
        let (gate2, gate3) = (gate(var2), gate(var3));
        // Grids over the unused particles of frames 1..3.
        let mut sc = std::mem::take(&mut self.scratch);
        for k in 1..INIT_FRAMES {
            let fk = &f[idx[k]];
            let ids = &mut sc.init_idx[k - 1];
            ids.clear();
            unused_indices(&fk.used[..fk.dets.len()], ids);
            sc.init_grids[k - 1].rebuild(ids.iter().map(|&i| (fk.dets[i].x, fk.dets[i].y)));
        }
        let near = |k: usize, x: f64, y: f64, r: f64, out: &mut Vec<(u32, f64)>| {
            out.clear();
            sc.init_grids[k - 1].within(x, y, r, out);
            for e in out.iter_mut() {
                e.0 = sc.init_idx[k - 1][e.0 as usize] as u32;
            }
        };
        let (mut n1, mut n2, mut n3) = (
            std::mem::take(&mut sc.near),
            std::mem::take(&mut sc.near2),
            std::mem::take(&mut sc.near3),
        );
        let (f0, f1, f2, f3) = (&f[idx[0]], &f[idx[1]], &f[idx[2]], &f[idx[3]]);
        let check = p.ghost_check_init && p.ghost_check_length > 0;
        // A chain that skips a pulse must show that it moves with the
        // local flow (an unknown flow is no excuse): it is the likelier
        // ghost (wider first steps, one image fewer per span).
        let gappy = span(0, INIT_FRAMES - 1) > (INIT_FRAMES - 1) as f64;
        // Its first step can be held to the flow at once
        // (`gap_first_step`): the pulse and Σ(τ − τ̄)² of the ghost test's
        // line fit, for its flow tolerance.
        let first_step_flow = gappy && check && p.gap_first_step;
        let taus: [f64; INIT_FRAMES] = std::array::from_fn(|k| span(0, k));
        let tau_mean = taus.iter().sum::<f64>() / INIT_FRAMES as f64;
        let stt: f64 = taus.iter().map(|t| (t - tau_mean).powi(2)).sum();
        let t_mid = (f0.pulse as f64 + tau_mean).round() as i64;
        let s2 = sigma * sigma;
        // (cost, [i0, i1, i2, i3])
        let mut chains: Vec<(f64, [usize; 4])> = Vec::new();
        for (i0, d0) in f0.dets.iter().enumerate() {
            if f0.used[i0] {
                continue;
            }
            let (cx, cy, r1) = match &p.prior {
                Some(prior) => {
                    let (u, v) = (prior.0)(d0.x, d0.y);
                    let s = dt(0, 1) * 1e-6;
                    (d0.x + u * s, d0.y + v * s, p.prior_radius * span(0, 1))
                }
                None => (d0.x, d0.y, p.max_disp * span(0, 1)),
            };
            if first_step_flow {
                let flow = match self.flow.at(t_mid, d0.x, d0.y) {
                    Some(e) if e.weight >= local_flow::MIN_FLOW_WEIGHT => e,
                    _ => continue,
                };
                // The ghost test's tolerance of the chain's velocity, and
                // three σ of the first step's own noise (√2 σ per axis)
                // plus 1 px for its difference from the chain's fitted
                // velocity (curvature over two pulses).
                let variation = (flow.spread2 - 2.0 * s2).max(0.0);
                let tol =
                    p.ghost_sigma * (variation + s2 / stt + flow.spread2 / flow.weight).sqrt();
                let s01 = span(0, 1);
                let r = (s01 * tol + 3.0 * std::f64::consts::SQRT_2 * sigma + 1.0).min(r1);
                near(1, d0.x + flow.u * s01, d0.y + flow.v * s01, r, &mut n1);
                // Within the plain first-step disc too.
                n1.retain(|&(i1, _)| {
                    let d1 = &f1.dets[i1 as usize];
                    (d1.x - cx).powi(2) + (d1.y - cy).powi(2) <= r1 * r1
                });
            } else {
                near(1, cx, cy, r1, &mut n1);
            }
            self.chains_enumerated += n1.len() as u64;
            for &(i1, _) in &n1 {
                let i1 = i1 as usize;
                let d1 = &f1.dets[i1];
                let (v1x, v1y) = ((d1.x - d0.x) / dt(0, 1), (d1.y - d0.y) / dt(0, 1));
                let (p2x, p2y) = (d1.x + v1x * dt(1, 2), d1.y + v1y * dt(1, 2));
                near(2, p2x, p2y, gate2, &mut n2);
                for &(i2, _) in &n2 {
                    let i2 = i2 as usize;
                    let d2 = &f2.dets[i2];
                    let (v2x, v2y) = ((d2.x - d1.x) / dt(1, 2), (d2.y - d1.y) / dt(1, 2));
                    let (p3x, p3y) = (d2.x + v2x * dt(2, 3), d2.y + v2y * dt(2, 3));
                    near(3, p3x, p3y, gate3, &mut n3);
                    for &(i3, _) in &n3 {
                        let i3 = i3 as usize;
                        let d3 = &f3.dets[i3];
                        let e2 = (d2.x - p2x).powi(2) + (d2.y - p2y).powi(2);
                        let e3 = (d3.x - p3x).powi(2) + (d3.y - p3y).powi(2);
                        chains.push((e2 / var2 + e3 / var3, [i0, i1, i2, i3]));
                    }
                }
            }
        }
        sc.near = n1;
        sc.near2 = n2;
        sc.near3 = n3;
        self.scratch = sc;
        let f = &self.frames;
        chains.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        let mut taken: Vec<Vec<bool>> = idx.iter().map(|&k| f[k].used.clone()).collect();
        for (_, ids) in chains {
            if (0..INIT_FRAMES).any(|k| taken[k][ids[k]]) {
                continue;
            }
            if check {
                let xy: [(i64, f64, f64); INIT_FRAMES] = std::array::from_fn(|k| {
                    let d = &f[idx[k]].dets[ids[k]];
                    (d.pulse, d.x, d.y)
                });
                match local_flow::flow_consistent(&xy, &self.flow, sigma, p.ghost_sigma) {
                    local_flow::FlowCheck::Ghost => continue,
                    local_flow::FlowCheck::Unknown if gappy => continue,
                    _ => {}
                }
            }
            for k in 0..INIT_FRAMES {
                taken[k][ids[k]] = true;
            }
            // Room for the track's first dozens of links: a track grows
            // a detection per pulse, and growing from four by doubling
            // cost ~1 400 instructions per step on the linking thread
            // (~8 000 per track; the allocator, copies).
            let mut dets = Vec::with_capacity(NEW_TRACK_CAPACITY);
            dets.extend((0..INIT_FRAMES).map(|k| f[idx[k]].dets[ids[k]]));
            out.push(ActiveTrack {
                uid: self.next_uid + out.len() as u64,
                dets,
                context: 0,
            });
        }
        for (k, t) in idx.iter().zip(taken) {
            self.frames[*k].used = t;
        }
    }

    /// Record `t` as the owner of its detections in the kept frames.
    fn set_owner(&mut self, t: &ActiveTrack) {
        for f in self.frames.iter_mut().chain(self.back_frames.iter_mut()) {
            if let Ok(i) = t.dets.binary_search_by_key(&f.pulse, |d| d.pulse) {
                if let Some(j) = f.index_of(t.dets[i].serial) {
                    f.owner[j] = t.uid;
                }
            }
        }
    }

    /// Position of an active track at `pulse` from a fit of its
    /// detections on both sides (pulse itself excluded), with the gate
    /// for a particle there: (x, y, radius).
    fn smoothed(&self, t: &ActiveTrack, pulse: i64) -> Option<(f64, f64, f64)> {
        const N: usize = 2 * REPAIR_WINDOW as usize;
        let lo = t.dets.partition_point(|d| d.pulse < pulse - REPAIR_WINDOW);
        let hi = t.dets.partition_point(|d| d.pulse <= pulse + REPAIR_WINDOW);
        let (mut tau, mut xs, mut ys) = ([0.0; N], [0.0; N], [0.0; N]);
        let mut n = 0;
        for d in t.dets[lo..hi].iter().filter(|d| d.pulse != pulse).take(N) {
            tau[n] = (d.pulse - pulse) as f64;
            xs[n] = d.x;
            ys[n] = d.y;
            n += 1;
        }
        if n < 3 {
            return None;
        }
        let f = fit::fit_eval(&tau[..n], &xs[..n], &ys[..n], self.predict_order(n), 0.0)?;
        let (r, _) = self.search_radius(f.leverage, 1);
        Some((f.x, f.y, r))
    }

    /// Revisit the links of pulse `k` (see `TrackParams::repair_lag`).
    fn repair(&mut self, k: i64) {
        let Some(fi) = self.frames.iter().position(|f| f.pulse == k) else {
            return;
        };
        let frame = &self.frames[fi];
        if frame.dets.is_empty() {
            return;
        }
        let find =
            |active: &[ActiveTrack], uid: u64| active.binary_search_by_key(&uid, |t| t.uid).ok();
        // Seeds: tracks that missed k. (Seeding also the owners of
        // particles in several gates or far from their prediction helps
        // the densest scenes, ppp 0.02 at 12 px/pulse: precision 0.754 →
        // 0.768, but not paper-like ones, and costs 7 % more linking.)
        let mut rows: Vec<usize> = frame
            .hungry
            .iter()
            .filter_map(|&uid| find(&self.active, uid))
            .collect();
        if rows.is_empty() {
            return;
        }
        rows.sort_unstable();
        rows.dedup();
        let mut row_of = vec![usize::MAX; self.active.len()];
        for (row, &ti) in rows.iter().enumerate() {
            row_of[ti] = row;
        }
        // Two-sided positions; owners of the seeds' candidates join in.
        let mut fits: Vec<Option<(f64, f64, f64)>> = Vec::new();
        let mut near = Vec::new();
        let mut i = 0;
        while i < rows.len() {
            let t = &self.active[rows[i]];
            let fit = if t.dets.len() < INIT_FRAMES
                || t.dets.partition_point(|d| d.pulse < k) < t.context
            {
                // Too short to lose a detection, or inside an already
                // handed-out segment: keeps what it has.
                None
            } else {
                self.smoothed(t, k)
            };
            fits.push(fit);
            if let Some((x, y, r)) = fit {
                near.clear();
                frame.grid.within(x, y, r, &mut near);
                for &(j, _) in &near {
                    let o = frame.owner[j as usize];
                    if o != NO_OWNER {
                        if let Some(ti) = find(&self.active, o) {
                            if row_of[ti] == usize::MAX {
                                row_of[ti] = rows.len();
                                rows.push(ti);
                            }
                        }
                    }
                }
            }
            i += 1;
        }
        // Particles in play: unused ones and those of the rows' tracks.
        let mut edges = Vec::new();
        let current: Vec<Option<usize>> = rows
            .iter()
            .map(|&ti| {
                let t = &self.active[ti];
                t.dets
                    .binary_search_by_key(&k, |d| d.pulse)
                    .ok()
                    .and_then(|i| frame.index_of(t.dets[i].serial))
            })
            .collect();
        // Particles of rows without a fit stay where they are.
        let mut locked = vec![false; frame.dets.len()];
        for (fit, cur) in fits.iter().zip(&current) {
            if let (None, Some(c)) = (fit, cur) {
                locked[*c] = true;
            }
        }
        for (row, (fit, &cur)) in fits.iter().zip(&current).enumerate() {
            let Some((x, y, r)) = *fit else {
                if let Some(c) = cur {
                    edges.push((row, c, 0.0));
                }
                continue;
            };
            near.clear();
            frame.grid.within(x, y, r, &mut near);
            for &(j, d2) in &near {
                let o = frame.owner[j as usize];
                if locked[j as usize] {
                    continue;
                }
                let free = o == NO_OWNER && !frame.used[j as usize];
                if free || find(&self.active, o).is_some_and(|ti| row_of[ti] != usize::MAX) {
                    edges.push((row, j as usize, d2 / (r * r)));
                }
            }
        }
        let sol = lap::assign_sparse(frame.dets.len(), &edges, &vec![1.0; rows.len()]);
        if sol == current {
            return;
        }
        let frame = &mut self.frames[fi];
        for (row, &ti) in rows.iter().enumerate() {
            if sol[row] == current[row] {
                continue;
            }
            let t = &mut self.active[ti];
            if let Some(c) = current[row] {
                let i = t
                    .dets
                    .binary_search_by_key(&k, |d| d.pulse)
                    .expect("current particle");
                t.dets.remove(i);
                if frame.owner[c] == t.uid {
                    frame.owner[c] = NO_OWNER;
                    frame.used[c] = false;
                }
            }
            if let Some(c) = sol[row] {
                let i = t.dets.partition_point(|d| d.pulse < k);
                t.dets.insert(i, frame.dets[c]);
                frame.owner[c] = t.uid;
                frame.used[c] = true;
            }
        }
    }

    /// Extend new tracks backwards through the unused particles of the
    /// `back_extend` pulses before their first detection: per older pulse
    /// each track predicts where its particle was (the predictor's fit over
    /// its first detections, extrapolated backwards, with the forward
    /// gate), and the candidates are assigned globally like a forward step.
    /// A track stops when it would bridge more than `max_gap` pulses.
    fn extend_backward(&mut self, tracks: &mut [ActiveTrack]) {
        // Older frames, newest first: those of `frames` before the
        // gap-free chains' first frame (with `init_gap`), then `back_frames`.
        let in_frames = self.frames.len().saturating_sub(INIT_FRAMES);
        let older: Vec<(bool, usize)> = (0..in_frames)
            .rev()
            .map(|i| (true, i))
            .chain((0..self.back_frames.len()).rev().map(|i| (false, i)))
            .collect();
        if tracks.is_empty() || older.is_empty() || self.params.back_extend == 0 {
            return;
        }
        let p = &self.params;
        let w = p.predict_window;
        let max_gap = p.max_gap as i64;
        let mut sc = std::mem::take(&mut self.scratch);
        let mut idx: Vec<usize> = Vec::new();
        for &(in_f, fi) in &older {
            let frame = if in_f {
                &self.frames[fi]
            } else {
                &self.back_frames[fi]
            };
            let reach = |ti: usize| tracks[ti].dets[0].pulse - frame.pulse - 1 <= max_gap;
            let open: Vec<usize> = (0..tracks.len())
                .filter(|&ti| tracks[ti].dets[0].pulse > frame.pulse && reach(ti))
                .collect();
            if open.is_empty() {
                if (0..tracks.len()).any(reach) {
                    continue; // tracks that start at or before this frame
                }
                break;
            }
            idx.clear();
            unused_indices(&frame.used[..frame.dets.len()], &mut idx);
            if idx.is_empty() {
                continue;
            }
            sc.grid
                .rebuild(idx.iter().map(|&i| (frame.dets[i].x, frame.dets[i].y)));
            sc.edges.clear();
            for (row, &ti) in open.iter().enumerate() {
                let dets = &tracks[ti].dets;
                let n = dets.len().min(w).min(BACK_FIT_WINDOW);
                let first = dets[0].pulse;
                let (mut tau, mut xs, mut ys) = (
                    [0.0; BACK_FIT_WINDOW],
                    [0.0; BACK_FIT_WINDOW],
                    [0.0; BACK_FIT_WINDOW],
                );
                for (i, d) in dets[..n].iter().enumerate() {
                    tau[i] = (d.pulse - first) as f64;
                    xs[i] = d.x;
                    ys[i] = d.y;
                }
                let order = self.predict_order(n);
                let at = (frame.pulse - first) as f64;
                let turned = if !self.params.turn_model {
                    None
                } else if order >= 2 {
                    turn::turn_eval(&tau[..n], &xs[..n], &ys[..n], at, true)
                        .map(|t| (t.x, t.y, t.leverage))
                } else {
                    // The line: young tracks' turning choice here cost the
                    // synthetic paper-like scene recall (0.9505 → 0.9493)
                    // and did not help the vortex.
                    young_prediction(
                        &tau[..n],
                        &xs[..n],
                        &ys[..n],
                        at,
                        self.position_sigma(),
                        0.0,
                    )
                };
                let f = match turned {
                    Some((x, y, leverage)) => fit::FitState {
                        x,
                        y,
                        vx: 0.0,
                        vy: 0.0,
                        ax: 0.0,
                        ay: 0.0,
                        rms_residual: 0.0,
                        leverage,
                        velocity_variance: 0.0,
                    },
                    None => {
                        let Some(f) = fit::fit_eval(&tau[..n], &xs[..n], &ys[..n], order, at)
                        else {
                            continue;
                        };
                        f
                    }
                };
                let (r, _) = self.search_radius(f.leverage, first - frame.pulse);
                sc.near.clear();
                sc.grid.within(f.x, f.y, r, &mut sc.near);
                for &(j, d2) in &sc.near {
                    sc.edges.push((row, idx[j as usize], d2 / (r * r)));
                }
            }
            if sc.edges.is_empty() {
                continue;
            }
            let sol = lap::assign_sparse(frame.dets.len(), &sc.edges, &vec![1.0; open.len()]);
            let frame = if in_f {
                &mut self.frames[fi]
            } else {
                &mut self.back_frames[fi]
            };
            for (row, c) in sol.into_iter().enumerate() {
                if let Some(c) = c {
                    frame.used[c] = true;
                    tracks[open[row]].dets.insert(0, frame.dets[c]);
                }
            }
        }
        self.scratch = sc;
    }

    /// Join new chains to ended tracks in the pool where both extrapolate
    /// onto each other across the gap; returns the chains left unjoined.
    fn stitch(&mut self, chains: Vec<ActiveTrack>) -> Vec<ActiveTrack> {
        if self.pool.is_empty() || chains.is_empty() {
            return chains;
        }
        let sigma = self.position_sigma();
        let p = &self.params;
        let mut edges = Vec::new();
        for (ri, old) in self.pool.iter().enumerate() {
            let end = old.last();
            // Chains start at the same pulse unless extended backwards:
            // each ended track is extrapolated once per start pulse.
            let mut fwd_at: Vec<(i64, Option<(f64, f64)>)> = Vec::new();
            for (ci, new) in chains.iter().enumerate() {
                let start = &new.dets[0];
                let gap = start.pulse - end.pulse - 1;
                if gap < 0 || gap > p.stitch_gap as i64 {
                    continue;
                }
                let r = p.min_search_radius * (1.0 + p.stitch_growth * gap as f64);
                // Out of reach whatever the extrapolation (cheap test first).
                let reach = (gap + 1) as f64 * p.max_disp + 2.0 * r;
                if (end.x - start.x).powi(2) + (end.y - start.y).powi(2) > reach * reach {
                    continue;
                }
                let fwd = match fwd_at.iter().find(|e| e.0 == start.pulse) {
                    Some(e) => e.1,
                    None => {
                        let f = extrapolate(&old.dets, p.predict_window, start.pulse, p, sigma);
                        fwd_at.push((start.pulse, f));
                        f
                    }
                };
                let Some(fwd) = fwd else {
                    continue;
                };
                let fwd_d2 = (fwd.0 - start.x).powi(2) + (fwd.1 - start.y).powi(2);
                if fwd_d2 > 2.0 * r * r {
                    continue;
                }
                // The old track's extrapolation reaches the chain, and one
                // turning path through both pieces has the residuals of
                // the position noise: the pair joins even where the young
                // chain's own line back across the gap is off (a vortex
                // core).
                if p.turn_model {
                    if let Some(z) = joint_turn_cost(&old.dets, &new.dets, sigma) {
                        if z <= 1.0 {
                            edges.push((ri, ci, z.max(0.5 * fwd_d2 / (r * r))));
                            continue;
                        }
                    }
                }
                let fwd = Some(fwd);
                let bwd = extrapolate(&new.dets, p.predict_window, end.pulse, p, sigma);
                let (Some(fwd), Some(bwd)) = (fwd, bwd) else {
                    continue;
                };
                let e = ((fwd.0 - start.x).powi(2)
                    + (fwd.1 - start.y).powi(2)
                    + (bwd.0 - end.x).powi(2)
                    + (bwd.1 - end.y).powi(2))
                    / 2.0;
                if e <= r * r {
                    edges.push((ri, ci, e / (r * r)));
                }
            }
        }
        let sol = lap::assign_sparse(chains.len(), &edges, &vec![1.0; self.pool.len()]);
        let mut chain_taken = vec![false; chains.len()];
        let mut revived = Vec::new();
        for (ri, c) in sol.iter().enumerate() {
            if let Some(c) = *c {
                chain_taken[c] = true;
                revived.push((ri, c));
            }
        }
        let mut chains: Vec<Option<ActiveTrack>> = chains.into_iter().map(Some).collect();
        let mut pool: Vec<Option<ActiveTrack>> = std::mem::take(&mut self.pool)
            .into_iter()
            .map(Some)
            .collect();
        for (ri, c) in revived {
            let mut old = pool[ri].take().expect("each pool row matched once");
            old.dets
                .extend(chains[c].take().expect("each chain matched once").dets);
            self.set_owner(&old);
            let at = self.active.partition_point(|t| t.uid < old.uid);
            self.active.insert(at, old);
            self.stats.tracks_stitched += 1;
        }
        self.pool = pool.into_iter().flatten().collect();
        chains.into_iter().flatten().collect()
    }

    /// Fit, validate and number the given ended tracks — here, or, after
    /// [`Tracker::defer_fits`], later by the [`Finaliser`] (with the
    /// outlier gate and noise of this moment either way).
    fn finalise(&mut self, ended: Vec<ActiveTrack>) -> Vec<LinkedTrack> {
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

/// Offset (px, as f32) from detection `c` to the nearest other detection
/// of `dets` (indexed by `grid`) within [`NEIGHBOUR_RADIUS`];
/// [`NO_NEIGHBOUR`] when there is none.
fn nearest_neighbour(
    grid: &GridIndex,
    dets: &[Det],
    c: usize,
    near: &mut Vec<(u32, f64)>,
) -> [f32; 2] {
    let d = &dets[c];
    near.clear();
    grid.within(d.x, d.y, NEIGHBOUR_RADIUS, near);
    near.iter()
        .filter(|&&(j, _)| j as usize != c)
        .min_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)))
        .map_or(NO_NEIGHBOUR, |&(j, _)| {
            let o = &dets[j as usize];
            [(o.x - d.x) as f32, (o.y - d.y) as f32]
        })
}

/// Cut an ended track at its steps (`TrackParams::step_split`, see
/// [`step::step_cuts`]): the pieces, in order, each to be fitted as a track
/// of its own, and the number of cuts. A pure function of the track, so
/// it runs on the finaliser's parallel workers, not on the linking thread.
fn cut_at_steps(
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
    tracks: Vec<ActiveTrack>,
    sigma: f64,
    gate: f64,
    /// The tracker's local-flow samples since the previous batch.
    flow_samples: Vec<local_flow::FlowSample>,
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
    params: TrackParams,
    accel_prior: fit::AccelPrior,
    /// A copy of the tracker's local flow, brought up to date from each
    /// batch's `flow_samples` (the ghost test of short tracks).
    flow: local_flow::LocalFlow,
    /// The same samples with their positions: the local linear flow of
    /// the output fit's velocity prior (`TrackParams::velocity_prior`).
    linear_flow: local_flow::FlowHistory,
    /// The prior's variance as measured on the tracks kept so far.
    prior_calibration: local_flow::PriorCalibration,
    next_id: u64,
    /// Numbered tracks waiting for [`Finaliser::refit_held`].
    held: Vec<(LinkedTrack, Box<Refit>)>,
}

impl Finaliser {
    fn new(params: TrackParams) -> Self {
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
const RUN_PRIOR_RADIUS: f64 = 24.0;

/// Its half window (pulses): 2 gave 0.055, 3 0.049, 5 0.047 px/pulse at
/// twice the cost of the queries.
const RUN_PRIOR_HALF_WINDOW: i64 = 3;

/// The two parts of a split image: event-weighted centroid (px) and
/// events of the part given to the first and to the second prediction.
pub type SplitParts = [(f64, f64, u32); 2];

/// A track's predicted position and search radius (px) at a pulse.
pub type Prediction = (f64, f64, f64);

/// Most pixels of an image that [`split_by_predictions`] tries to split
/// (it tries every partition; one or two particle images of 1–4 events
/// cover 2–5 pixels, and clustering already splits images ≥ 3 px wide).
pub const MAX_SPLIT_PIXELS: usize = 12;

/// Integer event sums (Σw, Σw·x, Σw·y) of a set of pixels: exact, so that
/// every way of adding them up gives the same cost bit for bit.
type Sums = (i64, i64, i64);

/// Cost of giving the pixels with sums `b` to prediction `pb` and the
/// rest (`total − b`) to `pa`: each part's centroid's squared distance
/// from its prediction over the squared search radius (the assignment's
/// cost); `None` when a part has no events.
fn split_cost(total: Sums, b: Sums, pa: Prediction, pb: Prediction) -> Option<f64> {
    let a = (total.0 - b.0, total.1 - b.1, total.2 - b.2);
    if a.0 == 0 || b.0 == 0 {
        return None;
    }
    let c = |s: Sums, p: Prediction| {
        let (x, y) = (s.1 as f64 / s.0 as f64, s.2 as f64 / s.0 as f64);
        ((x - p.0).powi(2) + (y - p.1).powi(2)) / (p.2 * p.2)
    };
    Some(c(a, pa) + c(b, pb))
}

fn sums_of(p: &ImagePixel) -> Sums {
    let w = p.count as i64;
    (w, w * p.x as i64, w * p.y as i64)
}

/// Split the pixels of one image between two predictions `a` and `b`
/// (x, y, search radius): of all partitions into two non-empty parts, the
/// one of least summed assignment cost (each part's centroid against its
/// own prediction, see [`split_cost`]; on equal costs the partition whose
/// mask — pixel i in part b = bit i — is smallest). `side` receives per
/// pixel `false` (a) or `true` (b). Returns the cost and the parts, or
/// `None` for fewer than 2 or more than [`MAX_SPLIT_PIXELS`] pixels.
///
/// Every partition is tried, in Gray-code order so that each step moves
/// one pixel and updates the parts' sums in O(1) (up to 4096 partitions;
/// images of 2–4 pixels have 2–14). Which pixels are whose cannot be read
/// from the image alone (both particles' images overlap): the predictions
/// decide. [`split_by_predictions_reference`] evaluates every partition
/// from scratch.
pub fn split_by_predictions(
    pixels: &[ImagePixel],
    a: Prediction,
    b: Prediction,
    side: &mut Vec<bool>,
) -> Option<(f64, SplitParts)> {
    let n = pixels.len();
    if !(2..=MAX_SPLIT_PIXELS).contains(&n) {
        return None;
    }
    let total = pixels
        .iter()
        .map(sums_of)
        .fold((0, 0, 0), |s, q| (s.0 + q.0, s.1 + q.1, s.2 + q.2));
    let (mut mask, mut inb) = (0u32, (0i64, 0i64, 0i64));
    let mut best: Option<(f64, u32)> = None;
    for i in 1u32..1 << n {
        // Gray code: step i flips bit trailing_zeros(i).
        let bit = i.trailing_zeros() as usize;
        let q = sums_of(&pixels[bit]);
        let sign = if mask >> bit & 1 == 1 { -1 } else { 1 };
        mask ^= 1 << bit;
        inb = (inb.0 + sign * q.0, inb.1 + sign * q.1, inb.2 + sign * q.2);
        if let Some(c) = split_cost(total, inb, a, b) {
            if best.map_or(true, |(bc, bm)| c < bc || (c == bc && mask < bm)) {
                best = Some((c, mask));
            }
        }
    }
    let (cost, mask) = best?;
    side.clear();
    side.extend((0..n).map(|i| mask >> i & 1 == 1));
    Some((cost, parts_of(pixels, side)))
}

/// Centroids and events of the two sides of a partition (both non-empty).
fn parts_of(pixels: &[ImagePixel], side: &[bool]) -> SplitParts {
    let mut acc = [(0i64, 0i64, 0i64); 2];
    for (p, &s) in pixels.iter().zip(side) {
        let q = sums_of(p);
        let a = &mut acc[s as usize];
        *a = (a.0 + q.0, a.1 + q.1, a.2 + q.2);
    }
    acc.map(|(w, sx, sy)| (sx as f64 / w as f64, sy as f64 / w as f64, w as u32))
}

/// [`split_by_predictions`] by plain enumeration: every mask from 1 to
/// 2ⁿ − 2 in increasing order, each part's sums added up afresh.
pub fn split_by_predictions_reference(
    pixels: &[ImagePixel],
    a: Prediction,
    b: Prediction,
) -> Option<(f64, Vec<bool>, SplitParts)> {
    let n = pixels.len();
    if !(2..=MAX_SPLIT_PIXELS).contains(&n) {
        return None;
    }
    let mut best: Option<(f64, u32)> = None;
    let total = pixels.iter().fold((0, 0, 0), |s, p| {
        let q = sums_of(p);
        (s.0 + q.0, s.1 + q.1, s.2 + q.2)
    });
    for mask in 1u32..(1 << n) - 1 {
        let mut inb = (0, 0, 0);
        for (i, p) in pixels.iter().enumerate() {
            if mask >> i & 1 == 1 {
                let q = sums_of(p);
                inb = (inb.0 + q.0, inb.1 + q.1, inb.2 + q.2);
            }
        }
        let c = split_cost(total, inb, a, b).expect("both parts hold pixels");
        if best.map_or(true, |(bc, _)| c < bc) {
            best = Some((c, mask));
        }
    }
    let (cost, mask) = best?;
    let side: Vec<bool> = (0..n).map(|i| mask >> i & 1 == 1).collect();
    let parts = parts_of(pixels, &side);
    Some((cost, side, parts))
}

/// Tracks ahead of the current one whose recent detections are prefetched.
const PREFETCH_AHEAD: usize = 6;

/// Append the indices of the `false` entries of `used` to `idx` (a plain
/// loop: the filtered `extend` it replaces cost ~20 instructions per
/// particle, 4 % of the linking).
fn unused_indices(used: &[bool], idx: &mut Vec<usize>) {
    for (i, &u) in used.iter().enumerate() {
        if !u {
            idx.push(i);
        }
    }
}

/// Ask the CPU to fetch the last `window` detections of a track into the
/// cache. Every pulse the tracker touches the recent history of each of
/// its ~3000 active tracks, each in its own heap block: without this the
/// walk is one cache miss after another (~40 % of the tracking thread's
/// cycles at full frame). A hint only: it changes no result.
#[inline]
fn prefetch_window(dets: &[Det], window: usize) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        let tail = &dets[dets.len().saturating_sub(window)..];
        let bytes = std::mem::size_of_val(tail);
        let base = tail.as_ptr() as *const i8;
        for off in (0..bytes).step_by(64) {
            // SAFETY: a prefetch never faults, and the address is inside `tail`.
            unsafe { _mm_prefetch::<_MM_HINT_T0>(base.wrapping_add(off)) };
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (dets, window);
}

/// What [`finalise_one`] made of an ended track.
enum Finalised {
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
struct Refit {
    own: Vec<u64>,
    period_s: f64,
    fit_vars: Vec<f64>,
}

/// Clean (outliers, unconfirmed tail), validate and fit one ended track;
/// `gate` is the outlier gate in px. Pure: the numbering and the counters
/// are [`Tracker::finalise`]'s.
fn finalise_one(
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
enum Verdict {
    Short,
    Ghost,
    Keep { by_flow: bool },
}

/// The length rules with the local-flow ghost test: below
/// `min_length_flow` detections a track is short; below
/// `ghost_check_length` it is tested against the local flow and dropped
/// as a ghost when it disagrees; below `min_length` it needs the flow's
/// approval (an unknown flow makes it short).
fn short_track_verdict(
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
fn remove_outliers(dets: &mut Vec<Det>, window: usize, gate: f64) {
    remove_outliers_with(dets, window, gate, true)
}

/// [`remove_outliers`] where the path turns: a detection whose window's
/// heading changes visibly (the output fit's screen, position noise
/// `sigma`) is predicted by the turning path through the window
/// ([`turn`]) instead of the quadratic, which would take good detections
/// of a vortex core for outliers and the stray one a young track took
/// there for good.
fn remove_outliers_turning(dets: &mut Vec<Det>, window: usize, gate: f64, sigma: f64) {
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
fn remove_outliers_with(dets: &mut Vec<Det>, window: usize, gate: f64, grid: bool) {
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
fn trim_unconfirmed_tail(dets: &mut Vec<Det>, confirm: usize) {
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

/// Detections of each piece the stitch test's joint turning path fits.
const JOINT_SIDE: usize = 8;

/// Cost of joining `old` to `new` (which starts after it) by one turning
/// path ([`turn::turn_rss`]) through the last [`JOINT_SIDE`] detections
/// of `old` and the first of `new`: its residual sum of squares over the
/// position noise `sigma`², in units of the χ² bound `dof + 3·√(2 dof)`
/// (dof = 2·points − 7); ≤ 1 is a fit by noise alone. `None`: fewer than
/// 6 detections on the old side or 10 in all.
fn joint_turn_cost(old: &[Det], new: &[Det], sigma: f64) -> Option<f64> {
    let a = old.len().min(JOINT_SIDE);
    let b = new.len().min(JOINT_SIDE);
    if a < 6 || a + b < 10 || sigma <= 0.0 {
        return None;
    }
    let t0 = old[old.len() - 1].pulse;
    let (mut tau, mut xs, mut ys) = (
        [0.0; 2 * JOINT_SIDE],
        [0.0; 2 * JOINT_SIDE],
        [0.0; 2 * JOINT_SIDE],
    );
    for (i, d) in old[old.len() - a..].iter().chain(&new[..b]).enumerate() {
        tau[i] = (d.pulse - t0) as f64;
        xs[i] = d.x;
        ys[i] = d.y;
    }
    let m = a + b;
    let rss = turn::turn_rss(&tau[..m], &xs[..m], &ys[..m])?;
    let dof = (2 * m - 7) as f64;
    Some(rss / (sigma * sigma) / (dof + 3.0 * (2.0 * dof).sqrt()))
}

/// Extrapolation of the positions of `dets` (the `window` detections
/// nearest to `pulse`) to pulse `pulse`: the turning path ([`turn`],
/// with `turn_model`, from 6 detections on), else a line through the
/// nearest `INIT_FRAMES` (`sigma`: the position noise).
fn extrapolate(
    dets: &[Det],
    window: usize,
    pulse: i64,
    p: &TrackParams,
    sigma: f64,
) -> Option<(f64, f64)> {
    let n = dets.len();
    let forward = pulse >= dets[n - 1].pulse;
    let w = window.min(n).clamp(1, 64);
    if p.turn_model && w >= 2 * INIT_FRAMES - 2 {
        let win = if forward { &dets[n - w..] } else { &dets[..w] };
        let (mut tau, mut xs, mut ys) = ([0.0; 64], [0.0; 64], [0.0; 64]);
        for (i, d) in win.iter().enumerate() {
            tau[i] = (d.pulse - pulse) as f64;
            xs[i] = d.x;
            ys[i] = d.y;
        }
        if let Some(f) = turn::turn_eval(&tau[..w], &xs[..w], &ys[..w], 0.0, true) {
            return Some((f.x, f.y));
        }
    }
    let w = if p.turn_model { w.min(INIT_FRAMES) } else { w };
    let win = if forward { &dets[n - w..] } else { &dets[..w] };
    let tau: Vec<f64> = win.iter().map(|d| d.pulse as f64 - pulse as f64).collect();
    let xs: Vec<f64> = win.iter().map(|d| d.x).collect();
    let ys: Vec<f64> = win.iter().map(|d| d.y).collect();
    if p.turn_model {
        return young_prediction(&tau, &xs, &ys, 0.0, sigma, 0.0).map(|(x, y, _)| (x, y));
    }
    fit::fit_eval(&tau, &xs, &ys, 1, 0.0).map(|f| (f.x, f.y))
}

/// The mean pulse period (s) over a track's detections: the output fit's
/// time unit.
fn fit_period_s(dets: &[Det]) -> f64 {
    let n = dets.len();
    ((dets[n - 1].t_us - dets[0].t_us) / (dets[n - 1].pulse - dets[0].pulse).max(1) as f64)
        .max(1e-9)
        * 1e-6
}

/// The output fit's velocity prior as one batch of the finaliser uses it:
/// the flow, the calibration's variance factor (`None`: not calibrated
/// yet, the prior is only checked) with the fits' typical noise variance,
/// and `TrackParams::velocity_prior`.
struct VelocityPriorUse<'a> {
    flow: &'a local_flow::FlowHistory,
    scale: Option<(f64, f64)>,
    strength: f64,
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
fn fit_track_with(
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

/// Link a whole set of particles (any order; grouped by pulse, pulses in
/// increasing order) into tracks. The detection serials of the returned
/// tracks index the particles sorted by `(pulse, input order)`; the second
/// value is that sorted order as indices into `particles`.
pub fn link_linked(
    particles: &[Particle],
    params: &TrackParams,
) -> Result<(Vec<LinkedTrack>, Vec<usize>, TrackerStats)> {
    let mut order: Vec<usize> = (0..particles.len()).collect();
    order.sort_by_key(|&i| particles[i].pulse); // stable: keeps input order within a pulse
    let sorted: Vec<Particle> = order.iter().map(|&i| particles[i]).collect();
    let mut tracker = Tracker::new(params.clone())?;
    let mut out = Vec::new();
    let mut s = 0;
    while s < sorted.len() {
        let mut e = s;
        while e < sorted.len() && sorted[e].pulse == sorted[s].pulse {
            e += 1;
        }
        out.extend(tracker.push_linked(sorted[s].pulse, sorted[s].t_us, &sorted[s..e])?);
        s = e;
    }
    let (rest, stats) = tracker.finish();
    out.extend(rest);
    Ok((out, order, stats))
}

/// Link particles into tracks (see [`link_linked`]).
pub fn link(particles: &[Particle], params: &TrackParams) -> Result<Vec<Track>> {
    Ok(link_linked(particles, params)?
        .0
        .into_iter()
        .map(|t| t.track)
        .collect())
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

#[cfg(test)]
mod tests {
    use super::*;

    fn particle(pulse: i64, x: f64, y: f64) -> Particle {
        Particle {
            pulse,
            t_us: pulse as f64 * 200.0,
            x,
            y,
            n_events: 1,
            n_pixels: 1,
            extent_x: 1.0,
            extent_y: 1.0,
            first_latency_us: 0.0,
        }
    }

    #[test]
    fn two_crossing_tracks_are_followed_with_exact_velocity() {
        // Two particles on straight lines crossing at pulse 10; 5 kHz.
        let mut ps = Vec::new();
        for k in 0..20 {
            let t = k as f64;
            ps.push(particle(k, 10.0 + 6.0 * t, 50.0 + 0.5 * t));
            ps.push(particle(k, 130.0 - 6.0 * t, 60.0 - 0.5 * t));
        }
        let tracks = link(&ps, &TrackParams::default()).unwrap();
        assert_eq!(tracks.len(), 2);
        for tr in &tracks {
            assert_eq!(tr.points.len(), 20);
            for pt in &tr.points {
                assert!((pt.u.abs() - 6.0 * 5000.0).abs() < 1e-6, "u = {}", pt.u);
                assert!((pt.v.abs() - 0.5 * 5000.0).abs() < 1e-6);
                assert!(pt.ax.abs() < 1e-3 && !pt.interpolated);
            }
            // Same direction from start to end (not swapped at the crossing).
            assert_eq!(tr.points[0].u.signum(), tr.points[19].u.signum());
        }
    }

    #[test]
    fn split_matches_the_brute_force_partition() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(11);
        let mut side = Vec::new();
        let mut split = 0;
        for case in 0..3000 {
            let n = 1 + case % 9;
            let mut pixels: Vec<ImagePixel> = Vec::new();
            while pixels.len() < n {
                let p = ImagePixel {
                    x: rng.gen_range(100..104),
                    y: rng.gen_range(200..204),
                    count: rng.gen_range(1..4),
                };
                if !pixels.iter().any(|q| (q.x, q.y) == (p.x, p.y)) {
                    pixels.push(p);
                }
            }
            let pred = |rng: &mut rand_pcg::Pcg64| {
                (
                    rng.gen_range(99.0..105.0),
                    rng.gen_range(199.0..205.0),
                    rng.gen_range(0.5..3.0),
                )
            };
            let (a, b) = (pred(&mut rng), pred(&mut rng));
            let fast = split_by_predictions(&pixels, a, b, &mut side);
            let reference = split_by_predictions_reference(&pixels, a, b);
            match (fast, reference) {
                (None, None) => assert!(n < 2, "case {case}"),
                (Some((c, parts)), Some((rc, rside, rparts))) => {
                    assert_eq!(c.to_bits(), rc.to_bits(), "case {case}");
                    assert_eq!(side, rside, "case {case}");
                    assert_eq!(parts, rparts, "case {case}");
                    assert_eq!(
                        parts[0].2 + parts[1].2,
                        pixels.iter().map(|p| p.count).sum::<u32>()
                    );
                    split += 1;
                }
                (f, r) => panic!("case {case}: {f:?} vs {r:?}"),
            }
        }
        assert!(split > 2000);
        // Two one-event pixels, each near one prediction: each to its own.
        let two = [
            ImagePixel {
                x: 10,
                y: 10,
                count: 1,
            },
            ImagePixel {
                x: 11,
                y: 10,
                count: 1,
            },
        ];
        let (c, parts) =
            split_by_predictions(&two, (11.1, 10.1, 1.5), (9.8, 9.9, 1.5), &mut side).unwrap();
        assert_eq!(side, [true, false]);
        assert_eq!(parts, [(11.0, 10.0, 1), (10.0, 10.0, 1)]);
        assert!((c - (0.02 + 0.05) / 2.25).abs() < 1e-12);
    }

    /// Two particles crossing at a shallow angle: their one-event images
    /// merge at pulses 9 (1 px apart), 10 (one pixel: nothing to split)
    /// and 11. With the pixels, the merged two-pixel images are split and
    /// each track gets its own particle's pixel; without, nothing is split.
    #[test]
    fn merged_images_are_split_between_their_tracks() {
        use crate::cluster::{cluster_pulse_with_pixels, ClusterParams};
        use crate::events::EventChunk;
        use crate::pulses::PulseEvents;
        let paths = |k: i64| [(20 + 5 * k, 50), (20 + 5 * k, 60 - k)];
        let run = |split: bool| {
            let mut t = Tracker::new(TrackParams {
                split_merged: split,
                ..Default::default()
            })
            .unwrap();
            t.record_splits(true);
            let mut tracks = Vec::new();
            let mut splits = Vec::new();
            for k in 0..21i64 {
                let mut ev = EventChunk::default();
                for (x, y) in paths(k) {
                    ev.push(k * 200 + 50, x as u16, y as u16, 1);
                }
                let pe = PulseEvents {
                    index: k,
                    start_us: k as f64 * 200.0,
                    events: ev,
                };
                let (ps, px) = cluster_pulse_with_pixels(&pe, &ClusterParams::default());
                tracks.extend(
                    t.push_linked_with_pixels(k, pe.start_us, &ps, Some(&px))
                        .unwrap(),
                );
                splits.extend(t.take_splits());
            }
            let (rest, stats) = t.finish();
            tracks.extend(rest);
            (tracks, splits, stats)
        };
        let (tracks, splits, stats) = run(true);
        assert_eq!(stats.images_split, 2);
        assert_eq!(splits.len(), 4);
        assert_eq!(tracks.len(), 2);
        for tr in &tracks {
            // Which particle: particle 0 stays at y = 50.
            let p = (tr.track.points[0].y - 50.0).abs() > 5.0;
            let mine: Vec<&SplitDetection> = splits
                .iter()
                .filter(|s| tr.detections.contains(&Some(s.serial)))
                .collect();
            assert_eq!(mine.len(), 2, "one part at pulse 9, one at 11");
            for s in mine {
                assert!(s.serial & SPLIT_SERIAL_BIT != 0);
                assert_eq!((s.x, s.y), {
                    let (x, y) = paths(s.pulse)[p as usize];
                    (x as f64, y as f64)
                });
            }
            assert_eq!(tr.track.points.len(), 21);
        }
        let (_, splits, stats) = run(false);
        assert_eq!((stats.images_split, splits.len()), (0, 0));
    }

    #[test]
    fn gaps_are_bridged_and_marked() {
        let mut ps = Vec::new();
        for k in 0..15 {
            if k == 7 || k == 8 {
                continue;
            }
            ps.push(particle(k, 5.0 + 4.0 * k as f64, 20.0));
        }
        let tracks = link(&ps, &TrackParams::default()).unwrap();
        assert_eq!(tracks.len(), 1);
        let pts = &tracks[0].points;
        assert_eq!(pts.len(), 15);
        assert!(pts[7].interpolated && pts[8].interpolated && !pts[9].interpolated);
        assert!((pts[7].x - 33.0).abs() < 1e-9);
        assert!((pts[7].t_us - 1400.0).abs() < 1e-9);
    }

    #[test]
    fn long_tracks_come_out_in_segments_covering_every_pulse_once() {
        let ps: Vec<Particle> = (0..130)
            .map(|k| particle(k, 5.0 + 2.0 * k as f64, 20.0 + 0.5 * k as f64))
            .collect();
        let p = TrackParams {
            max_track_length: 44, // ≥ 2 × the largest fit window (21)
            ..Default::default()
        };
        let tracks = link(&ps, &p).unwrap();
        assert!(tracks.len() >= 3, "{} segments", tracks.len());
        let pulses: Vec<i64> = tracks
            .iter()
            .flat_map(|t| t.points.iter().map(|q| q.pulse))
            .collect();
        assert_eq!(pulses, (0..130).collect::<Vec<_>>());
        for q in tracks.iter().flat_map(|t| &t.points) {
            assert!((q.u - 2.0 * 5000.0).abs() < 1e-6 && (q.v - 0.5 * 5000.0).abs() < 1e-6);
        }
        assert!(Tracker::new(TrackParams {
            max_track_length: 10,
            ..Default::default()
        })
        .is_err());
    }

    #[test]
    fn session_10_options_refuse_bad_values_by_name() {
        for bad in [-1.0, f64::NAN, f64::INFINITY] {
            let e = Tracker::new(TrackParams {
                step_split_hinted: bad,
                ..Default::default()
            })
            .err()
            .expect("a bad hinted step threshold is refused");
            assert!(e.to_string().contains("step_split_hinted"), "{e}");
        }
        let e = Tracker::new(TrackParams {
            velocity_prior_two_pass: true,
            velocity_prior: 0.0,
            ..Default::default()
        })
        .err()
        .expect("two passes without a prior are refused");
        assert!(e.to_string().contains("velocity_prior_two_pass"), "{e}");
        assert!(Tracker::new(TrackParams {
            velocity_prior_two_pass: true,
            velocity_prior: 1.0,
            step_split_hinted: 8.0,
            ..Default::default()
        })
        .is_ok());
    }

    #[test]
    fn init_gap_starts_a_particle_never_seen_four_times_in_a_row() {
        // Seen at pulses 0, 1, 3, 4, 5 (runs of 2 and 3): no four-frame
        // chain, but four detections in the five pulses 0..=4. A second
        // particle far away makes every pulse non-empty.
        let mut ps: Vec<Particle> = (0..6)
            .map(|k| particle(k, 200.0 + 3.0 * k as f64, 200.0))
            .collect();
        ps.extend(
            [0, 1, 3, 4, 5]
                .iter()
                .map(|&k| particle(k, 10.0 + 5.0 * k as f64, 30.0 + 0.5 * k as f64)),
        );
        let off = TrackParams {
            init_gap: false,
            ..Default::default()
        };
        assert_eq!(link(&ps, &off).unwrap().len(), 1);
        // The defaults (gapped chains and the ghost test): with no local
        // flow around (no track of 6+ detections yet) a gapped chain is
        // not started.
        assert_eq!(link(&ps, &TrackParams::default()).unwrap().len(), 1);
        // Without the ghost test at initialisation (with it, a chain with
        // a gap needs a known local flow, and this scene has none).
        let p = TrackParams {
            init_gap: true,
            ghost_check_init: false,
            ..Default::default()
        };
        let tracks = link(&ps, &p).unwrap();
        assert_eq!(tracks.len(), 2);
        let pts = &tracks
            .iter()
            .find(|t| t.points[0].x < 100.0)
            .unwrap()
            .points;
        assert_eq!(pts.len(), 6);
        assert!(pts[2].interpolated && !pts[3].interpolated);
        for q in pts {
            assert!((q.u - 5.0 * 5000.0).abs() < 1e-6, "u = {}", q.u);
        }
        // With gap-free chains around, the gap-tolerant pass adds nothing.
        let ps: Vec<Particle> = (0..12)
            .map(|k| particle(k, 10.0 + 5.0 * k as f64, 30.0))
            .collect();
        assert_eq!(link(&ps, &p).unwrap(), link(&ps, &off).unwrap());
    }

    #[test]
    fn long_gaps_are_stitched() {
        let mut ps = Vec::new();
        for k in 0..30 {
            if (10..13).contains(&k) {
                continue; // 3 missed pulses > max_gap
            }
            ps.push(particle(k, 5.0 + 3.0 * k as f64, 20.0 + 0.1 * k as f64));
        }
        let (tracks, _, stats) = link_linked(&ps, &TrackParams::default()).unwrap();
        assert_eq!(stats.tracks_stitched, 1);
        assert_eq!(tracks.len(), 1);
        assert_eq!(tracks[0].track.points.len(), 30);
    }

    #[test]
    fn bad_parameters_and_input() {
        let p = TrackParams {
            max_disp: 0.0,
            ..Default::default()
        };
        assert!(Tracker::new(p)
            .err()
            .unwrap()
            .to_string()
            .contains("max_disp"));
        let p = TrackParams {
            min_length: 2,
            ..Default::default()
        };
        assert!(Tracker::new(p)
            .err()
            .unwrap()
            .to_string()
            .contains("min_length"));
        let mut t = Tracker::new(TrackParams::default()).unwrap();
        t.push(5, 0.0, &[]).unwrap();
        assert!(t.push(5, 0.0, &[]).is_err());
        assert!(t.push(6, 0.0, &[particle(6, f64::NAN, 1.0)]).is_err());
        let no_pixels = crate::cluster::ParticlePixels::default();
        let err = t
            .push_linked_with_pixels(7, 0.0, &[particle(7, 1.0, 1.0)], Some(&no_pixels))
            .err()
            .unwrap();
        assert!(err.to_string().contains("pixel table"), "{err}");
    }

    #[test]
    fn grid_prior_is_bilinear() {
        let g = FlowPrior::grid(
            0.0,
            0.0,
            10.0,
            10.0,
            2,
            2,
            vec![0.0, 10.0, 20.0, 30.0],
            vec![0.0; 4],
        )
        .unwrap();
        let (u, _) = (g.0)(5.0, 5.0);
        assert!((u - 15.0).abs() < 1e-12);
        assert!(((g.0)(-5.0, 100.0).0 - 20.0).abs() < 1e-12);
        assert!(FlowPrior::grid(0.0, 0.0, 1.0, 1.0, 2, 2, vec![0.0; 3], vec![0.0; 4]).is_err());
    }

    #[test]
    fn tabulated_outlier_pass_matches_the_reference() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(8);
        let (mut removed, mut kept) = (0, 0);
        for case in 0..40 {
            let mut dets = Vec::new();
            let mut pulse = 0i64;
            for k in 0..[7, 12, 40, 90][case % 4] {
                if case % 2 == 1 && rng.gen_range(0.0..1.0) < 0.05 {
                    pulse += rng.gen_range(1..=2);
                }
                // Noise 0.2 px and now and then a stray detection.
                let stray = if rng.gen_range(0.0..1.0) < 0.05 {
                    3.0
                } else {
                    0.0
                };
                let s = k as f64;
                dets.push(Det {
                    serial: k as u64,
                    pulse,
                    t_us: pulse as f64 * 200.0,
                    x: 100.0 + 6.0 * s + 0.05 * s * s + rng.gen_range(-0.2..0.2) + stray,
                    y: 300.0 - 2.0 * s + rng.gen_range(-0.2..0.2) - stray,
                    nb: NO_NEIGHBOUR,
                });
                pulse += 1;
            }
            let (mut fast, mut reference) = (dets.clone(), dets.clone());
            remove_outliers_with(&mut fast, OUTLIER_WINDOW, 1.0, true);
            remove_outliers_with(&mut reference, OUTLIER_WINDOW, 1.0, false);
            let serials = |d: &[Det]| d.iter().map(|d| d.serial).collect::<Vec<_>>();
            assert_eq!(serials(&fast), serials(&reference), "case {case}");
            removed += dets.len() - fast.len();
            kept += fast.len();
        }
        assert!(removed > 5 && kept > 500, "{removed} {kept}");
    }

    #[test]
    fn tabulated_output_fit_matches_the_reference() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
        let params = TrackParams::default();
        let mut compared = 0;
        let mut prior_moved = 0;
        for case in 0..12 {
            // Pulse times as the pulses stage gives them (first + k·period,
            // far into a recording), or jittered (off the grid: the
            // reference path throughout).
            let (t0, period) = (3.7e6 + 1234.5 * case as f64, 199.987);
            let jitter = if case % 4 == 3 { 0.01 } else { 0.0 };
            let mut dets = Vec::new();
            let mut pulse = 1000 * case as i64;
            let n = [12, 150, 60, 30][case % 4];
            for k in 0..n {
                // Gaps of 1–3 pulses in half of the tracks.
                if case % 2 == 1 && k > 0 && rng.gen_range(0.0..1.0) < 0.03 {
                    pulse += rng.gen_range(1..=3);
                }
                let s = k as f64;
                dets.push(Det {
                    serial: k as u64,
                    pulse,
                    t_us: t0 + pulse as f64 * period + rng.gen_range(-jitter..=jitter),
                    x: 200.0
                        + 5.0 * s
                        + 30.0 * (0.02 * case as f64 * s).sin()
                        + rng.gen_range(-0.3..0.3),
                    y: 400.0 - 3.0 * s + 0.01 * s * s + rng.gen_range(-0.3..0.3),
                    nb: NO_NEIGHBOUR,
                });
                pulse += 1;
            }
            let sigma = 0.2;
            let mut grid_fits = 0;
            // Half the cases with the curvature prior.
            let accel = [0.0, 0.0, 0.08, 0.3][(case / 2) % 4];
            // Every third case with the velocity prior: links of a flow
            // close to the track's own motion all along it.
            let mut flow = local_flow::FlowHistory::new(FLOW_CELL, FLOW_MEMORY, 4, 8);
            for d in &dets {
                for k in 0..12 {
                    let (dx, dy) = ((k % 4) as f64 * 9.0 - 13.0, (k / 4) as f64 * 11.0 - 11.0);
                    flow.add_sample(local_flow::FlowSample {
                        pulse: d.pulse,
                        x: d.x + dx,
                        y: d.y + dy,
                        u: 5.2 + 0.01 * dx + rng.gen_range(-0.3..0.3),
                        v: -3.1 + rng.gen_range(-0.3..0.3),
                    });
                }
            }
            let with_prior = VelocityPriorUse {
                flow: &flow,
                scale: Some((1.0, 0.0005)),
                strength: 1.0,
            };
            let prior = (case % 3 == 2).then_some(&with_prior);
            let (mut cal_fast, mut cal_reference) = Default::default();
            let (fp, fs, frms) = fit_track_with(
                &dets,
                &params,
                sigma,
                accel,
                prior,
                &mut cal_fast,
                true,
                &mut grid_fits,
                None,
            );
            let (rp, rs, rrms) = fit_track_with(
                &dets,
                &params,
                sigma,
                accel,
                prior,
                &mut cal_reference,
                false,
                &mut 0,
                None,
            );
            // On the grid the tabulated path takes every detection whose
            // pilot window has no gap; jittered times never.
            if jitter > 0.0 {
                assert_eq!(grid_fits, 0, "case {case}");
            } else if case % 2 == 0 {
                assert_eq!(grid_fits, n, "case {case}");
            } else {
                assert!(grid_fits > 0, "case {case}");
            }
            assert_eq!(fs, rs);
            assert_eq!(fp.len(), rp.len());
            if prior.is_some() {
                // The prior moved the noisy points (the ends), and both
                // paths checked it at the same points.
                let (plain, _, _) = fit_track_with(
                    &dets,
                    &params,
                    sigma,
                    accel,
                    None,
                    &mut Default::default(),
                    true,
                    &mut 0,
                    None,
                );
                let moved = plain.iter().zip(&fp).filter(|(a, b)| a.u != b.u).count();
                assert!(moved > 0, "case {case}");
                prior_moved += moved;
                assert_eq!(
                    cal_fast.typical_fit_variance(),
                    cal_reference.typical_fit_variance(),
                    "case {case}"
                );
            }
            assert!((frms - rrms).abs() <= 1e-9 * rrms.max(1.0));
            for (f, r) in fp.iter().zip(&rp) {
                assert_eq!(
                    (f.pulse, f.t_us.to_bits(), f.interpolated),
                    (r.pulse, r.t_us.to_bits(), r.interpolated)
                );
                // 1e-9 relative, absolute below 1 px/pulse (px/pulse²):
                // the reference's τ are off the integers by ~1e-11 here.
                let (pu, pa) = (1e6 / period, (1e6 / period).powi(2));
                for (a, b, unit) in [
                    (f.x, r.x, 1.0),
                    (f.y, r.y, 1.0),
                    (f.u, r.u, pu),
                    (f.v, r.v, pu),
                    (f.ax, r.ax, pa),
                    (f.ay, r.ay, pa),
                ] {
                    assert!(
                        (a - b).abs() <= 1e-9 * b.abs().max(unit),
                        "case {case} pulse {}: {a} vs {b}",
                        f.pulse
                    );
                }
                compared += 1;
            }
        }
        assert!(compared > 500);
        assert!(prior_moved > 20, "{prior_moved}");
    }
}
