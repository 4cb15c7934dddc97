//! Velocity fields with exact u(x, y, t) (px, px/s, s).
//!
//! Every field is analytic (or, for `Gridded`, exactly the interpolant of
//! the user's grid), so the truth velocity of a particle is the field at its
//! position, not a finite difference. Fields that are not plainly parallel
//! derive from a stream function, which makes them divergence-free by
//! construction: particles neither bunch nor thin out, and ppp stays what the
//! scenario says.
//!
//! The unsteady fields are evaluated with the branch-free `exp`, `sin` and
//! `cos` of `sim::fastmath` (within 4e-16 of libm; the plain libm
//! formulas stay as the tests' reference) and on several points at once
//! (`Flow::velocity_lanes`): RK4 advection evaluates them four times per
//! particle and pulse, and libm's `cos` alone was two thirds of the CPU of
//! the turbulent preset.
//!
//! The turbulent field has its own RK4 sub-step
//! (`Turbulent::rk4_substep`): its modes' phases e^{iθ} are carried
//! from stage to stage and from step to step by rotations through small
//! angles (short polynomials, no range reduction; the advection by the
//! mean flow cancels in the phase increment), with a per-lane fallback to
//! the full field where an increment leaves the polynomials' domain.
//! Rounding-level differences only (tested against the full field and
//! the plain formulas); 16 modes × 4 stages of `cos` were most of the
//! advection's CPU.
//!
//! The gridded field (the model check replays a measured mean flow
//! through it) has lanes too (`Gridded::velocity_lanes`): each lane's
//! cell is located on its own (a uniform-spacing guess and at most a
//! step or two of correction: integer work), its four nodes gathered,
//! and the fractions' divisions and the bilinear arithmetic done for all
//! lanes at once, in the scalar formula's order (every lane is the
//! scalar interpolant bit for bit, tested). Its particles then move in
//! groups like those of the analytic fields. One at a time, the RK4
//! loop and its calls into the scalar interpolant were ~40 % of a model
//! check's CPU; in groups, about a quarter (the same instructions, run
//! several lanes to a register and without a call per stage).

use std::path::Path;

use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;

use super::fastmath;
use super::scenario::FlowSpec;
use crate::simd::Lanes;
use ebptv_io::error::{Error, Result};

/// A built velocity field.
#[derive(Debug, Clone)]
#[ebptv_macros::testkit]
pub(crate) enum Flow {
    /// The same velocity everywhere.
    Uniform {
        /// x velocity (px/s).
        u: f64,
        /// y velocity (px/s).
        v: f64,
    },
    /// Lamb–Oseen vortex on a uniform background.
    LambOseen {
        /// Core centre x (px).
        x0: f64,
        /// Core centre y (px).
        y0: f64,
        /// Circulation Γ (px²/s).
        gamma: f64,
        /// Squared core radius (px²).
        rc2: f64,
        /// 1/rc2 (the lane formula multiplies).
        inv_rc2: f64,
        /// Background x velocity (px/s).
        u: f64,
        /// Background y velocity (px/s).
        v: f64,
    },
    /// Plane Poiseuille channel along x.
    Poiseuille {
        /// Centre-line velocity (px/s).
        u_max: f64,
        /// Lower wall y (px).
        y0: f64,
        /// Channel width (px).
        width: f64,
    },
    /// Laminar boundary layer (Pohlhausen profile) along x.
    BoundaryLayer {
        /// Free-stream velocity (px/s).
        u_inf: f64,
        /// Layer thickness (px).
        delta: f64,
        /// Wall position y (px).
        wall_y: f64,
    },
    /// Random divergence-free Fourier modes on a mean shear flow.
    Turbulent(Box<Turbulent>),
    /// Plane jet: two tanh shear layers.
    Jet {
        /// Centre-line velocity (px/s).
        u_center: f64,
        /// Co-flow velocity (px/s).
        u_coflow: f64,
        /// Jet axis y (px).
        y_center: f64,
        /// Half width (px).
        half_width: f64,
        /// Shear-layer thickness (px).
        thickness: f64,
    },
    /// Periodic vortex shedding behind an obstacle.
    Shedding(Shedding),
    /// A user's steady field on a grid.
    Gridded(Box<Gridded>),
    /// Tests: the field evaluated by its plain formulas (libm), never in
    /// lanes: the reference the fast fields are advected against.
    #[cfg(feature = "testkit")]
    Plain(Box<Flow>),
}

/// Random Fourier modes of a stream function ψ = Σ a_n sin(k_n·x − ω_n t + φ_n)
/// on a mean shear flow.
#[derive(Debug, Clone)]
#[ebptv_macros::testkit]
pub(crate) struct Turbulent {
    /// Mean x velocity at `y_ref` (px/s).
    pub u_mean: f64,
    /// Mean y velocity (px/s).
    pub v_mean: f64,
    /// Mean shear du/dy (1/s).
    pub shear: f64,
    /// Reference y of the mean shear (px).
    pub y_ref: f64,
    /// (a k_x, a k_y, k_x, k_y, ω, φ) per mode.
    modes: Vec<[f64; 6]>,
    /// max |k_x| and max |k_y| over the modes (the bound of a phase
    /// increment by a displacement: [`Turbulent::rk4_substep`]).
    kx_max: f64,
    ky_max: f64,
}

/// The phases of the turbulent modes at a point, as (cos θ, sin θ) per
/// mode, and the scratch of [`Turbulent::rk4_substep`].
#[derive(Debug, Clone)]
pub(crate) struct Phases<T> {
    /// e^{iθ} per mode at the point a sub-step starts from.
    pub(crate) cs: Vec<(T, T)>,
    /// Fresh phases (a fallback's, or the caller's for stale lanes).
    pub(crate) fresh: Vec<(T, T)>,
    /// Per mode within a sub-step: e^{iθ₂} (then e^{iθ₁+2iα}), sin α,
    /// cos α − 1.
    w: Vec<[T; 4]>,
}

impl<T: Lanes> Phases<T> {
    pub(crate) fn new(n_modes: usize) -> Phases<T> {
        let z = T::splat(0.0);
        Phases {
            cs: vec![(z, z); n_modes],
            fresh: vec![(z, z); n_modes],
            w: vec![[z; 4]; n_modes],
        }
    }
}

/// Tests: lanes of [`Turbulent::rk4_substep`] that took the fallback
/// (all threads: the advection runs on rayon's).
#[cfg(feature = "testkit")]
pub(crate) static FALLBACK_LANES: std::sync::atomic::AtomicU64 =
    std::sync::atomic::AtomicU64::new(0);

/// Periodic vortex shedding behind an obstacle (built from [`FlowSpec::Shedding`]).
#[derive(Debug, Clone)]
#[ebptv_macros::testkit]
pub(crate) struct Shedding {
    u_inf: f64,
    x0: f64,
    yc: f64,
    size: f64,
    deficit: f64,
    width: f64,
    /// Shedding frequency (Hz).
    pub frequency_hz: f64,
    /// Stream-function amplitude and wavenumber of the travelling wave.
    a: f64,
    k: f64,
    /// 1/width and 1/size: the lane formula multiplies (a division by a
    /// constant costs ~5 multiplications of throughput).
    inv_width: f64,
    inv_size: f64,
}

/// A steady field on a regular grid, bilinearly interpolated (built from [`FlowSpec::Gridded`]).
#[derive(Debug, Clone)]
#[ebptv_macros::testkit]
pub(crate) struct Gridded {
    xs: Vec<f64>,
    ys: Vec<f64>,
    /// Nodes per unit length along x and y ([`Gridded::per_unit`]): the
    /// uniform-spacing guess of [`Gridded::locate`] by a multiplication.
    x_per_unit: f64,
    y_per_unit: f64,
    /// (u, v) per node, row-major (y, then x): one lookup reads both
    /// components from the same cache lines.
    uv: Vec<[f64; 2]>,
}

impl Flow {
    /// Builds the field a scenario describes; errors when the description is invalid or a grid file cannot be read.
    #[ebptv_macros::testkit]
    pub(crate) fn build(spec: &FlowSpec) -> Result<Flow> {
        Ok(match spec {
            FlowSpec::Uniform { u, v } => Flow::Uniform { u: *u, v: *v },
            FlowSpec::LambOseen {
                x0,
                y0,
                circulation,
                core_radius,
                u,
                v,
            } => Flow::LambOseen {
                x0: *x0,
                y0: *y0,
                gamma: *circulation,
                rc2: core_radius * core_radius,
                inv_rc2: 1.0 / (core_radius * core_radius),
                u: *u,
                v: *v,
            },
            FlowSpec::Poiseuille { u_max, y0, width } => Flow::Poiseuille {
                u_max: *u_max,
                y0: *y0,
                width: *width,
            },
            FlowSpec::BoundaryLayer {
                u_inf,
                delta,
                wall_y,
            } => Flow::BoundaryLayer {
                u_inf: *u_inf,
                delta: *delta,
                wall_y: *wall_y,
            },
            FlowSpec::Turbulent {
                u_mean,
                v_mean,
                shear,
                y_ref,
                rms,
                length_scale,
                time_scale_s,
                n_modes,
                seed,
            } => {
                let mut rng = Pcg64::seed_from_u64(*seed);
                let n = *n_modes as usize;
                // Each mode carries velocity amplitude A = |a k|; the sum of
                // (uu + vv) = n A²/2, so A = 2 rms / sqrt(n).
                let amp = 2.0 * rms / (n as f64).sqrt();
                let modes: Vec<[f64; 6]> = (0..n)
                    .map(|_| {
                        let kmag = std::f64::consts::TAU / length_scale
                            * (0.5f64).powf(rng.gen_range(-1.0..1.0));
                        let theta: f64 = rng.gen_range(0.0..std::f64::consts::TAU);
                        let (kx, ky) = (kmag * theta.cos(), kmag * theta.sin());
                        let a = amp / kmag;
                        // Convected with the mean flow plus a random decorrelation rate.
                        let omega =
                            kx * u_mean + ky * v_mean + rng.gen_range(-1.0..1.0) / time_scale_s;
                        let phi = rng.gen_range(0.0..std::f64::consts::TAU);
                        [a * kx, a * ky, kx, ky, omega, phi]
                    })
                    .collect();
                let kmax = |i: usize| modes.iter().map(|m| m[i].abs()).fold(0.0, f64::max);
                Flow::Turbulent(Box::new(Turbulent {
                    u_mean: *u_mean,
                    v_mean: *v_mean,
                    shear: *shear,
                    y_ref: *y_ref,
                    kx_max: kmax(2),
                    ky_max: kmax(3),
                    modes,
                }))
            }
            FlowSpec::Jet {
                u_center,
                u_coflow,
                y_center,
                half_width,
                thickness,
            } => Flow::Jet {
                u_center: *u_center,
                u_coflow: *u_coflow,
                y_center: *y_center,
                half_width: *half_width,
                thickness: *thickness,
            },
            FlowSpec::Shedding {
                u_inf,
                obstacle_x,
                y_center,
                size,
                strouhal,
                amplitude,
                deficit,
                wake_width,
            } => {
                let f = strouhal * u_inf / size;
                // Vortices convect at ~0.85 u_inf behind bluff bodies.
                let k = std::f64::consts::TAU * f / (0.85 * u_inf);
                Flow::Shedding(Shedding {
                    u_inf: *u_inf,
                    x0: *obstacle_x,
                    yc: *y_center,
                    size: *size,
                    deficit: *deficit,
                    width: *wake_width,
                    frequency_hz: f,
                    a: amplitude * u_inf / k,
                    k,
                    inv_width: 1.0 / wake_width,
                    inv_size: 1.0 / size,
                })
            }
            FlowSpec::Gridded { path, scale } => {
                Flow::Gridded(Box::new(Gridded::load(path, *scale)?))
            }
        })
    }

    /// Velocity (px/s) at (x, y) px and time t (s).
    #[inline]
    #[ebptv_macros::testkit]
    pub(crate) fn velocity(&self, x: f64, y: f64, t: f64) -> (f64, f64) {
        if self.has_lanes() {
            self.velocity_lanes(x, y, t)
        } else {
            self.velocity_plain(x, y, t)
        }
    }

    /// Whether [`Flow::velocity_lanes`] evaluates all lanes at once (the
    /// analytic unsteady fields, and the gridded one: its cells located
    /// lane by lane, the interpolation in lanes); for the others it
    /// evaluates lane by lane (steady parallel flows evaluate once per
    /// particle anyway).
    pub(crate) fn has_lanes(&self) -> bool {
        matches!(
            self,
            Flow::Uniform { .. }
                | Flow::LambOseen { .. }
                | Flow::Turbulent(_)
                | Flow::Shedding(_)
                | Flow::Gridded(_)
        )
    }

    /// [`Flow::velocity`] at several points at once ([`Lanes`]: one f64,
    /// or two in an SSE2 register). One formula for both widths, with the
    /// branch-free [`fastmath`] functions, so every lane is exactly the
    /// scalar result (test `lanes_are_the_scalar_field`).
    #[inline(always)]
    pub(crate) fn velocity_lanes<T: Lanes>(&self, x: T, y: T, t: T) -> (T, T) {
        let c = T::splat;
        match self {
            Flow::Uniform { u, v } => (c(*u), c(*v)),
            Flow::LambOseen {
                x0,
                y0,
                gamma,
                rc2,
                inv_rc2,
                u,
                v,
            } => {
                let (dx, dy) = (x - c(*x0), y - c(*y0));
                let r2 = dx * dx + dy * dy;
                // u_θ/r = Γ/(2π r²)(1 − e^{−r²/rc²}); finite limit Γ/(2π rc²)
                // at r → 0 (a select: the other side's inf/NaN is dropped).
                let far = c(*gamma) / (c(std::f64::consts::TAU) * r2)
                    * (c(1.0) - fastmath::exp_lanes(-r2 * c(*inv_rc2)));
                let near = c(gamma / (std::f64::consts::TAU * rc2));
                let f = r2.select_lt(c(1e-12 * rc2), near, far);
                (c(*u) - f * dy, c(*v) + f * dx)
            }
            Flow::Turbulent(tb) => tb.velocity(x, y, t),
            Flow::Shedding(s) => s.velocity(x, y, t),
            Flow::Gridded(g) => g.velocity_lanes(x, y),
            _ => {
                // Lane by lane (at most 8 lanes).
                let mut vs = [0.0; 8];
                let u = T::from_fn(|i| {
                    let (a, b) = self.velocity_plain(x.lane(i), y.lane(i), t.lane(i));
                    vs[i] = b;
                    a
                });
                (u, T::from_fn(|i| vs[i]))
            }
        }
    }

    /// The fields without lanes (steady; evaluated once per particle),
    /// the scalar gridded interpolant, and the plain formulas of the
    /// others (libm, the reference of the tests).
    fn velocity_plain(&self, x: f64, y: f64, t: f64) -> (f64, f64) {
        match self {
            Flow::Uniform { u, v } => (*u, *v),
            Flow::LambOseen {
                x0,
                y0,
                gamma,
                rc2,
                u,
                v,
                ..
            } => {
                let (dx, dy) = (x - x0, y - y0);
                let r2 = dx * dx + dy * dy;
                let f = if r2 < 1e-12 * rc2 {
                    gamma / (std::f64::consts::TAU * rc2)
                } else {
                    gamma / (std::f64::consts::TAU * r2) * (1.0 - (-r2 / rc2).exp())
                };
                (u - f * dy, v + f * dx)
            }
            Flow::Poiseuille { u_max, y0, width } => {
                let s = (y - y0) / width;
                if (0.0..=1.0).contains(&s) {
                    (4.0 * u_max * s * (1.0 - s), 0.0)
                } else {
                    (0.0, 0.0)
                }
            }
            Flow::BoundaryLayer {
                u_inf,
                delta,
                wall_y,
            } => {
                let eta = (wall_y - y) / delta;
                if eta <= 0.0 {
                    (0.0, 0.0)
                } else if eta >= 1.0 {
                    (*u_inf, 0.0)
                } else {
                    (u_inf * (2.0 * eta - 2.0 * eta.powi(3) + eta.powi(4)), 0.0)
                }
            }
            Flow::Turbulent(tb) => tb.velocity_plain(x, y, t),
            Flow::Jet {
                u_center,
                u_coflow,
                y_center,
                half_width,
                thickness,
            } => {
                let g = 0.5 * (1.0 + ((half_width - (y - y_center).abs()) / thickness).tanh());
                (u_coflow + (u_center - u_coflow) * g, 0.0)
            }
            Flow::Shedding(s) => s.velocity_plain(x, y, t),
            Flow::Gridded(g) => g.velocity(x, y),
            #[cfg(feature = "testkit")]
            Flow::Plain(f) => f.velocity_plain(x, y, t),
        }
    }

    /// Steady flows along x whose u depends on y only: pathlines are
    /// straight lines at constant speed and advection is exact.
    pub(crate) fn is_parallel_steady(&self) -> bool {
        match self {
            Flow::Uniform { v, .. } => *v == 0.0,
            Flow::Poiseuille { .. } | Flow::BoundaryLayer { .. } | Flow::Jet { .. } => true,
            _ => false,
        }
    }

    /// Whether (x, y) is fluid (particles are seeded and recycled only there).
    pub(crate) fn is_fluid(&self, _x: f64, y: f64) -> bool {
        match self {
            Flow::Poiseuille { y0, width, .. } => y >= *y0 && y <= y0 + width,
            Flow::BoundaryLayer { wall_y, .. } => y < *wall_y,
            _ => true,
        }
    }

    /// Exact Reynolds stresses (uu, vv, uv) of the fluctuations about the
    /// mean field, when the field is a statistical one.
    #[ebptv_macros::testkit]
    pub(crate) fn known_stresses(&self) -> Option<(f64, f64, f64)> {
        match self {
            Flow::Turbulent(tb) => Some(tb.stresses()),
            _ => None,
        }
    }

    /// Mean velocity (the field without fluctuations) for statistical fields.
    #[ebptv_macros::testkit]
    pub(crate) fn mean_velocity(&self, x: f64, y: f64) -> (f64, f64) {
        match self {
            Flow::Turbulent(tb) => (tb.u_mean + tb.shear * (y - tb.y_ref), tb.v_mean),
            _ => self.velocity(x, y, 0.0),
        }
    }

    /// Shedding frequency (Hz) for the shedding flow.
    #[ebptv_macros::testkit]
    pub(crate) fn shedding_frequency_hz(&self) -> Option<f64> {
        match self {
            Flow::Shedding(s) => Some(s.frequency_hz),
            _ => None,
        }
    }
}

impl Turbulent {
    /// The mode sum with the branch-free [`fastmath::cos_lanes`], the
    /// modes in order: the plain formula but for the cos.
    #[inline(always)]
    fn velocity<T: Lanes>(&self, x: T, y: T, t: T) -> (T, T) {
        let c = T::splat;
        let mut u = c(self.u_mean) + c(self.shear) * (y - c(self.y_ref));
        let mut v = c(self.v_mean);
        for m in &self.modes {
            let cs = fastmath::cos_lanes(c(m[2]) * x + c(m[3]) * y - c(m[4]) * t + c(m[5]));
            // u = ∂ψ/∂y, v = −∂ψ/∂x.
            u = u + c(m[1]) * cs;
            v = v - c(m[0]) * cs;
        }
        (u, v)
    }

    /// Number of modes (the length of a [`Phases`]).
    pub(crate) fn n_modes(&self) -> usize {
        self.modes.len()
    }

    /// [`Turbulent::velocity`] (bit for bit: [`fastmath::sincos_lanes`]'s
    /// cos is `cos_lanes`'s) and every mode's e^{iθ} there, into `cs`.
    #[inline(always)]
    pub(crate) fn anchor<T: Lanes>(&self, x: T, y: T, t: T, cs: &mut [(T, T)]) -> (T, T) {
        let c = T::splat;
        let mut u = c(self.u_mean) + c(self.shear) * (y - c(self.y_ref));
        let mut v = c(self.v_mean);
        for (m, e) in self.modes.iter().zip(cs.iter_mut()) {
            let (sn, cs) =
                fastmath::sincos_lanes(c(m[2]) * x + c(m[3]) * y - c(m[4]) * t + c(m[5]));
            *e = (cs, sn);
            u = u + c(m[1]) * cs;
            v = v - c(m[0]) * cs;
        }
        (u, v)
    }

    /// One classical RK4 sub-step of length `h` from (x, y) at `t`, k1
    /// (the velocity there) given and every mode's e^{iθ₁} there in
    /// `ph.cs`: returns the new position and the velocity there (at
    /// t + h), and leaves the modes' e^{iθ} there in `ph.cs` (the next
    /// sub-step's start).
    ///
    /// No range reduction: every stage's phase is a nearby one's plus a
    /// small increment, turned by a rotation with short polynomials
    /// ([`fastmath::sincos_small`], [`fastmath::sincos_tiny`]). With
    /// s_i the stage offsets (s₂ = h/2 k1, s₃ = h/2 k2, s₄ = h k3, s₅ the
    /// RK4 move) and α = k·s₂ − ω h/2 (the advection by the mean flow
    /// cancels in it: |α| is k times the move relative to the mean
    /// flow): θ₂ = θ₁ + α, θ₃ = θ₂ + k·(s₃ − s₂), θ₄ = θ₁ + 2α +
    /// k·(s₄ − 2s₂), θ₅ = θ₁ + 2α + k·(s₅ − 2s₂); the last increments are
    /// O(h²) (bounded per lane by k_max·|Δ|). The stages' positions, the
    /// weights and the move are the generic `rk4`'s expressions.
    ///
    /// Fallback: a lane whose |α| exceeds [`fastmath::SMALL_ANGLE`] for
    /// some mode or whose increment bound exceeds
    /// [`fastmath::TINY_ANGLE`] (short wavelengths, long steps) takes the
    /// generic sub-step (full `cos` per stage) and fresh phases at the
    /// end. Everything is per lane on the lane's own numbers, so a group
    /// gives each particle's scalar result bit for bit.
    #[inline(always)]
    pub(crate) fn rk4_substep<T: Lanes>(
        &self,
        x: T,
        y: T,
        k1: (T, T),
        t: T,
        h: T,
        ph: &mut Phases<T>,
    ) -> (T, T, T, T) {
        let c = T::splat;
        let mean_u = |y: T| c(self.u_mean) + c(self.shear) * (y - c(self.y_ref));
        let (kxm, kym) = (c(self.kx_max), c(self.ky_max));
        let (k1x, k1y) = k1;
        let hh = c(0.5) * h;
        // Stage 2 at x + h/2 k1, t + h/2: θ₂ = θ₁ + α.
        let (sx2, sy2) = (hh * k1x, hh * k1y);
        let (mut u2, mut v2) = (mean_u(y + sy2), c(self.v_mean));
        let mut amax = c(0.0);
        for ((m, e), w) in self.modes.iter().zip(&ph.cs).zip(ph.w.iter_mut()) {
            let a = c(m[2]) * sx2 + c(m[3]) * sy2 - c(m[4]) * hh;
            let aa = a.abs();
            amax = amax.select_lt(aa, aa, amax);
            let (sa, ca1) = fastmath::sincos_small(a);
            let (c1, s1) = *e;
            let c2 = c1 + (c1 * ca1 - s1 * sa);
            let s2 = s1 + (s1 * ca1 + c1 * sa);
            *w = [c2, s2, sa, ca1];
            u2 = u2 + c(m[1]) * c2;
            v2 = v2 - c(m[0]) * c2;
        }
        // Stage 3 at x + h/2 k2, t + h/2: θ₃ = θ₂ + k·(s₃ − s₂).
        let (sx3, sy3) = (hh * u2, hh * v2);
        let (dx, dy) = (sx3 - sx2, sy3 - sy2);
        let b3 = kxm * dx.abs() + kym * dy.abs();
        let (mut u3, mut v3) = (mean_u(y + sy3), c(self.v_mean));
        for (m, w) in self.modes.iter().zip(&ph.w) {
            let (se, ce1) = fastmath::sincos_tiny(c(m[2]) * dx + c(m[3]) * dy);
            let c3 = w[0] + (w[0] * ce1 - w[1] * se);
            u3 = u3 + c(m[1]) * c3;
            v3 = v3 - c(m[0]) * c3;
        }
        // Stage 4 at x + h k3, t + h: θ₄ = θ₂ + α + k·(s₄ − 2 s₂).
        let (sx4, sy4) = (h * u3, h * v3);
        let (dx, dy) = (sx4 - (sx2 + sx2), sy4 - (sy2 + sy2));
        let b4 = kxm * dx.abs() + kym * dy.abs();
        let (mut u4, mut v4) = (mean_u(y + sy4), c(self.v_mean));
        for (m, w) in self.modes.iter().zip(ph.w.iter_mut()) {
            let [c2, s2, sa, ca1] = *w;
            let c4 = c2 + (c2 * ca1 - s2 * sa);
            let s4 = s2 + (s2 * ca1 + c2 * sa);
            (w[0], w[1]) = (c4, s4);
            let (se, ce1) = fastmath::sincos_tiny(c(m[2]) * dx + c(m[3]) * dy);
            let cth = c4 + (c4 * ce1 - s4 * se);
            u4 = u4 + c(m[1]) * cth;
            v4 = v4 - c(m[0]) * cth;
        }
        let h6 = h / c(6.0);
        let nx = x + h6 * (k1x + c(2.0) * u2 + c(2.0) * u3 + u4);
        let ny = y + h6 * (k1y + c(2.0) * v2 + c(2.0) * v3 + v4);
        // The end at t + h: θ₅ = θ₂ + α + k·(s₅ − 2 s₂), the next start.
        let (dx, dy) = ((nx - x) - (sx2 + sx2), (ny - y) - (sy2 + sy2));
        let b5 = kxm * dx.abs() + kym * dy.abs();
        let (mut u5, mut v5) = (mean_u(ny), c(self.v_mean));
        for ((m, w), e) in self.modes.iter().zip(&ph.w).zip(ph.cs.iter_mut()) {
            let (se, ce1) = fastmath::sincos_tiny(c(m[2]) * dx + c(m[3]) * dy);
            let (c4, s4) = (w[0], w[1]);
            let c5 = c4 + (c4 * ce1 - s4 * se);
            let s5 = s4 + (s4 * ce1 + c4 * se);
            *e = (c5, s5);
            u5 = u5 + c(m[1]) * c5;
            v5 = v5 - c(m[0]) * c5;
        }
        // Lanes out of the polynomials' domains (a NaN bound too): 1.
        let (tiny, out) = (c(fastmath::TINY_ANGLE), |b: T, lim: T| {
            b.select_lt(lim, c(0.0), c(1.0))
        });
        let bad =
            out(amax, c(fastmath::SMALL_ANGLE)) + out(b3, tiny) + out(b4, tiny) + out(b5, tiny);
        let mut res = (nx, ny, u5, v5);
        if (0..T::N).any(|i| bad.lane(i) != 0.0) {
            #[cfg(feature = "testkit")]
            FALLBACK_LANES.fetch_add(
                (0..T::N).filter(|&i| bad.lane(i) != 0.0).count() as u64,
                std::sync::atomic::Ordering::Relaxed,
            );
            let fb = self.rk4_substep_full(x, y, k1, t, h, &mut ph.fresh);
            let sel = |fast: T, full: T| bad.select_lt(c(0.5), fast, full);
            res = (sel(nx, fb.0), sel(ny, fb.1), sel(u5, fb.2), sel(v5, fb.3));
            for (e, f) in ph.cs.iter_mut().zip(&ph.fresh) {
                *e = (sel(e.0, f.0), sel(e.1, f.1));
            }
        }
        res
    }

    /// The generic RK4 sub-step (the full field per stage, as `rk4` in
    /// `seeding`) and fresh phases at its end, into `cs`: the fallback of
    /// [`Turbulent::rk4_substep`]. The stage formula is written out here
    /// and in `rk4` on purpose: one shared step taking the field as a
    /// closure compiles the closure without the caller's AVX2 target
    /// feature and does not inline it (tried: `rib_wake` 4.7× slower).
    #[inline(always)]
    fn rk4_substep_full<T: Lanes>(
        &self,
        x: T,
        y: T,
        k1: (T, T),
        t: T,
        h: T,
        cs: &mut [(T, T)],
    ) -> (T, T, T, T) {
        let c = T::splat;
        let (k1x, k1y) = k1;
        let hh = c(0.5) * h;
        let (k2x, k2y) = self.velocity(x + hh * k1x, y + hh * k1y, t + hh);
        let (k3x, k3y) = self.velocity(x + hh * k2x, y + hh * k2y, t + hh);
        let (k4x, k4y) = self.velocity(x + h * k3x, y + h * k3y, t + h);
        let h6 = h / c(6.0);
        let nx = x + h6 * (k1x + c(2.0) * k2x + c(2.0) * k3x + k4x);
        let ny = y + h6 * (k1y + c(2.0) * k2y + c(2.0) * k3y + k4y);
        let (u, v) = self.anchor(nx, ny, t + h, cs);
        (nx, ny, u, v)
    }

    /// The plain formula (libm cos).
    fn velocity_plain(&self, x: f64, y: f64, t: f64) -> (f64, f64) {
        let mut u = self.u_mean + self.shear * (y - self.y_ref);
        let mut v = self.v_mean;
        for m in &self.modes {
            let c = (m[2] * x + m[3] * y - m[4] * t + m[5]).cos();
            u += m[1] * c;
            v -= m[0] * c;
        }
        (u, v)
    }

    /// Time-averaged (uu, vv, uv) at any point: with distinct frequencies,
    /// cross terms average out and each mode contributes half its square.
    pub(crate) fn stresses(&self) -> (f64, f64, f64) {
        let (mut uu, mut vv, mut uv) = (0.0, 0.0, 0.0);
        for m in &self.modes {
            uu += 0.5 * m[1] * m[1];
            vv += 0.5 * m[0] * m[0];
            uv -= 0.5 * m[0] * m[1];
        }
        (uu, vv, uv)
    }
}

impl Shedding {
    /// The field with the branch-free [`fastmath`] functions and
    /// multiplications by the reciprocals of width and size (the plain
    /// formula's operations otherwise).
    #[inline(always)]
    fn velocity<T: Lanes>(&self, x: T, y: T, t: T) -> (T, T) {
        let c = T::splat;
        let (inv_w, inv_s) = (c(self.inv_width), c(self.inv_size));
        let eta = (y - c(self.yc)) * inv_w;
        let g = fastmath::exp_lanes(-eta * eta);
        let dg = c(-2.0) * eta * inv_w * g;
        // Smooth onset of the wave behind the obstacle (logistic in x).
        let s = c(1.0) / (c(1.0) + fastmath::exp_lanes(-(x - c(self.x0)) * inv_s));
        let ds = s * (c(1.0) - s) * inv_s;
        let theta = c(std::f64::consts::TAU * self.frequency_hz) * t - c(self.k) * x;
        let (sn, cs) = (fastmath::sin_lanes(theta), fastmath::cos_lanes(theta));
        let u = c(self.u_inf) * (c(1.0) - c(self.deficit) * s * g) + c(self.a) * s * dg * sn;
        // The deficit's stream function ∫U(1 − d s g)dy depends on x through
        // s; its −∂/∂x part keeps the field divergence-free.
        let erf_part = c(self.u_inf * self.deficit)
            * ds
            * c(self.width)
            * c(0.5)
            * c(std::f64::consts::PI.sqrt())
            * erf_given_exp(eta, g);
        let v = erf_part - c(self.a) * g * (ds * sn - c(self.k) * s * cs);
        (u, v)
    }

    /// The plain formula (libm exp and sin_cos).
    fn velocity_plain(&self, x: f64, y: f64, t: f64) -> (f64, f64) {
        let eta = (y - self.yc) / self.width;
        let g = (-eta * eta).exp();
        let dg = -2.0 * eta / self.width * g;
        let s = 1.0 / (1.0 + (-(x - self.x0) / self.size).exp());
        let ds = s * (1.0 - s) / self.size;
        let theta = std::f64::consts::TAU * self.frequency_hz * t - self.k * x;
        let (sn, cs) = theta.sin_cos();
        let u = self.u_inf * (1.0 - self.deficit * s * g) + self.a * s * dg * sn;
        let erf_part = self.u_inf
            * self.deficit
            * ds
            * self.width
            * 0.5
            * std::f64::consts::PI.sqrt()
            * erf_plain(eta);
        let v = erf_part - self.a * g * (ds * sn - self.k * s * cs);
        (u, v)
    }
}

#[cfg(feature = "testkit")]
/// Error function (Abramowitz–Stegun 7.1.26, |error| < 1.5e-7).
#[inline]
pub(crate) fn erf(x: f64) -> f64 {
    erf_lanes(x)
}

#[cfg(feature = "testkit")]
/// [`erf`] per lane, with [`fastmath::exp_lanes`].
#[inline(always)]
fn erf_lanes<T: Lanes>(x: T) -> T {
    erf_given_exp(x, fastmath::exp_lanes(-x * x))
}

/// [`erf_lanes`] with its exp(−x²) given: the shedding field has it
/// already (its Gaussian g; the same bits, as (−|x|)|x| = (−x)x).
#[inline(always)]
fn erf_given_exp<T: Lanes>(x: T, exp_minus_x2: T) -> T {
    let c = T::splat;
    let s = x.sign_one();
    let x = x.abs();
    let t = c(1.0) / (c(1.0) + c(0.327_591_1) * x);
    let y = c(1.0)
        - (((((c(1.061_405_429) * t - c(1.453_152_027)) * t) + c(1.421_413_741)) * t
            - c(0.284_496_736))
            * t
            + c(0.254_829_592))
            * t
            * exp_minus_x2;
    s * y
}

/// [`erf`] with libm exp (the reference).
fn erf_plain(x: f64) -> f64 {
    let s = x.signum();
    let x = x.abs();
    let t = 1.0 / (1.0 + 0.327_591_1 * x);
    let y = 1.0
        - (((((1.061_405_429 * t - 1.453_152_027) * t) + 1.421_413_741) * t - 0.284_496_736) * t
            + 0.254_829_592)
            * t
            * (-x * x).exp();
    s * y
}

impl Gridded {
    /// Reads a grid field from a CSV file `x,y,u,v`; `scale` multiplies u and v.
    pub(crate) fn load(path: &Path, scale: f64) -> Result<Gridded> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let mut lines = text
            .lines()
            .enumerate()
            .filter(|(_, l)| !l.trim().is_empty());
        let (_, header) = lines.next().ok_or_else(|| Error::Empty {
            path: path.into(),
            why: "empty velocity-field file".into(),
        })?;
        let cols: Vec<String> = header
            .split(',')
            .map(|c| c.trim().to_ascii_lowercase())
            .collect();
        let idx = |name: &str| {
            cols.iter()
                .position(|c| c == name)
                .ok_or_else(|| Error::Config {
                    path: path.into(),
                    why: format!("header lacks column `{name}` (need x,y,u,v)"),
                })
        };
        let (ix, iy, iu, iv) = (idx("x")?, idx("y")?, idx("u")?, idx("v")?);
        let mut rows = Vec::new();
        for (ln, line) in lines {
            let f: Vec<&str> = line.split(',').collect();
            let get = |i: usize| -> Result<f64> {
                let v: f64 = f
                    .get(i)
                    .and_then(|s| s.trim().parse().ok())
                    .ok_or_else(|| Error::Config {
                        path: path.into(),
                        why: format!("line {}: bad number in column {}", ln + 1, cols[i]),
                    })?;
                if v.is_finite() {
                    Ok(v)
                } else {
                    Err(Error::Config {
                        path: path.into(),
                        why: format!("line {}: non-finite {}", ln + 1, cols[i]),
                    })
                }
            };
            rows.push((get(ix)?, get(iy)?, get(iu)? * scale, get(iv)? * scale));
        }
        let uniq = |mut v: Vec<f64>| {
            v.sort_by(f64::total_cmp);
            v.dedup();
            v
        };
        let xs = uniq(rows.iter().map(|r| r.0).collect());
        let ys = uniq(rows.iter().map(|r| r.1).collect());
        if xs.len() < 2 || ys.len() < 2 {
            return Err(Error::Config {
                path: path.into(),
                why: "need at least 2 distinct x and 2 distinct y grid nodes".into(),
            });
        }
        let n = xs.len() * ys.len();
        let mut u = vec![f64::NAN; n];
        let mut v = vec![f64::NAN; n];
        for r in &rows {
            let i = xs.binary_search_by(|a| a.total_cmp(&r.0)).unwrap();
            let j = ys.binary_search_by(|a| a.total_cmp(&r.1)).unwrap();
            u[j * xs.len() + i] = r.2;
            v[j * xs.len() + i] = r.3;
        }
        if let Some(k) = u.iter().position(|a| a.is_nan()) {
            return Err(Error::Config {
                path: path.into(),
                why: format!(
                    "not a full regular grid: node x={}, y={} missing",
                    xs[k % xs.len()],
                    ys[k / xs.len()]
                ),
            });
        }
        Ok(Gridded {
            x_per_unit: Self::per_unit(&xs),
            y_per_unit: Self::per_unit(&ys),
            uv: u.iter().zip(&v).map(|(&a, &b)| [a, b]).collect(),
            xs,
            ys,
        })
    }

    /// Intervals per unit length of an axis of ≥ 2 increasing nodes.
    fn per_unit(axis: &[f64]) -> f64 {
        (axis.len() - 1) as f64 / (axis[axis.len() - 1] - axis[0])
    }

    /// The interval of `axis` holding `x` and the fraction along it
    /// (clamped at the ends); `per_unit` is [`Gridded::per_unit`] of it.
    #[inline(always)]
    fn locate(axis: &[f64], per_unit: f64, x: f64) -> (usize, f64) {
        let (i, [a, b, d]) = Self::locate_parts(axis, per_unit, x);
        (i, (a - b) / d)
    }

    /// [`Gridded::locate`] without its division: the interval and
    /// (a, b, d) with (a − b)/d the fraction, i.e. (x, its lower node,
    /// the interval's length) inside and (0, 0, 1) or (1, 0, 1) (exactly
    /// 0 and 1) when clamped. The lanes path divides all lanes at once.
    #[inline(always)]
    fn locate_parts(axis: &[f64], per_unit: f64, x: f64) -> (usize, [f64; 3]) {
        if x <= axis[0] {
            return (0, [0.0, 0.0, 1.0]);
        }
        let last = axis.len() - 1;
        if x >= axis[last] {
            return (last - 1, [1.0, 0.0, 1.0]);
        }
        // The last node at or below x, as `partition_point(|a| *a <= x) - 1`
        // would find it, but started from the uniform-spacing guess: the
        // gridded fields the baseline builds are uniform, so the two
        // correction loops run zero or one step instead of a binary search
        // per velocity lookup (11 % of a model check's CPU). Exact for any
        // axis: the loops walk to the same node.
        let guess = (x - axis[0]) * per_unit;
        let mut i = (guess as usize).min(last - 1);
        while i + 1 < last && axis[i + 1] <= x {
            i += 1;
        }
        while axis[i] > x {
            i -= 1;
        }
        (i, [x, axis[i], axis[i + 1] - axis[i]])
    }

    /// Bilinear interpolation. Both lookups inlined: their divisions (the
    /// fraction along each axis) then overlap instead of waiting in turn.
    #[inline]
    fn velocity(&self, x: f64, y: f64) -> (f64, f64) {
        let (i, fx) = Self::locate(&self.xs, self.x_per_unit, x);
        let (j, fy) = Self::locate(&self.ys, self.y_per_unit, y);
        let w = self.xs.len();
        let (n00, n10) = (self.uv[j * w + i], self.uv[j * w + i + 1]);
        let (n01, n11) = (self.uv[(j + 1) * w + i], self.uv[(j + 1) * w + i + 1]);
        let bil = |c: usize| {
            (n00[c] * (1.0 - fx) + n10[c] * fx) * (1.0 - fy)
                + (n01[c] * (1.0 - fx) + n11[c] * fx) * fy
        };
        (bil(0), bil(1))
    }

    /// [`Gridded::velocity`] at several points at once: per lane the
    /// cells are located (integer work, [`Gridded::locate_parts`]) and
    /// their four nodes gathered; the fractions' divisions and the
    /// bilinear arithmetic run in lanes, with the scalar formula's
    /// operations in its order, so every lane is the scalar result bit
    /// for bit (test `gridded_lanes_are_the_scalar_interpolant`).
    #[inline(always)]
    fn velocity_lanes<T: Lanes>(&self, x: T, y: T) -> (T, T) {
        let w = self.xs.len();
        // Per lane (the lane in the last index, so each row loads as one
        // value): the fractions' parts along x and y, and the cell's nodes
        // (i, j), (i + 1, j), (i, j + 1), (i + 1, j + 1) for u, then v.
        let (mut px, mut py) = ([[0.0; 8]; 3], [[0.0; 8]; 3]);
        let mut nodes = [[0.0; 8]; 8];
        for l in 0..T::N {
            let (i, a) = Self::locate_parts(&self.xs, self.x_per_unit, x.lane(l));
            let (j, b) = Self::locate_parts(&self.ys, self.y_per_unit, y.lane(l));
            for c in 0..3 {
                (px[c][l], py[c][l]) = (a[c], b[c]);
            }
            // Two adjacent pairs, one slice (bounds check) each.
            let k = j * w + i;
            let (r0, r1) = (&self.uv[k..k + 2], &self.uv[k + w..k + w + 2]);
            for c in 0..2 {
                nodes[4 * c][l] = r0[0][c];
                nodes[4 * c + 1][l] = r0[1][c];
                nodes[4 * c + 2][l] = r1[0][c];
                nodes[4 * c + 3][l] = r1[1][c];
            }
        }
        let fx = (rows::<T>(&px[0]) - rows::<T>(&px[1])) / rows::<T>(&px[2]);
        let fy = (rows::<T>(&py[0]) - rows::<T>(&py[1])) / rows::<T>(&py[2]);
        let (gx, gy) = (T::splat(1.0) - fx, T::splat(1.0) - fy);
        (
            bilinear(&nodes[..4], (fx, gx), (fy, gy)),
            bilinear(&nodes[4..], (fx, gx), (fy, gy)),
        )
    }

    /// The bilinear interpolant by binary search and the component arrays
    /// as loaded: the reference [`Gridded::velocity`] is tested against.
    #[cfg(feature = "testkit")]
    fn velocity_reference(&self, x: f64, y: f64) -> (f64, f64) {
        let find = |axis: &[f64], x: f64| -> (usize, f64) {
            let last = axis.len() - 1;
            if x <= axis[0] {
                return (0, 0.0);
            }
            if x >= axis[last] {
                return (last - 1, 1.0);
            }
            let i = axis.partition_point(|a| *a <= x) - 1;
            (i, (x - axis[i]) / (axis[i + 1] - axis[i]))
        };
        let (i, fx) = find(&self.xs, x);
        let (j, fy) = find(&self.ys, y);
        let w = self.xs.len();
        let comp = |c: usize| -> Vec<f64> { self.uv.iter().map(|n| n[c]).collect() };
        let bil = |a: &[f64]| {
            let a00 = a[j * w + i];
            let a10 = a[j * w + i + 1];
            let a01 = a[(j + 1) * w + i];
            let a11 = a[(j + 1) * w + i + 1];
            (a00 * (1.0 - fx) + a10 * fx) * (1.0 - fy) + (a01 * (1.0 - fx) + a11 * fx) * fy
        };
        (bil(&comp(0)), bil(&comp(1)))
    }
}

/// The first `T::N` values of a row as lanes.
#[inline(always)]
fn rows<T: Lanes>(a: &[f64; 8]) -> T {
    T::from_fn(|l| a[l])
}

/// The bilinear formula of [`Gridded::velocity`] in lanes (the same
/// operations in the same order): `n` the rows of the four nodes,
/// (fx, 1 − fx) and (fy, 1 − fy) the fractions. A function, not a
/// closure: closures called from the AVX2 dispatch are not always
/// inlined, and then lose its target features.
#[inline(always)]
fn bilinear<T: Lanes>(n: &[[f64; 8]], (fx, gx): (T, T), (fy, gy): (T, T)) -> T {
    (rows::<T>(&n[0]) * gx + rows::<T>(&n[1]) * fx) * gy
        + (rows::<T>(&n[2]) * gx + rows::<T>(&n[3]) * fx) * fy
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;

    fn divergence(f: &Flow, x: f64, y: f64, t: f64) -> f64 {
        let h = 1e-3;
        let (u1, _) = f.velocity(x + h, y, t);
        let (u0, _) = f.velocity(x - h, y, t);
        let (_, v1) = f.velocity(x, y + h, t);
        let (_, v0) = f.velocity(x, y - h, t);
        (u1 - u0 + v1 - v0) / (2.0 * h)
    }

    #[ebptv_macros::unit_test]
    fn locate_matches_binary_search_on_any_axis() {
        let uniform: Vec<f64> = (0..41).map(|k| 16.0 * k as f64 + 8.0).collect();
        let skewed: Vec<f64> = (0..30).map(|k| (k as f64).powi(3) * 0.01 - 5.0).collect();
        for axis in [&uniform, &skewed] {
            let (lo, hi) = (axis[0], axis[axis.len() - 1]);
            let mut xs: Vec<f64> = (0..5000)
                .map(|k| lo + (hi - lo) * (k as f64 / 4999.0))
                .collect();
            xs.extend(axis.iter().copied());
            xs.extend(axis.iter().map(|a| a + 1e-12));
            xs.extend(axis.iter().map(|a| a - 1e-12));
            for x in xs {
                if x <= lo || x >= hi {
                    continue;
                }
                let i = axis.partition_point(|a| *a <= x) - 1;
                let want = (i, (x - axis[i]) / (axis[i + 1] - axis[i]));
                assert_eq!(
                    Gridded::locate(axis, Gridded::per_unit(axis), x),
                    want,
                    "x = {x}"
                );
            }
        }
    }

    #[ebptv_macros::unit_test]
    fn fields_are_divergence_free() {
        let specs = [
            FlowSpec::LambOseen {
                x0: 100.0,
                y0: 80.0,
                circulation: 5e5,
                core_radius: 20.0,
                u: 10.0,
                v: 0.0,
            },
            FlowSpec::Turbulent {
                u_mean: 2000.0,
                v_mean: 0.0,
                shear: 3.0,
                y_ref: 0.0,
                rms: 300.0,
                length_scale: 60.0,
                time_scale_s: 0.01,
                n_modes: 32,
                seed: 7,
            },
            FlowSpec::Shedding {
                u_inf: 5000.0,
                obstacle_x: 100.0,
                y_center: 300.0,
                size: 40.0,
                strouhal: 0.145,
                amplitude: 0.3,
                deficit: 0.4,
                wake_width: 60.0,
            },
        ];
        for s in &specs {
            let f = Flow::build(s).unwrap();
            let mut scale = 0.0f64;
            for k in 0..50 {
                let (x, y) = (13.7 * k as f64, 300.0 + 7.1 * k as f64 - 170.0);
                let (u, v) = f.velocity(x, y, 1e-3 * k as f64);
                scale = scale.max(u.abs() + v.abs());
                let d = divergence(&f, x, y, 1e-3 * k as f64);
                assert!(
                    d.abs() < 1e-5 * scale.max(1.0),
                    "{s:?}: div {d} at ({x},{y})"
                );
            }
        }
    }

    #[ebptv_macros::unit_test]
    fn lamb_oseen_profile() {
        let f = Flow::build(&FlowSpec::LambOseen {
            x0: 0.0,
            y0: 0.0,
            circulation: 1000.0,
            core_radius: 5.0,
            u: 0.0,
            v: 0.0,
        })
        .unwrap();
        let r: f64 = 50.0; // far field: potential vortex
        let (_, v) = f.velocity(r, 0.0, 0.0);
        let expect = 1000.0 / (std::f64::consts::TAU * r) * (1.0 - (-(r * r) / 25.0).exp());
        assert!((v - expect).abs() < 1e-12);
        assert!(v > 0.0, "counter-clockwise circulation turns +x into +y");
    }

    /// The fields with lanes and the fast functions against their plain
    /// formulas (libm): the turbulent mode sum (the preset's 16 modes and
    /// 61 others), the rib wake and the demo vortex (with its core), on
    /// and around the presets' ROIs, for 100 s of phases: the difference
    /// stays below 1e-15 of the size of the terms summed (rounding).
    #[ebptv_macros::unit_test]
    fn fast_fields_match_plain_formulas() {
        let mut specs = vec![];
        for name in ["turbulent_bl", "rib_wake", "demo"] {
            specs.push(crate::presets::preset(name).unwrap().flow);
        }
        specs.push(FlowSpec::Turbulent {
            u_mean: -3000.0,
            v_mean: 500.0,
            shear: 4.0,
            y_ref: 100.0,
            rms: 900.0,
            length_scale: 40.0,
            time_scale_s: 0.001,
            n_modes: 61,
            seed: 2,
        });
        for spec in &specs {
            let f = Flow::build(spec).unwrap();
            assert!(f.has_lanes());
            let mut worst = 0.0f64;
            for k in 0..200_000u64 {
                let h = |s: u64| ((k.wrapping_mul(s) % 100_003) as f64) / 100_003.0;
                let (x, y, t) = (
                    -50.0 + 1400.0 * h(7919),
                    -50.0 + 820.0 * h(104_729),
                    100.0 * h(31),
                );
                let (u, v) = f.velocity(x, y, t);
                let (ur, vr) = f.velocity_plain(x, y, t);
                // The size of the terms summed: the error scale.
                let scale = match &f {
                    Flow::Turbulent(tb) => {
                        let amp: f64 = tb.modes.iter().map(|m| m[0].abs() + m[1].abs()).sum();
                        amp + tb.u_mean.abs() + (tb.shear * (y - tb.y_ref)).abs()
                    }
                    // 1 − e^{−r²/rc²} cancels near the core: an error of
                    // ε in exp is ε Γ/(2π r) in the velocity, for libm too.
                    Flow::LambOseen { x0, y0, gamma, .. } => {
                        let r = (x - x0).hypot(y - y0);
                        ur.abs() + vr.abs() + gamma.abs() / (std::f64::consts::TAU * r)
                    }
                    _ => ur.abs() + vr.abs() + 1.0,
                };
                worst = worst.max((u - ur).abs().max((v - vr).abs()) / scale);
            }
            assert!(worst < 1e-15, "{spec:?}: {worst:e}");
        }
        // The vortex core: the finite limit.
        let f = Flow::build(&specs[2]).unwrap();
        let Flow::LambOseen { x0, y0, .. } = f else {
            panic!()
        };
        for d in [0.0, 1e-9, 1e-6, 1e-3] {
            let (a, b) = (
                f.velocity(x0 + d, y0 - d, 0.0),
                f.velocity_plain(x0 + d, y0 - d, 0.0),
            );
            assert!(
                (a.0 - b.0).abs() + (a.1 - b.1).abs() <= 1e-12 * (b.0.abs() + b.1.abs() + 1.0),
                "{d}"
            );
        }
    }

    /// Two points at once give each point's scalar velocity bit for bit,
    /// for every field (the lane-by-lane fallback included).
    #[ebptv_macros::unit_test]
    fn lanes_are_the_scalar_field() {
        use crate::simd::F64x2;
        let mut specs = vec![];
        for name in crate::presets::names() {
            specs.push(crate::presets::preset(name).unwrap().flow);
        }
        specs.push(FlowSpec::Uniform { u: 3.0, v: -2.0 });
        specs.push(FlowSpec::Poiseuille {
            u_max: 100.0,
            y0: 10.0,
            width: 300.0,
        });
        for spec in &specs {
            let f = Flow::build(spec).unwrap();
            for k in 0..20_000u64 {
                let h = |s: u64| ((k.wrapping_mul(s) % 10_007) as f64) / 10_007.0;
                let p = [
                    (
                        -50.0 + 1400.0 * h(7919),
                        -50.0 + 820.0 * h(104_729),
                        2.0 * h(31),
                    ),
                    (-50.0 + 1400.0 * h(13), -50.0 + 820.0 * h(101), 2.0 * h(7)),
                ];
                let (u, v) = f.velocity_lanes(
                    F64x2::new([p[0].0, p[1].0]),
                    F64x2::new([p[0].1, p[1].1]),
                    F64x2::new([p[0].2, p[1].2]),
                );
                for (i, q) in p.iter().enumerate() {
                    let (su, sv) = f.velocity(q.0, q.1, q.2);
                    assert_eq!(
                        (u.to_array()[i].to_bits(), v.to_array()[i].to_bits()),
                        (su.to_bits(), sv.to_bits()),
                        "{spec:?} at {q:?}"
                    );
                }
            }
        }
    }

    /// One sub-step of [`Turbulent::rk4_substep`] (phases by small
    /// rotations) against the full-field sub-step, and its phases carried
    /// over 200 sub-steps against fresh ones, on the preset's field with
    /// 2.5 px moves. One step: positions within 2e-13 px, velocities
    /// within 4e-15 of the mode amplitudes' sum, phases within 3e-14 of
    /// fresh ones (whose own phase k·x − ω t + φ, up to ~50 rad, is
    /// rounded to 7e-15). 200 steps: phases within 4e-13 of fresh ones
    /// (~130 rad, rounded to 3e-14) and |e^{iθ}|² within 2e-14 of 1
    /// (the carried rotations' drift).
    #[ebptv_macros::unit_test]
    fn turbulent_rotation_step_matches_full_step() {
        let f = Flow::build(&crate::presets::preset("turbulent_bl").unwrap().flow).unwrap();
        let Flow::Turbulent(tb) = &f else { panic!() };
        let amp: f64 = tb.modes.iter().map(|m| m[0].abs() + m[1].abs()).sum();
        let h = 1e-4;
        let mut ph = Phases::<f64>::new(tb.n_modes());
        let mut fresh = vec![(0.0, 0.0); tb.n_modes()];
        let (mut wx, mut wu, mut wp1, mut wp, mut wm) = (0.0f64, 0.0f64, 0.0f64, 0.0f64, 0.0f64);
        for k in 0..2000u64 {
            let q = |s: u64| ((k.wrapping_mul(s) % 10_007) as f64) / 10_007.0;
            // Near the origin of x and t: the full field's phase
            // k·x − ω t + φ is then rounded to ~1e-14 (at t = 1 s it
            // is ~2500 rad, rounded to 4.5e-13), below what is checked.
            let (mut x, mut y, mut t) = (60.0 * q(7919), 200.0 + 320.0 * q(104_729), 0.01 * q(31));
            let mut k1 = tb.anchor(x, y, t, &mut ph.cs);
            for step in 0..if k < 20 { 200 } else { 1 } {
                let full = tb.rk4_substep_full(x, y, k1, t, h, &mut fresh);
                let fast = tb.rk4_substep(x, y, k1, t, h, &mut ph);
                if step == 0 {
                    wx = wx.max((fast.0 - full.0).abs()).max((fast.1 - full.1).abs());
                    wu = wu.max((fast.2 - full.2).abs().max((fast.3 - full.3).abs()) / amp);
                    for (a, b) in ph.cs.iter().zip(&fresh) {
                        wp1 = wp1.max((a.0 - b.0).abs()).max((a.1 - b.1).abs());
                    }
                }
                (x, y, k1, t) = (fast.0, fast.1, (fast.2, fast.3), t + h);
            }
            tb.anchor(x, y, t, &mut fresh);
            for (a, b) in ph.cs.iter().zip(&fresh) {
                wp = wp.max((a.0 - b.0).abs()).max((a.1 - b.1).abs());
                wm = wm.max((a.0 * a.0 + a.1 * a.1 - 1.0).abs());
            }
        }
        eprintln!(
            "step: |dx| {wx:e} px, |du| {wu:e} of the amplitudes, phases {wp1:e}; \
             200 steps: phases {wp:e}, ||e^iθ|² − 1| {wm:e}"
        );
        assert!(
            wx <= 2e-13 && wu <= 4e-15 && wp1 <= 3e-14,
            "{wx:e} {wu:e} {wp1:e}"
        );
        assert!(wp <= 4e-13 && wm <= 2e-14, "{wp:e} {wm:e}");
    }

    #[ebptv_macros::unit_test]
    fn turbulent_stresses_match_time_average() {
        let f = Flow::build(&FlowSpec::Turbulent {
            u_mean: 0.0,
            v_mean: 0.0,
            shear: 0.0,
            y_ref: 0.0,
            rms: 100.0,
            length_scale: 50.0,
            time_scale_s: 0.002,
            n_modes: 8,
            seed: 3,
        })
        .unwrap();
        let (uu, vv, uv) = f.known_stresses().unwrap();
        assert!(((uu + vv) / 2.0 - 100.0f64.powi(2)).abs() < 1e-6 * 1e4);
        // Brute-force time average at a point (a long record).
        let n = 400_000;
        let (mut su, mut sv, mut suv) = (0.0, 0.0, 0.0);
        for k in 0..n {
            let (u, v) = f.velocity(10.0, 20.0, k as f64 * 5e-5);
            su += u * u;
            sv += v * v;
            suv += u * v;
        }
        let n = n as f64;
        let tol = 0.05 * (uu + vv);
        assert!((su / n - uu).abs() < tol, "uu {} vs {uu}", su / n);
        assert!((sv / n - vv).abs() < tol, "vv {} vs {vv}", sv / n);
        assert!((suv / n - uv).abs() < tol, "uv {} vs {uv}", suv / n);
    }

    #[ebptv_macros::unit_test]
    fn erf_is_accurate() {
        // Reference values of erf.
        for (x, e) in [
            (0.0, 0.0),
            (0.5, 0.520_499_877_8),
            (1.0, 0.842_700_792_9),
            (2.0, 0.995_322_265),
            (-1.0, -0.842_700_792_9),
        ] {
            assert!((erf(x) - e).abs() < 2e-7, "erf({x})");
        }
    }

    /// The gridded field in lanes ([`Gridded::velocity_lanes`], the
    /// advection's path) is the scalar interpolant bit for bit, and so
    /// the binary-search reference: at every lane width (one f64, SSE2
    /// pairs, four, and eight in AVX registers where the CPU has them),
    /// on random points inside, on nodes and cell edges, on the grid's
    /// border and outside it (clamped), on a uniform grid (as the model
    /// check's baseline writes) and on a non-uniform one.
    #[ebptv_macros::unit_test]
    fn gridded_lanes_are_the_scalar_interpolant() {
        use crate::simd::{Dispatch, F64x2, F64x4, LaneKernel};
        let mut rng = Pcg64::seed_from_u64(5);
        let grid = |xs: &[f64], ys: &[f64], rng: &mut Pcg64| {
            let uv = (0..xs.len() * ys.len())
                .map(|_| {
                    let s = 10f64.powf(rng.gen_range(-2.0..4.0));
                    [s * rng.gen_range(-1.0..1.0), s * rng.gen_range(-1.0..1.0)]
                })
                .collect();
            Gridded {
                x_per_unit: Gridded::per_unit(xs),
                y_per_unit: Gridded::per_unit(ys),
                uv,
                xs: xs.to_vec(),
                ys: ys.to_vec(),
            }
        };
        let uniform = grid(
            &(0..41).map(|k| 8.0 + 16.0 * k as f64).collect::<Vec<_>>(),
            &(0..31).map(|k| 8.0 + 16.0 * k as f64).collect::<Vec<_>>(),
            &mut rng,
        );
        let skewed = grid(
            &(0..23)
                .map(|k| (k as f64).powi(3) * 0.07 - 5.0)
                .collect::<Vec<_>>(),
            &[-3.0, 0.5, 0.75, 40.0, 41.0, 200.0],
            &mut rng,
        );
        for g in [&uniform, &skewed] {
            let (x0, x1) = (g.xs[0], *g.xs.last().unwrap());
            let (y0, y1) = (g.ys[0], *g.ys.last().unwrap());
            let pick = |rng: &mut Pcg64, axis: &[f64], lo: f64, hi: f64| -> f64 {
                let a = axis[rng.gen_range(0..axis.len())];
                match rng.gen_range(0..6) {
                    // Inside (and a little outside).
                    0 | 1 => rng.gen_range(lo - 0.05 * (hi - lo)..hi + 0.05 * (hi - lo)),
                    // On a node (cell edges, the border).
                    2 => a,
                    // Next to a node, either side.
                    3 => a + [-1.0, 1.0][rng.gen_range(0..2)] * a.abs().max(1.0) * 1e-15,
                    // Far outside: clamped.
                    4 => [lo - 1e6, hi + 1e6, lo - 1e-9, hi + 1e-9][rng.gen_range(0..4)],
                    _ => [lo, hi][rng.gen_range(0..2)],
                }
            };
            let pts: Vec<(f64, f64)> = (0..40_000)
                .map(|_| (pick(&mut rng, &g.xs, x0, x1), pick(&mut rng, &g.ys, y0, y1)))
                .collect();
            let want: Vec<(u64, u64)> = pts
                .iter()
                .map(|&(x, y)| {
                    let (u, v) = g.velocity(x, y);
                    assert_eq!((u, v), g.velocity_reference(x, y), "({x}, {y})");
                    (u.to_bits(), v.to_bits())
                })
                .collect();
            struct Eval<'a>(&'a Gridded, &'a [(f64, f64)]);
            impl LaneKernel for Eval<'_> {
                type Out = Vec<(u64, u64)>;
                #[inline(always)]
                fn run<T: Lanes>(self) -> Vec<(u64, u64)> {
                    eval::<T>(self.0, self.1)
                }
            }
            fn eval<T: Lanes>(g: &Gridded, pts: &[(f64, f64)]) -> Vec<(u64, u64)> {
                let mut out = Vec::new();
                for c in pts.chunks_exact(T::N) {
                    let (u, v) = g.velocity_lanes(T::from_fn(|l| c[l].0), T::from_fn(|l| c[l].1));
                    out.extend((0..T::N).map(|l| (u.lane(l).to_bits(), v.lane(l).to_bits())));
                }
                out
            }
            assert_eq!(eval::<f64>(g, &pts), want);
            assert_eq!(eval::<F64x2>(g, &pts), want);
            assert_eq!(eval::<F64x4>(g, &pts), want);
            assert_eq!(Dispatch::portable().run(Eval(g, &pts)), want);
            assert_eq!(Dispatch::detect().run(Eval(g, &pts)), want);
        }
    }

    #[ebptv_macros::unit_test]
    fn gridded_interpolates_and_rejects_holes() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("f.csv");
        let mut s = String::from("x,y,u,v\n");
        for j in 0..3 {
            for i in 0..4 {
                let (x, y) = (i as f64 * 10.0, j as f64 * 20.0);
                s += &format!("{x},{y},{},{}\n", 2.0 * x + y, -y);
            }
        }
        std::fs::write(&p, &s).unwrap();
        let f = Flow::build(&FlowSpec::Gridded {
            path: p.clone(),
            scale: 1.0,
        })
        .unwrap();
        let (u, v) = f.velocity(15.0, 7.0, 0.0);
        assert!(
            (u - 37.0).abs() < 1e-9 && (v + 7.0).abs() < 1e-9,
            "bilinear is exact on a linear field"
        );
        // The fast lookup (uniform guess, interleaved nodes) is the
        // reference interpolant bit for bit, inside, on nodes and outside,
        // on a field that differs from cell to cell and a non-uniform x axis.
        let q = dir.path().join("g.csv");
        let mut t = String::from("x,y,u,v\n");
        for (j, y) in [0.0, 20.0, 40.0].iter().enumerate() {
            for (i, x) in [0.0, 10.0, 25.0, 30.0].iter().enumerate() {
                t += &format!(
                    "{x},{y},{},{}\n",
                    ((i * i * 7 + j * 3) % 5) as f64,
                    (i * j) as f64
                );
            }
        }
        std::fs::write(&q, &t).unwrap();
        let g = Gridded::load(&q, 1.0).unwrap();
        for k in 0..4000 {
            let x = -7.0 + 44.0 * ((k * 37) % 4000) as f64 / 3999.0;
            let y = -5.0 + 50.0 * ((k * 91) % 4000) as f64 / 3999.0;
            assert_eq!(g.velocity(x, y), g.velocity_reference(x, y), "({x}, {y})");
        }
        for (x, y) in [(10.0, 20.0), (0.0, 0.0), (30.0, 40.0), (20.0, 40.0)] {
            assert_eq!(g.velocity(x, y), g.velocity_reference(x, y), "({x}, {y})");
        }
        let holed: String = s.lines().take(6).collect::<Vec<_>>().join("\n");
        std::fs::write(&p, holed).unwrap();
        let e = Flow::build(&FlowSpec::Gridded {
            path: p,
            scale: 1.0,
        })
        .unwrap_err()
        .to_string();
        assert!(e.contains("missing"), "{e}");
    }
}
