//! Multi-frame predictor tracking of particles across pulses.
//!
//! (Design notes to be written with the implementation.)

use serde::{Deserialize, Serialize};

/// One point of a track: the track's fitted state at one pulse.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TrackPoint {
    pub pulse: i64,
    pub t_us: f64,
    /// Fitted position (px).
    pub x: f64,
    pub y: f64,
    /// Fitted velocity (px/s).
    pub u: f64,
    pub v: f64,
    /// Fitted acceleration (px/s²).
    pub ax: f64,
    pub ay: f64,
    /// True where the point bridges a gap (no detection at this pulse).
    pub interpolated: bool,
}

/// A Lagrangian track.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Track {
    pub id: u64,
    pub points: Vec<TrackPoint>,
}
