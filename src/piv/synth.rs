//! Synthetic particle images with a known displacement field, for tests,
//! benchmarks and the peer comparison.
//!
//! Particles are seeded uniformly (density in particles per pixel) over the
//! image plus a margin, so that particles flow in through the borders, and
//! advanced from frame to frame by a displacement field `f(x, y)` (px per
//! frame step) with a midpoint (RK2) step. Each frame renders either
//! Gaussian particle images at sub-pixel positions (classic PIV images), or
//! — `binary_sigma` set — pulsed-event pseudo-images: one lit pixel at the
//! rounded particle position, blurred, as `super::pseudo` builds them
//! from events.

use rand::{Rng, SeedableRng};

use super::pseudo::{blur, gaussian_kernel};
use super::Image;

/// Options of the synthetic image generator.
#[derive(Debug, Clone, Copy, PartialEq)]
#[ebptv_macros::testkit]
pub(crate) struct SynthOptions {
    /// Image width (px).
    pub width: usize,
    /// Image height (px).
    pub height: usize,
    /// Particles per pixel.
    pub ppp: f64,
    /// Gaussian particle image σ (px) (diameter ≈ 4σ).
    pub particle_sigma: f64,
    /// Number of frames.
    pub frames: usize,
    /// `Some(σ)`: render binary pseudo-images blurred with σ instead.
    pub binary_sigma: Option<f64>,
    /// Random seed.
    pub seed: u64,
}

impl Default for SynthOptions {
    fn default() -> Self {
        SynthOptions {
            width: 256,
            height: 256,
            ppp: 0.02,
            particle_sigma: 0.8,
            frames: 2,
            binary_sigma: None,
            seed: 1,
        }
    }
}

/// Uniformly random particle positions at density `o.ppp` over the image
/// enlarged by `margin` on every side (so particles move in and out).
fn seed_particles(o: &SynthOptions, rng: &mut rand_pcg::Pcg64, margin: f64) -> Vec<(f64, f64)> {
    let (ew, eh) = (
        o.width as f64 + 2.0 * margin,
        o.height as f64 + 2.0 * margin,
    );
    let n = (o.ppp * ew * eh).round() as usize;
    (0..n)
        .map(|_| {
            (
                rng.gen::<f64>() * ew - margin,
                rng.gen::<f64>() * eh - margin,
            )
        })
        .collect()
}

/// Generate `o.frames` frames of particles moved by `disp` per frame step.
#[ebptv_macros::testkit]
pub(crate) fn particle_frames(
    o: &SynthOptions,
    disp: &dyn Fn(f64, f64) -> (f64, f64),
) -> Vec<Image> {
    let mut rng = rand_pcg::Pcg64::seed_from_u64(o.seed);
    // Margin wide enough for the largest displacement over the sequence.
    let mut vmax: f64 = 0.0;
    for j in 0..=8 {
        for i in 0..=8 {
            let (u, v) = disp(
                i as f64 * o.width as f64 / 8.0,
                j as f64 * o.height as f64 / 8.0,
            );
            vmax = vmax.max(u.abs()).max(v.abs());
        }
    }
    let margin = (vmax * o.frames as f64).ceil() + 4.0;
    let mut pts = seed_particles(o, &mut rng, margin);
    let kernel = o.binary_sigma.map(gaussian_kernel);
    let mut tmp = Vec::new();
    let mut frames = Vec::with_capacity(o.frames);
    for _ in 0..o.frames {
        frames.push(render_frame(o, &pts, kernel.as_deref(), &mut tmp));
        for p in pts.iter_mut() {
            let (u, v) = disp(p.0, p.1);
            let (um, vm) = disp(p.0 + 0.5 * u, p.1 + 0.5 * v);
            p.0 += um;
            p.1 += vm;
        }
    }
    frames
}

#[cfg(feature = "testkit")]
/// Frames of particles in a spatially uniform but accelerating motion:
/// frame `k` shows every particle at `p + d0·k + a·k²/2`, so the
/// displacement from frame `k` to `k+1` is `d0 + a·(k + ½)` and the velocity
/// (px per frame step) at frame time `t` is `d0 + a·t`.
pub(crate) fn accelerating_frames(o: &SynthOptions, d0: (f64, f64), a: (f64, f64)) -> Vec<Image> {
    let mut rng = rand_pcg::Pcg64::seed_from_u64(o.seed);
    let n = o.frames as f64;
    let reach = |d: f64, a: f64| (d.abs() * n + 0.5 * a.abs() * n * n).ceil() + 4.0;
    let margin = reach(d0.0, a.0).max(reach(d0.1, a.1));
    let start = seed_particles(o, &mut rng, margin);
    let kernel = o.binary_sigma.map(gaussian_kernel);
    let mut tmp = Vec::new();
    (0..o.frames)
        .map(|k| {
            let t = k as f64;
            let pts: Vec<(f64, f64)> = start
                .iter()
                .map(|&(x, y)| {
                    (
                        x + d0.0 * t + 0.5 * a.0 * t * t,
                        y + d0.1 * t + 0.5 * a.1 * t * t,
                    )
                })
                .collect();
            render_frame(o, &pts, kernel.as_deref(), &mut tmp)
        })
        .collect()
}

/// One frame of particles at `pts`: Gaussian particle images, or binary
/// pixels blurred with `kernel`.
fn render_frame(
    o: &SynthOptions,
    pts: &[(f64, f64)],
    kernel: Option<&[f32]>,
    tmp: &mut Vec<f32>,
) -> Image {
    let mut img = Image::zeros(o.width, o.height);
    match kernel {
        Some(k) => {
            for &(x, y) in pts {
                let (xi, yi) = (x.round(), y.round());
                if xi >= 0.0 && yi >= 0.0 && (xi as usize) < o.width && (yi as usize) < o.height {
                    img.data[yi as usize * o.width + xi as usize] = 1.0;
                }
            }
            blur(&mut img, k, tmp);
        }
        None => {
            let s = o.particle_sigma;
            let r = (3.0 * s).ceil() as i64;
            let c = 1.0 / (2.0 * s * s);
            for &(x, y) in pts {
                let (xc, yc) = (x.round() as i64, y.round() as i64);
                for yy in (yc - r).max(0)..=(yc + r).min(o.height as i64 - 1) {
                    for xx in (xc - r).max(0)..=(xc + r).min(o.width as i64 - 1) {
                        let d2 = (xx as f64 - x).powi(2) + (yy as f64 - y).powi(2);
                        img.data[yy as usize * o.width + xx as usize] += (-d2 * c).exp() as f32;
                    }
                }
            }
        }
    }
    img
}
