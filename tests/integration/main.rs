//! The integration tests: one binary, each area a module (`tests/<area>/`),
//! as ripgrep keeps one. One binary links the library once and runs every
//! test on the test threads together, instead of one area after the other.
//!
//! One area: `cargo test --release --test integration ptv::`.

#[path = "../cli/mod.rs"]
mod cli;
#[path = "../grid/mod.rs"]
mod grid;
#[path = "../io/mod.rs"]
mod io;
#[path = "../modelcheck/mod.rs"]
mod modelcheck;
#[path = "../piv/mod.rs"]
mod piv;
#[path = "../ptv/mod.rs"]
mod ptv;
#[path = "../pulses/mod.rs"]
mod pulses;
#[path = "../robust/mod.rs"]
mod robust;
#[path = "../sim/mod.rs"]
mod sim;

/// The library's unit tests (`#[ebptv_macros::unit_test]` in src/), under
/// their module paths: `cargo test --release --test integration unit::grid::`.
mod unit {
    include!(concat!(env!("OUT_DIR"), "/unit_tests.rs"));
}

// Helpers shared by several areas.
#[path = "../cli_common/mod.rs"]
mod cli_common;
#[path = "../grid_common/mod.rs"]
mod grid_common;
#[path = "../turning_gen/mod.rs"]
mod turning_gen;
