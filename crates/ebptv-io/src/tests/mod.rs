//! Unit tests of the readers and writers: each decoder against plain
//! reference decoders and the `evt3` crate, fuzzed inputs, format sniffing,
//! AEDAT 4 compression, and NumPy loading our `.npy` files.

pub(crate) mod aedat4_zstd;
pub(crate) mod decode;
pub(crate) mod fuzz;
pub(crate) mod npy_numpy;
pub(crate) mod reference;
pub(crate) mod sniff;
