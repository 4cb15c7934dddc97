//! Particle motion shared between simulations that differ only in the
//! sensor.
//!
//! A simulation is two halves: the particles' motion (seeding, pathlines
//! through the flow, the snapshot of the lit ones at every pulse) and the
//! camera's response to it (rendering, pixel, noise, readout). The motion
//! depends on the flow, the seeding, the region, the particle image size
//! (the seeding margin), the pulse times and the seed — nothing of the
//! pixel, the readout or the noise. A model check simulates the same scene
//! hundreds of times with one seed (common random numbers) and only the
//! sensor's parameters changed; advecting the particles through the flow
//! was a quarter of its time, spent on the same pathlines again and again.
//!
//! [`MotionCache`] keeps the snapshots of the motions simulated through it
//! (per block of pulses, as the simulator makes them), keyed by everything
//! the motion depends on ([`MotionKey`]); [`simulate_with`](crate::simulate_with)
//! replays a cached motion instead of advecting. A replay gives the
//! simulator the very snapshots an advection would (the same values in
//! the same order), so the output is bit-identical with or without the
//! cache (tested). A flow read from a file is keyed by the file's path,
//! length and modification time as well, so a changed file is simulated
//! afresh. The cache holds a fixed budget of snapshot memory (128 MiB by
//! default); the least recently used motions leave first, so the seeds a
//! search keeps coming back to stay while one-off replicates pass
//! through; a motion larger than the whole budget is simulated but not
//! kept.

use std::sync::{Arc, Mutex};

use crate::scenario::{ClockDrift, FlowSpec, Roi, Scenario, Seeding};
use crate::seeding::Snapshot;

/// Everything a simulation's particle motion depends on.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct MotionKey {
    seed: u64,
    duration_s: f64,
    flow: FlowSpec,
    /// Length and modification time of a gridded flow's file.
    flow_file: Option<(u64, Option<std::time::SystemTime>)>,
    seeding: Seeding,
    roi: Roi,
    particle_diameter_px: f64,
    pulse_hz: f64,
    first_pulse_us: f64,
    clock_drift: Option<ClockDrift>,
}

impl MotionKey {
    pub(crate) fn of(sc: &Scenario, seed: u64) -> MotionKey {
        let flow_file = match &sc.flow {
            FlowSpec::Gridded { path, .. } => std::fs::metadata(path)
                .ok()
                .map(|m| (m.len(), m.modified().ok())),
            _ => None,
        };
        MotionKey {
            seed,
            duration_s: sc.duration_s,
            flow: sc.flow.clone(),
            flow_file,
            seeding: sc.seeding,
            roi: sc.roi(),
            particle_diameter_px: sc.optics.particle_diameter_px,
            pulse_hz: sc.light.pulse_hz,
            first_pulse_us: sc.light.first_pulse_us,
            clock_drift: sc.light.clock_drift,
        }
    }
}

/// The snapshots of one block of pulses: one list per pulse.
pub(crate) type BlockSnapshots = Arc<Vec<Vec<Snapshot>>>;

/// One simulated motion: the particle count and every block's snapshots.
#[derive(Debug)]
pub(crate) struct Motion {
    pub(crate) key: MotionKey,
    pub(crate) particles: usize,
    pub(crate) blocks: Vec<BlockSnapshots>,
    bytes: usize,
}

impl Motion {
    pub(crate) fn new(key: MotionKey, particles: usize, blocks: Vec<BlockSnapshots>) -> Motion {
        let bytes = blocks
            .iter()
            .flat_map(|b| b.iter())
            .map(|s| s.len() * std::mem::size_of::<Snapshot>())
            .sum();
        Motion {
            key,
            particles,
            blocks,
            bytes,
        }
    }
}

/// Particle motions kept for simulations of the same scene with another
/// sensor (see the module documentation). Share one between the
/// simulations (it is `Sync`); [`crate::simulate_with`] looks up and
/// fills it.
#[derive(Debug)]
pub struct MotionCache {
    max_bytes: usize,
    /// Least recently used first.
    motions: Mutex<Vec<Arc<Motion>>>,
}

/// A cache of 128 MiB of snapshots.
impl Default for MotionCache {
    fn default() -> Self {
        MotionCache::with_budget(MotionCache::DEFAULT_BYTES)
    }
}

impl MotionCache {
    /// Snapshot memory a default cache keeps: 128 MiB (~2.8 M particle
    /// snapshots; a model check's scene of 200 pulses on a 640×360 sensor
    /// at 0.008 particles per pixel takes 10 MB per seed, and its search
    /// comes back to two or three seeds hundreds of times).
    pub(crate) const DEFAULT_BYTES: usize = 128 << 20;

    /// A cache that keeps at most `max_bytes` of snapshots.
    pub(crate) fn with_budget(max_bytes: usize) -> MotionCache {
        MotionCache {
            max_bytes,
            motions: Mutex::new(Vec::new()),
        }
    }

    pub(crate) fn get(&self, key: &MotionKey) -> Option<Arc<Motion>> {
        let mut m = self.motions.lock().unwrap_or_else(|e| e.into_inner());
        let i = m.iter().position(|x| x.key == *key)?;
        // Most recently used last.
        let hit = m.remove(i);
        m.push(hit.clone());
        Some(hit)
    }

    pub(crate) fn insert(&self, motion: Motion) {
        if motion.bytes > self.max_bytes {
            return;
        }
        let mut m = self.motions.lock().unwrap_or_else(|e| e.into_inner());
        // Simulations run in parallel may have made the same motion.
        if m.iter().any(|x| x.key == motion.key) {
            return;
        }
        let mut held: usize = m.iter().map(|x| x.bytes).sum();
        while held + motion.bytes > self.max_bytes && !m.is_empty() {
            held -= m.remove(0).bytes;
        }
        m.push(Arc::new(motion));
    }

    /// Number of motions held.
    #[cfg(feature = "testkit")]
    pub(crate) fn len(&self) -> usize {
        self.motions.lock().unwrap_or_else(|e| e.into_inner()).len()
    }
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;
    use crate::{presets, scenario, simulate, simulate_with, SimOutput};

    fn same(a: &SimOutput, b: &SimOutput, what: &str) {
        assert_eq!(a.events, b.events, "{what}: events");
        assert_eq!(a.triggers, b.triggers, "{what}: triggers");
        assert_eq!(a.truth, b.truth, "{what}: truth");
        assert_eq!(a.pulse_starts_us, b.pulse_starts_us, "{what}: pulses");
    }

    /// A small scene of two blocks and a bit, its flow the analytic rib
    /// wake or that wake as a grid in a file (as the model check replays a
    /// measured one; `seeding`'s tests' grid).
    fn scene(dir: &std::path::Path, gridded: bool) -> Scenario {
        let mut sc = if gridded {
            crate::seeding::tests::gridded_rib_wake(dir)
        } else {
            presets::preset("rib_wake").unwrap()
        };
        sc.duration_s = 0.0051;
        sc.sensor.roi = Some(scenario::Roi {
            x: 100,
            y: 150,
            width: 300,
            height: 200,
        });
        sc
    }

    #[ebptv_macros::unit_test]
    fn replayed_motion_gives_the_simulation_without_cache() {
        let dir = tempfile::tempdir().unwrap();
        for gridded in [true, false] {
            let sc = scene(dir.path(), gridded);
            let cache = Arc::new(MotionCache::default());
            let plain = simulate(&sc, 7).unwrap();
            assert!(plain.events.len() > 1000 && plain.pulse_starts_us.len() > 20);
            // Made and kept, then replayed.
            same(&plain, &simulate_with(&sc, 7, &cache).unwrap(), "first");
            assert_eq!(cache.len(), 1);
            same(&plain, &simulate_with(&sc, 7, &cache).unwrap(), "replay");
            assert_eq!(cache.len(), 1);
            // Another sensor on the same motion: replayed, and the same as
            // simulating that sensor afresh.
            let mut sensor = sc.clone();
            sensor.pixel.latency_us *= 1.5;
            sensor.pixel.refractory = Some(scenario::Refractory { period_us: 40.0 });
            sensor.noise.background_noise = Some(scenario::BackgroundNoise { rate_hz: 2.0 });
            let fresh = simulate(&sensor, 7).unwrap();
            assert_ne!(fresh.events, plain.events);
            same(
                &fresh,
                &simulate_with(&sensor, 7, &cache).unwrap(),
                "sensor",
            );
            assert_eq!(cache.len(), 1);
            // What moves the particles is a motion of its own.
            let mut moved = sc.clone();
            moved.seeding.ppp *= 1.2;
            let mut drift = sc.clone();
            drift.light.clock_drift = Some(scenario::ClockDrift {
                ppm: 300.0,
                wander_ppm: 0.0,
                wander_period_s: 1.0,
            });
            for (k, (m, seed)) in [(&moved, 7), (&sc, 8), (&drift, 7)].into_iter().enumerate() {
                same(
                    &simulate(m, seed).unwrap(),
                    &simulate_with(m, seed, &cache).unwrap(),
                    "new",
                );
                assert_eq!(cache.len(), 2 + k);
            }
        }
    }

    #[ebptv_macros::unit_test]
    fn a_changed_flow_file_is_a_new_motion_and_the_budget_holds() {
        let dir = tempfile::tempdir().unwrap();
        let sc = scene(dir.path(), true);
        let cache = Arc::new(MotionCache::default());
        simulate_with(&sc, 1, &cache).unwrap();
        let FlowSpec::Gridded { path, .. } = &sc.flow else {
            unreachable!()
        };
        // Rewritten with the velocities doubled (a different length).
        let csv = std::fs::read_to_string(path).unwrap();
        let mut doubled = String::from("x,y,u,v\n");
        for line in csv.lines().skip(1) {
            let v: Vec<f64> = line.split(',').map(|s| s.parse().unwrap()).collect();
            doubled += &format!("{},{},{},{}\n", v[0], v[1], 2.0 * v[2], 2.0 * v[3]);
        }
        std::fs::write(path, doubled).unwrap();
        same(
            &simulate(&sc, 1).unwrap(),
            &simulate_with(&sc, 1, &cache).unwrap(),
            "rewritten",
        );
        assert_eq!(cache.len(), 2);
        // A budget below one motion keeps none; one motion's worth keeps
        // the latest.
        let none = Arc::new(MotionCache::with_budget(1000));
        simulate_with(&sc, 1, &none).unwrap();
        assert_eq!(none.len(), 0);
        let one = cache.get(&MotionKey::of(&sc, 1)).unwrap().bytes;
        let small = Arc::new(MotionCache::with_budget(one + one / 2));
        for seed in [1, 2, 3] {
            simulate_with(&sc, seed, &small).unwrap();
        }
        assert_eq!(small.len(), 1);
        assert!(small.get(&MotionKey::of(&sc, 3)).is_some());
        // Least recently used leaves first: with room for two, a seed used
        // again between new ones stays.
        let two = Arc::new(MotionCache::with_budget(2 * one + one / 2));
        for seed in [1, 2, 1, 3, 1, 4] {
            simulate_with(&sc, seed, &two).unwrap();
        }
        assert_eq!(two.len(), 2);
        assert!(two.get(&MotionKey::of(&sc, 1)).is_some());
        assert!(two.get(&MotionKey::of(&sc, 4)).is_some());
    }
}
