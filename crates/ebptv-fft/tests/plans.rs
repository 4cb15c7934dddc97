//! The plans against the defining sum, through the crate's public functions
//! (an integration test: the crate is compiled once, not again as a
//! unit-test harness with its RustFFT instantiations).

use ebptv_fft::{plan_f32, plan_f64, Complex32, Complex64, Direction};

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
                            let a = sign * 2.0 * std::f64::consts::PI * (j * k) as f64 / n as f64;
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
