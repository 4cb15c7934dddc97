//! Model check: where simulation and measured data disagree, which effect
//! is missing, fitted, with the gap before and after.
//!
//! The building blocks:
//! - [`signatures`]: summaries (histograms, profiles, scalars) computed by
//!   one code path on measured and simulated events, with binnings fixed by
//!   a shared [`signatures::SignatureConfig`];
//! - [`distance`]: distances between signatures (Wasserstein, chi-square,
//!   profile and scalar differences), standardised against
//!   simulation-vs-simulation replicates, and the ranking table.

pub mod baseline;
pub mod distance;
pub mod report;
pub mod scene;
pub mod signatures;
pub mod workflow;
