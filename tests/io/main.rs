//! Integration tests of the io area, one binary (modules by concern).

mod aedat4_zstd;
mod cli_info_convert;
mod decode;
mod fuzz;
mod npy_numpy;
mod real_files;
mod reference;
mod roundtrip;
mod sim_roundtrip;
mod sniff;
