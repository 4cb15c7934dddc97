//! Integration tests of the piv area, one binary (modules by concern).

mod cli;
#[allow(dead_code)]
#[path = "../cli_common/mod.rs"]
mod cli_common;
mod image_formats;
mod sim;
