//! Unit tests of PIV: correlation, peaks, multipass and the image pyramid
//! against known flows.

pub(crate) mod accuracy;
pub(crate) mod flows;
pub(crate) mod pyramid;
