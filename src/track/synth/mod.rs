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
//! `oracle_tracks`: what a tracker that knew every particle would
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
//! output fit (`fit_detections`: same code, the tracker's final
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
//! point (`quadratic_velocity_variance_factor`), with X over (a) the
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
//! `best_window` (`best_window_mse`) is the least mean square error of
//! a sliding quadratic (centred as the output fit centres its windows)
//! whose window, 3 detections to the whole track, is chosen per point
//! knowing the true path — the error of fitting the true positions plus
//! the noise of the window — without and with the acceleration prior.
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
//!
//! [`identity_labels`]: crate::track::synth::identity_labels
//! [`oracle_report`]: crate::track::synth::oracle_report
//! [`attribute_nearest`]: crate::track::synth::attribute_nearest

use std::collections::{HashMap, HashSet};

use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal, Poisson};
use rand_pcg::Pcg64;
use serde::{Deserialize, Serialize};

use super::LinkedTrack;
use crate::cluster::{
    particles_from_labels, pixel_labels_with, pulse_pixels, split_wide_clusters, ClusterParams,
    Particle,
};
use crate::events::{EventChunk, ON};
use crate::pulses::PulseEvents;
use crate::sim::TruthSample;

mod diagnose;
pub(crate) mod oracle;
mod run;
mod score;

#[ebptv_macros::testkit]
pub(crate) use diagnose::*;
#[ebptv_macros::testkit]
pub(crate) use oracle::*;
#[ebptv_macros::testkit]
pub(crate) use run::*;
#[ebptv_macros::testkit]
pub(crate) use score::*;

/// Scene parameters.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[ebptv_macros::testkit]
pub(crate) struct SynthParams {
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
#[ebptv_macros::testkit]
pub(crate) struct SynthPulse {
    pub pulse: PulseEvents,
    pub event_truth: Vec<Option<u64>>,
    pub truth: Vec<TruthSample>,
}

impl SynthParams {
    /// The 384² scene of the conditions tables (`benches/examples/ptv_conditions.rs`,
    /// `ptv_diagnose`, `ptv_bounds`): the defaults with these four changed.
    #[ebptv_macros::testkit]
    pub(crate) fn conditions(ppp: f64, max_disp: f64, noise_fraction: f64, seed: u64) -> Self {
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
    #[ebptv_macros::testkit]
    pub(crate) fn search_reach(&self) -> f64 {
        (self.max_disp * 1.25).max(10.0)
    }

    fn speed_scale(&self) -> f64 {
        let mag = (0.9f64.powi(2) + 0.35f64.powi(2)).sqrt();
        self.max_disp / mag
    }

    /// Velocity (px per pulse) at a position.
    pub(crate) fn velocity(&self, x: f64, y: f64) -> (f64, f64) {
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
#[ebptv_macros::testkit]
pub(crate) fn generate(p: &SynthParams) -> Vec<SynthPulse> {
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
#[ebptv_macros::testkit]
pub(crate) fn cluster_with_truth(
    sp: &SynthPulse,
    params: &ClusterParams,
) -> (Vec<Particle>, Vec<Option<u64>>) {
    let (p, ids, _) = cluster_with_truth_mixed(sp, params);
    (p, ids)
}

/// [`cluster_with_truth`], also telling for each particle whether its
/// events came from more than one source (two particles, or a particle and
/// noise): a merged image.
#[ebptv_macros::testkit]
pub(crate) fn cluster_with_truth_mixed(
    sp: &SynthPulse,
    params: &ClusterParams,
) -> (Vec<Particle>, Vec<Option<u64>>, Vec<bool>) {
    let (p, ids, mixed, _) = cluster_with_truth_sources(sp, params);
    (p, ids, mixed)
}

/// Particles, their truth ids, merged flags and event sources (see
/// [`cluster_with_truth_sources`]).
pub(crate) type TruthClusters = (Vec<Particle>, Vec<Option<u64>>, Vec<bool>, Vec<Vec<u64>>);

/// [`cluster_with_truth_mixed`], also listing for each particle every
/// truth particle that made at least one of its events (sorted).
pub(crate) fn cluster_with_truth_sources(sp: &SynthPulse, params: &ClusterParams) -> TruthClusters {
    let pixels = pulse_pixels(&sp.pulse, params);
    let mut labels = pixel_labels_with(&pixels, params);
    split_wide_clusters(&pixels, &mut labels, params.split_extent);
    let particles = particles_from_labels(&sp.pulse, &pixels, &labels, params);
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
    (particles, ids, mixed, sources)
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
#[ebptv_macros::testkit]
pub(crate) fn attribute_nearest(
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

#[cfg(feature = "testkit")]
pub(crate) mod tests {
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

    #[ebptv_macros::unit_test]
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

    #[ebptv_macros::unit_test]
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

    #[ebptv_macros::unit_test]
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

    #[ebptv_macros::unit_test]
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

    #[ebptv_macros::unit_test]
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

    #[ebptv_macros::unit_test]
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

    #[ebptv_macros::unit_test]
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

    #[ebptv_macros::unit_test]
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

    #[ebptv_macros::unit_test]
    fn the_oracle_scores_its_own_links_perfectly_and_fits_as_the_tracker() {
        // Fixed noise and no curvature prior: the tracker's fit of a track
        // depends on its detections only, so refitting them with
        // `fit_detections` must give its points exactly.
        let tp = super::super::TrackParams {
            gates: crate::track::GateParams {
                sigma_floor: 0.4,
                sigma_ceiling: 0.4,
                ..Default::default()
            },
            fit: crate::track::FitParams {
                fit_accel_rms: Some(0.0),
                ..Default::default()
            },
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
            tp.stitch.stitch_gap,
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
