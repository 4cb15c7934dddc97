//! A small synthetic PTV scene with ground truth, and the link scores.
//!
//! The full simulator (`crate::sim`) models the sensor and its readout; this
//! generator models only what clustering and tracking see — a few events per
//! particle per pulse around the particle's image centre, noise events, and
//! particles that leave and enter the light sheet — so that the PTV stage
//! can be tested and benchmarked on its own, quickly, against exact truth:
//! every event knows which particle (or noise) made it.
//!
//! # Scene
//! A steady, curved 2-D flow on a `width × height` frame,
//! `u = U (0.5 + 0.4 sin(2π y/L))`, `v = 0.35 U cos(2π x/L)` (px per pulse,
//! `L = flow_scale`),
//! with `U` set so the largest speed is `max_disp` px per pulse. Particles
//! (density `ppp` per pixel) are advected with RK4; a particle leaves the
//! sheet with probability `1/sheet_life` per pulse or by crossing the frame
//! edge, and a new one appears at a random place so the density stays put.
//! Each pulse, particle `i` fires with probability `p_detect`, then
//! `1 + Poisson(m_i - 1)` ON events (`m_i` uniform in
//! `events_per_particle`, the mean events of a firing particle) on pixels drawn from a Gaussian image of standard
//! deviation `image_sigma` px around its centre; `noise_fraction` times as
//! many noise events land on uniformly random pixels.
//!
//! # Link scores (the definition used in tests and docs)
//! A detection (particle) belongs to the truth particle that made most of
//! its events (none if noise made most). When two particles made equally
//! many events of one merged image, it belongs to the one whose true
//! position is nearest its centroid (noise never wins a tie). (Counting
//! such ties as noise would score every link through a 1 + 1 event
//! merged image as wrong, even the link of the particle the image sits
//! on.) A *link* is a pair of consecutive
//! detections of one output track (across a bridged gap, too); it is
//! correct when both detections belong to the same truth particle.
//! *Precision* = correct links / output links. A wrong link whose two
//! detections both hold events of one truth particle (the track follows
//! it through an image merged with another particle's, which no detector
//! could have resolved) is *merged-consistent*; `precision_merged_ok`
//! counts those as correct too — both are reported. A *truth link* is a truth
//! particle detected in two consecutive pulses k, k+1; it is found when an
//! output track holds that pair of detections consecutively.
//! *Recall* = found truth links / truth links; `recall_present` divides by
//! the truth particles *present* at k and k+1 instead, detected or not.
//! The velocity error is the
//! fitted track velocity minus the true velocity at every detection of a
//! correctly identified track point, in px per pulse interval.
//!
//! # Identity scoring
//! Strict scoring asks of a merged image which particle made *most* of
//! its 2–3 events, which no detector can tell; merged-ok forgives any
//! link whose two ends share a particle, also one where a track changes
//! particle inside a merge (A → AB → B: strict one wrong link, merged-ok
//! none). Identity scoring asks whether the track keeps following one
//! particle. Each detection has the set S of truth particles that made at
//! least one of its events (noise excluded; a split image's parts by the
//! events on their pixels, as above). For each output track one label per
//! detection is chosen from its S so that the labels change between
//! consecutive detections as rarely as possible (dynamic programming over
//! the track, [`identity_labels`]); a detection with empty S (noise only)
//! has no label and both links touching it are wrong. A link is correct
//! iff its two ends carry the same label. The count of wrong links is the
//! minimum, the same for every optimal labelling; the labelling itself is
//! made unique by taking, among the optimal ones, the one that agrees
//! with the strict attribution at the most detections, then the smaller
//! particle id. So A → AB → B is one wrong link, a track that follows A
//! through a stream of AB images none, and without merged images identity
//! equals strict. *Identity precision* (`precision_identity`) = correct /
//! links; strict ≤ identity ≤ merged-ok always. The velocity error is the
//! fitted velocity minus the true velocity of the *labelled* particle.
//! Recall: besides the strict one, a *set-valued* recall (`recall_set`):
//! a truth link of p is (k, p) with a detection at k and one at k + 1
//! both holding events of p; it is found when one output track holds two
//! such detections consecutively, both labelled p. A tracker that puts
//! each detection on one track cannot find both particles' links through
//! a merged image, so set-valued recall is below strict recall; and two
//! tracks through the same merged images get the same labels there.
//!
//! # Oracle tracks
//! [`oracle_tracks`]: what a tracker that knew every particle would
//! output — per truth particle the detections holding its events, one per
//! pulse (a merged image is on both particles' tracks); gaps of up to
//! `TrackParams::stitch_gap` (3) missed pulses are bridged, as the tracker
//! bridges them (a gap of `max_gap` while running, longer by stitching),
//! longer gaps cut the track; one-detection pieces are dropped.
//! [`oracle_report`] scores them strictly, merged-ok and by identity
//! (strict is then the ceiling of strict precision for a tracker that
//! follows every particle through its merged images), also with each
//! detection on one track only (*exclusive*: the particle whose true,
//! or truth-plus-Gaussian-noise, position is nearest the centroid gets
//! it: a tracker with perfect, or σ-accurate, predictions), without the
//! merged images (their particles' tracks bridge them: a tracker that
//! knew which images are merged and refused them), and fits the
//! tracks of at least `min_length` detections with the tracker's own
//! output fit ([`super::fit_detections`]: same code, the tracker's final
//! noise estimate, the curvature prior estimated from those tracks; no
//! outlier removal, step cuts or flow prior): the velocity error with
//! perfect links, at every detection and at interior points.
//!
//! # Velocity floor
//! For those tracks, at each detection, the variance of the best velocity
//! estimate when the path is a quadratic in time (per axis, τ = pulse
//! index) and the centroids carry i.i.d. Gaussian noise σ = `sigma_all`
//! (centroid minus the particle's true position, rms per axis over those
//! detections, merged images included): σ² (XᵀX)⁻¹ for the slope at the
//! point ([`quadratic_velocity_variance_factor`]), with X over (a) the
//! whole track (`floor_track`; the Cramér–Rao bound of unbiased
//! estimators if the whole track were one quadratic), (b) the
//! `fit_window` (21) detections nearest the point (`floor_window`: the
//! fitter's longest window), (c) as (b) with a Gaussian prior of rms
//! `fit_accel_rms` on the acceleration (`floor_window_prior`: the
//! Bayesian bound, which also holds for biased estimators such as the
//! fit's own ridge), (d) as (c) with each detection's noise known from
//! its event count (`floor_window_prior_weighted`). The floors are rms
//! over the same points as the fit's error. They count noise only: the
//! bias of a quadratic on a path that is not one comes on top, and they
//! bound single-track estimators — a prior from other tracks (the flow)
//! is outside the model. Bias included, but for the fitter's family only:
//! `best_window` ([`best_window_mse`]) is the least mean square error of
//! a sliding quadratic (centred as the output fit centres its windows)
//! whose window, 3 detections to the whole track, is chosen per point
//! knowing the true path — the error of fitting the true positions plus
//! the noise of the window — without and with the acceleration prior.
//!
//! # Split images
//! With `TrackParams::split_merged` the tracker may replace a merged image
//! by two parts (new detections, serials with `SPLIT_SERIAL_BIT`).
//! [`run_scene`] renumbers them after the pushed particles and attributes
//! each part by the events on its pixels, with the rule above; the split
//! image keeps no truth (it is on no track, and the particle it was
//! attributed to is detected by its part). A part is a detection like any
//! other, so a particle outvoted in a merged image becomes detected there
//! and the truth-link count grows.
//!
//! # One definition, two kinds of truth
//! A correct link is the same everywhere: two consecutive detections of
//! one track that are images of one truth particle. What differs is how a
//! detection is known to be an image of a particle:
//! - here (and with [`attribute_nearest`] for positional truth) the
//!   *detection* is attributed — by its events when they are known (the
//!   exact rule: the particle that made most of them), else by the nearest
//!   truth particle;
//! - `crate::evaluate` scores the files a user gets, `tracks.csv`, whose
//!   points are the *fitted* positions: a point is matched to the nearest
//!   truth particle within 1 px, each truth particle claimed once.
//!
//! The second is the more lenient on merged images: when two particles
//! closer than ~1 px make one image, the detection belongs (here) to one
//! of them, and the track of the other that picks it up has a wrong link;
//! its fitted point, smoothed by the neighbours, still lies on its own
//! particle and is matched to it there. Physically that link is not a
//! tracking error (the detection saw one image where two particles were,
//! and the track still follows its particle), which is why the demo
//! scores 0.994 in `evaluate` and 0.984 here (tests/ptv_sim.rs). Both
//! readings are reported; the tests hold the stricter, detection-level one.
//! Recall likewise: `recall` counts truth links whose two detections
//! exist (the tracker's share), `recall_present` and `evaluate` also the
//! pulses where the particle made no image (the detector's share too).

use std::collections::{HashMap, HashSet};

use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal, Poisson};
use rand_pcg::Pcg64;
use serde::{Deserialize, Serialize};

use super::LinkedTrack;
use crate::cluster::{
    particle_pixels_from_labels, particles_from_labels, pixel_labels_with, pulse_pixels,
    split_wide_clusters, ClusterParams, Particle, ParticlePixels,
};
use crate::events::{EventChunk, ON};
use crate::pulses::PulseEvents;
use crate::sim::TruthSample;

/// Scene parameters.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct SynthParams {
    pub width: u16,
    pub height: u16,
    /// Particles per pixel in the sheet.
    pub ppp: f64,
    pub pulses: usize,
    pub period_us: f64,
    /// Largest displacement per pulse (px).
    pub max_disp: f64,
    /// Range of the mean events per particle per pulse.
    pub events_per_particle: (f64, f64),
    /// Noise events as a fraction of particle events.
    pub noise_fraction: f64,
    /// Mean residence time in the sheet (pulses).
    pub sheet_life: f64,
    /// Standard deviation of the particle image (px).
    pub image_sigma: f64,
    /// Probability that a particle in the sheet fires at all in a pulse.
    pub p_detect: f64,
    /// Wavelength (px) of the flow's structures.
    pub flow_scale: f64,
    pub seed: u64,
}

impl Default for SynthParams {
    /// Paper-like conditions.
    fn default() -> Self {
        SynthParams {
            width: 256,
            height: 256,
            ppp: 0.01,
            pulses: 60,
            period_us: 200.0,
            max_disp: 8.0,
            events_per_particle: (1.3, 2.0),
            noise_fraction: 0.01,
            sheet_life: 40.0,
            image_sigma: 0.35,
            p_detect: 0.95,
            flow_scale: 512.0,
            seed: 1,
        }
    }
}

/// One pulse of the scene: its events, the truth id of each event (`None`
/// for noise) and the truth of every particle in the sheet.
#[derive(Debug, Clone)]
pub struct SynthPulse {
    pub pulse: PulseEvents,
    pub event_truth: Vec<Option<u64>>,
    pub truth: Vec<TruthSample>,
}

impl SynthParams {
    /// The 384² scene of the conditions tables (`tests/ptv_conditions.rs`,
    /// `ptv_diagnose`, `ptv_bounds`): the defaults with these four changed.
    pub fn conditions(ppp: f64, max_disp: f64, noise_fraction: f64, seed: u64) -> Self {
        SynthParams {
            ppp,
            max_disp,
            noise_fraction,
            width: 384,
            height: 384,
            seed,
            ..Default::default()
        }
    }

    /// The tracker's search reach for this scene, as the conditions tables
    /// track it: 1.25× the largest displacement, never below the default
    /// 10 px.
    pub fn search_reach(&self) -> f64 {
        (self.max_disp * 1.25).max(10.0)
    }

    fn speed_scale(&self) -> f64 {
        let mag = (0.9f64.powi(2) + 0.35f64.powi(2)).sqrt();
        self.max_disp / mag
    }

    /// Velocity (px per pulse) at a position.
    pub fn velocity(&self, x: f64, y: f64) -> (f64, f64) {
        let u0 = self.speed_scale();
        let tau = std::f64::consts::TAU;
        (
            u0 * (0.5 + 0.4 * (tau * y / self.flow_scale).sin()),
            0.35 * u0 * (tau * x / self.flow_scale).cos(),
        )
    }

    fn advect(&self, x: f64, y: f64) -> (f64, f64) {
        let (k1x, k1y) = self.velocity(x, y);
        let (k2x, k2y) = self.velocity(x + 0.5 * k1x, y + 0.5 * k1y);
        let (k3x, k3y) = self.velocity(x + 0.5 * k2x, y + 0.5 * k2y);
        let (k4x, k4y) = self.velocity(x + k3x, y + k3y);
        (
            x + (k1x + 2.0 * k2x + 2.0 * k3x + k4x) / 6.0,
            y + (k1y + 2.0 * k2y + 2.0 * k3y + k4y) / 6.0,
        )
    }
}

/// Generate the scene, pulse by pulse.
pub fn generate(p: &SynthParams) -> Vec<SynthPulse> {
    struct P {
        id: u64,
        x: f64,
        y: f64,
        m: f64,
    }
    let mut rng = Pcg64::seed_from_u64(p.seed);
    let (w, h) = (p.width as f64, p.height as f64);
    let n = (p.ppp * w * h).round() as usize;
    let mut next_id = 0u64;
    let mut spawn = |rng: &mut Pcg64| {
        next_id += 1;
        P {
            id: next_id - 1,
            x: rng.gen_range(0.0..w - 1.0),
            y: rng.gen_range(0.0..h - 1.0),
            m: rng.gen_range(p.events_per_particle.0..=p.events_per_particle.1),
        }
    };
    let mut parts: Vec<P> = (0..n).map(|_| spawn(&mut rng)).collect();
    let blur = Normal::new(0.0, p.image_sigma.max(1e-9)).expect("finite sigma");
    let latency = Normal::new(100.0f64, 20.0).expect("finite");
    let period_s = p.period_us * 1e-6;
    let mut out = Vec::with_capacity(p.pulses);
    for k in 0..p.pulses {
        let start = 1000.0 + k as f64 * p.period_us;
        let mut events: Vec<(i64, u16, u16, Option<u64>)> = Vec::new();
        let mut truth = Vec::with_capacity(parts.len());
        for q in &parts {
            let (u, v) = p.velocity(q.x, q.y);
            truth.push(TruthSample {
                pulse: k as i64,
                t_us: start,
                particle_id: q.id,
                x: q.x,
                y: q.y,
                u: u / period_s,
                v: v / period_s,
            });
            let ne = if rng.gen_bool(p.p_detect.clamp(0.0, 1.0)) {
                1 + Poisson::new(q.m - 1.0)
                    .map(|d| d.sample(&mut rng) as usize)
                    .unwrap_or(0)
            } else {
                0
            };
            for _ in 0..ne {
                let ex = (q.x + blur.sample(&mut rng)).round();
                let ey = (q.y + blur.sample(&mut rng)).round();
                if ex >= 0.0 && ey >= 0.0 && ex < w && ey < h {
                    let t = start + latency.sample(&mut rng).max(1.0);
                    events.push((t as i64, ex as u16, ey as u16, Some(q.id)));
                }
            }
        }
        let n_noise = (events.len() as f64 * p.noise_fraction).round() as usize;
        for _ in 0..n_noise {
            let t = start + rng.gen_range(0.0..p.period_us);
            events.push((
                t as i64,
                rng.gen_range(0..p.width),
                rng.gen_range(0..p.height),
                None,
            ));
        }
        events.sort_by_key(|e| e.0);
        let mut chunk = EventChunk::with_capacity(events.len());
        for e in &events {
            chunk.push(e.0, e.1, e.2, ON);
        }
        out.push(SynthPulse {
            pulse: PulseEvents {
                index: k as i64,
                start_us: start,
                events: chunk,
            },
            event_truth: events.iter().map(|e| e.3).collect(),
            truth,
        });
        // Advance: advect, lose particles out of frame or sheet, refill.
        let mut kept = Vec::with_capacity(parts.len());
        for q in parts {
            let (x, y) = p.advect(q.x, q.y);
            let in_frame = x >= 0.0 && y >= 0.0 && x < w - 1.0 && y < h - 1.0;
            if in_frame && !rng.gen_bool((1.0 / p.sheet_life).min(1.0)) {
                kept.push(P { x, y, ..q });
            }
        }
        while kept.len() < n {
            kept.push(spawn(&mut rng));
        }
        parts = kept;
    }
    out
}

/// Cluster one synthetic pulse and attribute each particle to the truth
/// particle that made most of its events.
pub fn cluster_with_truth(
    sp: &SynthPulse,
    params: &ClusterParams,
) -> (Vec<Particle>, Vec<Option<u64>>) {
    let (p, ids, _) = cluster_with_truth_mixed(sp, params);
    (p, ids)
}

/// [`cluster_with_truth`], also telling for each particle whether its
/// events came from more than one source (two particles, or a particle and
/// noise): a merged image.
pub fn cluster_with_truth_mixed(
    sp: &SynthPulse,
    params: &ClusterParams,
) -> (Vec<Particle>, Vec<Option<u64>>, Vec<bool>) {
    let (p, ids, mixed, _) = cluster_with_truth_sources(sp, params);
    (p, ids, mixed)
}

/// Particles, their truth ids, merged flags and event sources (see
/// [`cluster_with_truth_sources`]).
pub type TruthClusters = (Vec<Particle>, Vec<Option<u64>>, Vec<bool>, Vec<Vec<u64>>);

/// [`cluster_with_truth_mixed`], also listing for each particle every
/// truth particle that made at least one of its events (sorted).
pub fn cluster_with_truth_sources(sp: &SynthPulse, params: &ClusterParams) -> TruthClusters {
    cluster_with_truth_pixels(sp, params).0
}

/// [`cluster_with_truth_sources`], also with the pixels of each particle
/// (for the tracker's split of merged images).
pub fn cluster_with_truth_pixels(
    sp: &SynthPulse,
    params: &ClusterParams,
) -> (TruthClusters, ParticlePixels) {
    let pixels = pulse_pixels(&sp.pulse, params);
    let mut labels = pixel_labels_with(&pixels, params);
    split_wide_clusters(&pixels, &mut labels, params.split_extent);
    let particles = particles_from_labels(&sp.pulse, &pixels, &labels, params);
    let table = particle_pixels_from_labels(&pixels, &labels, params);
    let label_of: HashMap<(u16, u16), u32> = pixels
        .iter()
        .zip(&labels)
        .map(|(p, &l)| ((p.x, p.y), l))
        .collect();
    let n_labels = labels.iter().map(|&l| l as usize + 1).max().unwrap_or(0);
    let mut votes: Vec<HashMap<Option<u64>, u32>> = vec![HashMap::new(); n_labels];
    let mut size = vec![0u32; n_labels];
    let ev = &sp.pulse.events;
    for i in 0..ev.len() {
        if params.on_only && ev.p[i] != ON {
            continue;
        }
        if let Some(&l) = label_of.get(&(ev.x[i], ev.y[i])) {
            *votes[l as usize].entry(sp.event_truth[i]).or_default() += 1;
            size[l as usize] += 1;
        }
    }
    let kept: Vec<usize> = (0..n_labels)
        .filter(|&l| size[l] >= params.min_events && size[l] <= params.max_events)
        .collect();
    let mixed: Vec<bool> = kept.iter().map(|&l| votes[l].len() > 1).collect();
    let sources: Vec<Vec<u64>> = kept
        .iter()
        .map(|&l| {
            let mut v: Vec<u64> = votes[l].keys().flatten().copied().collect();
            v.sort_unstable();
            v
        })
        .collect();
    let truth_xy: HashMap<u64, (f64, f64)> = sp
        .truth
        .iter()
        .map(|t| (t.particle_id, (t.x, t.y)))
        .collect();
    let ids: Vec<Option<u64>> = kept
        .iter()
        .zip(&particles)
        .map(|(&l, part)| attribute_votes(&votes[l], (part.x, part.y), &truth_xy))
        .collect();
    debug_assert_eq!(ids.len(), particles.len());
    ((particles, ids, mixed, sources), table)
}

/// The truth particle an image belongs to, from the sources of its events
/// (`votes`: events per source, `None` = noise): the one that made most;
/// among equals the one whose true position is nearest the centroid;
/// noise never wins a tie.
fn attribute_votes(
    votes: &HashMap<Option<u64>, u32>,
    centroid: (f64, f64),
    truth_xy: &HashMap<u64, (f64, f64)>,
) -> Option<u64> {
    let top = votes.values().copied().max().unwrap_or(0);
    votes
        .iter()
        .filter_map(|(id, &c)| match id {
            Some(id) if c == top => {
                let (x, y) = truth_xy.get(id).copied().unwrap_or((f64::MAX, f64::MAX));
                Some(((x - centroid.0).hypot(y - centroid.1), *id))
            }
            _ => None,
        })
        .min_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)))
        .map(|(_, id)| id)
}

/// Attribute each particle to the nearest truth particle of its pulse
/// within `max_dist` px (for truth that knows positions but not which
/// events each particle made, e.g. the full simulator's
/// `truth_particles.csv`). Particles must be grouped by pulse in the order
/// the truth lists pulses or not: any order works.
pub fn attribute_nearest(
    particles: &[Particle],
    truth: &[TruthSample],
    max_dist: f64,
) -> Vec<Option<u64>> {
    let mut by_pulse: HashMap<i64, Vec<&TruthSample>> = HashMap::new();
    for t in truth {
        by_pulse.entry(t.pulse).or_default().push(t);
    }
    let trees: HashMap<i64, kiddo::ImmutableKdTree<f64, 2>> = by_pulse
        .iter()
        .map(|(k, v)| {
            (
                *k,
                kiddo::ImmutableKdTree::new_from_slice(
                    &v.iter().map(|t| [t.x, t.y]).collect::<Vec<_>>(),
                ),
            )
        })
        .collect();
    particles
        .iter()
        .map(|p| {
            let tree = trees.get(&p.pulse)?;
            let nn = tree.nearest_one::<kiddo::SquaredEuclidean>(&[p.x, p.y]);
            (nn.distance <= max_dist * max_dist)
                .then(|| by_pulse[&p.pulse][nn.item as usize].particle_id)
        })
        .collect()
}

/// Link scores against truth (see the module docs for the definitions).
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct LinkScore {
    pub links: u64,
    pub correct_links: u64,
    /// Wrong links whose two detections both hold events of one truth
    /// particle: the track follows that particle through an image merged
    /// with another's (known only with event-level truth; 0 otherwise).
    pub merged_consistent_links: u64,
    /// (correct + merged-consistent links) / links: precision when a link
    /// through an unresolvable merged image of the track's own particle is
    /// not counted as a tracking error.
    pub precision_merged_ok: f64,
    pub truth_links: u64,
    pub found_truth_links: u64,
    pub precision: f64,
    pub recall: f64,
    /// Truth particles present in the sheet at k and k+1, detected or not
    /// (the truth links of `crate::evaluate`).
    pub truth_links_present: u64,
    /// Found truth links / present truth links: recall including the
    /// detection losses (what `crate::evaluate::score_tracks` reports).
    pub recall_present: f64,
    /// Rms of each velocity component's error (px per pulse interval).
    pub velocity_rms_px_per_pulse: f64,
    pub velocity_samples: u64,
    /// The same over track points at least `interior_margin` points from
    /// both ends of their track, where the sliding fit window is centred.
    pub velocity_rms_interior_px_per_pulse: f64,
    pub velocity_samples_interior: u64,
    /// Identity scoring (module docs, "Identity scoring"; needs the event
    /// sources, 0 without them): links whose two ends carry different
    /// labels in the track's optimal labelling, or touch a detection
    /// without particle events.
    #[serde(default)]
    pub identity_wrong_links: u64,
    /// (links − identity-wrong links) / links.
    #[serde(default)]
    pub precision_identity: f64,
    /// Set-valued truth links: (k, p) with a detection at k and one at
    /// k + 1 both holding events of particle p.
    #[serde(default)]
    pub truth_links_set: u64,
    /// ... found: one output track holds two such detections
    /// consecutively, both labelled p.
    #[serde(default)]
    pub found_truth_links_set: u64,
    #[serde(default)]
    pub recall_set: f64,
    /// Rms velocity error per component (px per pulse interval) against
    /// the labelled particle's true velocity, every labelled detection.
    #[serde(default)]
    pub velocity_rms_identity_px_per_pulse: f64,
    #[serde(default)]
    pub velocity_samples_identity: u64,
    /// ... interior points only (`interior_margin`, as above).
    #[serde(default)]
    pub velocity_rms_identity_interior_px_per_pulse: f64,
    #[serde(default)]
    pub velocity_samples_identity_interior: u64,
}

/// Squared velocity errors over a track's points, all and interior (≥
/// `margin` points from both ends), for an rms per component.
struct VelocityErrors {
    margin: usize,
    sq: f64,
    n: u64,
    sq_interior: f64,
    n_interior: u64,
}

impl VelocityErrors {
    fn new(margin: usize) -> Self {
        VelocityErrors {
            margin,
            sq: 0.0,
            n: 0,
            sq_interior: 0.0,
            n_interior: 0,
        }
    }

    /// The fitted velocity `(u, v)` of point `i` of a track of `len`
    /// points against the truth `(tu, tv)`, px/s; `k` = period in s.
    #[allow(clippy::too_many_arguments)]
    fn add(&mut self, i: usize, len: usize, u: f64, v: f64, tu: f64, tv: f64, k: f64) {
        let e2 = ((u - tu) * k).powi(2) + ((v - tv) * k).powi(2);
        self.sq += e2;
        self.n += 1;
        if i >= self.margin && len - 1 - i >= self.margin {
            self.sq_interior += e2;
            self.n_interior += 1;
        }
    }

    /// (rms all, samples, rms interior, samples), px per pulse per component.
    fn rms(&self) -> (f64, u64, f64, u64) {
        let rms = |sq: f64, n: u64| {
            if n > 0 {
                (sq / (2 * n) as f64).sqrt()
            } else {
                0.0
            }
        };
        (
            rms(self.sq, self.n),
            self.n,
            rms(self.sq_interior, self.n_interior),
            self.n_interior,
        )
    }
}

/// Score linked tracks. `det_truth[serial]` is the truth id of each
/// detection (serials as the tracker numbered them), `det_pulse[serial]`
/// its pulse; `truth` the truth samples of all pulses.
pub fn score(
    tracks: &[LinkedTrack],
    det_truth: &[Option<u64>],
    det_pulse: &[i64],
    truth: &[TruthSample],
    period_us: f64,
    interior_margin: usize,
) -> LinkScore {
    score_with_sources(
        tracks,
        det_truth,
        &[],
        det_pulse,
        truth,
        period_us,
        interior_margin,
    )
}

/// [`score`] with, per detection, every truth particle that made one of
/// its events (`det_sources[serial]`, sorted; empty slice when unknown),
/// which tells the merged-consistent links.
pub fn score_with_sources(
    tracks: &[LinkedTrack],
    det_truth: &[Option<u64>],
    det_sources: &[Vec<u64>],
    det_pulse: &[i64],
    truth: &[TruthSample],
    period_us: f64,
    interior_margin: usize,
) -> LinkScore {
    let mut s = LinkScore::default();
    // Truth links: (pulse k, id) detected at k and k+1.
    let detected: HashSet<(i64, u64)> = det_truth
        .iter()
        .zip(det_pulse)
        .filter_map(|(id, &k)| id.map(|id| (k, id)))
        .collect();
    s.truth_links = detected
        .iter()
        .filter(|&&(k, id)| detected.contains(&(k + 1, id)))
        .count() as u64;
    let present: HashSet<(i64, u64)> = truth.iter().map(|t| (t.pulse, t.particle_id)).collect();
    s.truth_links_present = present
        .iter()
        .filter(|&&(k, id)| present.contains(&(k + 1, id)))
        .count() as u64;
    let truth_vel: HashMap<(i64, u64), (f64, f64)> = truth
        .iter()
        .map(|t| ((t.pulse, t.particle_id), (t.u, t.v)))
        .collect();
    let mut found: HashSet<(i64, u64)> = HashSet::new();
    let mut vel = VelocityErrors::new(interior_margin);
    for t in tracks {
        let serials: Vec<u64> = t.detections.iter().flatten().copied().collect();
        for w in serials.windows(2) {
            s.links += 1;
            let (a, b) = (w[0] as usize, w[1] as usize);
            let correct = match (det_truth[a], det_truth[b]) {
                (Some(ia), Some(ib)) if ia == ib => {
                    s.correct_links += 1;
                    if det_pulse[b] == det_pulse[a] + 1 {
                        found.insert((det_pulse[a], ia));
                    }
                    true
                }
                _ => false,
            };
            if !correct && !det_sources.is_empty() {
                let (sa, sb) = (&det_sources[a], &det_sources[b]);
                if sa.iter().any(|id| sb.binary_search(id).is_ok()) {
                    s.merged_consistent_links += 1;
                }
            }
        }
        let n = t.track.points.len();
        for (i, (pt, d)) in t.track.points.iter().zip(&t.detections).enumerate() {
            let Some(serial) = d else { continue };
            let Some(id) = det_truth[*serial as usize] else {
                continue;
            };
            if let Some(&(u, v)) = truth_vel.get(&(pt.pulse, id)) {
                vel.add(i, n, pt.u, pt.v, u, v, period_us * 1e-6);
            }
        }
    }
    s.found_truth_links = found.len() as u64;
    if !det_sources.is_empty() {
        score_identity(
            &mut s,
            tracks,
            det_truth,
            det_sources,
            det_pulse,
            &truth_vel,
            period_us,
            interior_margin,
        );
    }
    s.precision = if s.links > 0 {
        s.correct_links as f64 / s.links as f64
    } else {
        0.0
    };
    s.recall = if s.truth_links > 0 {
        s.found_truth_links as f64 / s.truth_links as f64
    } else {
        0.0
    };
    s.precision_merged_ok = if s.links > 0 {
        (s.correct_links + s.merged_consistent_links) as f64 / s.links as f64
    } else {
        0.0
    };
    s.recall_present = if s.truth_links_present > 0 {
        s.found_truth_links as f64 / s.truth_links_present as f64
    } else {
        0.0
    };
    (
        s.velocity_rms_px_per_pulse,
        s.velocity_samples,
        s.velocity_rms_interior_px_per_pulse,
        s.velocity_samples_interior,
    ) = vel.rms();
    s
}

/// The identity part of [`score_with_sources`] (module docs, "Identity
/// scoring"): fills the `identity`/`set` fields of `s` (`s.links` must be
/// counted already).
#[allow(clippy::too_many_arguments)]
fn score_identity(
    s: &mut LinkScore,
    tracks: &[LinkedTrack],
    det_truth: &[Option<u64>],
    det_sources: &[Vec<u64>],
    det_pulse: &[i64],
    truth_vel: &HashMap<(i64, u64), (f64, f64)>,
    period_us: f64,
    interior_margin: usize,
) {
    let holds: HashSet<(i64, u64)> = det_sources
        .iter()
        .zip(det_pulse)
        .flat_map(|(src, &k)| src.iter().map(move |&id| (k, id)))
        .collect();
    s.truth_links_set = holds
        .iter()
        .filter(|&&(k, id)| holds.contains(&(k + 1, id)))
        .count() as u64;
    let mut found: HashSet<(i64, u64)> = HashSet::new();
    let mut vel = VelocityErrors::new(interior_margin);
    let k = period_us * 1e-6;
    for t in tracks {
        let serials: Vec<usize> = t.detections.iter().flatten().map(|&d| d as usize).collect();
        let labels = identity_labels(&serials, det_truth, det_sources);
        for (i, w) in serials.windows(2).enumerate() {
            match (labels[i], labels[i + 1]) {
                (Some(a), Some(b)) if a == b => {
                    if det_pulse[w[1]] == det_pulse[w[0]] + 1 {
                        found.insert((det_pulse[w[0]], a));
                    }
                }
                _ => s.identity_wrong_links += 1,
            }
        }
        let n = t.track.points.len();
        let mut j = 0; // index into serials/labels
        for (i, (pt, d)) in t.track.points.iter().zip(&t.detections).enumerate() {
            if d.is_none() {
                continue;
            }
            let label = labels[j];
            j += 1;
            let Some(&(u, v)) = label.and_then(|id| truth_vel.get(&(pt.pulse, id))) else {
                continue;
            };
            vel.add(i, n, pt.u, pt.v, u, v, k);
        }
    }
    s.found_truth_links_set = found.len() as u64;
    let ratio = |a: u64, b: u64| if b > 0 { a as f64 / b as f64 } else { 0.0 };
    s.precision_identity = ratio(s.links - s.identity_wrong_links, s.links);
    s.recall_set = ratio(s.found_truth_links_set, s.truth_links_set);
    (
        s.velocity_rms_identity_px_per_pulse,
        s.velocity_samples_identity,
        s.velocity_rms_identity_interior_px_per_pulse,
        s.velocity_samples_identity_interior,
    ) = vel.rms();
}

/// The optimal labelling of one track (module docs, "Identity scoring"):
/// for the detections `serials` (in track order) one truth particle each
/// from its event sources `det_sources[serial]` (sorted), `None` where
/// the sources are empty (noise only), such that the labels change
/// between consecutive detections as rarely as possible. Among the
/// labellings with fewest changes the one that agrees most often with
/// the strict attribution `det_truth` is taken (so a track through a
/// merged image keeps the particle it follows, and without merged
/// images the labels are `det_truth`), then the smaller particle id
/// (earliest in the track first): one labelling, deterministic.
pub fn identity_labels(
    serials: &[usize],
    det_truth: &[Option<u64>],
    det_sources: &[Vec<u64>],
) -> Vec<Option<u64>> {
    let mut out = vec![None; serials.len()];
    let mut i = 0;
    while i < serials.len() {
        if det_sources[serials[i]].is_empty() {
            i += 1;
            continue;
        }
        // A detection without sources ends the segment: both its links
        // are wrong whatever the labels, so the segments are labelled
        // independently.
        let mut j = i;
        while j < serials.len() && !det_sources[serials[j]].is_empty() {
            j += 1;
        }
        label_segment(&serials[i..j], det_truth, det_sources, &mut out[i..j]);
        i = j;
    }
    out
}

/// [`identity_labels`] of a run of detections that all have sources:
/// dynamic programming over the track, cost (label changes, disagreements
/// with `det_truth`) compared lexicographically.
fn label_segment(
    seg: &[usize],
    det_truth: &[Option<u64>],
    det_sources: &[Vec<u64>],
    out: &mut [Option<u64>],
) {
    // cost[i][c]: least cost of labelling seg[..=i] with label
    // det_sources[seg[i]][c] at i; back[i][c]: the label index at i − 1.
    let mut cost: Vec<Vec<(u32, u32)>> = Vec::with_capacity(seg.len());
    let mut back: Vec<Vec<usize>> = Vec::with_capacity(seg.len());
    for (i, &d) in seg.iter().enumerate() {
        let src = &det_sources[d];
        let mut row = Vec::with_capacity(src.len());
        let mut brow = Vec::with_capacity(src.len());
        for &l in src {
            let disagrees = u32::from(det_truth[d] != Some(l));
            if i == 0 {
                row.push((0, disagrees));
                brow.push(0);
                continue;
            }
            let prev = &det_sources[seg[i - 1]];
            // Least cost; among equals staying on l, else the smallest
            // label (sources are sorted, the first minimum wins).
            let mut best = (u32::MAX, u32::MAX);
            let mut arg = 0;
            for (c, &pl) in prev.iter().enumerate() {
                let pc = cost[i - 1][c];
                let cand = (pc.0 + u32::from(pl != l), pc.1);
                if cand < best || (cand == best && pl == l) {
                    best = cand;
                    arg = c;
                }
            }
            row.push((best.0, best.1 + disagrees));
            brow.push(arg);
        }
        cost.push(row);
        back.push(brow);
    }
    let last = seg.len() - 1;
    let mut c = (0..cost[last].len())
        .min_by_key(|&c| cost[last][c])
        .expect("a segment's detections have sources");
    for i in (0..seg.len()).rev() {
        out[i] = Some(det_sources[seg[i]][c]);
        c = back[i][c];
    }
}

/// Track points at least this many detections from both ends of their
/// track count as interior in [`run_and_score`] (the half-width of the
/// 11-point fixed output window, kept so numbers compare across fits).
pub const INTERIOR_MARGIN: usize = 5;

/// A scene clustered and tracked, with the truth of every detection
/// (indexed by detection: the serials of [`super::Tracker`], with the parts
/// of split images renumbered after all pushed particles).
#[derive(Debug, Clone)]
pub struct SceneRun {
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
    pub stats: super::TrackerStats,
    /// Per part of a split image: (its detection index, the image's index,
    /// whether the image held events of more than one source).
    pub split_parts: Vec<(usize, usize, bool)>,
}

/// Cluster every pulse (with the pixel table, so that the tracker can
/// split merged images when `tparams.split_merged`), track, and attribute
/// every detection — also the parts of split images, by the events on
/// their pixels, with the rule of [`cluster_with_truth`]. A split image
/// is replaced by its parts: it keeps no truth (it is on no track, and a
/// particle it was attributed to is detected by the part with its events).
pub fn run_scene(
    scene: &[SynthPulse],
    cparams: &ClusterParams,
    tparams: &super::TrackParams,
) -> crate::Result<SceneRun> {
    let mut tracker = super::Tracker::new(tparams.clone())?;
    tracker.record_splits(true);
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
        split_parts: Vec::new(),
    };
    // Split parts: (serial, truth, sources, mixed, pulse, parent serial,
    // events, centroid).
    type Part = (u64, Option<u64>, Vec<u64>, bool, i64, u64, u32, [f64; 2]);
    let mut parts_of_splits: Vec<Part> = Vec::new();
    for sp in scene {
        let ((parts, ids, mixed, sources), table) = cluster_with_truth_pixels(sp, cparams);
        run.det_pulse
            .extend(std::iter::repeat(sp.pulse.index).take(parts.len()));
        run.det_truth.extend(ids);
        run.det_events.extend(parts.iter().map(|p| p.n_events));
        run.det_xy.extend(parts.iter().map(|p| [p.x, p.y]));
        run.det_t_us
            .extend(std::iter::repeat(sp.pulse.start_us).take(parts.len()));
        run.det_mixed.extend(mixed);
        run.det_sources.extend(sources);
        run.tracks.extend(tracker.push_linked_with_pixels(
            sp.pulse.index,
            sp.pulse.start_us,
            &parts,
            Some(&table),
        )?);
        run.truth.extend_from_slice(&sp.truth);
        let splits = tracker.take_splits();
        if splits.is_empty() {
            continue;
        }
        let mut at_pixel: HashMap<(u16, u16), Vec<Option<u64>>> = HashMap::new();
        let ev = &sp.pulse.events;
        for i in 0..ev.len() {
            if !(cparams.on_only && ev.p[i] != ON) {
                at_pixel
                    .entry((ev.x[i], ev.y[i]))
                    .or_default()
                    .push(sp.event_truth[i]);
            }
        }
        let truth_xy: HashMap<u64, (f64, f64)> = sp
            .truth
            .iter()
            .map(|t| (t.particle_id, (t.x, t.y)))
            .collect();
        for d in splits {
            let mut votes: HashMap<Option<u64>, u32> = HashMap::new();
            for p in &d.pixels {
                for id in at_pixel.get(&(p.x, p.y)).into_iter().flatten() {
                    *votes.entry(*id).or_default() += 1;
                }
            }
            let mut src: Vec<u64> = votes.keys().flatten().copied().collect();
            src.sort_unstable();
            let id = attribute_votes(&votes, (d.x, d.y), &truth_xy);
            let n: u32 = d.pixels.iter().map(|p| p.count).sum();
            parts_of_splits.push((
                d.serial,
                id,
                src,
                votes.len() > 1,
                d.pulse,
                d.parent,
                n,
                [d.x, d.y],
            ));
        }
    }
    run.position_sigma = tracker.position_sigma();
    let (rest, stats) = tracker.finish();
    run.tracks.extend(rest);
    run.stats = stats;
    if !parts_of_splits.is_empty() {
        let base = run.det_truth.len() as u64;
        let index: HashMap<u64, u64> = parts_of_splits
            .iter()
            .enumerate()
            .map(|(k, p)| (p.0, base + k as u64))
            .collect();
        for (_, id, src, mixed, pulse, parent, n, xy) in parts_of_splits {
            run.det_events.push(n);
            let parent = parent as usize;
            run.det_xy.push(xy);
            run.det_t_us.push(run.det_t_us[parent]);
            let was_mixed = run.det_mixed[parent] || run.det_sources[parent].len() > 1;
            run.split_parts
                .push((run.det_truth.len(), parent, was_mixed));
            run.det_truth[parent] = None;
            run.det_sources[parent].clear();
            run.det_mixed[parent] = false;
            run.det_truth.push(id);
            run.det_sources.push(src);
            run.det_mixed.push(mixed);
            run.det_pulse.push(pulse);
        }
        for t in &mut run.tracks {
            for d in t.detections.iter_mut().flatten() {
                if *d & super::SPLIT_SERIAL_BIT != 0 {
                    *d = index[d];
                }
            }
        }
    }
    Ok(run)
}

/// Run the whole PTV stage on a scene: cluster every pulse, track, score
/// ([`run_scene`]; detections of the returned tracks numbered as there).
pub fn run_and_score(
    scene: &[SynthPulse],
    cparams: &ClusterParams,
    tparams: &super::TrackParams,
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

/// An ideal track (module docs, "Oracle tracks"): one truth particle and
/// the detections holding its events, in pulse order (indices as in
/// [`SceneRun`]).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct OracleTrack {
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
pub fn oracle_tracks(
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
pub struct OracleReport {
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
pub fn best_window_mse(
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
fn inverse_row_1(m: &[[f64; 3]; 3]) -> Option<[f64; 3]> {
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
pub fn quadratic_velocity_variance_factor(
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

/// Build the oracle tracks of a scene run ([`oracle_tracks`], gaps of up
/// to `tparams.stitch_gap` missed pulses bridged — the longest the
/// tracker bridges, by stitching — longer ones cut), fit each with the
/// tracker's output fit ([`super::fit_detections`]) and score them: links
/// (strict, merged-ok, identity; all, long, exclusive), the velocity
/// error with perfect links, and the floors (module docs).
pub fn oracle_report(
    run: &SceneRun,
    tparams: &super::TrackParams,
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
        tparams.stitch_gap,
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
    let mut prior = super::fit::AccelPrior::default();
    for t in oracle.iter().filter(|t| long(t)) {
        let pulses: Vec<i64> = t.detections.iter().map(|&d| run.det_pulse[d]).collect();
        let xy: Vec<[f64; 2]> = t.detections.iter().map(|&d| run.det_xy[d]).collect();
        prior.add_track(&pulses, &xy);
    }
    r.fit_sigma = run.position_sigma;
    r.fit_accel_rms = tparams
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
        let tracks = oracle_tracks(&run.det_truth, sources, &run.det_pulse, tparams.stitch_gap);
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
        let w = tparams.fit_window.min(n);
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
fn fit_oracle(
    run: &SceneRun,
    oracle: &[OracleTrack],
    tparams: &super::TrackParams,
    sigma: f64,
    accel_rms: f64,
) -> Vec<LinkedTrack> {
    use rayon::prelude::*;
    oracle
        .par_iter()
        .map(|t| {
            let input: Vec<super::FitInput> = t
                .detections
                .iter()
                .map(|&d| super::FitInput {
                    serial: d as u64,
                    pulse: run.det_pulse[d],
                    t_us: run.det_t_us[d],
                    x: run.det_xy[d][0],
                    y: run.det_xy[d][1],
                })
                .collect();
            super::fit_detections(&input, tparams, sigma, accel_rms)
        })
        .collect()
}

/// Where wrong links and missed truth links come from (see [`diagnose`]).
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct LinkDiagnosis {
    pub links: u64,
    pub wrong_links: u64,
    /// Wrong links with a merged image (events of two sources, particles
    /// or noise) at one end.
    pub wrong_merged: u64,
    /// Wrong links with a pure noise detection at one end.
    pub wrong_noise: u64,
    /// Wrong links between two clean images of different particles.
    pub wrong_swap: u64,
    /// ... of which the two truth particles were < 2 px apart at the
    /// second pulse (co-moving neighbours).
    pub wrong_swap_close: u64,
    /// Wrong links that are a track's first link (initialisation).
    pub wrong_first: u64,
    /// Wrong links that are a track's last link (the tail).
    pub wrong_last: u64,
    /// Wrong links across a bridged gap.
    pub wrong_gap: u64,
    pub truth_links: u64,
    pub missed: u64,
    /// Missed truth links whose first detection is on no kept track.
    pub missed_a_off_track: u64,
    /// ... whose second detection is on no kept track.
    pub missed_b_off_track: u64,
    /// ... both on tracks (different ones, or not consecutive).
    pub missed_both_on_tracks: u64,
    /// ... with a merged image at either end.
    pub missed_merged: u64,
    /// The tracker's position noise estimate at the end (px per axis).
    pub position_sigma: f64,
}

/// Classify every wrong link and every missed truth link of `tracks`
/// (detections numbered as in [`score`]; `det_mixed[serial]` tells merged
/// images, `det_xy` the detection positions, `truth` the truth samples).
pub fn diagnose(
    tracks: &[LinkedTrack],
    det_truth: &[Option<u64>],
    det_mixed: &[bool],
    det_pulse: &[i64],
    truth: &[TruthSample],
) -> LinkDiagnosis {
    let mut d = LinkDiagnosis::default();
    let pos: HashMap<(i64, u64), (f64, f64)> = truth
        .iter()
        .map(|t| ((t.pulse, t.particle_id), (t.x, t.y)))
        .collect();
    let mut on_track = vec![false; det_truth.len()];
    let mut found: HashSet<(i64, u64)> = HashSet::new();
    for t in tracks {
        let serials: Vec<u64> = t.detections.iter().flatten().copied().collect();
        for &s in &serials {
            on_track[s as usize] = true;
        }
        let n = serials.len();
        for (i, w) in serials.windows(2).enumerate() {
            d.links += 1;
            let (a, b) = (w[0] as usize, w[1] as usize);
            let (ia, ib) = (det_truth[a], det_truth[b]);
            if ia.is_some() && ia == ib {
                if det_pulse[b] == det_pulse[a] + 1 {
                    found.insert((det_pulse[a], ia.unwrap()));
                }
                continue;
            }
            d.wrong_links += 1;
            if i == 0 {
                d.wrong_first += 1;
            }
            if i + 2 == n {
                d.wrong_last += 1;
            }
            if det_pulse[b] != det_pulse[a] + 1 {
                d.wrong_gap += 1;
            }
            if det_mixed[a] || det_mixed[b] {
                d.wrong_merged += 1;
            } else if ia.is_none() || ib.is_none() {
                d.wrong_noise += 1;
            } else {
                d.wrong_swap += 1;
                let k = det_pulse[b];
                if let (Some(pa), Some(pb)) =
                    (pos.get(&(k, ia.unwrap())), pos.get(&(k, ib.unwrap())))
                {
                    if (pa.0 - pb.0).hypot(pa.1 - pb.1) < 2.0 {
                        d.wrong_swap_close += 1;
                    }
                }
            }
        }
    }
    let mut det_of: HashMap<(i64, u64), usize> = HashMap::new();
    for (s, (id, &k)) in det_truth.iter().zip(det_pulse).enumerate() {
        if let Some(id) = id {
            det_of.entry((k, *id)).or_insert(s);
        }
    }
    for (&(k, id), &a) in &det_of {
        let Some(&b) = det_of.get(&(k + 1, id)) else {
            continue;
        };
        d.truth_links += 1;
        if found.contains(&(k, id)) {
            continue;
        }
        d.missed += 1;
        if det_mixed[a] || det_mixed[b] {
            d.missed_merged += 1;
        }
        match (on_track[a], on_track[b]) {
            (false, _) => d.missed_a_off_track += 1,
            (true, false) => d.missed_b_off_track += 1,
            (true, true) => d.missed_both_on_tracks += 1,
        }
    }
    d
}

/// Cluster, track and [`diagnose`] a scene.
pub fn run_and_diagnose(
    scene: &[SynthPulse],
    cparams: &ClusterParams,
    tparams: &super::TrackParams,
) -> crate::Result<LinkDiagnosis> {
    let run = run_scene(scene, cparams, tparams)?;
    let mut d = diagnose(
        &run.tracks,
        &run.det_truth,
        &run.det_mixed,
        &run.det_pulse,
        &run.truth,
    );
    d.position_sigma = run.position_sigma;
    Ok(d)
}

/// A finer breakdown than [`diagnose`], by cause, for the accuracy work:
/// counts under self-explaining keys. Missed truth links (particle `id`
/// detected at `k` and `k + 1`, the pair not a link of one track):
/// - `missed/never_tracked/run<4`: no detection of the particle is on a
///   kept track and it never has 4 consecutive detections (a new track
///   needs 4; a physical limit of four-frame initialisation);
/// - `missed/never_tracked/run>=4`: never tracked although it could be;
/// - `missed/before_start`: before the first tracked detection of the
///   particle (late initialisation);
/// - `missed/after_end`: after the last tracked detection (early end);
/// - `missed/between`: between tracked detections (a broken track, a
///   swap, a detection taken by another track);
///
/// Wrong links (`wrong/...`): `merged_consistent` (both ends hold events
/// of one particle) split into `.../owner_on_other_track` (the merged
/// image's owner has its own images within 2 pulses on another track: two
/// tracks, and the wrong one took it) and `.../pair_on_one_track` (one
/// track follows two particles whose images stay merged, and the
/// attribution flips with the event majority: no tracker can tell them
/// apart),
/// `noise`, `swap/first|last|gap|interior` (clean images of two
/// particles, by position in the track).
pub fn diagnose_detail(
    tracks: &[LinkedTrack],
    det_truth: &[Option<u64>],
    det_sources: &[Vec<u64>],
    det_pulse: &[i64],
) -> std::collections::BTreeMap<String, u64> {
    let mut out: std::collections::BTreeMap<String, u64> = Default::default();
    let mut bump = |k: &str| *out.entry(k.to_string()).or_default() += 1;
    let n_det = det_truth.len();
    let mut on_track = vec![false; n_det];
    let mut track_of = vec![usize::MAX; n_det];
    let mut found: HashSet<(i64, u64)> = HashSet::new();
    for (ti, t) in tracks.iter().enumerate() {
        for s in t.detections.iter().flatten() {
            on_track[*s as usize] = true;
            track_of[*s as usize] = ti;
        }
    }
    // Per particle: detected pulses (the detection attributed to it) and
    // the pulses where a detection of it is on a track.
    let mut det_of: HashMap<(i64, u64), usize> = HashMap::new();
    for (s, (id, &k)) in det_truth.iter().zip(det_pulse).enumerate() {
        if let Some(id) = id {
            det_of.entry((k, *id)).or_insert(s);
        }
    }
    let mut detected_pulses: HashMap<u64, Vec<i64>> = HashMap::new();
    let mut tracked_range: HashMap<u64, (i64, i64)> = HashMap::new();
    for (&(k, id), &s) in &det_of {
        detected_pulses.entry(id).or_default().push(k);
        if on_track[s] {
            let e = tracked_range.entry(id).or_insert((k, k));
            e.0 = e.0.min(k);
            e.1 = e.1.max(k);
        }
    }
    let mut longest_run: HashMap<u64, usize> = HashMap::new();
    for (id, ks) in &mut detected_pulses {
        ks.sort_unstable();
        let (mut best, mut run) = (1, 1);
        for w in ks.windows(2) {
            run = if w[1] == w[0] + 1 { run + 1 } else { 1 };
            best = best.max(run);
        }
        longest_run.insert(*id, best);
    }
    for (ti, t) in tracks.iter().enumerate() {
        let serials: Vec<usize> = t.detections.iter().flatten().map(|&s| s as usize).collect();
        let n = serials.len();
        for (i, w) in serials.windows(2).enumerate() {
            let (a, b) = (w[0], w[1]);
            let (ia, ib) = (det_truth[a], det_truth[b]);
            if ia.is_some() && ia == ib {
                if det_pulse[b] == det_pulse[a] + 1 {
                    found.insert((det_pulse[a], ia.unwrap()));
                }
                continue;
            }
            bump("wrong");
            let (sa, sb) = (&det_sources[a], &det_sources[b]);
            if sa.iter().any(|id| sb.binary_search(id).is_ok()) {
                // The end that is not its track's particle's own image.
                let merged_end = if sa.len() > 1 { a } else { b };
                let owner = det_truth[merged_end];
                let k = det_pulse[merged_end];
                // The owner's own images nearby on another track: two
                // tracks, and the wrong one took the merged image.
                let owner_elsewhere = owner.is_some_and(|o| {
                    (k - 2..=k + 2).any(|kk| {
                        det_of
                            .get(&(kk, o))
                            .is_some_and(|&s| on_track[s] && track_of[s] != ti)
                    })
                });
                bump(if owner_elsewhere {
                    "wrong/merged_consistent/owner_on_other_track"
                } else {
                    "wrong/merged_consistent/pair_on_one_track"
                });
            } else if ia.is_none() || ib.is_none() {
                bump("wrong/noise");
            } else if i == 0 {
                bump("wrong/swap/first");
            } else if i + 2 == n {
                bump("wrong/swap/last");
            } else if det_pulse[b] != det_pulse[a] + 1 {
                bump("wrong/swap/gap");
            } else {
                bump("wrong/swap/interior");
            }
        }
    }
    for (&(k, id), &a) in &det_of {
        let Some(&b) = det_of.get(&(k + 1, id)) else {
            continue;
        };
        bump("truth_links");
        if found.contains(&(k, id)) {
            continue;
        }
        bump("missed");
        match tracked_range.get(&id) {
            None if longest_run[&id] < INIT_FRAMES_SYNTH => bump("missed/never_tracked/run<4"),
            None => bump("missed/never_tracked/run>=4"),
            Some(&(lo, _)) if k < lo => bump("missed/before_start"),
            Some(&(_, hi)) if k + 1 > hi => bump("missed/after_end"),
            Some(_) => bump(match (on_track[a], on_track[b]) {
                (true, true) if track_of[a] == track_of[b] => "missed/between/same_track",
                (true, true) => "missed/between/two_tracks",
                (false, _) => "missed/between/a_off",
                (true, false) => "missed/between/b_off",
            }),
        }
    }
    out
}

const INIT_FRAMES_SYNTH: usize = super::INIT_FRAMES;

/// Cluster, track and [`diagnose_detail`] a scene.
pub fn run_and_diagnose_detail(
    scene: &[SynthPulse],
    cparams: &ClusterParams,
    tparams: &super::TrackParams,
) -> crate::Result<std::collections::BTreeMap<String, u64>> {
    let run = run_scene(scene, cparams, tparams)?;
    Ok(diagnose_detail(
        &run.tracks,
        &run.det_truth,
        &run.det_sources,
        &run.det_pulse,
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::track::{Track, TrackPoint};

    /// A track through detections `serials` at consecutive pulses from 0,
    /// velocity `vel` (px/s) at every point.
    fn track(serials: &[u64], vel: (f64, f64)) -> LinkedTrack {
        LinkedTrack {
            track: Track {
                id: 0,
                points: (0..serials.len())
                    .map(|k| TrackPoint {
                        pulse: k as i64,
                        t_us: k as f64 * 200.0,
                        x: 0.0,
                        y: 0.0,
                        u: vel.0,
                        v: vel.1,
                        ax: 0.0,
                        ay: 0.0,
                        interpolated: false,
                    })
                    .collect(),
            },
            detections: serials.iter().map(|&s| Some(s)).collect(),
        }
    }

    /// Truth of particles `ids` at pulses 0..n, particle `id` moving at
    /// `id` px/s along x (so labels are told apart by the velocity).
    fn truth(ids: &[u64], n: i64) -> Vec<TruthSample> {
        ids.iter()
            .flat_map(|&id| {
                (0..n).map(move |k| TruthSample {
                    pulse: k,
                    t_us: k as f64 * 200.0,
                    particle_id: id,
                    x: 0.0,
                    y: 0.0,
                    u: id as f64,
                    v: 0.0,
                })
            })
            .collect()
    }

    /// Score one track whose detection i is at pulse i with sources
    /// `sources[i]` and strict owner `owners[i]`.
    fn score_one(sources: &[&[u64]], owners: &[Option<u64>], vel: (f64, f64)) -> LinkScore {
        let n = sources.len();
        let serials: Vec<u64> = (0..n as u64).collect();
        let src: Vec<Vec<u64>> = sources.iter().map(|s| s.to_vec()).collect();
        let pulses: Vec<i64> = (0..n as i64).collect();
        score_with_sources(
            &[track(&serials, vel)],
            owners,
            &src,
            &pulses,
            &truth(&[1, 2], n as i64),
            200.0,
            0,
        )
    }

    const A: u64 = 1;
    const B: u64 = 2;

    #[test]
    fn a_track_from_one_particle_through_their_merge_to_another_has_one_wrong_link() {
        for owner in [A, B] {
            let s = score_one(
                &[&[A], &[A, B], &[B]],
                &[Some(A), Some(owner), Some(B)],
                (0.0, 0.0),
            );
            assert_eq!(s.links, 2);
            assert_eq!(s.identity_wrong_links, 1, "{s:?}");
            // Merged-ok forgives both links, strict counts one.
            assert_eq!(s.links - s.correct_links - s.merged_consistent_links, 0);
            assert_eq!(s.correct_links, 1);
            // Set-valued truth links: A 0→1, B 1→2; the labelling keeps
            // one of them.
            assert_eq!(s.truth_links_set, 2);
            assert_eq!(s.found_truth_links_set, 1);
        }
    }

    #[test]
    fn a_track_following_its_particle_through_merged_images_has_no_wrong_link() {
        // A co-moving pair: one track holds A's images and the merged
        // ones, whose event majority flips between A and B.
        let sources: [&[u64]; 5] = [&[A], &[A, B], &[A, B], &[A, B], &[A]];
        let owners = [Some(A), Some(B), Some(A), Some(B), Some(A)];
        let s = score_one(&sources, &owners, (A as f64, 0.0));
        assert_eq!(s.links, 4);
        assert_eq!(s.correct_links, 0, "strict: every link touches a B image");
        assert_eq!(s.identity_wrong_links, 0, "{s:?}");
        assert_eq!(s.precision_identity, 1.0);
        // Every point labelled A, whose true velocity the track has.
        assert_eq!(s.velocity_samples_identity, 5);
        assert_eq!(s.velocity_rms_identity_px_per_pulse, 0.0);
        assert!(s.velocity_rms_px_per_pulse > 0.0, "strict scores vs B");
        assert_eq!(s.found_truth_links_set, 4);
        // B's truth links (1→2, 2→3) are not this track's.
        assert_eq!(s.truth_links_set, 6);
    }

    #[test]
    fn the_labelling_follows_the_majority_among_equal_labellings() {
        // A pair merged throughout: all-A and all-B change nothing; the
        // labelling agreeing with more owners (B: 2 of 3) is taken.
        let sources = vec![vec![A, B]; 3];
        let owners = [Some(B), Some(A), Some(B)];
        assert_eq!(identity_labels(&[0, 1, 2], &owners, &sources), [Some(B); 3]);
        // A → AB → B: one change wherever it is put; the merged image
        // keeps its owner.
        let sources = vec![vec![A], vec![A, B], vec![B]];
        for owner in [A, B] {
            let owners = [Some(A), Some(owner), Some(B)];
            let l = identity_labels(&[0, 1, 2], &owners, &sources);
            assert_eq!(l, [Some(A), Some(owner), Some(B)]);
        }
    }

    #[test]
    fn a_noise_detection_makes_both_its_links_wrong() {
        let s = score_one(
            &[&[A], &[A], &[], &[A], &[A]],
            &[Some(A), Some(A), None, Some(A), Some(A)],
            (0.0, 0.0),
        );
        assert_eq!(s.links, 4);
        assert_eq!(s.identity_wrong_links, 2);
        assert_eq!(s.correct_links, 2);
        // A noise detection at the end: its one link.
        let s = score_one(&[&[A], &[A], &[]], &[Some(A), Some(A), None], (0.0, 0.0));
        assert_eq!(s.identity_wrong_links, 1);
        // Events of A and noise (noise the majority): labelled A.
        let s = score_one(&[&[A], &[A], &[A]], &[Some(A), None, Some(A)], (0.0, 0.0));
        assert_eq!(s.identity_wrong_links, 0);
        assert_eq!(s.correct_links, 0);
    }

    /// A small paper-like scene, clustered and tracked.
    fn small_run(tp: &super::super::TrackParams) -> (SynthParams, SceneRun) {
        let sp = SynthParams {
            width: 128,
            height: 128,
            pulses: 30,
            ..Default::default()
        };
        let run = run_scene(&generate(&sp), &ClusterParams::default(), tp).unwrap();
        (sp, run)
    }

    #[test]
    fn without_merged_images_identity_scoring_is_strict_scoring() {
        let (sp, run) = small_run(&Default::default());
        assert!(
            run.det_sources.iter().any(|s| s.len() > 1),
            "the scene has merged images, else the check below is idle"
        );
        // Every detection reduced to its strict owner: no merged image.
        let single: Vec<Vec<u64>> = run
            .det_truth
            .iter()
            .map(|t| t.iter().copied().collect())
            .collect();
        let s = score_with_sources(
            &run.tracks,
            &run.det_truth,
            &single,
            &run.det_pulse,
            &run.truth,
            sp.period_us,
            INTERIOR_MARGIN,
        );
        assert!(s.links > 1000 && s.correct_links < s.links, "{s:?}");
        assert_eq!(s.identity_wrong_links, s.links - s.correct_links);
        assert_eq!(s.precision_identity, s.precision);
        assert_eq!(s.truth_links_set, s.truth_links);
        assert_eq!(s.found_truth_links_set, s.found_truth_links);
        assert_eq!(s.velocity_samples_identity, s.velocity_samples);
        assert_eq!(
            s.velocity_rms_identity_px_per_pulse,
            s.velocity_rms_px_per_pulse
        );
        // With the real sources identity sits between strict and
        // merged-ok.
        let s = score_with_sources(
            &run.tracks,
            &run.det_truth,
            &run.det_sources,
            &run.det_pulse,
            &run.truth,
            sp.period_us,
            INTERIOR_MARGIN,
        );
        assert!(s.identity_wrong_links <= s.links - s.correct_links);
        assert!(
            s.identity_wrong_links >= s.links - s.correct_links - s.merged_consistent_links,
            "{s:?}"
        );
    }

    #[test]
    fn oracle_tracks_share_merged_images_and_bridge_short_gaps_only() {
        // Particle 1 at pulses 0, 1, (merged with 2 at) 2, 4, 9, 10;
        // particle 2 at 2 (merged), 3; noise at 1.
        let det_pulse = [0, 1, 2, 4, 9, 10, 3, 1];
        let det_sources = vec![
            vec![1],
            vec![1],
            vec![1, 2],
            vec![1],
            vec![1],
            vec![1],
            vec![2],
            vec![],
        ];
        let det_truth = [
            Some(1),
            Some(1),
            Some(2),
            Some(1),
            Some(1),
            Some(1),
            Some(2),
            None,
        ];
        let o = oracle_tracks(&det_truth, &det_sources, &det_pulse, 3);
        assert_eq!(
            o,
            [
                OracleTrack {
                    particle: 1,
                    detections: vec![0, 1, 2, 3]
                },
                OracleTrack {
                    particle: 1,
                    detections: vec![4, 5]
                },
                OracleTrack {
                    particle: 2,
                    detections: vec![2, 6]
                },
            ]
        );
        // Two detections of one pulse with its events: the one it owns.
        let o = oracle_tracks(
            &[Some(1), Some(2), Some(1)],
            &[vec![1], vec![1, 2], vec![1]],
            &[0, 1, 1],
            0,
        );
        assert_eq!(o[0].detections, [0, 2]);
    }

    #[test]
    fn the_quadratic_velocity_variance_factor() {
        // Symmetric window: the slope is orthogonal to the other terms,
        // factor 1 / Σ τ².
        let taus: Vec<f64> = (-5..=5).map(f64::from).collect();
        let f = quadratic_velocity_variance_factor(&taus, &[], 0.0, 0.0).unwrap();
        assert!((f - 1.0 / 110.0).abs() < 1e-12, "{f}");
        // Three points 0, 1, 2 at the end τ = 2: v = (3x₂ − 4x₁ + x₀)/2,
        // factor (9 + 16 + 1)/4.
        let f = quadratic_velocity_variance_factor(&[0.0, 1.0, 2.0], &[], 2.0, 0.0).unwrap();
        assert!((f - 6.5).abs() < 1e-9, "{f}");
        assert!(quadratic_velocity_variance_factor(&[0.0, 1.0, 1.0], &[], 0.0, 0.0).is_none());
        // A prior that pins the curvature leaves the straight line's
        // slope variance, 1 / Σ (τ − τ̄)².
        let f = quadratic_velocity_variance_factor(&[0.0, 1.0, 2.0], &[], 2.0, 1e12).unwrap();
        assert!((f - 0.5).abs() < 1e-6, "{f}");
        // ... which two times determine as well.
        let f = quadratic_velocity_variance_factor(&[0.0, 1.0], &[], 2.0, 1e12).unwrap();
        assert!((f - 2.0).abs() < 1e-6, "{f}");
        // Weights: a sample of weight 2 counts as two of weight 1.
        let a = quadratic_velocity_variance_factor(
            &[0.0, 1.0, 2.0, 3.0],
            &[1.0, 2.0, 1.0, 1.0],
            3.0,
            0.5,
        );
        let b = quadratic_velocity_variance_factor(&[0.0, 1.0, 1.0, 2.0, 3.0], &[], 3.0, 0.5);
        assert!((a.unwrap() - b.unwrap()).abs() < 1e-12, "{a:?} {b:?}");
    }

    #[test]
    fn the_best_window_trades_curvature_bias_against_noise() {
        // A true quadratic path: no bias, so the longest window (all 31
        // samples) wins, and its error is the noise floor.
        let taus: Vec<f64> = (0..31).map(f64::from).collect();
        let quad: Vec<[f64; 2]> = taus.iter().map(|t| [0.1 * t * t, 2.0 * t]).collect();
        let mse = best_window_mse(&taus, &quad, 15, [3.0, 2.0], 0.4, 0.0);
        let floor = 0.16 * quadratic_velocity_variance_factor(&taus, &[], 15.0, 0.0).unwrap();
        assert!((mse - floor).abs() < 1e-12, "{mse} {floor}");
        // A sine: the long windows are biased, the best one is shorter
        // and its error above the noise floor of the whole track.
        let sine: Vec<[f64; 2]> = taus.iter().map(|t| [10.0 * (t / 3.0).sin(), 0.0]).collect();
        let v = [10.0 / 3.0 * (5.0f64).cos(), 0.0];
        let mse = best_window_mse(&taus, &sine, 15, v, 0.4, 0.0);
        assert!(mse > floor && mse < 0.16, "{mse}");
        // Without noise the shortest exact window is free of error only
        // if the path is a quadratic there: 3 points of the sine are not.
        let mse = best_window_mse(&taus, &sine, 15, v, 0.0, 0.0);
        assert!(mse > 0.0 && mse < 1e-2, "{mse}");
    }

    #[test]
    fn the_oracle_scores_its_own_links_perfectly_and_fits_as_the_tracker() {
        // Fixed noise and no curvature prior: the tracker's fit of a track
        // depends on its detections only, so refitting them with
        // `fit_detections` must give its points exactly.
        let tp = super::super::TrackParams {
            sigma_floor: 0.4,
            sigma_ceiling: 0.4,
            fit_accel_rms: Some(0.0),
            ..Default::default()
        };
        let (sp, run) = small_run(&tp);
        let mut compared = 0;
        for t in &run.tracks {
            let input: Vec<super::super::FitInput> = t
                .detections
                .iter()
                .flatten()
                .map(|&d| super::super::FitInput {
                    serial: d,
                    pulse: run.det_pulse[d as usize],
                    t_us: run.det_t_us[d as usize],
                    x: run.det_xy[d as usize][0],
                    y: run.det_xy[d as usize][1],
                })
                .collect();
            let refit = super::super::fit_detections(&input, &tp, 0.4, 0.0);
            assert_eq!(refit.detections, t.detections);
            assert_eq!(refit.track.points, t.track.points);
            compared += 1;
        }
        assert!(compared > 50, "{compared} tracks");
        let r = oracle_report(&run, &tp, sp.period_us, INTERIOR_MARGIN);
        // Every truth link (strict or set-valued) is a link of the
        // particle's oracle track, and every oracle link joins two images
        // of its particle.
        assert_eq!(r.score.recall, 1.0, "{r:?}");
        assert_eq!(r.score.identity_wrong_links, 0, "{r:?}");
        // Set-valued: a particle whose every oracle image also holds
        // another particle's events may have its track labelled with the
        // other one (equal cost, majority tie-break); those of its links
        // may be missed, nothing else.
        let oracle = oracle_tracks(
            &run.det_truth,
            &run.det_sources,
            &run.det_pulse,
            tp.stitch_gap,
        );
        let mut relabelled = HashSet::new();
        for t in &oracle {
            let labels = identity_labels(&t.detections, &run.det_truth, &run.det_sources);
            for (w, l) in t.detections.windows(2).zip(labels.windows(2)) {
                if run.det_pulse[w[1]] == run.det_pulse[w[0]] + 1 && l[0] != Some(t.particle) {
                    relabelled.insert((run.det_pulse[w[0]], t.particle));
                }
            }
        }
        let missed = r.score.truth_links_set - r.score.found_truth_links_set;
        assert!(
            missed as usize <= relabelled.len(),
            "{missed} {relabelled:?}"
        );
        assert!(r.score.correct_links < r.score.links, "merged images");
        // The floors are below the fit, the window's above the track's.
        assert!(r.floor_track <= r.floor_window && r.floor_window < r.velocity_rms_fit);
        // This run fits without the prior (`fit_accel_rms` 0): no ridge.
        assert_eq!(r.floor_window_prior, r.floor_window);
        // Exclusive: each image on one track; strict can only gain, recall
        // only lose (the image's other particle misses a pulse).
        assert!(r.score_exclusive.precision > r.score.precision, "{r:?}");
        assert!(r.score_exclusive.links < r.score.links);
        assert_eq!(r.score_exclusive.identity_wrong_links, 0);
        // Without merged images every link left is strictly correct,
        // unless noise outvoted the particle in one of its images.
        let s = &r.score_skip_merged;
        assert!(s.precision > r.score_exclusive.precision, "{s:?}");
        assert!(s.recall < r.score_exclusive.recall, "{s:?}");
        assert!(r.sigma_clean > 0.2 && r.sigma_clean < r.sigma_all, "{r:?}");
    }
}
