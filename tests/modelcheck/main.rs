//! Integration tests of the modelcheck area, one binary (modules by concern).

mod baseline;
mod cli;
mod decision;
mod hidden_more;
#[path = "../modelcheck_common/mod.rs"]
mod modelcheck_common;
mod scene;
mod signatures;
mod workflow;
