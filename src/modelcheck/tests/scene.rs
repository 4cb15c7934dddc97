//! The model-check search driven by ebptv's own simulator (`crate::sim`):
//! hidden effects in "measured" recordings simulated with seeds the search
//! never sees.
use super::modelcheck_common;

use modelcheck_common::{base, setting, strength};

use std::time::Instant;

use crate::modelcheck::scene::{default_catalogue, SceneSimulator};
use crate::modelcheck::workflow::{
    run, EffectSetting, ModelCheckResult, Simulator, Verdict, WorkflowOptions,
};
use crate::sim::scenario::{FlowSpec, Scenario, Sensor};
use rand::seq::SliceRandom;
use rand::SeedableRng;
use rand_pcg::Pcg64;

/// A scene whose particles change paths over the recording (out-of-plane
/// motion, a flow of 9300, 1300 px/s: not a whole number of pixels per
/// pulse) on a small sensor for many pulses (0.1 s = 500 pulses on 64x48:
/// ~6 particle visits per pixel). On [`base`] the lit particles never leave
/// the sheet and move exactly 2 px per pulse, so the same particles cross
/// the same pixels at the same sub-pixel phase all recording long: a fixed
/// pattern of their own that hides threshold mismatch, and a few hundred
/// independent particle images whose brightness swamps the streak length.
fn mixing() -> Scenario {
    let mut s = Scenario {
        name: "modelcheck-mixing".into(),
        duration_s: 0.1,
        sensor: Sensor {
            width: 64,
            height: 48,
            roi: None,
        },
        flow: FlowSpec::Uniform {
            u: 9300.0,
            v: 1300.0,
        },
        ..Scenario::default()
    };
    s.seeding.ppp = 0.006;
    s.seeding.out_of_plane_rms = 2000.0;
    s.light.energy = crate::sim::presets::WATER_ENERGY;
    s
}

fn opts() -> WorkflowOptions {
    WorkflowOptions {
        replicates: 4,
        max_evaluations: 14,
        max_effects: 2,
        seed: 77,
        ..WorkflowOptions::default()
    }
}

/// Measured = the scene with `truth` on, two seeds the search never uses.
fn check_hidden(truth: Option<EffectSetting>, seed: u64, order_seed: u64) -> ModelCheckResult {
    check_hidden_with(truth, seed, order_seed, None)
}

/// [`check_hidden`] with a given catalogue (default: all effects).
fn check_hidden_with(
    truth: Option<EffectSetting>,
    seed: u64,
    order_seed: u64,
    catalogue: Option<Vec<crate::modelcheck::workflow::EffectSpec>>,
) -> ModelCheckResult {
    check_hidden_on(base(), truth, seed, order_seed, catalogue)
}

/// [`check_hidden_with`] on a given scene.
fn check_hidden_on(
    scene: Scenario,
    truth: Option<EffectSetting>,
    seed: u64,
    order_seed: u64,
    catalogue: Option<Vec<crate::modelcheck::workflow::EffectSpec>>,
) -> ModelCheckResult {
    let mut catalogue = catalogue.unwrap_or_else(|| default_catalogue(&scene));
    catalogue.shuffle(&mut Pcg64::seed_from_u64(order_seed));
    let sim = SceneSimulator::new(scene)
        .unwrap()
        .with_catalogue(catalogue);
    let truth_v: Vec<EffectSetting> = truth.into_iter().collect();
    let fit = sim.simulate(&truth_v, 1_000_000 + seed).unwrap();
    let hold = sim.simulate(&truth_v, 2_000_000 + seed).unwrap();
    let mut cfg = sim.signature_config();
    cfg.latency_bin_us = 2.0;
    let clean = sim.simulate(&[], 3_000_000 + seed).unwrap();
    let lat = crate::modelcheck::workflow::signatures_of(&cfg, &clean).unwrap();
    cfg.burst_window_us = Some(
        crate::modelcheck::signatures::burst_window(lat.histogram("latency").unwrap(), 0.99)
            .unwrap(),
    );
    let t = Instant::now();
    let res = run(&sim, &cfg, &fit, &hold, &[], &opts()).unwrap();
    let worst: Vec<(String, f64)> = res
        .final_table
        .rows
        .iter()
        .take(3)
        .map(|r| (r.signature.clone(), r.stats.z))
        .collect();
    println!(
        "truth {:?}\n -> {:?} {:?} in {:?}; worst rows after: {:?}",
        truth_v,
        res.verdict,
        res.effects,
        t.elapsed(),
        worst
    );
    res
}

/// Named first, parameters within 30 %, gap at least halved.
fn assert_recovered(res: &ModelCheckResult, truth: &EffectSetting) {
    let first = res
        .effects
        .first()
        .unwrap_or_else(|| panic!("nothing found: {:#?}", res.rounds));
    assert_eq!(first.name, truth.name, "{:#?}", res.rounds);
    for (k, v) in &truth.parameters {
        let got = first.parameters[k];
        assert!(
            (got - v).abs() <= 0.3 * v.abs(),
            "{k}: fitted {got}, true {v}"
        );
    }
    assert!(first.gap_after <= 0.5 * first.gap_before, "{first:?}");
}

#[ebptv_macros::unit_test]
fn real_sim_hidden_latency_jitter() {
    let truth = setting("latency_jitter", &[("spread_us", strength(1, 6.0, 20.0))]);
    let res = check_hidden(Some(truth.clone()), 1, 11);
    assert_recovered(&res, &truth);
}

#[ebptv_macros::unit_test]
fn real_sim_null_case_names_nothing() {
    let res = check_hidden(None, 2, 12);
    assert!(res.effects.is_empty(), "{:#?}", res.rounds);
    assert_eq!(
        res.verdict,
        Verdict::Consistent,
        "{}",
        res.final_table.to_markdown()
    );
}

// Hot pixels stay in CI: they are missed when a zero-spread scalar swamps
// the fit objective, or when no signature tells count from rate.
#[ebptv_macros::unit_test]
fn real_sim_hidden_hot_pixels() {
    let truth = setting(
        "hot_pixels",
        &[
            ("count", strength(5, 20.0, 60.0).round()),
            ("rate_hz", strength(6, 300.0, 3000.0)),
        ],
    );
    assert_recovered(&check_hidden(Some(truth.clone()), 5, 15), &truth);
}

// Every hidden-effect test below runs in CI (6-21 s of CPU each).
// Intensity latency needs the second stage of two-parameter fits to
// search locally (without it: exponent 0.31 for 0.55).

/// Also the catalogue-order check on the real simulator: the same
/// recording with the catalogue in another order gives the same answer.
#[ebptv_macros::unit_test]
fn real_sim_hidden_background_noise_in_any_catalogue_order() {
    let truth = setting("background_noise", &[("rate_hz", strength(3, 2.0, 20.0))]);
    let a = check_hidden(Some(truth.clone()), 3, 13);
    assert_recovered(&a, &truth);
    let b = check_hidden(Some(truth.clone()), 3, 14);
    assert_eq!(a.effects, b.effects);
    assert_eq!(a.verdict, b.verdict);
}

#[ebptv_macros::unit_test]
fn real_sim_hidden_refractory() {
    let truth = setting("refractory", &[("period_us", strength(4, 4.0, 15.0))]);
    assert_recovered(&check_hidden(Some(truth.clone()), 4, 14), &truth);
}

#[ebptv_macros::unit_test]
fn real_sim_hidden_intensity_latency() {
    let truth = setting(
        "intensity_latency",
        &[
            ("exponent", strength(7, 0.5, 1.5)),
            ("reference", strength(8, 2.0, 6.0)),
        ],
    );
    assert_recovered(&check_hidden(Some(truth.clone()), 7, 17), &truth);
}

#[ebptv_macros::unit_test]
fn real_sim_hidden_arbiter_saturation() {
    let truth = setting(
        "arbiter_saturation",
        &[
            ("row_time_us", strength(9, 0.02, 0.1)),
            ("event_time_us", strength(10, 0.05, 0.3)),
        ],
    );
    assert_recovered(&check_hidden(Some(truth.clone()), 9, 19), &truth);
}

// Pulse streaks, threshold mismatch, rate limiter, OFF events: each has a signature that sees it (elongation,
// yield_split_covariance / yield_split_correlation, events_per_pulse /
// latency, on_fraction / off_latency).
//
// Streaks and mismatch run on the `mixing` scene. On `base`
// they are not met (streaks 10.3 → unexplained, nothing
// named; mismatch σ 0.32 → "consistent"): its lit particles cross the same
// pixels at the same sub-pixel phase all recording long, so the per-pixel
// yields carry a fixed pattern without any mismatch (split-half r 0.33 ±
// 0.07 clean) and extent_x follows the brightness of a few hundred
// particles (replicate spread as large as a scale-10 streak).
#[ebptv_macros::unit_test]
fn real_sim_hidden_pulse_streaks() {
    let truth = setting("pulse_streaks", &[("scale", strength(21, 10.0, 25.0))]);
    assert_recovered(
        &check_hidden_on(mixing(), Some(truth.clone()), 21, 31, None),
        &truth,
    );
}

#[ebptv_macros::unit_test]
fn real_sim_hidden_threshold_mismatch() {
    let truth = setting("threshold_mismatch", &[("sigma", strength(22, 0.15, 0.35))]);
    assert_recovered(
        &check_hidden_on(mixing(), Some(truth.clone()), 22, 32, None),
        &truth,
    );
}

#[ebptv_macros::unit_test]
fn real_sim_mixing_scene_null_case_names_nothing() {
    let res = check_hidden_on(mixing(), None, 27, 37, None);
    assert!(res.effects.is_empty(), "{:#?}", res.rounds);
    assert_eq!(
        res.verdict,
        Verdict::Consistent,
        "{}",
        res.final_table.to_markdown()
    );
}

#[ebptv_macros::unit_test]
fn real_sim_hidden_off_events() {
    let truth = setting(
        "off_events",
        &[
            ("threshold", strength(23, 0.15, 0.4)),
            ("tau_us", strength(24, 10.0, 50.0)),
        ],
    );
    assert_recovered(&check_hidden(Some(truth.clone()), 23, 33), &truth);
}

#[ebptv_macros::unit_test]
fn real_sim_hidden_rate_limiter() {
    // A ceiling below the burst: each window keeps 40-70 % of what the
    // clean scene puts into it at the burst's peak (~300 events per pulse
    // in ~15 µs).
    let window = strength(25, 10.0, 30.0);
    let keep = strength(26, 0.4, 0.7);
    let max_rate = keep * 20.0 * 1e6;
    let truth = setting(
        "rate_limiter",
        &[("max_rate_ev_s", max_rate), ("window_us", window)],
    );
    assert_recovered(&check_hidden(Some(truth.clone()), 25, 35), &truth);
}

// Out-of-catalogue, null and order checks with the real simulator.

#[ebptv_macros::unit_test]
fn real_sim_effect_outside_the_catalogue_is_unexplained() {
    // Long pulse streaks, with `pulse_streaks` removed from the catalogue:
    // no other candidate elongates particle images along the flow.
    let truth = setting("pulse_streaks", &[("scale", strength(41, 20.0, 30.0))]);
    let mut catalogue = default_catalogue(&base());
    catalogue.retain(|c| c.name != "pulse_streaks");
    let res = check_hidden_with(Some(truth), 41, 51, Some(catalogue));
    assert_eq!(res.verdict, Verdict::Unexplained, "{:#?}", res.rounds);
    assert!(
        res.effects.is_empty(),
        "named {:?} for an effect outside the catalogue",
        res.effects
    );
}
