//! Synthetic particle-like event streams for decode benchmarks: seeded
//! particles drift across a 1280x720 sensor; a laser pulse every 100 µs
//! makes each one fire 1-4 events in neighbouring pixels with a latency of
//! 0-90 µs, plus sparse background noise. Events come time-ordered, and
//! within one µs grouped by row, polarity and increasing x, as a sensor's
//! readout delivers them.

use ebptv::events::Chunk;
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;

pub struct ParticleStream {
    rng: Pcg64,
    particles: Vec<[f32; 4]>,
    pulse: u64,
    pub t0: u64,
    buf: Vec<(i64, u16, u8, u16)>,
}

impl ParticleStream {
    /// `t0` in µs; starting just before 2^24 exercises the EVT3 clock loop.
    pub fn new(seed: u64, n_particles: usize, t0: u64) -> Self {
        let mut rng = Pcg64::seed_from_u64(seed);
        let particles = (0..n_particles)
            .map(|_| {
                [
                    rng.gen_range(0.0..1280.0),
                    rng.gen_range(0.0..720.0),
                    rng.gen_range(-0.5..2.0),
                    rng.gen_range(-0.3..0.3),
                ]
            })
            .collect();
        ParticleStream {
            rng,
            particles,
            pulse: 0,
            t0,
            buf: Vec::new(),
        }
    }

    /// Append the events of the next laser pulse to `chunk`.
    pub fn next_pulse(&mut self, chunk: &mut Chunk) {
        let tp = self.t0 as i64 + self.pulse as i64 * 100;
        self.pulse += 1;
        self.buf.clear();
        for p in &mut self.particles {
            p[0] = (p[0] + p[2]).rem_euclid(1278.0);
            p[1] = (p[1] + p[3]).rem_euclid(718.0);
            let n = self.rng.gen_range(1..=4u32);
            let lat = self.rng.gen_range(0..90);
            for k in 0..n {
                let (dx, dy) = [(0, 0), (1, 0), (0, 1), (1, 1)][k as usize];
                self.buf.push((
                    tp + lat + (k as i64 & 1),
                    p[1] as u16 + dy,
                    1,
                    p[0] as u16 + dx,
                ));
            }
        }
        for _ in 0..self.particles.len() / 20 {
            let t = tp + self.rng.gen_range(0..100);
            self.buf.push((
                t,
                self.rng.gen_range(0..720),
                self.rng.gen_range(0..2),
                self.rng.gen_range(0..1280),
            ));
        }
        self.buf.sort_unstable();
        self.buf.dedup();
        for &(t, y, p, x) in &self.buf {
            chunk.events.push(t, x, y, p);
        }
    }
}
