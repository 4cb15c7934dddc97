//! Model check: where simulation and measured data disagree, which effect
//! is missing, fitted, with the gap before and after.
//!
//! (Design notes to be written with the implementation.)
