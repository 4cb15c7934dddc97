//! Per-pulse clustering of events into particles with a k-d tree (kiddo).
//!
//! (Design notes to be written with the implementation.)

use serde::{Deserialize, Serialize};

/// One particle detected in one pulse.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Particle {
    pub pulse: i64,
    /// Time of the pulse start the particle belongs to (µs).
    pub t_us: f64,
    /// Sub-pixel centroid (px).
    pub x: f64,
    pub y: f64,
    pub n_events: u32,
    /// Number of distinct pixels.
    pub n_pixels: u32,
    /// Bounding-box extent (px) along x and y (max - min + 1).
    pub extent_x: f32,
    pub extent_y: f32,
    /// Latency of the first event after the pulse start (µs).
    pub first_latency_us: f32,
}
