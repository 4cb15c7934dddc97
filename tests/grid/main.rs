//! Integration tests of the grid area, one binary (modules by concern).

mod calib_mask;
mod cli;
#[path = "../grid_common/mod.rs"]
mod grid_common;
mod shedding;
mod shedding_dev;
mod to_dir;
