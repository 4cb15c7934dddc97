//! Integration tests of the ptv area, one binary (modules by concern).

mod cli;
#[allow(dead_code)]
#[path = "../cli_common/mod.rs"]
mod cli_common;
mod sim;
#[allow(dead_code)]
#[path = "../turning_gen/mod.rs"]
mod turning_gen;
mod vortex_core;
