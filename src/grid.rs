//! Eulerian projection of track samples onto a grid.
//!
//! (Design notes to be written with the implementation.)

use serde::{Deserialize, Serialize};

/// One Lagrangian velocity sample to be binned.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Sample {
    pub x: f64,
    pub y: f64,
    pub u: f64,
    pub v: f64,
    pub t_us: f64,
    pub track_id: u64,
}
