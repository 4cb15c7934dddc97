//! Integration tests of the grid area, one binary (modules by concern).

mod accuracy;
mod calib_mask;
#[path = "../chain_common/mod.rs"]
mod chain_common;
mod cli;
#[path = "../grid_common/mod.rs"]
mod grid_common;
mod merge;
mod shedding;
mod shedding_dev;
mod sim;
mod to_dir;
mod welch;
