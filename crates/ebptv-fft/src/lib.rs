//! FFT plans for ebptv's spectra, pulse timing and PIV correlation.
//!
//! RustFFT is generic over the float type: a crate that calls
//! `FftPlanner::<f64>::new()` compiles the planner and every algorithm it
//! may choose (scalar, SSE and AVX butterflies, mixed radix, Bluestein, …)
//! for that type, in that crate. In ebptv's library this was about a third
//! of its LLVM IR, compiled again after every change to any of its
//! modules. Here the
//! planners are instantiated once, behind the non-generic functions below;
//! the library only calls the returned plans through their trait objects.
//!
//! The plans are RustFFT's own (`Arc<dyn Fft<T>>`), unnormalised like
//! RustFFT's: a forward and an inverse transform scale by `n`.
//!
//! ```
//! use ebptv_fft::{plan_f64, Complex64, Direction};
//!
//! let mut x = vec![Complex64::new(1.0, 0.0); 8];
//! plan_f64(8, Direction::Forward).process(&mut x);
//! assert_eq!(x[0], Complex64::new(8.0, 0.0)); // all power in the mean
//! plan_f64(8, Direction::Inverse).process(&mut x);
//! assert!((x[3].re - 8.0).abs() < 1e-12); // back, scaled by n
//! ```

#![warn(missing_docs)]

use std::sync::Arc;

pub use rustfft::num_complex::{Complex, Complex32, Complex64};
pub use rustfft::Fft;
use rustfft::{FftDirection, FftPlanner};

/// A forward or inverse FFT of length `n` in single precision.
pub fn plan_f32(n: usize, direction: Direction) -> Arc<dyn Fft<f32>> {
    FftPlanner::<f32>::new().plan_fft(n, direction.into())
}

/// A forward or inverse FFT of length `n` in double precision.
pub fn plan_f64(n: usize, direction: Direction) -> Arc<dyn Fft<f64>> {
    FftPlanner::<f64>::new().plan_fft(n, direction.into())
}

/// The sign of the transform's exponent.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Direction {
    /// `X_k = Σ x_j e^{-2πi jk/n}`.
    Forward,
    /// `x_j = Σ X_k e^{+2πi jk/n}` (not divided by `n`).
    Inverse,
}

impl From<Direction> for FftDirection {
    fn from(d: Direction) -> Self {
        match d {
            Direction::Forward => FftDirection::Forward,
            Direction::Inverse => FftDirection::Inverse,
        }
    }
}
