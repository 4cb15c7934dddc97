//! Particles: seeding, advection and recycling.
//!
//! Particles live in a slab 1.5 light-sheet thicknesses deep over the ROI
//! plus a margin (so images straddling the ROI edge are right). They move
//! with the flow (exactly for steady parallel flows, else classical RK4
//! with sub-steps of at most 4 px, far finer than any field's length scale) and out of plane with a
//! per-particle constant velocity. A particle leaving the slab or the domain
//! is recycled as a *new* particle (new id): periodically wrapped in x/y
//! (which keeps the density of parallel flows exact), or re-seeded at a
//! random fluid position entering the slab from the side it left.
//!
//! Every particle slot has its own random stream, so advancing slots in
//! parallel gives the same result as advancing them one by one.
//!
//! Through the unsteady analytic fields (vortex, shedding, turbulent
//! modes) and a gridded field (a measured flow the model check replays:
//! `Gridded::velocity_lanes` locates each lane's cell and gathers its
//! nodes, then interpolates all lanes at once) particles move in groups: the RK4 stages of a group are
//! evaluated together (`Flow::velocity_lanes`; four particles in two SSE2
//! pairs, or eight in two AVX registers where the CPU has AVX2), each lane
//! with its own sub-step count, doing exactly the scalar operations on its
//! own numbers — the same bits as one particle at a time (tested), so
//! neither the grouping nor the CPU shows in the output.
//!
//! The turbulent field moves particles with its own RK4 sub-step
//! (`Turbulent::rk4_substep`, `rk4_turbulent`): each particle's mode
//! phases are carried from one pulse's step to the next (`TurbState`,
//! fresh at the start of every `advance_and_snapshot` call and after a
//! recycling), the same way in a group as one at a time.

use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, StandardNormal};
use rand_pcg::Pcg64;

use super::flow::{Flow, Phases, Turbulent};
use super::scenario::Scenario;
use super::simd::{Dispatch, LaneKernel, Lanes};
use super::stream_seed;

/// Half-depth of the slab relative to the sheet thickness.
const SLAB_HALF: f64 = 0.75;

/// Longest RK4 sub-step (px of displacement).
pub(crate) const SUBSTEP_PX: f64 = 4.0;

/// One seeded particle.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Particle {
    /// x (px).
    pub x: f64,
    /// y (px).
    pub y: f64,
    /// Out-of-plane position (sheet centre 0).
    pub z: f64,
    /// Out-of-plane velocity (px/s).
    pub w: f64,
    /// Brightness (relative).
    pub brightness: f64,
    /// Particle id.
    pub id: u64,
    generation: u64,
    /// The field's velocity at `vel_at` (bits of x, y, t; x and t zero
    /// for a steady parallel flow, whose u depends on y only): the same
    /// number a new evaluation there would give, so the next step starts
    /// from it (saves one field evaluation per particle per pulse, e.g.
    /// the jet's `tanh`, or the RK4 field's value at the snapshot). For
    /// the turbulent field, the velocity its RK4 step ended with (the
    /// carried phases': a fresh evaluation's up to rounding).
    vel: (f64, f64),
    vel_at: Option<(u64, u64, u64)>,
}

impl Particle {
    /// The key of `vel_at` for a velocity at (x, y, t).
    #[inline]
    fn vel_key(&self, parallel_steady: bool, t: f64) -> (u64, u64, u64) {
        if parallel_steady {
            (0, self.y.to_bits(), 0)
        } else {
            (self.x.to_bits(), self.y.to_bits(), t.to_bits())
        }
    }

    /// The field's velocity at the particle at time `t`, through the cache.
    #[inline]
    fn velocity(&mut self, flow: &Flow, t: f64) -> (f64, f64) {
        self.velocity_in(flow, flow.is_parallel_steady(), t)
    }

    /// [`Particle::velocity`] with `flow.is_parallel_steady()` given.
    #[inline(always)]
    fn velocity_in(&mut self, flow: &Flow, parallel_steady: bool, t: f64) -> (f64, f64) {
        let key = self.vel_key(parallel_steady, t);
        if self.vel_at != Some(key) {
            self.evaluate_velocity(flow, t, key);
        }
        self.vel
    }

    /// Fill the cache (kept out of line: the advection loops of steady
    /// parallel flows come here only when a particle is new).
    #[inline(never)]
    fn evaluate_velocity(&mut self, flow: &Flow, t: f64, key: (u64, u64, u64)) {
        self.vel = flow.velocity(self.x, self.y, t);
        self.vel_at = Some(key);
    }
}

/// The rectangle particles live in (px).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Domain {
    /// Left edge.
    pub x0: f64,
    /// Right edge.
    pub x1: f64,
    /// Top edge.
    pub y0: f64,
    /// Bottom edge.
    pub y1: f64,
}

/// A particle at one pulse, as the renderer needs it.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Snapshot {
    /// Image centre x (px).
    pub x: f64,
    /// Image centre y (px).
    pub y: f64,
    /// x velocity (px/s).
    pub u: f64,
    /// y velocity (px/s).
    pub v: f64,
    /// Brightness at this pulse (relative).
    pub brightness: f64,
    /// Particle id.
    pub id: u64,
}

/// The particles of a run and their advection.
pub(crate) struct Particles {
    /// The particles.
    pub particles: Vec<Particle>,
    rngs: Vec<Pcg64>,
    /// The rectangle they live in.
    pub domain: Domain,
    sheet_half: f64,
    slab_half: f64,
    out_of_plane_rms: f64,
    brightness_spread: f64,
}

/// The seeding domain of `sc`: its region of interest with a margin for
/// images that reach in from outside.
fn seeding_domain(sc: &Scenario) -> Domain {
    let roi = sc.roi();
    let margin = 2.0 + 1.5 * sc.optics.particle_diameter_px;
    Domain {
        x0: roi.x as f64 - 0.5 - margin,
        x1: (roi.x + roi.width) as f64 - 0.5 + margin,
        y0: roi.y as f64 - 0.5 - margin,
        y1: (roi.y + roi.height) as f64 - 0.5 + margin,
    }
}

/// The number of particles [`Particles::seed`] makes when the whole domain
/// is fluid: the upper bound the scenario's validation checks.
pub(crate) fn particle_count_bound(sc: &Scenario) -> f64 {
    let d = seeding_domain(sc);
    sc.seeding.ppp * (d.x1 - d.x0) * (d.y1 - d.y0) * SLAB_HALF / 0.5
}

impl Particles {
    /// Seeds the particles of scenario `sc` in `flow`; `seed` fixes the draws.
    pub(crate) fn seed(sc: &Scenario, flow: &Flow, seed: u64) -> Particles {
        let domain = seeding_domain(sc);
        // Fluid fraction of the domain, for the particle count.
        let mut fluid = 0usize;
        let probes = 64;
        for j in 0..probes {
            for i in 0..probes {
                let x = domain.x0 + (i as f64 + 0.5) / probes as f64 * (domain.x1 - domain.x0);
                let y = domain.y0 + (j as f64 + 0.5) / probes as f64 * (domain.y1 - domain.y0);
                fluid += flow.is_fluid(x, y) as usize;
            }
        }
        let area = (domain.x1 - domain.x0) * (domain.y1 - domain.y0) * fluid as f64
            / (probes * probes) as f64;
        let sheet_half = 0.5 * sc.seeding.sheet_thickness;
        let slab_half = SLAB_HALF * sc.seeding.sheet_thickness;
        let n = (sc.seeding.ppp * area * slab_half / sheet_half).round() as usize;
        let mut ps = Particles {
            particles: Vec::with_capacity(n),
            rngs: Vec::with_capacity(n),
            domain,
            sheet_half,
            slab_half,
            out_of_plane_rms: sc.seeding.out_of_plane_rms,
            brightness_spread: sc.seeding.brightness_spread,
        };
        for slot in 0..n {
            let mut rng = Pcg64::seed_from_u64(stream_seed(seed, 1, slot as u64));
            let mut p = Particle {
                x: 0.0,
                y: 0.0,
                z: 0.0,
                w: 0.0,
                brightness: 1.0,
                id: slot as u64,
                generation: 0,
                vel: (0.0, 0.0),
                vel_at: None,
            };
            ps.fresh(&mut p, &mut rng, flow, 0.0, None);
            ps.particles.push(p);
            ps.rngs.push(rng);
        }
        ps
    }

    /// No particles (a simulator that replays a cached motion).
    pub(crate) fn empty() -> Particles {
        Particles {
            particles: Vec::new(),
            rngs: Vec::new(),
            domain: Domain {
                x0: 0.0,
                x1: 0.0,
                y0: 0.0,
                y1: 0.0,
            },
            sheet_half: 0.0,
            slab_half: 0.0,
            out_of_plane_rms: 0.0,
            brightness_spread: 0.0,
        }
    }

    /// Number of particles.
    pub(crate) fn len(&self) -> usize {
        self.particles.len()
    }

    /// Give slot `p` a new particle: random fluid position, brightness and
    /// out-of-plane velocity; `enter_side` places it at the slab face it
    /// enters through (recycling), else anywhere in the slab.
    fn fresh(
        &self,
        p: &mut Particle,
        rng: &mut Pcg64,
        flow: &Flow,
        t: f64,
        enter_side: Option<f64>,
    ) {
        let d = &self.domain;
        let mut tries = 0;
        loop {
            p.x = rng.gen_range(d.x0..d.x1);
            p.y = rng.gen_range(d.y0..d.y1);
            tries += 1;
            if flow.is_fluid(p.x, p.y) || tries > 1000 {
                break;
            }
        }
        let _ = t;
        let g: f64 = StandardNormal.sample(rng);
        p.brightness = (self.brightness_spread * g).exp();
        let gw: f64 = StandardNormal.sample(rng);
        p.w = self.out_of_plane_rms * gw;
        p.z = match enter_side {
            Some(side) => side * self.slab_half,
            None => rng.gen_range(-self.slab_half..self.slab_half),
        };
    }

    fn renew_id(p: &mut Particle, slot: usize, n_slots: usize) {
        p.generation += 1;
        p.id = slot as u64 + n_slots as u64 * p.generation;
    }

    /// Whether the particle is lit by the sheet.
    #[inline]
    pub(crate) fn in_sheet(&self, p: &Particle) -> bool {
        p.z.abs() <= self.sheet_half
    }

    #[cfg(feature = "testkit")]
    /// Advance every particle from `t0` to each of `times` in turn (s) and
    /// return, per time, the lit particles as snapshots (in slot order).
    pub(crate) fn advance_and_snapshot(
        &mut self,
        flow: &Flow,
        t0: f64,
        times: &[f64],
    ) -> Vec<Vec<Snapshot>> {
        let mut merged = Vec::new();
        self.advance_and_snapshot_into(flow, t0, times, &mut merged);
        merged
    }

    /// [`Particles::advance_and_snapshot`] into `merged` (one list per
    /// time, the lists of an earlier call reused: a block's snapshots are
    /// ~1.5 MB at full frame, whose fresh pages cost more system time
    /// than the copy into them).
    pub(crate) fn advance_and_snapshot_into(
        &mut self,
        flow: &Flow,
        t0: f64,
        times: &[f64],
        merged: &mut Vec<Vec<Snapshot>>,
    ) {
        use rayon::prelude::*;
        // Small enough for several tasks per thread (load balance), large
        // enough to amortise the per-task vectors.
        const CHUNK: usize = 512;
        let n_slots = self.particles.len();
        let parallel_steady = flow.is_parallel_steady() && !PLAIN_ADVECTION.with(|c| c.get());
        let pairs =
            !flow.is_parallel_steady() && flow.has_lanes() && !SCALAR_ADVECTION.with(|c| c.get());
        // The same loop compiled for AVX2 (groups of eight in two AVX
        // registers instead of four in two SSE2 pairs) where the CPU has
        // it: the same arithmetic per lane, so the same bits
        // (`avx_lanes_are_the_sse2_lanes`).
        let lanes = if FORCE_SSE2.with(|c| c.get()) {
            Dispatch::portable()
        } else {
            Dispatch::detect()
        };
        let mut particles = std::mem::take(&mut self.particles);
        let mut rngs = std::mem::take(&mut self.rngs);
        let this = &*self;
        let parts: Vec<Vec<Vec<Snapshot>>> = particles
            .par_chunks_mut(CHUNK)
            .zip(rngs.par_chunks_mut(CHUNK))
            .enumerate()
            .map(|(ci, (pc, rc))| {
                // Lit: about sheet/slab of the slots.
                let expect = pc.len() * 3 / 4 + 16;
                let mut out: Vec<Vec<Snapshot>> = (0..times.len())
                    .map(|_| Vec::with_capacity(expect))
                    .collect();
                if parallel_steady {
                    this.advance_parallel(pc, rc, ci * CHUNK, n_slots, flow, t0, times, &mut out);
                    return out;
                }
                if pairs {
                    lanes.run(AdvanceLanes {
                        this,
                        pc,
                        rc,
                        slot0: ci * CHUNK,
                        n_slots,
                        flow,
                        t0,
                        times,
                        out: &mut out,
                    });
                    return out;
                }
                let mut turb = TurbState::<f64>::new(flow);
                for (k, (p, rng)) in pc.iter_mut().zip(rc.iter_mut()).enumerate() {
                    let slot = ci * CHUNK + k;
                    let mut t = t0;
                    if let Some(ts) = &mut turb {
                        ts.keys = [None; 8];
                    }
                    for (ti, &t1) in times.iter().enumerate() {
                        let known = this.step(p, rng, flow, t, t1, slot, n_slots, turb.as_mut());
                        t = t1;
                        if this.in_sheet(p) {
                            let (u, v) = known.unwrap_or_else(|| p.velocity(flow, t1));
                            out[ti].push(Snapshot {
                                x: p.x,
                                y: p.y,
                                u,
                                v,
                                brightness: p.brightness,
                                id: p.id,
                            });
                        }
                    }
                }
                out
            })
            .collect();
        self.particles = particles;
        self.rngs = rngs;
        merged.resize_with(times.len(), Vec::new);
        for (i, m) in merged.iter_mut().enumerate() {
            m.clear();
            m.reserve(parts.iter().map(|p| p[i].len()).sum());
        }
        for part in parts {
            for (m, s) in merged.iter_mut().zip(part) {
                m.extend(s);
            }
        }
    }

    /// Advance one particle from `t0` to `t1`. Returns its velocity at
    /// `t1` when that is known without evaluating the field (a steady
    /// parallel flow, u(y) only, and the particle was not recycled).
    #[allow(clippy::too_many_arguments)]
    fn step(
        &self,
        p: &mut Particle,
        rng: &mut Pcg64,
        flow: &Flow,
        t0: f64,
        t1: f64,
        slot: usize,
        n_slots: usize,
        turb: Option<&mut TurbState<f64>>,
    ) -> Option<(f64, f64)> {
        let dt = t1 - t0;
        if dt <= 0.0 {
            return None;
        }
        let (u, v) = p.velocity(flow, t0);
        let mut known = None;
        if flow.is_parallel_steady() {
            p.x += u * dt;
            known = Some((u, v));
        } else if let (Flow::Turbulent(tb), Some(ts)) = (flow, turb) {
            let n = substeps(u, v, dt);
            ts.refresh(tb, std::slice::from_ref(p), t0);
            let (x, y, u1, v1) =
                rk4_turbulent(tb, (p.x, p.y), (u, v), t0, dt, n as f64, n, &mut ts.ph);
            (p.x, p.y) = (x, y);
            ts.moved(std::slice::from_mut(p), (u1, v1), t1);
        } else {
            let n = substeps(u, v, dt);
            (p.x, p.y) = rk4(flow, (p.x, p.y), (u, v), t0, dt, n as f64, n);
        }
        p.z += p.w * dt;
        if self.recycle_if_left(p, rng, flow, t1, slot, n_slots) {
            return None;
        }
        known
    }

    /// After a move: a particle that left the slab or the domain is
    /// recycled (see the module docs) and true returned.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn recycle_if_left(
        &self,
        p: &mut Particle,
        rng: &mut Pcg64,
        flow: &Flow,
        t1: f64,
        slot: usize,
        n_slots: usize,
    ) -> bool {
        let d = &self.domain;
        if p.z.abs() > self.slab_half {
            // Left the slab: a new particle enters through the opposite face.
            let side = -p.z.signum();
            self.fresh(p, rng, flow, t1, Some(side));
            // Keep its direction into the slab.
            if p.w * side > 0.0 {
                p.w = -p.w;
            }
            Self::renew_id(p, slot, n_slots);
            return true;
        }
        let (wx, wy) = (d.x1 - d.x0, d.y1 - d.y0);
        let mut wrapped = false;
        if p.x < d.x0 || p.x >= d.x1 {
            p.x = d.x0 + (p.x - d.x0).rem_euclid(wx);
            wrapped = true;
        }
        if p.y < d.y0 || p.y >= d.y1 {
            p.y = d.y0 + (p.y - d.y0).rem_euclid(wy);
            wrapped = true;
        }
        if wrapped {
            if !flow.is_fluid(p.x, p.y) {
                self.fresh(p, rng, flow, t1, None);
            } else {
                p.z = rng.gen_range(-self.slab_half..self.slab_half);
            }
            Self::renew_id(p, slot, n_slots);
            // Wrapped in y or re-seeded: the velocity changed.
            return true;
        }
        false
    }

    /// The particle loop of [`Particles::advance_and_snapshot`] for the
    /// fields that are not steady parallel and have lanes
    /// ([`Flow::has_lanes`]: the unsteady analytic ones and the gridded): `T::N` particles at
    /// a time (a [`Dispatch`]'s lanes: four as two SSE2 pairs, or eight
    /// as two AVX registers, so two dependency chains overlap, each RK4
    /// stage needing the previous one), their RK4 stages and velocities evaluated
    /// together, lane for lane the scalar operations of
    /// [`Particles::step`] (so the same numbers, tested). Every particle's
    /// velocity at the pulse is evaluated right after its move, lit or not
    /// (the next move starts from it: the same value, only sooner).
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn advance_lanes<T: Lanes>(
        &self,
        pc: &mut [Particle],
        rc: &mut [Pcg64],
        slot0: usize,
        n_slots: usize,
        flow: &Flow,
        t0: f64,
        times: &[f64],
        out: &mut [Vec<Snapshot>],
    ) {
        // The turbulent field's phases: one state per group (lanes), one
        // per particle of a partial group.
        let mut turb = TurbState::<T>::new(flow);
        let mut turb1: Vec<Option<TurbState<f64>>> = Vec::new();
        for (k, (pp, rr)) in pc.chunks_mut(T::N).zip(rc.chunks_mut(T::N)).enumerate() {
            let slot = slot0 + k * T::N;
            let mut t = t0;
            if let Some(ts) = &mut turb {
                ts.keys = [None; 8];
            }
            if pp.len() != T::N {
                turb1 = pp.iter().map(|_| TurbState::<f64>::new(flow)).collect();
            }
            for (&t1, snaps) in times.iter().zip(out.iter_mut()) {
                if pp.len() == T::N {
                    self.step_lanes::<T>(pp, rr, flow, t, t1, slot, n_slots, turb.as_mut());
                    velocity_lanes::<T>(pp, flow, t1);
                } else {
                    // The last particles of a chunk, one by one.
                    for (i, ((p, rng), ts)) in pp
                        .iter_mut()
                        .zip(rr.iter_mut())
                        .zip(turb1.iter_mut())
                        .enumerate()
                    {
                        self.step(p, rng, flow, t, t1, slot + i, n_slots, ts.as_mut());
                        p.velocity(flow, t1);
                    }
                }
                t = t1;
                for p in pp.iter() {
                    if self.in_sheet(p) {
                        snaps.push(Snapshot {
                            x: p.x,
                            y: p.y,
                            u: p.vel.0,
                            v: p.vel.1,
                            brightness: p.brightness,
                            id: p.id,
                        });
                    }
                }
            }
        }
    }

    /// [`Particles::step`] for `T::N` particles (slots from `slot`) of a
    /// field that is not steady parallel.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn step_lanes<T: Lanes>(
        &self,
        ps: &mut [Particle],
        rngs: &mut [Pcg64],
        flow: &Flow,
        t0: f64,
        t1: f64,
        slot: usize,
        n_slots: usize,
        turb: Option<&mut TurbState<T>>,
    ) {
        let dt = t1 - t0;
        if dt <= 0.0 {
            return;
        }
        velocity_lanes::<T>(ps, flow, t0);
        let mut n_max = 0;
        let n = T::from_fn(|i| {
            let n = substeps(ps[i].vel.0, ps[i].vel.1, dt);
            n_max = n_max.max(n);
            n as f64
        });
        if let (Flow::Turbulent(tb), Some(ts)) = (flow, turb) {
            ts.refresh(tb, ps, t0);
            let (x, y, u, v) = rk4_turbulent(
                tb,
                (T::from_fn(|i| ps[i].x), T::from_fn(|i| ps[i].y)),
                (T::from_fn(|i| ps[i].vel.0), T::from_fn(|i| ps[i].vel.1)),
                t0,
                dt,
                n,
                n_max,
                &mut ts.ph,
            );
            for (i, p) in ps.iter_mut().enumerate() {
                (p.x, p.y) = (x.lane(i), y.lane(i));
            }
            ts.moved(ps, (u, v), t1);
            for (i, (p, rng)) in ps.iter_mut().zip(rngs.iter_mut()).enumerate() {
                p.z += p.w * dt;
                self.recycle_if_left(p, rng, flow, t1, slot + i, n_slots);
            }
            return;
        }
        let (x, y) = rk4(
            flow,
            (T::from_fn(|i| ps[i].x), T::from_fn(|i| ps[i].y)),
            (T::from_fn(|i| ps[i].vel.0), T::from_fn(|i| ps[i].vel.1)),
            t0,
            dt,
            n,
            n_max,
        );
        for (i, (p, rng)) in ps.iter_mut().zip(rngs.iter_mut()).enumerate() {
            (p.x, p.y) = (x.lane(i), y.lane(i));
            p.z += p.w * dt;
            self.recycle_if_left(p, rng, flow, t1, slot + i, n_slots);
        }
    }

    /// [`Particles::recycle_if_left`] out of line (the fast loop's rare
    /// case).
    #[inline(never)]
    #[allow(clippy::too_many_arguments)]
    fn recycle_cold(
        &self,
        p: &mut Particle,
        rng: &mut Pcg64,
        flow: &Flow,
        t1: f64,
        slot: usize,
        n_slots: usize,
    ) -> bool {
        self.recycle_if_left(p, rng, flow, t1, slot, n_slots)
    }

    /// The particle loop of [`Particles::advance_and_snapshot`] for a
    /// steady parallel flow: the same operations as [`Particles::step`]
    /// and the snapshot (so the same numbers, tested), with the flow's
    /// kind, the domain and the sheet hoisted out of the loop and the
    /// rare cases (a new particle's velocity, recycling) out of line, so
    /// a particle-pulse is a few multiply-adds, comparisons and a push.
    #[allow(clippy::too_many_arguments)]
    fn advance_parallel(
        &self,
        pc: &mut [Particle],
        rc: &mut [Pcg64],
        slot0: usize,
        n_slots: usize,
        flow: &Flow,
        t0: f64,
        times: &[f64],
        out: &mut [Vec<Snapshot>],
    ) {
        let d = self.domain;
        let (slab_half, sheet_half) = (self.slab_half, self.sheet_half);
        for (k, (p, rng)) in pc.iter_mut().zip(rc.iter_mut()).enumerate() {
            let slot = slot0 + k;
            let mut t = t0;
            for (&t1, snaps) in times.iter().zip(out.iter_mut()) {
                let dt = t1 - t;
                let mut known = false;
                // As `step`: only dt ≤ 0 skips the move (a NaN dt moves).
                #[allow(clippy::neg_cmp_op_on_partial_ord)]
                let moves = !(dt <= 0.0);
                if moves {
                    let (u, _) = p.velocity_in(flow, true, t);
                    p.x += u * dt;
                    known = true;
                    p.z += p.w * dt;
                    let left = p.z.abs() > slab_half
                        || p.x < d.x0
                        || p.x >= d.x1
                        || p.y < d.y0
                        || p.y >= d.y1;
                    if left && self.recycle_cold(p, rng, flow, t1, slot, n_slots) {
                        known = false;
                    }
                }
                t = t1;
                if p.z.abs() <= sheet_half {
                    let (u, v) = if known {
                        p.vel
                    } else {
                        p.velocity_in(flow, true, t1)
                    };
                    snaps.push(Snapshot {
                        x: p.x,
                        y: p.y,
                        u,
                        v,
                        brightness: p.brightness,
                        id: p.id,
                    });
                }
            }
        }
    }
}

/// RK4 sub-steps for a move of velocity (u, v) over dt: at most
/// [`SUBSTEP_PX`] each. The fields vary over tens of px, so the pathline
/// error stays far below 1e-3 px.
#[inline(always)]
fn substeps(u: f64, v: f64, dt: f64) -> usize {
    let disp = (u * u + v * v).sqrt() * dt;
    ((disp / SUBSTEP_PX).ceil() as usize).clamp(1, 256)
}

/// Classical RK4 from (x, y) at `t0` over `dt` in `n` equal sub-steps
/// (`n` also as a float), k1 of the first sub-step given (the velocity at
/// (x, y, t0), already known), per lane: with [`F64x2`] two particles at
/// once, each with its own sub-step count (`n_max` the largest; a lane
/// whose steps are done keeps its position). Every lane does exactly the
/// scalar operations on its own numbers, so a pair gives the bits of two
/// scalar calls (test `lane_advection_matches_scalar`).
#[inline(always)]
fn rk4<T: Lanes>(
    flow: &Flow,
    xy: (T, T),
    k1: (T, T),
    t0: f64,
    dt: f64,
    n: T,
    n_max: usize,
) -> (T, T) {
    let c = T::splat;
    let (mut x, mut y) = xy;
    let h = c(dt) / n;
    let mut t = c(t0);
    for i in 0..n_max {
        // The first k1 is the velocity at (x, y, t0) already known.
        let (k1x, k1y) = if i == 0 {
            k1
        } else {
            flow.velocity_lanes(x, y, t)
        };
        let hh = c(0.5) * h;
        let (k2x, k2y) = flow.velocity_lanes(x + hh * k1x, y + hh * k1y, t + hh);
        let (k3x, k3y) = flow.velocity_lanes(x + hh * k2x, y + hh * k2y, t + hh);
        let (k4x, k4y) = flow.velocity_lanes(x + h * k3x, y + h * k3y, t + h);
        let h6 = h / c(6.0);
        let nx = x + h6 * (k1x + c(2.0) * k2x + c(2.0) * k3x + k4x);
        let ny = y + h6 * (k1y + c(2.0) * k2y + c(2.0) * k3y + k4y);
        if T::N == 1 {
            (x, y) = (nx, ny);
        } else {
            // Lanes with i < n move on.
            let i = c(i as f64);
            x = i.select_lt(n, nx, x);
            y = i.select_lt(n, ny, y);
        }
        t = t + h;
    }
    (x, y)
}

/// The turbulent field's mode phases (e^{iθ}) at `T::N` particles'
/// positions, carried from one pulse's RK4 step to the next (each step
/// starts from the phases the previous one ended with), and per lane the
/// (x, y, t) they are at: a lane whose particle is elsewhere (new block,
/// recycled) gets fresh ones ([`Turbulent::anchor`]). The phases then
/// depend on the particle's own steps since then only, lane for lane the
/// same in a group as for one particle alone.
pub(crate) struct TurbState<T> {
    ph: Phases<T>,
    keys: [Option<(u64, u64, u64)>; 8],
}

impl<T: Lanes> TurbState<T> {
    /// A state for the turbulent field, none for the others.
    fn new(flow: &Flow) -> Option<TurbState<T>> {
        match flow {
            Flow::Turbulent(tb) => Some(TurbState {
                ph: Phases::new(tb.n_modes()),
                keys: [None; 8],
            }),
            _ => None,
        }
    }

    /// Fresh phases for the lanes whose particle is not where they are.
    #[inline(always)]
    fn refresh(&mut self, tb: &Turbulent, ps: &[Particle], t0: f64) {
        let c = T::splat;
        let stale = T::from_fn(|i| (self.keys[i] != Some(ps[i].vel_key(false, t0))) as u8 as f64);
        if (0..T::N).all(|i| stale.lane(i) == 0.0) {
            return;
        }
        tb.anchor(
            T::from_fn(|i| ps[i].x),
            T::from_fn(|i| ps[i].y),
            c(t0),
            &mut self.ph.fresh,
        );
        for (e, f) in self.ph.cs.iter_mut().zip(&self.ph.fresh) {
            *e = (
                stale.select_lt(c(0.5), e.0, f.0),
                stale.select_lt(c(0.5), e.1, f.1),
            );
        }
    }

    /// After a move to the particles' positions at `t1`: the velocity
    /// there (u, v) into their caches, the phases' keys.
    #[inline(always)]
    fn moved(&mut self, ps: &mut [Particle], (u, v): (T, T), t1: f64) {
        for (i, p) in ps.iter_mut().enumerate() {
            p.vel = (u.lane(i), v.lane(i));
            let key = p.vel_key(false, t1);
            p.vel_at = Some(key);
            self.keys[i] = Some(key);
        }
    }
}

/// [`rk4`] for the turbulent field ([`Turbulent::rk4_substep`]: the
/// stages' phases by small rotations from `ph.cs`, the phases at the
/// start), per lane `n` sub-steps (`n_max` the largest; a lane whose steps
/// are done keeps its position, velocity and phases). Returns the new
/// position and the velocity there at the end of its last sub-step.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn rk4_turbulent<T: Lanes>(
    tb: &Turbulent,
    xy: (T, T),
    k1: (T, T),
    t0: f64,
    dt: f64,
    n: T,
    n_max: usize,
    ph: &mut Phases<T>,
) -> (T, T, T, T) {
    let c = T::splat;
    let ((mut x, mut y), (mut u, mut v)) = (xy, k1);
    let h = c(dt) / n;
    let mut t = c(t0);
    let mut keep: Vec<(T, T)> = Vec::new();
    for i in 0..n_max {
        let i = c(i as f64);
        let all = (0..T::N).all(|l| i.lane(l) < n.lane(l));
        if !all {
            keep.clear();
            keep.extend_from_slice(&ph.cs);
        }
        let (nx, ny, nu, nv) = tb.rk4_substep(x, y, (u, v), t, h, ph);
        if all {
            (x, y, u, v) = (nx, ny, nu, nv);
        } else {
            // Lanes with i < n move on.
            let sel = |a: T, b: T| i.select_lt(n, a, b);
            (x, y, u, v) = (sel(nx, x), sel(ny, y), sel(nu, u), sel(nv, v));
            for (e, k) in ph.cs.iter_mut().zip(&keep) {
                *e = (sel(e.0, k.0), sel(e.1, k.1));
            }
        }
        t = t + h;
    }
    (x, y, u, v)
}

/// [`Particle::velocity`] at `t` for `T::N` particles of a field that is
/// not steady parallel: one evaluation of all lanes when every cache
/// misses (the common case), else one by one.
#[inline(always)]
fn velocity_lanes<T: Lanes>(ps: &mut [Particle], flow: &Flow, t: f64) {
    let all_miss = ps.iter().all(|p| p.vel_at != Some(p.vel_key(false, t)));
    if all_miss {
        let (u, v) = flow.velocity_lanes(
            T::from_fn(|i| ps[i].x),
            T::from_fn(|i| ps[i].y),
            T::splat(t),
        );
        for (i, p) in ps.iter_mut().enumerate() {
            p.vel = (u.lane(i), v.lane(i));
            p.vel_at = Some(p.vel_key(false, t));
        }
    } else {
        for p in ps.iter_mut() {
            p.velocity_in(flow, false, t);
        }
    }
}

/// [`Particles::advance_lanes`] as a [`LaneKernel`]: run by
/// [`Dispatch::run`] on four lanes (two SSE2 pairs) or, where the CPU has
/// AVX2, eight (two AVX registers). Everything it calls on lanes is
/// `#[inline(always)]`, so it is compiled inside the dispatcher's AVX2
/// function too.
struct AdvanceLanes<'a> {
    this: &'a Particles,
    pc: &'a mut [Particle],
    rc: &'a mut [Pcg64],
    slot0: usize,
    n_slots: usize,
    flow: &'a Flow,
    t0: f64,
    times: &'a [f64],
    out: &'a mut [Vec<Snapshot>],
}

impl LaneKernel for AdvanceLanes<'_> {
    type Out = ();
    #[inline(always)]
    fn run<T: Lanes>(self) {
        let AdvanceLanes {
            this,
            pc,
            rc,
            slot0,
            n_slots,
            flow,
            t0,
            times,
            out,
        } = self;
        this.advance_lanes::<T>(pc, rc, slot0, n_slots, flow, t0, times, out);
    }
}

std::thread_local! {
    /// Tests: force the generic particle loop (the reference of
    /// [`Particles::advance_parallel`]).
    static PLAIN_ADVECTION: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
    /// Tests: advance the unsteady fields one particle at a time (the
    /// reference of [`Particles::advance_lanes`]).
    static SCALAR_ADVECTION: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
    /// Tests: keep the SSE2 groups on an AVX2 machine (the comparison
    /// path of the AVX2 groups).
    static FORCE_SSE2: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;
    use crate::presets;

    /// The steady-parallel-flow loop gives exactly what the generic loop
    /// gives: snapshots, ids (recycling through both faces of the slab and
    /// the periodic x wrap), particle states and random streams, for the
    /// jet, a boundary layer (walls: re-seeding), a Poiseuille channel and
    /// a uniform flow, over blocks with repeated times (dt = 0).
    #[ebptv_macros::unit_test]
    fn parallel_flow_loop_matches_generic_loop() {
        use crate::scenario::FlowSpec;
        let mut cases = Vec::new();
        for name in ["water_jet_5khz", "laminar_bl"] {
            cases.push(presets::preset(name).unwrap());
        }
        let mut sc = presets::preset("water_jet_5khz").unwrap();
        sc.flow = FlowSpec::Poiseuille {
            u_max: 30_000.0,
            y0: 150.0,
            width: 200.0,
        };
        cases.push(sc.clone());
        sc.flow = FlowSpec::Uniform {
            u: -25_000.0,
            v: 0.0,
        };
        cases.push(sc);
        for mut sc in cases {
            sc.sensor.roi = Some(crate::scenario::Roi {
                x: 100,
                y: 200,
                width: 300,
                height: 200,
            });
            // Fast out-of-plane motion: many particles leave the slab.
            sc.seeding.out_of_plane_rms *= 20.0;
            let flow = Flow::build(&sc.flow).unwrap();
            assert!(flow.is_parallel_steady(), "{}", sc.name);
            let mut fast = Particles::seed(&sc, &flow, 5);
            let mut plain = Particles::seed(&sc, &flow, 5);
            let mut t = 0.0;
            let mut recycled = 0;
            for block in 0..8 {
                let mut times: Vec<f64> =
                    (0..6).map(|k| (block * 6 + k + 1) as f64 * 2e-4).collect();
                times[3] = times[2]; // dt = 0
                let a = fast.advance_and_snapshot(&flow, t, &times);
                PLAIN_ADVECTION.with(|c| c.set(true));
                let b = plain.advance_and_snapshot(&flow, t, &times);
                PLAIN_ADVECTION.with(|c| c.set(false));
                t = *times.last().unwrap();
                assert_eq!(a.len(), b.len());
                for (x, y) in a.iter().zip(&b) {
                    assert!(!x.is_empty());
                    assert_eq!(x.len(), y.len(), "{}", sc.name);
                    for (p, q) in x.iter().zip(y) {
                        assert_eq!(
                            (p.x, p.y, p.u, p.v, p.brightness, p.id),
                            (q.x, q.y, q.u, q.v, q.brightness, q.id),
                            "{}",
                            sc.name
                        );
                    }
                }
                for (p, q) in fast.particles.iter().zip(&plain.particles) {
                    assert_eq!(
                        (p.x, p.y, p.z, p.w, p.id, p.vel, p.vel_at),
                        (q.x, q.y, q.z, q.w, q.id, q.vel, q.vel_at),
                        "{}",
                        sc.name
                    );
                    recycled += (p.generation > 0) as usize;
                }
                for (r, s) in fast.rngs.iter_mut().zip(plain.rngs.iter_mut()) {
                    assert_eq!(r.gen::<u64>(), s.gen::<u64>());
                }
            }
            assert!(recycled > 100, "{}: {recycled}", sc.name);
        }
    }

    /// Advancing four particles at a time through the unsteady fields
    /// gives exactly what one at a time gives: snapshots (positions,
    /// velocities, ids), particle states and random streams, with
    /// recycling through the slab faces and the domain edges, mixed
    /// sub-step counts within a group (the rib wake at a doubled time
    /// step), repeated times (dt = 0) and a particle count that leaves a
    /// partial group at the end; the turbulent field also at a doubled
    /// time step and with 12 px modes, where groups mix lanes of the
    /// small-rotation step and of its full-field fallback; a gridded
    /// field (the rib wake sampled on a grid, part of the domain outside
    /// it) at both time steps.
    #[ebptv_macros::unit_test]
    fn lane_advection_matches_scalar() {
        let p = |n| presets::preset(n).unwrap();
        let dir = tempfile::tempdir().unwrap();
        for (sc, dt_scale) in [
            (p("demo"), 1.0),
            (p("rib_wake"), 1.0),
            (p("rib_wake"), 2.0),
            (p("turbulent_bl"), 1.0),
            (p("turbulent_bl"), 2.0),
            (turbulent_with_length(12.0), 1.0),
            (gridded_rib_wake(dir.path()), 1.0),
            (gridded_rib_wake(dir.path()), 2.0),
        ] {
            let (mut sc, name) = (sc.clone(), sc.name);
            sc.sensor.roi = Some(crate::scenario::Roi {
                x: 100,
                y: 200,
                width: 301,
                height: 203,
            });
            sc.seeding.out_of_plane_rms *= 20.0;
            let flow = Flow::build(&sc.flow).unwrap();
            assert!(flow.has_lanes() && !flow.is_parallel_steady());
            let mut lanes = Particles::seed(&sc, &flow, 9);
            let mut scalar = Particles::seed(&sc, &flow, 9);
            assert_ne!(lanes.len() % 4, 0, "{name}: a partial group");
            let (mut t, mut recycled, mut mixed) = (0.0, 0, 0);
            for block in 0..6 {
                let mut times: Vec<f64> = (0..5)
                    .map(|k| (block * 5 + k + 1) as f64 * 2e-4 * dt_scale)
                    .collect();
                // dt = 0 once.
                times[2] = times[1];
                // Groups whose sub-step counts differ (the masked lanes).
                for g in lanes.particles.chunks(4) {
                    let dt = times[0] - t;
                    let n: Vec<usize> = g
                        .iter()
                        .map(|p| {
                            let (u, v) = flow.velocity(p.x, p.y, t);
                            substeps(u, v, dt)
                        })
                        .collect();
                    mixed += n.iter().any(|&k| k != n[0]) as usize;
                }
                let a = lanes.advance_and_snapshot(&flow, t, &times);
                SCALAR_ADVECTION.with(|c| c.set(true));
                let b = scalar.advance_and_snapshot(&flow, t, &times);
                SCALAR_ADVECTION.with(|c| c.set(false));
                t = *times.last().unwrap();
                assert_eq!(a.len(), b.len());
                for (x, y) in a.iter().zip(&b) {
                    assert!(!x.is_empty());
                    assert_eq!(x.len(), y.len(), "{name}");
                    for (p, q) in x.iter().zip(y) {
                        assert_eq!(
                            (p.x, p.y, p.u, p.v, p.brightness, p.id),
                            (q.x, q.y, q.u, q.v, q.brightness, q.id),
                            "{name}"
                        );
                    }
                }
                for (p, q) in lanes.particles.iter().zip(&scalar.particles) {
                    assert_eq!(
                        (p.x, p.y, p.z, p.w, p.id),
                        (q.x, q.y, q.z, q.w, q.id),
                        "{name}"
                    );
                    recycled += (p.generation > 0) as usize;
                }
                for (r, s) in lanes.rngs.iter_mut().zip(scalar.rngs.iter_mut()) {
                    assert_eq!(r.gen::<u64>(), s.gen::<u64>());
                }
            }
            assert!(recycled > 100, "{name}: {recycled}");
            if dt_scale > 1.0 {
                assert!(mixed > 50, "{name}: {mixed} groups with mixed sub-steps");
            }
        }
    }

    /// On an AVX2 + FMA machine the AVX2-compiled groups give exactly
    /// what the SSE2 pairs give (snapshots, particle states, random
    /// streams) on the three unsteady presets and the turbulent field with
    /// 12 px modes (lanes of the fallback) and a gridded field, recycling
    /// included. (Without
    /// AVX2 + FMA there is no second path to compare; the test then says
    /// so and passes.)
    #[ebptv_macros::unit_test]
    fn avx_lanes_are_the_sse2_lanes() {
        if !crate::simd::avx2_fma() {
            eprintln!("no AVX2 + FMA on this CPU: one path only");
            return;
        }
        let mut cases: Vec<_> = ["demo", "rib_wake", "turbulent_bl"]
            .iter()
            .map(|n| presets::preset(n).unwrap())
            .collect();
        cases.push(turbulent_with_length(12.0));
        let dir = tempfile::tempdir().unwrap();
        cases.push(gridded_rib_wake(dir.path()));
        for sc in cases {
            let (mut sc, name) = (sc.clone(), sc.name);
            sc.sensor.roi = Some(crate::scenario::Roi {
                x: 100,
                y: 200,
                width: 301,
                height: 203,
            });
            sc.seeding.out_of_plane_rms *= 20.0;
            let flow = Flow::build(&sc.flow).unwrap();
            let mut avx = Particles::seed(&sc, &flow, 7);
            let mut sse = Particles::seed(&sc, &flow, 7);
            let mut t = 0.0;
            for block in 0..6 {
                let times: Vec<f64> = (0..5).map(|k| (block * 5 + k + 1) as f64 * 2e-4).collect();
                let a = avx.advance_and_snapshot(&flow, t, &times);
                FORCE_SSE2.with(|c| c.set(true));
                let b = sse.advance_and_snapshot(&flow, t, &times);
                FORCE_SSE2.with(|c| c.set(false));
                t = *times.last().unwrap();
                for (x, y) in a.iter().zip(&b) {
                    assert!(!x.is_empty());
                    assert_eq!(x.len(), y.len(), "{name}");
                    for (p, q) in x.iter().zip(y) {
                        assert_eq!(
                            (
                                p.x.to_bits(),
                                p.y.to_bits(),
                                p.u.to_bits(),
                                p.v.to_bits(),
                                p.id
                            ),
                            (
                                q.x.to_bits(),
                                q.y.to_bits(),
                                q.u.to_bits(),
                                q.v.to_bits(),
                                q.id
                            ),
                            "{name}"
                        );
                    }
                }
                for (p, q) in avx.particles.iter().zip(&sse.particles) {
                    assert_eq!(
                        (p.x, p.y, p.z, p.id, p.vel),
                        (q.x, q.y, q.z, q.id, q.vel),
                        "{name}"
                    );
                }
                for (r, s) in avx.rngs.iter_mut().zip(sse.rngs.iter_mut()) {
                    assert_eq!(r.gen::<u64>(), s.gen::<u64>());
                }
            }
        }
    }

    /// The turbulent preset with the modes' length scale `ls` px (the
    /// preset's is 120; short ones push the phase increments of a step
    /// past the small-angle polynomials' domains: the fallback).
    fn turbulent_with_length(ls: f64) -> crate::Scenario {
        use crate::scenario::FlowSpec;
        let mut sc = presets::preset("turbulent_bl").unwrap();
        let FlowSpec::Turbulent { length_scale, .. } = &mut sc.flow else {
            panic!()
        };
        *length_scale = ls;
        sc.name = format!("turbulent_bl, length scale {ls} px");
        sc
    }

    /// The rib wake's field at t = 0 on a 16 px grid (a `Gridded` flow,
    /// as the model check replays a measured one), written into `dir`.
    /// The grid starts at x = 150 inside the tests' ROI (x from 100), so
    /// some particles move through the clamped border.
    pub(crate) fn gridded_rib_wake(dir: &std::path::Path) -> crate::Scenario {
        use crate::scenario::FlowSpec;
        let mut sc = presets::preset("rib_wake").unwrap();
        let wake = Flow::build(&sc.flow).unwrap();
        let mut csv = String::from("x,y,u,v\n");
        for j in 0..30 {
            for i in 0..40 {
                let (x, y) = (150.0 + 16.0 * i as f64, 120.0 + 16.0 * j as f64);
                let (u, v) = wake.velocity(x, y, 0.0);
                csv += &format!("{x},{y},{u},{v}\n");
            }
        }
        let path = dir.join("wake.csv");
        std::fs::write(&path, csv).unwrap();
        sc.flow = FlowSpec::Gridded { path, scale: 1.0 };
        sc.name = "rib_wake, gridded".into();
        sc
    }

    /// The fast fields (branch-free cos/exp, groups of particles; the
    /// turbulent field by small rotations of its modes' phases) move
    /// particles along the same pathlines as the plain formulas (libm,
    /// one at a time, the full field at every RK4 stage): over 1 000
    /// pulses of the demo vortex, the rib wake and the turbulent field
    /// (the preset, and with length scales of 12 and 4 px, where some or
    /// most lanes take the full-field fallback; 100 and 30 pulses there,
    /// the flow being chaotic at those scales), the same particles are lit
    /// and positions agree to 1e-10 px, velocities to 1e-10 relative
    /// (rounding differences carried along the pathlines; measured
    /// ≤ 4.3e-11 px and 8.3e-13).
    #[ebptv_macros::unit_test]
    fn fast_fields_advect_like_plain_formulas() {
        use std::sync::atomic::Ordering::Relaxed;
        let mut cases: Vec<_> = ["demo", "rib_wake", "turbulent_bl"]
            .iter()
            .map(|n| (presets::preset(n).unwrap(), 100))
            .collect();
        // Chaotic at these scales (rounding differences grow ~10× per
        // 100 pulses at 12 px, faster at 4 px): fewer pulses.
        cases.push((turbulent_with_length(12.0), 10));
        cases.push((turbulent_with_length(4.0), 3));
        for (mut sc, blocks) in cases {
            let name = sc.name.clone();
            sc.sensor.roi = Some(crate::scenario::Roi {
                x: 300,
                y: 250,
                width: 200,
                height: 150,
            });
            let fast = Flow::build(&sc.flow).unwrap();
            let plain = Flow::Plain(Box::new(fast.clone()));
            assert!(!plain.has_lanes());
            let mut a = Particles::seed(&sc, &fast, 4);
            let mut b = Particles::seed(&sc, &plain, 4);
            let (mut t, mut dx, mut du, mut rows) = (0.0, 0.0f64, 0.0f64, 0);
            let period = 1.0 / sc.light.pulse_hz;
            let fallbacks = crate::flow::FALLBACK_LANES.load(Relaxed);
            for block in 0..blocks {
                let times: Vec<f64> = (0..10)
                    .map(|k| (block * 10 + k + 1) as f64 * period)
                    .collect();
                let sa = a.advance_and_snapshot(&fast, t, &times);
                let sb = b.advance_and_snapshot(&plain, t, &times);
                t = *times.last().unwrap();
                for (x, y) in sa.iter().zip(&sb) {
                    assert_eq!(x.len(), y.len(), "{name}");
                    for (p, q) in x.iter().zip(y) {
                        assert_eq!(p.id, q.id, "{name}");
                        dx = dx.max((p.x - q.x).abs()).max((p.y - q.y).abs());
                        let speed = q.u.hypot(q.v).max(1.0);
                        du = du.max((p.u - q.u).abs().max((p.v - q.v).abs()) / speed);
                        rows += 1;
                    }
                }
            }
            // Other tests' fallbacks may count too (threads): a lower
            // bound for the short scales only.
            let fallbacks = crate::flow::FALLBACK_LANES.load(Relaxed) - fallbacks;
            let steps = (a.len() * blocks * 10) as u64;
            eprintln!(
                "{name}: |dx| {dx:e} px, |du|/|u| {du:e}, fallback lanes ≤ {fallbacks} of {steps} steps"
            );
            if name.contains("length scale") {
                assert!(fallbacks > steps / 100, "{name}: {fallbacks} fallbacks");
            }
            assert!(rows > 500 * blocks, "{name}: {rows}");
            assert!(
                dx <= 1e-10 && du <= 1e-10,
                "{name}: |dx| {dx:e} px, |du|/|u| {du:e}"
            );
        }
    }

    /// The velocity cache gives the numbers a fresh field evaluation
    /// gives: advancing with the caches emptied before every pulse (the
    /// plain path: every velocity evaluated) yields identical snapshots.
    #[ebptv_macros::unit_test]
    fn velocity_cache_changes_nothing() {
        for name in ["water_jet_5khz", "demo", "rib_wake"] {
            let mut sc = presets::preset(name).unwrap();
            sc.sensor.roi = Some(crate::scenario::Roi {
                x: 100,
                y: 200,
                width: 300,
                height: 200,
            });
            let flow = Flow::build(&sc.flow).unwrap();
            let mut cached = Particles::seed(&sc, &flow, 3);
            let mut plain = Particles::seed(&sc, &flow, 3);
            let mut t = 0.0;
            for block in 0..6 {
                let times: Vec<f64> = (0..5).map(|k| (block * 5 + k + 1) as f64 * 2e-4).collect();
                let a = cached.advance_and_snapshot(&flow, t, &times);
                let mut b = Vec::new();
                for (i, &t1) in times.iter().enumerate() {
                    plain.particles.iter_mut().for_each(|p| p.vel_at = None);
                    let t0 = if i == 0 { t } else { times[i - 1] };
                    b.extend(plain.advance_and_snapshot(&flow, t0, &[t1]));
                }
                t = *times.last().unwrap();
                assert_eq!(a.len(), b.len());
                for (x, y) in a.iter().zip(&b) {
                    assert!(!x.is_empty());
                    assert_eq!(x.len(), y.len(), "{name}");
                    for (p, q) in x.iter().zip(y) {
                        assert_eq!(
                            (p.x, p.y, p.u, p.v, p.id),
                            (q.x, q.y, q.u, q.v, q.id),
                            "{name}"
                        );
                    }
                }
            }
        }
    }
}
