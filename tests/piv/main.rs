//! Integration tests of the piv area, one binary (modules by concern).

mod accuracy;
mod cli;
#[allow(dead_code)]
#[path = "../cli_common/mod.rs"]
mod cli_common;
mod flows;
mod image_formats;
mod pyramid;
mod sim;
