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
//! # Algorithm (streaming, one pulse at a time: `Tracker::push`)
//! The tracker's state, one pulse's step and the life cycle of a track
//! are in `state.rs`, its options ([`TrackParams`]: five top-level knobs
//! and the parts `gates`, `init`, `stitch`, `fit`) in `params.rs`, the full
//! set of a run ([`TrackConfig`]: run options, clustering, tracker; the
//! TOML of `ebptv track --params`) in `config.rs`. Each pulse runs these
//! stages, in this order:
//!
//! 1. **Predict** (`predict.rs`) every active track at the new pulse time:
//!    a polynomial fit (order ≤ 2) over its last `gates.predict_window`
//!    detections, extrapolated;
//!    where the window visibly turns, a path turning at a constant rate
//!    (`turn`, `turn_model`), and for young tracks the line unless it
//!    misses the constant-speed turning path by `gates.young_turn_sigma`.
//!    The search radius is `gates.n_sigma` times the predictor's position
//!    uncertainty (the position noise σ, estimated from the innovations of
//!    accepted links between `gates.sigma_floor` and `gates.sigma_ceiling`,
//!    times the fit's leverage at the extrapolation point), clamped to
//!    `[gates.min_search_radius, max_disp]` and grown by `gates.gap_growth`
//!    per missed pulse.
//! 2. **Gate and assign** (`assign.rs`) globally: candidates inside each
//!    track's radius come from a grid index over the pulse's particles;
//!    the cost of a pair is `(d / radius)²`, the cost of a miss 1. A
//!    minimum-total-cost assignment (`lap`, Hungarian on the connected
//!    components of the sparse candidate graph) resolves conflicts — no
//!    first-come order. Tracks that reached `gates.max_track_length` hand out
//!    their detections as a segment and go on (`state.rs`).
//! 3. **Bridge gaps and repair** (`bridge.rs`): a track without a match
//!    keeps predicting for up to `max_gap` pulses with a growing radius;
//!    then it ends. The pulse `gates.repair_lag` pulses back is revisited
//!    (a fixed-lag smoother): tracks that missed it are fitted on both
//!    sides of it and its particles in their gates are assigned again.
//! 4. **Initialise** (`state.rs`; four-frame best estimate, as MyPTV/OpenPTV
//!    and Shake-The-Box's initialisation): particles left unassigned in the
//!    last four pulses are chained p0→p1 (within `max_disp`, or around
//!    `p0 + u(p0)·Δt` within `init.prior_radius` when a mean-flow prior is given),
//!    →p2 and →p3 (within `init.init_radius` of the constant-velocity
//!    prediction). A chain's cost is the sum of its squared velocity changes;
//!    chains are accepted best-first without sharing particles, except
//!    those whose velocity disagrees with the local flow of the
//!    established tracks (`local_flow`, `init.ghost_check_init`). Chains of
//!    four detections over five pulses (`init.init_gap`) follow, for particles
//!    missed once early; they need a known local flow that they match.
//!    New tracks are then extended backward into the pulses before their
//!    start (`init.back_extend`, `bridge.rs`).
//! 5. **Stitch** (`bridge.rs`): a new chain may be the continuation of a
//!    track that ended in the last `stitch.stitch_gap` pulses (lost through a
//!    longer gap or a missed detection streak). Ends and starts are matched
//!    by the same assignment solver on the cost of extrapolating each
//!    across the gap, and a matched pair becomes one track.
//! 6. **Finish and validate** (`finalise.rs`): a track whose stitch window
//!    has passed is first cut where its positions jump to a close neighbour
//!    and stay there (`step`, `stitch.step_split`: its particle was missed and an
//!    untracked neighbour in the gate took its place); detections further
//!    than `fit.outlier_sigma` σ from their neighbours' fit are removed,
//!    detections after a last gap with fewer than
//!    `stitch.confirm_after_gap` behind it are cut, and each piece is
//!    fitted ([`fit`]: local polynomial of order `fit.fit_order` over a sliding
//!    window of `fit.fit_min_window`..=`fit.fit_window` detections around each
//!    pulse, chosen per pulse from the position noise by
//!    `fit::fit_adaptive` (through the one fit API, `fit::OutputFit`:
//!    tabulated, running or gap backends where the pulses are regular),
//!    with a prior on the curvature
//!    (`fit.fit_accel_rms`, estimated from the tracks kept so far unless
//!    set) and, where the heading visibly turns, the turning path over
//!    `fit.turn_fit_window` detections: position, velocity in px/s from the
//!    pulse times, acceleration in px/s²), and kept when it has at
//!    least `min_length` detections and the rms fit residual is at most
//!    `fit.max_fit_residual`. Tracks of fewer than `init.ghost_check_length`
//!    detections are tested against the local flow and dropped as ghosts
//!    (images of different particles in a line) when they disagree; those
//!    of `init.min_length_flow..min_length` detections are kept when they
//!    agree.
//!    The fits can run off the linking thread (`Finaliser`).
//!
//! Around the tracker: `stream` runs it over a recording (pulses,
//! clustering, writer thread), `io` reads and writes its files,
//! `slice` is the per-slice variant for time-resolved slices.
//!
//! Memory is bounded by the active tracks, the last four pulses of
//! unassigned particles and the stitch pool; finished tracks are handed out
//! as soon as they can no longer change.

pub(crate) mod config;
pub mod fit;
pub(crate) mod grid_index;
pub(crate) mod io;
pub(crate) mod lap;
pub(crate) mod local_flow;
pub(crate) mod sink;
pub(crate) mod slice;
pub(crate) mod step;
pub(crate) mod stream;
/// Synthetic scenes with ground truth, oracles and link scores for the
/// tests and benches (feature `testkit`).
#[cfg(feature = "testkit")]
#[allow(missing_docs)]
// the tests' and benches' kit, not the user API: its fields are documented by the module doc
pub mod synth;
pub(crate) mod turn;

mod assign;
pub(crate) mod bridge;
mod finalise;
mod params;
pub(crate) mod predict;
mod state;

use std::collections::VecDeque;
use std::sync::Arc;

use serde::{Deserialize, Serialize};

use crate::cluster::Particle;
use crate::error::{Error, Result};
use grid_index::GridIndex;

use assign::*;
pub use config::{Linker, RunParams, TrackConfig};
pub(crate) use finalise::*;
#[ebptv_macros::testkit]
pub(crate) use io::{
    read_particles, read_tracks, write_particles_csv, Summary, TrackRow, PARTICLE_COLUMNS,
    TRACK_COLUMNS,
};
pub(crate) use io::{
    write_summary_json, ParticlesWriter, SummaryAcc, TracksNpyWriter, TracksWriter,
};
pub use params::*;
use predict::*;
pub use sink::{
    resolve_config, stream_of, track_into, track_to_dir, track_to_dir_with, DirRun, TrackInput,
    TrackProgress, TrackStage,
};
pub(crate) use slice::SliceParams;
pub use state::*;
#[ebptv_macros::testkit]
pub(crate) use stream::{track_recording, PtvSink, PtvStream, TrackingRun};

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    // Linking against brute-force oracles, the slice tracker, track
    // accuracy and the output fit on synthetic scenes (src/track/tests/).
    pub(crate) mod accuracy;
    pub(crate) mod fit_accuracy;
    pub(crate) mod oracle;
    pub(crate) mod slice;

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

    #[ebptv_macros::unit_test]
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

    #[ebptv_macros::unit_test]
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

    #[ebptv_macros::unit_test]
    fn long_tracks_come_out_in_segments_covering_every_pulse_once() {
        let ps: Vec<Particle> = (0..130)
            .map(|k| particle(k, 5.0 + 2.0 * k as f64, 20.0 + 0.5 * k as f64))
            .collect();
        let p = TrackParams {
            gates: GateParams {
                max_track_length: 44, // ≥ 2 × the largest fit window (21)
                ..Default::default()
            },
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
            gates: GateParams {
                max_track_length: 10,
                ..Default::default()
            },
            ..Default::default()
        })
        .is_err());
    }

    #[ebptv_macros::unit_test]
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
            init: InitParams {
                init_gap: false,
                ..Default::default()
            },
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
            init: InitParams {
                init_gap: true,
                ghost_check_init: false,
                ..Default::default()
            },
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

    #[ebptv_macros::unit_test]
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

    #[ebptv_macros::unit_test]
    fn no_stitch_across_a_masked_region() {
        let mut ps = Vec::new();
        for k in 0..30 {
            if (10..13).contains(&k) {
                continue; // the particle is behind a masked strut
            }
            ps.push(particle(k, 5.0 + 3.0 * k as f64, 20.0 + 0.1 * k as f64));
        }
        // x = 35 + 3·k for k = 10, 11, 12: columns 36..43 masked.
        let mut strut = crate::calib::PixelMask::new(100, 40);
        for y in 0..40 {
            for x in 36..44 {
                strut.set(x, y);
            }
        }
        let p = TrackParams {
            mask: Some(std::sync::Arc::new(strut)),
            ..Default::default()
        };
        let (tracks, _, stats) = link_linked(&ps, &p).unwrap();
        assert_eq!(stats.tracks_stitched, 0);
        assert_eq!(tracks.len(), 2);
        assert_eq!(tracks[0].track.points.len(), 10);
        assert_eq!(tracks[1].track.points.len(), 17);
    }

    #[ebptv_macros::unit_test]
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
    }

    #[ebptv_macros::unit_test]
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

    #[ebptv_macros::unit_test]
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

    #[ebptv_macros::unit_test]
    fn tabulated_output_fit_matches_the_reference() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
        let params = TrackParams::default();
        let mut compared = 0;
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
                });
                pulse += 1;
            }
            let sigma = 0.2;
            // Half the cases with the curvature prior.
            let accel = [0.0, 0.0, 0.08, 0.3][(case / 2) % 4];
            let (rp, rs, rrms) = fit_track_with(
                &dets,
                &params,
                sigma,
                accel,
                fit::FitPath::Plain,
                &mut (0, 0),
            );
            for path in [fit::FitPath::Tabulated, fit::FitPath::Fast] {
                let mut fits = (0, 0);
                let (fp, fs, frms) = fit_track_with(&dets, &params, sigma, accel, path, &mut fits);
                let (grid_fits, gap_fits) = fits;
                // On the grid the tabulated path takes every detection whose
                // pilot window has no gap, the gap path (`Fast`) every other
                // sample; jittered times neither.
                let samples = (dets[n - 1].pulse - dets[0].pulse + 1) as usize;
                if jitter > 0.0 {
                    assert_eq!((grid_fits, gap_fits), (0, 0), "case {case}");
                } else if case % 2 == 0 {
                    assert_eq!(grid_fits, n, "case {case}");
                } else {
                    assert!(grid_fits > 0, "case {case}");
                    if path == fit::FitPath::Fast {
                        assert_eq!(grid_fits + gap_fits, samples, "case {case}");
                    }
                }
                assert_eq!(fs, rs);
                assert_eq!(fp.len(), rp.len());
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
        }
        assert!(compared > 500);
    }
}
