//! FFT plans for ebptv's spectra, pulse timing and PIV correlation.
//!
//! RustFFT is generic over the float type: a crate that calls
//! `FftPlanner::<f64>::new()` compiles the planner and every algorithm it
//! may choose (scalar, SSE and AVX butterflies, mixed radix, Bluestein, …)
//! for that type, in that crate. In ebptv's library this was about a third
//! of its LLVM IR, compiled twice over (the library and its unit-test
//! harness) and again after every change to any of its modules. Here the
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

#[cfg(test)]
mod tests {
    use super::*;

    /// The plans against the defining sum, for a power of two, a prime
    /// (Bluestein/Rader paths) and a mixed length, in both precisions.
    #[test]
    fn plans_match_the_direct_transform() {
        for n in [16usize, 31, 60] {
            let x: Vec<Complex64> = (0..n)
                .map(|j| Complex64::new((j as f64 * 0.7).sin(), (j as f64 * 0.3).cos()))
                .collect();
            for dir in [Direction::Forward, Direction::Inverse] {
                let sign = if dir == Direction::Forward { -1.0 } else { 1.0 };
                let direct: Vec<Complex64> = (0..n)
                    .map(|k| {
                        x.iter()
                            .enumerate()
                            .map(|(j, &v)| {
                                let a =
                                    sign * 2.0 * std::f64::consts::PI * (j * k) as f64 / n as f64;
                                v * Complex64::new(a.cos(), a.sin())
                            })
                            .sum()
                    })
                    .collect();
                let mut y = x.clone();
                plan_f64(n, dir).process(&mut y);
                let mut y32: Vec<Complex32> = x
                    .iter()
                    .map(|c| Complex32::new(c.re as f32, c.im as f32))
                    .collect();
                plan_f32(n, dir).process(&mut y32);
                for k in 0..n {
                    assert!((y[k] - direct[k]).norm() < 1e-10, "f64 n={n} k={k}");
                    let e = Complex64::new(y32[k].re as f64, y32[k].im as f64) - direct[k];
                    assert!(e.norm() < 1e-4, "f32 n={n} k={k}: {e}");
                }
            }
        }
    }
}
