//! Unit tests of the grid and spectra stages: binning, merging, estimates
//! against known flows, Welch spectra, and the simulated chain scored
//! against the simulator's flow.

mod accuracy;
mod chain_common;
// Shared with the command tests in tests/grid/.
#[path = "../../../tests/grid_common/mod.rs"]
mod grid_common;
mod merge;
mod sim;
mod welch;
