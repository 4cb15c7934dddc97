//! Eulerian projection of track samples onto a grid.
//!
//! What users publish are Eulerian statistics — mean velocity, Reynolds
//! stresses, spectra — on a grid, while the tracker gives Lagrangian samples
//! (position, velocity, time, track). This module bins the samples:
//!
//! * `spec`: the bin lattice — regular, rectangular bins (`bin_w × bin_h`,
//!   e.g. wide and thin near a wall), overlap, a fixed origin so that runs
//!   over different slices land on the same bins; top-hat or Gaussian
//!   weighting.
//! * `accumulate`: per-bin *power sums* (compensated), which merge exactly:
//!   slices of a long recording processed separately (one machine or the
//!   tasks of a batch array) and merged give the numbers of one run. The
//!   sums include what in-bin polynomial fits need, and per-track cluster
//!   sums for honest standard errors.
//! * `estimate`: the statistics from the sums — top-hat / Gaussian mean,
//!   or an in-bin linear / quadratic fit of velocity over position that
//!   removes the unresolved-gradient bias of top-hat stresses
//!   (≈ (dU/dy)²·b²/12); minimum count, noise-bias correction, standard
//!   errors with the track as the independent unit.
//! * `fields`: time-resolved fields on the grid (every k pulses from the
//!   samples in a short window) and point time series for spectra.
//! * `profiles`: a profile at x, the wall position, wall shear, u_τ,
//!   inner scaling.
//! * [`noise`]: the per-sample velocity noise from pairs of nearby
//!   samples at one instant, and the dynamic velocity range.
//! * [`io`]: the mergeable state file, the `grid` and `grid_extra` tables, maps.
//!
//! Typical use: `GridSpec::covering` the samples' extent →
//! `GridAccumulator::add` each sample (streaming, bounded memory) →
//! [`estimate()`] → `io::write_grid_table`. What `ebptv grid` writes
//! (tracks table or merged states → the grid folder) is one call:
//! [`grid_to_dir`].

pub(crate) mod accumulate;
mod dir;
pub mod estimate;
pub(crate) mod fields;
pub mod io;
pub mod noise;
pub(crate) mod profiles;
pub(crate) mod spec;

use serde::{Deserialize, Serialize};

#[ebptv_macros::testkit]
pub(crate) use accumulate::GridAccumulator;
pub use dir::{grid_to_dir, GridDirOptions, GridDirRun, GridInput, GridProgress, ProfileOptions};
pub use estimate::{estimate, BinStats, EstimateOptions, Fit, GridStats};
#[ebptv_macros::testkit]
pub(crate) use profiles::WallSide;
pub use spec::{GridSpec, Lattice, Weighting};

use crate::error::{Error, Result};

/// One Lagrangian velocity sample to be binned.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Sample {
    /// Position x (px).
    pub x: f64,
    /// Position y (px).
    pub y: f64,
    /// Velocity along x (px/s).
    pub u: f64,
    /// Velocity along y (px/s).
    pub v: f64,
    /// Time of the sample (µs).
    pub t_us: f64,
    /// Id of the track the sample belongs to (the independent unit for standard errors).
    pub track_id: u64,
}

impl Sample {
    /// The sample of one point of a track.
    pub fn from_track_point(track_id: u64, p: &crate::track::TrackPoint) -> Sample {
        Sample {
            x: p.x,
            y: p.y,
            u: p.u,
            v: p.v,
            t_us: p.t_us,
            track_id,
        }
    }
}

/// The samples of a tracks table (tracks.parquet, .csv or .npy); an
/// error when it holds no track point.
pub(crate) fn read_track_samples(path: &std::path::Path) -> Result<Vec<Sample>> {
    let tracks = crate::track::io::read_tracks(path)?;
    let samples: Vec<Sample> = tracks
        .iter()
        .flat_map(|t| {
            t.points
                .iter()
                .map(move |p| Sample::from_track_point(t.id, p))
        })
        .collect();
    if samples.is_empty() {
        return Err(Error::Empty {
            path: path.into(),
            why: "tracks file has a header but no track points".into(),
        });
    }
    Ok(samples)
}

/// Bounding box `(x_min, x_max, y_min, y_max)` of the finite samples;
/// an error naming `what` when there are none.
pub(crate) fn extent(samples: &[Sample], what: &str) -> Result<(f64, f64, f64, f64)> {
    let mut e = (
        f64::INFINITY,
        f64::NEG_INFINITY,
        f64::INFINITY,
        f64::NEG_INFINITY,
    );
    for s in samples {
        if s.x.is_finite() && s.y.is_finite() && s.u.is_finite() && s.v.is_finite() {
            e.0 = e.0.min(s.x);
            e.1 = e.1.max(s.x);
            e.2 = e.2.min(s.y);
            e.3 = e.3.max(s.y);
        }
    }
    if e.0 > e.1 {
        return Err(Error::analysis(format!(
            "{what}: no finite track samples to bin"
        )));
    }
    Ok(e)
}

/// Bin all samples on a grid covering their extent (convenience for
/// in-memory data).
pub fn bin_samples(
    samples: &[Sample],
    lattice: Lattice,
    weighting: Weighting,
) -> Result<GridAccumulator> {
    let (x0, x1, y0, y1) = extent(samples, "samples")?;
    let spec = GridSpec::covering(lattice, weighting, x0, x1, y0, y1)?;
    let mut acc = GridAccumulator::new(spec);
    acc.add_all(samples);
    Ok(acc)
}

/// Bins with fewer samples are empty (NaN): the `--min-count` of
/// `ebptv grid`.
pub(crate) const DEFAULT_MIN_COUNT: u64 = 10;

/// The lattice and weighting of `ebptv grid` (its options and defaults).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BinOptions {
    /// Bin width (px).
    pub bin: f64,
    /// Bin height (px); `None`: square bins.
    pub bin_h: Option<f64>,
    /// Fraction of a bin shared with its neighbour, in [0, 1).
    pub overlap: f64,
    /// Lattice origin (px); bins of runs to be merged must share it.
    pub origin: (f64, f64),
    /// Sample weighting inside a bin.
    pub weighting: Weighting,
}

impl Default for BinOptions {
    fn default() -> Self {
        BinOptions {
            bin: 16.0,
            bin_h: None,
            overlap: 0.0,
            origin: (-0.5, -0.5),
            weighting: Weighting::TopHat,
        }
    }
}

impl BinOptions {
    /// The lattice (an error on a bad bin size or overlap).
    pub(crate) fn lattice(&self) -> Result<Lattice> {
        Lattice::with_origin(
            self.bin,
            self.bin_h.unwrap_or(self.bin),
            self.overlap,
            self.origin.0,
            self.origin.1,
        )
    }
}

/// Samples per step of [`accumulate`] (each step binned on all cores).
const ACCUMULATE_STEP: usize = 1 << 22;

/// What `ebptv grid` does with a tracks table: a window covering the
/// samples (`what` names them in errors), every sample binned on all
/// cores; `on_step(samples binned)` after each step of a few million.
/// Accumulators of parts of a table merge ([`GridAccumulator::merge`], in
/// order) into the accumulator of the whole, to rounding.
#[ebptv_macros::testkit]
pub(crate) fn accumulate(
    samples: &[Sample],
    opts: &BinOptions,
    what: &str,
    on_step: &mut dyn FnMut(usize),
) -> Result<GridAccumulator> {
    let lattice = opts.lattice()?;
    let (x0, x1, y0, y1) = extent(samples, what)?;
    let spec = GridSpec::covering(lattice, opts.weighting, x0, x1, y0, y1)?;
    let mut acc = GridAccumulator::new(spec);
    for chunk in samples.chunks(ACCUMULATE_STEP) {
        acc.add_par(chunk);
        on_step(chunk.len());
    }
    Ok(acc)
}

#[cfg(feature = "testkit")]
pub(crate) mod tests;
