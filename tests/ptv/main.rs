//! Integration tests of the ptv area, one binary (modules by concern).

mod accuracy;
#[path = "../chain_common/mod.rs"]
mod chain_common;
mod cli;
#[allow(dead_code)]
#[path = "../cli_common/mod.rs"]
mod cli_common;
mod fit_accuracy;
mod oracle;
mod sim;
mod slice;
#[allow(dead_code)]
#[path = "../turning_gen/mod.rs"]
mod turning_gen;
mod vortex_core;
