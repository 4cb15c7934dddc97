//! Unit tests of the readers and writers: each decoder against plain
//! reference decoders and the `evt3` crate, fuzzed inputs, format sniffing,
//! AEDAT 4 compression, and NumPy loading our `.npy` files.

mod aedat4_zstd;
mod decode;
mod fuzz;
mod npy_numpy;
mod reference;
mod sniff;
