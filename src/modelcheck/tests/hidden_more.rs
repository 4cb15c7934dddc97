//! Model check with the real simulator: the clock-drift
//! candidate (signature and hidden-effect search) and two hidden effects at
//! once (both named, joint refit). "Measured" recordings are simulated with
//! seeds the search never uses.
use super::modelcheck_common;

use modelcheck_common::{base, setting, strength};

use std::collections::BTreeMap;
use std::time::Instant;

use crate::modelcheck::scene::{default_catalogue, SceneSimulator};
use crate::modelcheck::signatures::{burst_window, LATENCY_DRIFT};
use crate::modelcheck::workflow::{
    run, signatures_of, EffectSetting, EffectSpec, ModelCheckResult, Simulator, Verdict,
    WorkflowOptions,
};

use rand::seq::SliceRandom;
use rand::SeedableRng;
use rand_pcg::Pcg64;

fn opts(max_effects: usize) -> WorkflowOptions {
    WorkflowOptions {
        replicates: 4,
        max_evaluations: 14,
        max_effects,
        seed: 77,
        ..WorkflowOptions::default()
    }
}

/// Measured = the scene with `truth` on (fit and held-out blocks from two
/// seeds the search never uses); the catalogue shuffled by `order_seed`.
fn check_hidden(
    truth: &[EffectSetting],
    seed: u64,
    order_seed: u64,
    catalogue: Option<Vec<EffectSpec>>,
    max_effects: usize,
) -> ModelCheckResult {
    check_hidden_opts(truth, seed, order_seed, catalogue, &opts(max_effects))
}

/// [`check_hidden`] with given options.
fn check_hidden_opts(
    truth: &[EffectSetting],
    seed: u64,
    order_seed: u64,
    catalogue: Option<Vec<EffectSpec>>,
    options: &WorkflowOptions,
) -> ModelCheckResult {
    let mut catalogue = catalogue.unwrap_or_else(|| default_catalogue(&base()));
    catalogue.shuffle(&mut Pcg64::seed_from_u64(order_seed));
    let sim = SceneSimulator::new(base())
        .unwrap()
        .with_catalogue(catalogue);
    let fit = sim.simulate(truth, 1_000_000 + seed).unwrap();
    let hold = sim.simulate(truth, 2_000_000 + seed).unwrap();
    let mut cfg = sim.signature_config();
    cfg.latency_bin_us = 2.0;
    let clean = sim.simulate(&[], 3_000_000 + seed).unwrap();
    let lat = signatures_of(&cfg, &clean).unwrap();
    cfg.burst_window_us = Some(burst_window(lat.histogram("latency").unwrap(), 0.99).unwrap());
    let t = Instant::now();
    let res = run(&sim, &cfg, &fit, &hold, &[], options).unwrap();
    println!(
        "truth {:?}\n -> {:?} {:?} in {:?}",
        truth,
        res.verdict,
        res.effects,
        t.elapsed()
    );
    for r in &res.rounds {
        let top: Vec<String> = r
            .candidates
            .iter()
            .take(4)
            .map(|c| format!("{} {:.1}", c.name, c.gap_after))
            .collect();
        println!(
            "  round: gap {:.1} (null sd {:.2}); {}; {}",
            r.gap_before,
            r.gap_null_sd,
            top.join(", "),
            r.note
        );
    }
    res
}

fn assert_parameters(found: &BTreeMap<String, f64>, truth: &EffectSetting) {
    for (k, v) in &truth.parameters {
        let got = found[k];
        assert!(
            (got - v).abs() <= 0.3 * v.abs(),
            "{} {k}: fitted {got}, true {v}",
            truth.name
        );
    }
}

/// The signature against the simulator's ground truth: the drift in ppm
/// comes back as the latency slope, with its sign; without drift the slope
/// is within the noise of zero.
#[ebptv_macros::unit_test]
fn latency_drift_signature_measures_the_simulated_drift() {
    let sim = SceneSimulator::new(base()).unwrap();
    let cfg = sim.signature_config();
    let slope = |ppm: Option<f64>, seed: u64| -> f64 {
        let effects: Vec<EffectSetting> = ppm
            .map(|p| setting("clock_drift", &[("ppm", p)]))
            .into_iter()
            .collect();
        let rec = sim.simulate(&effects, seed).unwrap();
        signatures_of(&cfg, &rec)
            .unwrap()
            .scalar(LATENCY_DRIFT)
            .unwrap()
    };
    let clean: Vec<f64> = (0..3).map(|s| slope(None, 10 + s)).collect();
    println!("no drift: {clean:?} ppm");
    for c in &clean {
        assert!(c.abs() < 40.0, "slope {c} ppm without drift");
    }
    for (ppm, seed) in [(250.0, 21), (-250.0, 22), (120.0, 23)] {
        let got = slope(Some(ppm), seed);
        println!("drift {ppm} ppm: slope {got:.1} ppm");
        assert!(
            (got - ppm).abs() <= 0.2 * ppm.abs(),
            "drift {ppm} ppm measured as {got}"
        );
    }
}

#[ebptv_macros::unit_test]
fn real_sim_hidden_clock_drift() {
    // A slow laser clock or a fast one: the sign is part of the truth.
    let ppm = -strength(61, 150.0, 400.0);
    let truth = setting("clock_drift", &[("ppm", ppm)]);
    let res = check_hidden(std::slice::from_ref(&truth), 61, 71, None, 2);
    let first = res
        .effects
        .first()
        .unwrap_or_else(|| panic!("nothing found: {:#?}", res.rounds));
    assert_eq!(first.name, "clock_drift", "{:#?}", res.rounds);
    assert_parameters(&first.parameters, &truth);
    assert!(first.gap_after <= 0.5 * first.gap_before, "{first:?}");
}

/// Both of `truth` named, each within 30 %, the model with both
/// consistent with the held-out data, the gap at least halved.
fn assert_both_found(truth: &[EffectSetting], seed: u64, order_seed: u64) {
    let res = check_hidden(truth, seed, order_seed, None, 3);
    for t in truth {
        let found = res
            .effects
            .iter()
            .find(|e| e.name == t.name)
            .unwrap_or_else(|| panic!("{} not named: {:#?}", t.name, res.rounds));
        assert_parameters(&found.parameters, t);
    }
    assert_eq!(res.effects.len(), 2, "{:?}", res.effects);
    assert_eq!(res.verdict, Verdict::Explained, "{:#?}", res.rounds);
    let first_gap = res.effects[0].gap_before;
    let last_gap = res.effects.last().unwrap().gap_after;
    assert!(last_gap <= 0.5 * first_gap, "{:?}", res.effects);
}

/// The two hidden effects of the test below.
fn hot_pixels_and_clock_drift() -> [EffectSetting; 2] {
    [
        setting(
            "hot_pixels",
            &[
                ("count", strength(64, 20.0, 60.0).round()),
                ("rate_hz", strength(65, 300.0, 3000.0)),
            ],
        ),
        setting("clock_drift", &[("ppm", strength(66, 150.0, 400.0))]),
    ]
}

// Not met reliably: two catalogue effects at once, seen by different
// signatures (a fixed pattern of off-burst activity; the latency's slope
// over the recording); the second round's acceptance triggers the joint
// refit of both. Clock drift is named first with every seed; the hot
// pixels' improvement in the second round (~37) sits at the chance bar
// (3 null sd, 35–40), so they are named with about half the recording
// seeds (`two_hidden_effects_over_seeds`).
#[ebptv_macros::unit_test]
#[ignore]
fn real_sim_two_hidden_effects_hot_pixels_and_clock_drift() {
    assert_both_found(&hot_pixels_and_clock_drift(), 64, 74);
}

/// The same two effects over ten recording seeds (`cargo test --release
/// --test integration -- --ignored two_hidden_effects_over_seeds
/// --nocapture`, ~40 s): clock drift named first every time, both in at
/// least half of the runs.
#[ebptv_macros::unit_test]
#[ignore]
fn two_hidden_effects_over_seeds() {
    let truth = hot_pixels_and_clock_drift();
    let (mut first, mut both) = (0, 0);
    for seed in 100..110u64 {
        let res = check_hidden(&truth, seed, seed + 10, None, 3);
        let names: Vec<&str> = res.effects.iter().map(|e| e.name.as_str()).collect();
        println!("seed {seed}: {names:?}");
        first += (names.first() == Some(&"clock_drift")) as usize;
        both += truth.iter().all(|t| names.contains(&t.name.as_str())) as usize;
    }
    println!("clock drift first {first} of 10, both {both} of 10");
    assert_eq!(first, 10);
    assert!(both >= 5, "{both} of 10");
}

// Not met (default judgement): hot pixels 23 px × 2089 Hz + latency jitter
// 14.2 µs. Round 1: `intensity_latency` leaves 78.6 of 2160, the true
// `latency_jitter` 95.7 (both leave the hot pixels' part): a near tie of
// two rival explanations of the burst's width, so nothing is accepted
// ("unexplained").
#[ebptv_macros::unit_test]
#[ignore]
fn real_sim_two_hidden_effects_hot_pixels_and_latency_jitter() {
    let truth = [
        setting(
            "hot_pixels",
            &[
                ("count", strength(64, 20.0, 60.0).round()),
                ("rate_hz", strength(65, 300.0, 3000.0)),
            ],
        ),
        setting("latency_jitter", &[("spread_us", strength(63, 6.0, 15.0))]),
    ];
    assert_both_found(&truth, 62, 72);
}

// Not met (default judgement): background noise 13.5 Hz + latency jitter 14.2 µs.
// `off_events` with τ at its range's end (300 µs) is named first and
// leaves 310 of 3255: its OFF events mimic both the OFF half of the
// background (spread over the period by the long decay) and the jitter
// (OFF events after the burst widen the all-events latency histogram);
// no signature separates ON-only latency from OFF activity well enough.
#[ebptv_macros::unit_test]
#[ignore]
fn real_sim_two_hidden_effects_background_and_latency_jitter() {
    let truth = [
        setting("background_noise", &[("rate_hz", strength(62, 3.0, 15.0))]),
        setting("latency_jitter", &[("spread_us", strength(63, 6.0, 15.0))]),
    ];
    assert_both_found(&truth, 62, 72);
}
