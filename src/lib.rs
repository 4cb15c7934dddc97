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
//!
//! ## The pipeline in one example
//!
//! Open a recording, find the light pulses, cluster each pulse's events
//! into particles, link them into tracks and bin the tracks onto a grid.
//! The recording here is simulated and written to a temporary file, so the
//! example runs anywhere; point [`io::open`] at a camera file instead. The
//! function is `examples/rust/src/pipeline.rs`, which `examples/rust` (a
//! program that depends on ebptv with default features, as a user's does)
//! also runs: the test command builds and runs it.
//!
//! ```
//! # use ebptv::{io, sim, Chunk};
//! # fn main() -> Result<(), Box<dyn std::error::Error>> {
//! # let dir = std::env::temp_dir().join(format!("ebptv-doc-{}", std::process::id()));
//! # std::fs::create_dir_all(&dir)?;
//! # let path = dir.join("vortex.raw");
//! # let mut scenario = sim::presets::preset("demo")?;
//! # scenario.duration_s = 0.01; // 50 pulses at 5 kHz
//! # let rec = sim::simulate(&scenario, 1)?;
//! # let mut w = io::create(&path, None, rec.geometry.unwrap())?;
//! # let mut chunk = Chunk::default();
//! # chunk.events = rec.events;
//! # chunk.triggers = rec.triggers;
//! # w.write_chunk(&chunk)?;
//! # w.finish()?;
//! # pipeline(&path)?;
//! # std::fs::remove_dir_all(&dir)?;
//! # Ok(())
//! # }
#![doc = include_str!("../examples/rust/src/pipeline.rs")]
//! ```
//!
//! The `ebptv` command line runs the same stages with streaming, progress
//! and files (`ebptv track`, `ebptv grid`, …). What `ebptv track` writes
//! (particles, tracks, pulses, summary, figure, the run's parameters) is one
//! call: [`track::track_to_dir`]`(recording, &config, out_dir, &on_progress)`;
//! so are the folders of `ebptv pulses` ([`pulses::pulses_to_dir`]), `ebptv
//! grid` ([`grid::grid_to_dir`]), `ebptv spectra` ([`spectra::spectra_to_dir`])
//! and `ebptv compare` ([`compare::compare_to_dir`]).

#![warn(missing_docs)]
// The command line (`cli`) and the unit tests name the crate `ebptv`, as
// the integration tests in tests/ and the Python bindings do.
extern crate self as ebptv;

pub mod decimal;
pub use ebptv_io as io;
pub use ebptv_io::{error, events};
pub use ebptv_sim as sim;

pub mod calib;
pub mod cancel;
/// The `ebptv` command line (argument parsing, progress, files), run by
/// the binary's `main`; not an API. It lives in the library so that the
/// stages' internals it drives need not be public. Its behaviour is tested
/// through the binary.
#[doc(hidden)]
pub mod cli;
pub mod cluster;
pub mod compare;
pub mod evaluate;
pub mod grid;
pub mod modelcheck;
pub mod piv;
pub mod plot;
pub mod provenance;
pub mod pulses;
#[cfg(feature = "python")]
pub mod python;
pub mod spectra;
pub mod table;
pub mod track;

pub use cancel::Cancel;
pub use error::{Error, Result};
pub use events::{Chunk, Edge, Event, EventChunk, Geometry, Trigger};

// The unit tests, indexed for the integration-test binary (`unit_tests`; build.rs,
// `ebptv-testgen`); test kit only.
#[cfg(feature = "testkit")]
include!(concat!(env!("OUT_DIR"), "/unit_index.rs"));
