//! Turning flows: the 8 px/pulse Lamb–Oseen vortex of
//! `data/scenarios/paper_like_vortex_8px.toml` (peak swirl ~8 px per
//! pulse, ~1 px/pulse² centripetal acceleration in the core) through the
//! full simulator and `ebptv track`, and scenes of an independent
//! generator (`turning_gen`: a Scully vortex and a shear layer with its
//! own image, latency and out-of-plane models). A straight line through
//! a young track's first 4–5 detections misses a path accelerating at
//! 1 px/pulse² by 2.5–3.5 px and a quadratic through 12 detections of a
//! path turning at 0.2 rad/pulse by ~3 px (outside the gate): the
//! tracker predicts with a constant-turn-rate path (`track::turn`,
//! `TrackParams::turn_model`, `young_turn_sigma`) and its output fit
//! follows it where the heading turns (`turn_fit_window`).
use crate::turning_gen;

use std::path::Path;
use std::process::Command;

use ebptv::compare::read_table;

const CENTRE: (f64, f64) = (320.0, 180.0);
/// Pulse period (s) of the scenario (5 kHz).
const PERIOD_S: f64 = 200e-6;

fn ebptv(args: &[&str], out: &Path) {
    let o = Command::new(env!("CARGO_BIN_EXE_ebptv"))
        .args(args)
        .arg("--out")
        .arg(out)
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "ebptv {args:?} failed: {}",
        String::from_utf8_lossy(&o.stderr)
    );
}

/// Per ring of radius `r_max` around the centre: the fraction of truth
/// samples with a track point within 1 px at the same pulse, and the
/// velocity rms (px/pulse per component) of those track points.
fn core_scores(tracks: &Path, truth: &Path, r_max: f64) -> (f64, f64) {
    let t = read_table(truth, &["pulse", "x", "y", "u", "v"]).unwrap();
    let k = read_table(tracks, &["pulse", "x", "y", "u", "v"]).unwrap();
    let c = |tab: &ebptv::compare::Table, n: &str| tab.col(n).unwrap().to_vec();
    let (tp, tx, ty, tu, tv) = (
        c(&t, "pulse"),
        c(&t, "x"),
        c(&t, "y"),
        c(&t, "u"),
        c(&t, "v"),
    );
    let (kp, kx, ky, ku, kv) = (
        c(&k, "pulse"),
        c(&k, "x"),
        c(&k, "y"),
        c(&k, "u"),
        c(&k, "v"),
    );
    let in_core = |x: f64, y: f64| (x - CENTRE.0).hypot(y - CENTRE.1) < r_max;
    // Track points near the core (a point up to 1 px outside may match a
    // truth sample inside), grouped by pulse.
    let mut by_pulse: std::collections::HashMap<i64, Vec<usize>> = Default::default();
    for i in 0..k.rows() {
        if (kx[i] - CENTRE.0).hypot(ky[i] - CENTRE.1) < r_max + 1.0 {
            by_pulse.entry(kp[i] as i64).or_default().push(i);
        }
    }
    let (mut n, mut hit, mut sq) = (0usize, 0usize, 0.0);
    for j in 0..t.rows() {
        if !in_core(tx[j], ty[j]) {
            continue;
        }
        n += 1;
        let near = by_pulse.get(&(tp[j] as i64)).and_then(|pts| {
            pts.iter()
                .map(|&i| (i, (kx[i] - tx[j]).hypot(ky[i] - ty[j])))
                .filter(|&(_, d)| d < 1.0)
                .min_by(|a, b| a.1.total_cmp(&b.1))
        });
        if let Some((i, _)) = near {
            hit += 1;
            sq += ((ku[i] - tu[j]) * PERIOD_S).powi(2) + ((kv[i] - tv[j]) * PERIOD_S).powi(2);
        }
    }
    assert!(n > 1000, "too few core samples ({n}) to score");
    (hit as f64 / n as f64, (sq / (2 * hit.max(1)) as f64).sqrt())
}

#[test]
fn fast_vortex_core_is_tracked() {
    let dir = tempfile::tempdir().unwrap();
    let sim = dir.path().join("sim");
    let scene = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/data/scenarios/paper_like_vortex_8px.toml"
    );
    // 100 pulses (the scenario's 250 take ~2.5× as long to simulate).
    ebptv(
        &[
            "simulate",
            "--config",
            scene,
            "--seconds",
            "0.02",
            "--seed",
            "2",
        ],
        &sim,
    );
    let ptv = dir.path().join("ptv");
    let rec = sim.join("recording.raw");
    ebptv(&["track", rec.to_str().unwrap()], &ptv);
    let truth = sim.join("truth_particles.parquet");
    let tracks = ptv.join("tracks.parquet");

    // Inside the core radius (60 px): with the line-only young predictor
    // 0.12 of the truth samples had a track point within 1 px, with the
    // quadratic fallback of young tracks 0.95.
    let (cover, _) = core_scores(&tracks, &truth, 60.0);
    assert!(cover > 0.8, "core (r < 60 px) coverage {cover:.3}");
    // Within 90 px (the swirl's peak at ~67 px): velocity rms of the
    // covered samples 0.72 px/pulse before, 0.29 now.
    let (_, vel) = core_scores(&tracks, &truth, 90.0);
    assert!(vel < 0.4, "velocity rms within r < 90 px {vel:.3} px/pulse");

    // The whole scene, scored as the demo does: before 0.9866 / 0.8801 /
    // 0.181, now 0.9880 / 0.9316 / 0.102.
    let t = ebptv::evaluate::Truth::read(&truth).unwrap();
    let s = ebptv::evaluate::score_tracks(&tracks, &t, PERIOD_S * 1e6, 1.0).unwrap();
    assert!(s.link_precision > 0.98, "{s:?}");
    assert!(s.link_recall > 0.91, "{s:?}");
    assert!(s.velocity_rms_px_per_pulse < 0.14, "{s:?}");
}

use ebptv::track::{link, TrackParams};
use turning_gen::{generate, score, Config, Flow, Scores};

/// Track a scene of the independent generator with `params` and score it.
fn independent(flow: Flow, seed: u64, params: &TrackParams, core: f64) -> Scores {
    let cfg = Config {
        flow,
        width: 360,
        height: 280,
        particles: 900,
        pulses: 160,
        period_us: 200.0,
        events_per_particle: 1.7,
        noise_per_pulse: 4.0,
        seed,
    };
    let scene = generate(&cfg);
    let tracks = link(&scene.particles, params).unwrap();
    score(&scene, &tracks, &flow, core)
}

const SCULLY: Flow = Flow::Vortex {
    xc: 180.0,
    yc: 140.0,
    rc: 25.0,
    vmax: 5.0,
    u0: 1.5,
    v0: 0.3,
};

/// A Scully vortex (rc 25 px, peak 5 px/pulse on 1.5 px/pulse of drift)
/// from the independent generator, with the defaults and with the
/// polynomial path (`turn_model: false`). Measured (seed 11): precision
/// 0.985 / 0.985, recall 0.915 / 0.916, velocity 0.068 / 0.064 px/pulse,
/// within 1.5 rc 0.067 / 0.056, coverage there 0.864 / 0.867: on this
/// generator's vortex the turning path does not help (its tracks do not
/// break in the core as those of `ptvdev_vortex` did) and costs a little
/// velocity noise. Guards against both paths getting worse.
#[test]
fn independent_vortex_core_is_tracked() {
    let on = independent(SCULLY, 11, &TrackParams::default(), 37.5);
    let off = independent(
        SCULLY,
        11,
        &TrackParams {
            turn_model: false,
            ..Default::default()
        },
        37.5,
    );
    eprintln!("turning path: {on:?}\npolynomial:   {off:?}");
    assert!(on.precision > 0.98 && on.recall > 0.90, "{on:?}");
    assert!(on.vel_rms < 0.075, "{on:?}");
    assert!(on.core_vel_rms < 0.08, "{on:?}");
    assert!(on.core_coverage > 0.84, "{on:?}");
    assert!(on.ends_vel_rms < 0.18, "{on:?}");
    assert!(
        on.core_vel_rms < 1.3 * off.core_vel_rms,
        "{on:?} vs {off:?}"
    );
    assert!(
        on.core_coverage > off.core_coverage - 0.01,
        "{on:?} vs {off:?}"
    );
}

/// A shear layer (1 → 5 px/pulse across 2·15 px) rolled into travelling
/// cat's eyes, from the independent generator. Measured (seed 12):
/// precision 0.981, recall 0.907, velocity 0.082 px/pulse, coverage
/// 0.849, ends 0.190.
#[test]
fn independent_shear_layer_is_tracked() {
    let flow = Flow::Shear {
        yc: 140.0,
        delta: 15.0,
        uc: 3.0,
        du: 4.0,
        amp: 25.0,
        wavelength: 120.0,
    };
    let s = independent(flow, 12, &TrackParams::default(), f64::INFINITY);
    eprintln!("shear layer: {s:?}");
    assert!(s.precision > 0.975 && s.recall > 0.895, "{s:?}");
    assert!(s.vel_rms < 0.09, "{s:?}");
    assert!(s.coverage > 0.835, "{s:?}");
    assert!(s.ends_vel_rms < 0.21, "{s:?}");
}

/// `ptvdev_vortex` of the shared independent recordings (Lamb–Oseen,
/// rc 30 px, 4 px/pulse on 2 px/pulse), scored by the shared scorers
/// (Python 3 with numpy and scipy). Ignored by default:
/// `cargo test --release --test integration -- --ignored --nocapture ptv::vortex_core::`
/// (`PTVDEV_DIR` overrides the folder).
#[test]
#[ignore]
fn ptvdev_vortex_meets_the_goals() {
    let root = concat!(env!("CARGO_MANIFEST_DIR"), "/../shared");
    let dir =
        std::env::var("PTVDEV_DIR").unwrap_or_else(|_| format!("{root}/data/dev/ptvdev_vortex"));
    let eval = std::env::var("PTVDEV_EVAL").unwrap_or_else(|_| format!("{root}/eval"));
    let out = tempfile::tempdir().unwrap();
    // The scorers read CSV.
    ebptv(
        &[
            "--table-format",
            "csv",
            "track",
            &format!("{dir}/events.raw"),
        ],
        out.path(),
    );
    let py = |args: &[&str]| {
        let o = Command::new("python3").args(args).output().unwrap();
        let text = String::from_utf8_lossy(&o.stdout).to_string();
        eprintln!("{text}");
        assert!(
            o.status.success(),
            "{args:?}: {text}{}",
            String::from_utf8_lossy(&o.stderr)
        );
    };
    let tracks = out.path().join("tracks.csv");
    py(&[
        &format!("{eval}/score_tracks.py"),
        &dir,
        tracks.to_str().unwrap(),
        "--min-recall",
        "0.96",
        "--max-vel-rms",
        "0.05",
    ]);
    py(&[
        &format!("{eval}/vortex_breakdown.py"),
        &dir,
        out.path().to_str().unwrap(),
    ]);
}
