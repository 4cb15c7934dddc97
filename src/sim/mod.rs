//! Simulator of pulsed event-based imaging with ground truth.
//!
//! (Design notes to be written with the implementation.)

use serde::{Deserialize, Serialize};

/// Ground truth of one particle at one pulse (`truth_particles.csv`).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TruthSample {
    pub pulse: i64,
    /// Pulse start time (µs).
    pub t_us: f64,
    pub particle_id: u64,
    /// Particle-image centre at the pulse (px).
    pub x: f64,
    pub y: f64,
    /// True velocity (px/s).
    pub u: f64,
    pub v: f64,
}

use crate::events::{EventChunk, Geometry, Trigger};

/// A whole simulated recording in memory (tests, small scenes). Long
/// recordings stream through `Simulator` (an `EventSource`) instead.
#[derive(Debug, Clone, Default)]
pub struct SimOutput {
    pub geometry: Option<Geometry>,
    /// Events in readout order (time-ordered).
    pub events: EventChunk,
    pub triggers: Vec<Trigger>,
    pub truth: Vec<TruthSample>,
    /// True start time of every light pulse (µs).
    pub pulse_starts_us: Vec<f64>,
}
