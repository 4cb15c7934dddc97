//! Integration tests of the io area (modules by concern).

mod cli_info_convert;
mod real_files;
mod roundtrip;
mod sim_roundtrip;
