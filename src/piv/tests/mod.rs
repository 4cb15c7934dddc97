//! Unit tests of PIV: correlation, peaks, multipass and the image pyramid
//! against known flows.

mod accuracy;
mod flows;
mod pyramid;
