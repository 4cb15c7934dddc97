//! Integration tests of the pulses area, one binary (modules by concern).

mod cli;
#[allow(dead_code)]
#[path = "../cli_common/mod.rs"]
mod cli_common;
mod live;
#[allow(dead_code)]
#[path = "../robust/mod.rs"]
mod robust;
mod sim;
mod simulator;
