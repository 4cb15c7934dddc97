//! Integration tests of the grid area (modules by concern).

mod calib_mask;
mod cli;
mod shedding;
mod shedding_dev;
mod to_dir;
