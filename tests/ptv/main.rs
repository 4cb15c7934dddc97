//! Integration tests of the ptv area, one binary (modules by concern).

mod accuracy;
mod bounds;
#[path = "../chain_common/mod.rs"]
mod chain_common;
mod cli;
#[allow(dead_code)]
#[path = "../cli_common/mod.rs"]
mod cli_common;
mod conditions;
mod diagnose;
mod fit_accuracy;
mod ghost;
mod oracle;
mod sim;
mod slice;
mod swaps;
mod synth_export;
#[allow(dead_code)]
#[path = "../turning_gen/mod.rs"]
mod turning_gen;
mod velocity_breakdown;
mod vortex_core;
