//! Synthetic track samples from analytic flows, for the grid tests.
#![allow(dead_code)]

use std::path::Path;

use ebptv::grid::Sample;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Normal};
use rand_pcg::Pcg64;

/// Lamb–Oseen vortex centred at (xc, yc): core radius rc (px), peak
/// azimuthal speed `vmax` (px/s, reached at r ≈ 1.1209 rc).
#[derive(Clone, Copy)]
pub struct Vortex {
    pub xc: f64,
    pub yc: f64,
    pub rc: f64,
    pub vmax: f64,
}

impl Vortex {
    pub fn velocity(&self, x: f64, y: f64) -> (f64, f64) {
        let (dx, dy) = (x - self.xc, y - self.yc);
        let r2 = dx * dx + dy * dy;
        // u_θ = Γ/(2πr)(1 − e^{−r²/rc²}); Γ/(2π rc) = vmax / 0.638_16.
        let k = self.vmax / 0.638_161_4 * self.rc;
        let f = if r2 < 1e-12 {
            1.0 / (self.rc * self.rc)
        } else {
            (1.0 - (-r2 / (self.rc * self.rc)).exp()) / r2
        };
        (-k * f * dy, k * f * dx)
    }
}

/// Tracks of `n_samples` points, `dt_us` apart, seeded uniformly in
/// [0, w) × [0, h), advected (RK2) by `flow`; velocity samples get white
/// noise of rms `noise` (px/s). Rows grouped by track, as in tracks.csv.
#[allow(clippy::too_many_arguments)]
pub fn tracks_in_steady_flow(
    flow: impl Fn(f64, f64) -> (f64, f64),
    w: f64,
    h: f64,
    n_tracks: usize,
    n_samples: usize,
    dt_us: f64,
    noise: f64,
    seed: u64,
) -> Vec<Sample> {
    let mut rng = Pcg64::seed_from_u64(seed);
    let nz = Normal::new(0.0, noise.max(1e-300)).unwrap();
    let dt = dt_us * 1e-6;
    let mut out = Vec::with_capacity(n_tracks * n_samples);
    for id in 0..n_tracks {
        let (mut x, mut y) = (rng.gen::<f64>() * w, rng.gen::<f64>() * h);
        let t0 = rng.gen_range(0..1000) as f64 * dt_us;
        for k in 0..n_samples {
            let (u, v) = flow(x, y);
            let (nu, nv) = if noise > 0.0 {
                (nz.sample(&mut rng), nz.sample(&mut rng))
            } else {
                (0.0, 0.0)
            };
            out.push(Sample {
                x,
                y,
                u: u + nu,
                v: v + nv,
                t_us: t0 + k as f64 * dt_us,
                track_id: id as u64,
            });
            let (u1, v1) = flow(x + 0.5 * dt * u, y + 0.5 * dt * v);
            x += dt * u1;
            y += dt * v1;
        }
    }
    out
}

/// Homogeneous "turbulent" shear flow: U = u0 + shear·y, V = 0, plus
/// fluctuations with rms (su, sv) and correlation coefficient rho, an AR(1)
/// process along each track (correlation `corr` between consecutive
/// samples), so consecutive samples of a track are not independent.
pub struct Shear {
    pub u0: f64,
    pub shear: f64,
    pub su: f64,
    pub sv: f64,
    pub rho: f64,
}

impl Shear {
    pub fn uu(&self) -> f64 {
        self.su * self.su
    }
    pub fn vv(&self) -> f64 {
        self.sv * self.sv
    }
    pub fn uv(&self) -> f64 {
        self.rho * self.su * self.sv
    }
    pub fn mean_u(&self, y: f64) -> f64 {
        self.u0 + self.shear * y
    }

    #[allow(clippy::too_many_arguments)]
    pub fn tracks(
        &self,
        w: f64,
        h: f64,
        n_tracks: usize,
        n_samples: usize,
        dt_us: f64,
        corr: f64,
        seed: u64,
    ) -> Vec<Sample> {
        let mut rng = Pcg64::seed_from_u64(seed);
        let n01 = Normal::new(0.0, 1.0).unwrap();
        let dt = dt_us * 1e-6;
        let c2 = (1.0 - self.rho * self.rho).sqrt();
        let innov = (1.0 - corr * corr).sqrt();
        let mut out = Vec::with_capacity(n_tracks * n_samples);
        for id in 0..n_tracks {
            let (mut x, mut y) = (rng.gen::<f64>() * w, rng.gen::<f64>() * h);
            let (mut a, mut b): (f64, f64) = (n01.sample(&mut rng), n01.sample(&mut rng));
            for k in 0..n_samples {
                if k > 0 {
                    a = corr * a + innov * n01.sample(&mut rng);
                    b = corr * b + innov * n01.sample(&mut rng);
                }
                let up = self.su * a;
                let vp = self.sv * (self.rho * a + c2 * b);
                let u = self.mean_u(y) + up;
                let v = vp;
                out.push(Sample {
                    x,
                    y,
                    u,
                    v,
                    t_us: k as f64 * dt_us,
                    track_id: id as u64,
                });
                x += u * dt;
                y += v * dt;
            }
        }
        out
    }
}

pub fn median(mut v: Vec<f64>) -> f64 {
    assert!(!v.is_empty(), "median of nothing");
    v.sort_by(|a, b| a.total_cmp(b));
    v[v.len() / 2]
}

/// Samples written as a tracks CSV (the file contract's columns; pulses
/// of 100 µs).
pub fn write_tracks(path: &Path, s: &[Sample]) {
    let mut t = String::from("track_id,pulse,t_us,x,y,u,v\n");
    for p in s {
        t.push_str(&format!(
            "{},{},{},{},{},{},{}\n",
            p.track_id,
            (p.t_us / 100.0).round() as i64,
            p.t_us,
            p.x,
            p.y,
            p.u,
            p.v
        ));
    }
    std::fs::write(path, t).unwrap();
}
