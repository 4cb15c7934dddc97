//! Shared by the hidden-effect tests (modelcheck_scene, modelcheck_hidden_more):
//! the small test scene, effect settings and seeded strengths.

#![allow(dead_code)]

use std::collections::BTreeMap;

use crate::modelcheck::workflow::EffectSetting;
use crate::sim::scenario::{Scenario, Sensor};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;

/// The small scene: 160×120, 0.02 s (100 pulses), sparse seeding.
pub(crate) fn base() -> Scenario {
    let mut s = Scenario {
        name: "modelcheck-small".into(),
        duration_s: 0.02,
        sensor: Sensor {
            width: 160,
            height: 120,
            roi: None,
        },
        ..Scenario::default()
    };
    s.seeding.ppp = 0.006;
    s.light.energy = crate::sim::presets::WATER_ENERGY;
    s
}

/// A catalogue effect by name with the given parameters.
pub(crate) fn setting(name: &str, ps: &[(&str, f64)]) -> EffectSetting {
    EffectSetting {
        name: name.into(),
        parameters: ps
            .iter()
            .map(|&(k, v)| (k.to_string(), v))
            .collect::<BTreeMap<_, _>>(),
    }
}

/// A strength drawn from a seed the search never sees (log-uniform).
pub(crate) fn strength(seed: u64, lo: f64, hi: f64) -> f64 {
    let u: f64 = Pcg64::seed_from_u64(seed ^ 0x5EED).gen();
    (lo.ln() + u * (hi.ln() - lo.ln())).exp()
}
