//! Model check: where simulation and measured data disagree, which effect
//! is missing, fitted, with the gap before and after.
//!
//! The building blocks:
//! - `signatures`: summaries (histograms, profiles, scalars) computed by
//!   one code path on measured and simulated events, with binnings fixed by
//!   a shared `signatures::SignatureConfig`;
//! - `distance`: distances between signatures (Wasserstein, chi-square,
//!   profile and scalar differences), standardised against
//!   simulation-vs-simulation replicates, and the ranking table;
//! - `workflow`: the search (assess, fit every candidate, judge on
//!   held-out data, accept only a winner that beats chance and clearly
//!   beats its best rival, joint refit, repeat);
//! - `scene`: the bridge to `crate::sim` (the catalogue of switchable
//!   effects, including `clock_drift`, and the processing the measurement
//!   went through);
//! - `baseline`: the starting model built from the measurement itself;
//! - `standard`: the search against a standard sensor calibrated to the
//!   measurement (the default without a starting model): a yardstick per
//!   signature that tolerates what a well-behaved sensor may show, and the
//!   acceptance rule (half the gap, a clear lead over every rival);
//! - [`check`]: the whole run of `ebptv model-check` on a recording;
//! - `report`: `model_check.json`, the fitted scenario, Markdown + PNG.

pub(crate) mod baseline;
pub mod check;
pub(crate) mod distance;
pub(crate) mod report;
pub(crate) mod scene;
pub(crate) mod signatures;
pub(crate) mod standard;
pub(crate) mod workflow;

#[cfg(feature = "testkit")]
pub(crate) mod tests;
