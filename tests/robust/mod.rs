//! Damaged and unexpected recordings (issue: bounded memory, no false
//! pulses, no leftovers): regression cases built from the real recordings
//! in ../shared/data (skipped when absent) and a property test of the whole
//! chain.

mod damaged;
mod fuzz;
