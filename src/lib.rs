//! # ebptv — event-based particle tracking velocimetry for pulsed illumination
//!
//! An event camera watches a particle-seeded flow lit by a pulsed laser.
//! Every pulse makes each particle fire one to a few events after a sensor
//! latency. ebptv turns such recordings into velocity:
//!
//! ```text
//! file ─▶ io ─▶ pulses ─▶ cluster ─▶ track ─▶ grid / spectra
//!                  └────▶ piv ───────────────▶ compare
//! sim (ground truth) ─▶ io writers;  modelcheck: measured vs simulated
//! ```
//!
//! Each stage is a module with one entry point; the `ebptv` binary only
//! parses arguments, calls these, shows progress and writes files.
//! See ARCHITECTURE.md for the design and README.md for the file contracts.

pub mod decimal;
pub use ebptv_io as io;
pub use ebptv_io::{error, events};
pub use ebptv_sim as sim;

pub mod cluster;
pub mod compare;
pub mod evaluate;
pub mod grid;
pub mod modelcheck;
pub mod piv;
pub mod plot;
pub mod pulses;
pub mod spectra;
pub mod track;

pub use error::{Error, Result};
pub use events::{Chunk, Edge, Event, EventChunk, Geometry, Trigger};
