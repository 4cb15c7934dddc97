//! Unit tests of the grid and spectra stages: binning, merging, estimates
//! against known flows, Welch spectra, and the simulated chain scored
//! against the simulator's flow.

pub(crate) mod accuracy;
pub(crate) mod chain_common;
// Shared with the command tests in tests/grid/.
#[path = "../../../tests/grid_common/mod.rs"]
pub(crate) mod grid_common;
pub(crate) mod merge;
pub(crate) mod sim;
pub(crate) mod welch;
