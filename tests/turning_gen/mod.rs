//! A second, independent generator of pulsed-light event recordings for
//! tracking tests, written apart from `ebptv::sim` and
//! `ebptv::track::synth`: its own flows (a Scully vortex on a drifting
//! uniform flow, a tanh shear layer with travelling cat's eyes), its own
//! particle image (events drawn uniformly over a top-hat disc of radius
//! 0.75 px, Poisson counts scaled by a log-normal brightness), its own
//! latency (a 25 µs dead time plus a gamma-distributed delay; events later
//! than the pulse period land in the next pulse's window) and its own
//! out-of-plane motion (a random walk through a sheet of half-width 1).
//! Events are clustered by `ebptv::cluster::cluster_pulse`; the truth is
//! every in-sheet particle's position and velocity at each pulse.

use ebptv::cluster::{cluster_pulse, ClusterParams, Particle};
use ebptv::events::EventChunk;
use ebptv::pulses::PulseEvents;
use ebptv::track::Track;
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Gamma, LogNormal, Poisson};

#[derive(Debug, Clone, Copy)]
pub enum Flow {
    /// Scully vortex (tangential speed `2·vmax·(r/rc)/(1 + (r/rc)²)`,
    /// peak `vmax` at `rc`; counter-clockwise in x right, y down) on a
    /// uniform flow `(u0, v0)`; px, px per pulse.
    Vortex {
        xc: f64,
        yc: f64,
        rc: f64,
        vmax: f64,
        u0: f64,
        v0: f64,
    },
    /// Shear layer `u = uc + du/2·tanh((y − yc)/delta)` with the stream
    /// function perturbation `amp·cos(k(x − uc·t))·sech((y − yc)/delta)`.
    Shear {
        yc: f64,
        delta: f64,
        uc: f64,
        du: f64,
        amp: f64,
        wavelength: f64,
    },
}

impl Flow {
    /// Velocity (px per pulse) at `(x, y)` and time `t` (pulses).
    pub fn velocity(&self, x: f64, y: f64, t: f64) -> (f64, f64) {
        match *self {
            Flow::Vortex {
                xc,
                yc,
                rc,
                vmax,
                u0,
                v0,
            } => {
                let (dx, dy) = (x - xc, y - yc);
                let r2 = dx * dx + dy * dy;
                // v_θ / r = 2 vmax / (rc (1 + r²/rc²)) / rc
                let f = 2.0 * vmax / (rc * rc + r2);
                (u0 - f * dy, v0 + f * dx)
            }
            Flow::Shear {
                yc,
                delta,
                uc,
                du,
                amp,
                wavelength,
            } => {
                let k = 2.0 * std::f64::consts::PI / wavelength;
                let eta = (y - yc) / delta;
                let (th, sech) = (eta.tanh(), 1.0 / eta.cosh());
                let ph = k * (x - uc * t);
                // ψ' = amp cos(ph) sech(η): u' = ∂ψ'/∂y, v' = −∂ψ'/∂x.
                let u = uc + 0.5 * du * th - amp * ph.cos() * sech * th / delta;
                let v = amp * k * ph.sin() * sech;
                (u, v)
            }
        }
    }

    /// Distance (px) from the vortex centre (`None` for other flows).
    pub fn radius(&self, x: f64, y: f64) -> Option<f64> {
        match *self {
            Flow::Vortex { xc, yc, .. } => Some((x - xc).hypot(y - yc)),
            _ => None,
        }
    }
}

#[derive(Debug, Clone)]
pub struct Config {
    pub flow: Flow,
    pub width: u16,
    pub height: u16,
    pub particles: usize,
    pub pulses: usize,
    pub period_us: f64,
    /// Mean events of a particle of median brightness per pulse.
    pub events_per_particle: f64,
    /// Background events per pulse over the frame.
    pub noise_per_pulse: f64,
    pub seed: u64,
}

/// One in-sheet particle at one pulse (px, px per pulse).
#[derive(Debug, Clone, Copy)]
pub struct Truth {
    pub pulse: i64,
    pub pid: u64,
    pub x: f64,
    pub y: f64,
    pub u: f64,
    pub v: f64,
    pub events: u32,
}

pub struct Scene {
    pub particles: Vec<Particle>,
    pub truth: Vec<Truth>,
    pub period_us: f64,
}

struct Seed {
    pid: u64,
    x: f64,
    y: f64,
    z: f64,
    bright: f64,
}

fn rk4(flow: &Flow, x: f64, y: f64, t: f64, h: f64) -> (f64, f64) {
    let (a1, b1) = flow.velocity(x, y, t);
    let (a2, b2) = flow.velocity(x + 0.5 * h * a1, y + 0.5 * h * b1, t + 0.5 * h);
    let (a3, b3) = flow.velocity(x + 0.5 * h * a2, y + 0.5 * h * b2, t + 0.5 * h);
    let (a4, b4) = flow.velocity(x + h * a3, y + h * b3, t + h);
    (
        x + h / 6.0 * (a1 + 2.0 * a2 + 2.0 * a3 + a4),
        y + h / 6.0 * (b1 + 2.0 * b2 + 2.0 * b3 + b4),
    )
}

pub fn generate(cfg: &Config) -> Scene {
    let mut rng = rand_pcg::Pcg64::seed_from_u64(cfg.seed);
    let (w, h) = (cfg.width as f64, cfg.height as f64);
    let bright = LogNormal::new(0.0, 0.45).unwrap();
    let delay = Gamma::new(2.0, 20.0).unwrap();
    let mut next_pid = 0u64;
    let spawn = |rng: &mut rand_pcg::Pcg64, next_pid: &mut u64| {
        *next_pid += 1;
        Seed {
            pid: *next_pid,
            x: rng.gen_range(-2.0..w + 2.0),
            y: rng.gen_range(-2.0..h + 2.0),
            z: rng.gen_range(-1.5..1.5),
            bright: bright.sample(rng),
        }
    };
    let mut seeds: Vec<Seed> = (0..cfg.particles)
        .map(|_| spawn(&mut rng, &mut next_pid))
        .collect();
    // Events of each pulse window (time, x, y), including late ones
    // carried over from the previous pulse.
    let mut windows: Vec<Vec<(i64, u16, u16)>> = vec![Vec::new(); cfg.pulses + 1];
    let mut truth = Vec::new();
    let t0 = 1000.0;
    for k in 0..cfg.pulses {
        let start = t0 + k as f64 * cfg.period_us;
        for s in seeds.iter_mut() {
            let inside = s.x > -1.0 && s.x < w && s.y > -1.0 && s.y < h && s.z.abs() < 1.0;
            if inside {
                let mean = cfg.events_per_particle * s.bright * (1.0 - 0.5 * s.z * s.z);
                let n = if mean > 0.0 {
                    Poisson::new(mean).unwrap().sample(&mut rng) as u32
                } else {
                    0
                };
                let (u, v) = cfg.flow.velocity(s.x, s.y, k as f64);
                truth.push(Truth {
                    pulse: k as i64,
                    pid: s.pid,
                    x: s.x,
                    y: s.y,
                    u,
                    v,
                    events: n,
                });
                for _ in 0..n {
                    let r = 0.75 * rng.gen::<f64>().sqrt();
                    let ph = rng.gen_range(0.0..std::f64::consts::TAU);
                    let (px, py) = ((s.x + r * ph.cos()).round(), (s.y + r * ph.sin()).round());
                    if px < 0.0 || py < 0.0 || px >= w || py >= h {
                        continue;
                    }
                    let lat = 25.0 + delay.sample(&mut rng);
                    let t = start + lat;
                    let win = ((t - t0) / cfg.period_us).floor() as usize;
                    if win < windows.len() {
                        windows[win].push((t as i64, px as u16, py as u16));
                    }
                }
            }
        }
        let noise = Poisson::new(cfg.noise_per_pulse.max(1e-9))
            .unwrap()
            .sample(&mut rng) as usize;
        for _ in 0..noise {
            let t = start + rng.gen_range(0.0..cfg.period_us);
            windows[k].push((
                t as i64,
                rng.gen_range(0..cfg.width),
                rng.gen_range(0..cfg.height),
            ));
        }
        // Advance one pulse (four RK4 steps); out-of-plane random walk;
        // particles that leave the frame or the sheet's surroundings are
        // replaced by new ones (new ids).
        for s in seeds.iter_mut() {
            let (mut x, mut y) = (s.x, s.y);
            for q in 0..4 {
                (x, y) = rk4(&cfg.flow, x, y, k as f64 + 0.25 * q as f64, 0.25);
            }
            s.x = x;
            s.y = y;
            s.z += 0.06 * (rng.gen::<f64>() - 0.5) * 3.46;
            if s.x < -6.0 || s.x > w + 6.0 || s.y < -6.0 || s.y > h + 6.0 || s.z.abs() > 1.6 {
                *s = spawn(&mut rng, &mut next_pid);
            }
        }
    }
    let params = ClusterParams::default();
    let mut particles = Vec::new();
    for (k, win) in windows.iter_mut().enumerate().take(cfg.pulses) {
        win.sort_unstable();
        let mut ev = EventChunk::with_capacity(win.len());
        for &(t, x, y) in win.iter() {
            ev.push(t, x, y, 1);
        }
        let pulse = PulseEvents {
            index: k as i64,
            start_us: t0 + k as f64 * cfg.period_us,
            events: ev,
        };
        particles.extend(cluster_pulse(&pulse, &params));
    }
    Scene {
        particles,
        truth,
        period_us: cfg.period_us,
    }
}

/// Scores of tracks against the truth (velocities in px per pulse; a
/// track point is matched to the nearest truth particle of its pulse
/// within 1 px).
#[derive(Debug, Clone, Copy)]
pub struct Scores {
    pub precision: f64,
    pub recall: f64,
    pub vel_rms: f64,
    /// Within `core` px of the vortex centre (all points for other flows).
    pub core_vel_rms: f64,
    pub core_coverage: f64,
    pub coverage: f64,
    /// First and last point of each track.
    pub ends_vel_rms: f64,
}

pub fn score(scene: &Scene, tracks: &[Track], flow: &Flow, core: f64) -> Scores {
    use std::collections::{HashMap, HashSet};
    let scale = scene.period_us * 1e-6; // px/s → px per pulse
    let mut by_pulse: HashMap<i64, Vec<usize>> = HashMap::new();
    for (i, t) in scene.truth.iter().enumerate() {
        by_pulse.entry(t.pulse).or_default().push(i);
    }
    let in_core = |x: f64, y: f64| flow.radius(x, y).is_none_or(|r| r < core);
    let nearest = |pulse: i64, x: f64, y: f64| -> Option<usize> {
        let c = by_pulse.get(&pulse)?;
        let mut best = (1.0f64, None);
        for &i in c {
            let t = &scene.truth[i];
            let d2 = (t.x - x).powi(2) + (t.y - y).powi(2);
            if d2 <= best.0 {
                best = (d2, Some(i));
            }
        }
        best.1
    };
    let (mut e_all, mut n_all, mut e_core, mut n_core, mut e_end, mut n_end) =
        (0.0, 0usize, 0.0, 0usize, 0.0, 0usize);
    let (mut pairs, mut good_pairs) = (0usize, 0usize);
    let mut covered: HashSet<usize> = HashSet::new();
    let mut found_pairs: HashSet<(u64, i64)> = HashSet::new();
    for tr in tracks {
        let m: Vec<Option<usize>> = tr
            .points
            .iter()
            .map(|p| nearest(p.pulse, p.x, p.y))
            .collect();
        let n = tr.points.len();
        for (k, (p, mi)) in tr.points.iter().zip(&m).enumerate() {
            let Some(i) = *mi else { continue };
            covered.insert(i);
            let t = &scene.truth[i];
            let e = 0.5 * ((p.u * scale - t.u).powi(2) + (p.v * scale - t.v).powi(2));
            if !e.is_finite() {
                continue;
            }
            e_all += e;
            n_all += 1;
            if in_core(t.x, t.y) {
                e_core += e;
                n_core += 1;
            }
            if k == 0 || k + 1 == n {
                e_end += e;
                n_end += 1;
            }
        }
        for k in 1..n {
            pairs += 1;
            if let (Some(a), Some(b)) = (m[k - 1], m[k]) {
                let (ta, tb) = (&scene.truth[a], &scene.truth[b]);
                if ta.pid == tb.pid {
                    good_pairs += 1;
                    found_pairs.insert((ta.pid, ta.pulse));
                }
            }
        }
    }
    // Truth pairs: the same particle seen (≥ 1 event) at k and k + 1.
    let mut seen: HashMap<(u64, i64), bool> = HashMap::new();
    for t in &scene.truth {
        seen.insert((t.pid, t.pulse), t.events > 0);
    }
    let truth_pairs: Vec<(u64, i64)> = scene
        .truth
        .iter()
        .filter(|t| t.events > 0 && seen.get(&(t.pid, t.pulse + 1)) == Some(&true))
        .map(|t| (t.pid, t.pulse))
        .collect();
    let recall = truth_pairs
        .iter()
        .filter(|k| found_pairs.contains(k))
        .count() as f64
        / truth_pairs.len().max(1) as f64;
    let (mut vis, mut vis_core, mut cov, mut cov_core) = (0usize, 0usize, 0usize, 0usize);
    for (i, t) in scene.truth.iter().enumerate() {
        if t.events == 0 {
            continue;
        }
        vis += 1;
        let c = covered.contains(&i) as usize;
        cov += c;
        if in_core(t.x, t.y) {
            vis_core += 1;
            cov_core += c;
        }
    }
    let rms = |e: f64, n: usize| (e / n.max(1) as f64).sqrt();
    Scores {
        precision: good_pairs as f64 / pairs.max(1) as f64,
        recall,
        vel_rms: rms(e_all, n_all),
        core_vel_rms: rms(e_core, n_core),
        core_coverage: cov_core as f64 / vis_core.max(1) as f64,
        coverage: cov as f64 / vis.max(1) as f64,
        ends_vel_rms: rms(e_end, n_end),
    }
}
