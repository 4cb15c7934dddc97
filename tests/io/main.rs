//! Integration tests of the io area, one binary (modules by concern).

mod cli_info_convert;
mod real_files;
mod roundtrip;
mod sim_roundtrip;
