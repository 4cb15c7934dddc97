//! Correlation PIV on pulsed pseudo-images (the seed paper's method) and on
//! ordinary image sequences.
//!
//! The reference against which event-based PTV is judged: Willert (2023)
//! builds one binary pseudo-image per laser pulse from the events the pulse
//! caused, blurs it, and measures the flow with multi-frame
//! sum-of-correlation PIV. This module does the same, streaming:
//!
//! ```text
//! PulseEvents ─▶ pseudo::PseudoImager ─▶ pseudo::FrameRing (last N_f frames)
//!             ─▶ multipass::piv_frames (FFT sum of correlation over pairs
//!                (k, k+1) — or (k, k+s), s ≤ S, pyramid — multi-pass with
//!                deformation, median test)
//!             ─▶ PivStream: one field per step ─▶ FieldStats (mean, stresses)
//! ```
//!
//! * `correlate` — the FFT correlation (and the direct oracle).
//! * `multipass` — passes, window deformation, the node grid.
//! * `validate` — normalised median test, replacement, flags.
//! * `pseudo` — pseudo-images and the frame ring.
//! * [`images`] — PNG/TIFF input for `piv-images`.
//! * [`synth`] — synthetic particle images with known displacement.
//! * [`output`] — the `piv_mean`, `piv_steps` and per-frame vector tables
//!   (Parquet, CSV or `.npy`), `.npy` field stacks.
//! * `run` — `ebptv piv` on a recording, fields to a sink ([`run_recording`]).
//!
//! Only `N_f` images are ever in memory: a 10 s recording at 10 kHz is
//! 100 000 pulses; its fields go to disk step by step and its statistics
//! accumulate in `FieldStats`, which two time slices can
//! `FieldStats::merge`.

pub(crate) mod correlate;
pub mod images;
pub(crate) mod multipass;
pub mod output;
pub(crate) mod pseudo;
pub(crate) mod run;
pub mod synth;
pub(crate) mod validate;

pub use multipass::{node_grid, piv_frames, NodeGrid, PivOptions, VectorField};
pub(crate) use pseudo::{FrameRing, PseudoImager};
pub(crate) use pseudo::{PixelMode, PseudoOptions};
pub use run::{run_recording, PivProgress, PivRun, PivRunOptions, PivSink, PivStage};

use crate::error::{Error, Result};
use crate::pulses::{PulseEvents, PulseTiming};
use rayon::prelude::*;
use std::sync::Arc;

/// A grey-value image, row-major, `data[y * width + x]`.
#[derive(Debug, Clone, PartialEq)]
pub struct Image {
    /// Width (px).
    pub width: usize,
    /// Height (px).
    pub height: usize,
    /// Grey values, `width · height`, row-major.
    pub data: Vec<f32>,
}

impl Image {
    /// A black (all-zero) image of `width × height` px.
    pub(crate) fn zeros(width: usize, height: usize) -> Self {
        Image {
            width,
            height,
            data: vec![0.0; width * height],
        }
    }
    #[cfg(feature = "testkit")]
    #[inline]
    pub(crate) fn get(&self, x: usize, y: usize) -> f32 {
        self.data[y * self.width + x]
    }
}

/// Running statistics of velocity fields on one node grid (px/s).
///
/// Only valid vectors (flag 0) enter the moments; `valid` is the fraction
/// of evaluated steps in which the node was valid.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct FieldStats {
    /// The node grid the statistics are on.
    pub grid: NodeGrid,
    /// Number of fields added (evaluated time steps).
    pub steps: u64,
    /// Number of valid vectors per node, row-major (`j·nx + i`).
    pub n: Vec<u64>,
    su: Vec<f64>,
    sv: Vec<f64>,
    suu: Vec<f64>,
    svv: Vec<f64>,
    suv: Vec<f64>,
}

/// One row of the `piv_mean` table.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MeanRow {
    /// Node x (px).
    pub x: f64,
    /// Node y (px).
    pub y: f64,
    /// Mean velocity along x (px/s); NaN without a valid vector.
    pub u: f64,
    /// Mean velocity along y (px/s); NaN without a valid vector.
    pub v: f64,
    /// Reynolds normal stress ⟨u′u′⟩ ((px/s)²).
    pub uu: f64,
    /// Reynolds normal stress ⟨v′v′⟩ ((px/s)²).
    pub vv: f64,
    /// Reynolds shear stress ⟨u′v′⟩ ((px/s)²).
    pub uv: f64,
    /// Fraction of the evaluated steps in which the node was valid (0–1).
    pub valid: f64,
}

impl FieldStats {
    pub(crate) fn new(grid: NodeGrid) -> Self {
        let n = grid.len();
        FieldStats {
            grid,
            steps: 0,
            n: vec![0; n],
            su: vec![0.0; n],
            sv: vec![0.0; n],
            suu: vec![0.0; n],
            svv: vec![0.0; n],
            suv: vec![0.0; n],
        }
    }

    /// Add one field, its displacements multiplied by `scale` (e.g. the
    /// pulse frequency to get px/s).
    pub(crate) fn add(&mut self, f: &VectorField, scale: f64) {
        self.steps += 1;
        for k in 0..self.n.len() {
            if validate::is_valid(f.flags[k]) {
                let (u, v) = (f.u[k] * scale, f.v[k] * scale);
                self.n[k] += 1;
                self.su[k] += u;
                self.sv[k] += v;
                self.suu[k] += u * u;
                self.svv[k] += v * v;
                self.suv[k] += u * v;
            }
        }
    }

    /// Mean, Reynolds stresses (population moments) and valid fraction per
    /// node; NaN where no valid vector was seen.
    pub(crate) fn rows(&self) -> Vec<MeanRow> {
        (0..self.n.len())
            .map(|k| {
                let n = self.n[k] as f64;
                let (i, j) = (k % self.grid.nx, k / self.grid.nx);
                let (mut u, mut v, mut uu, mut vv, mut uv) =
                    (f64::NAN, f64::NAN, f64::NAN, f64::NAN, f64::NAN);
                if n > 0.0 {
                    u = self.su[k] / n;
                    v = self.sv[k] / n;
                    uu = (self.suu[k] / n - u * u).max(0.0);
                    vv = (self.svv[k] / n - v * v).max(0.0);
                    uv = self.suv[k] / n - u * v;
                }
                MeanRow {
                    x: self.grid.x(i),
                    y: self.grid.y(j),
                    u,
                    v,
                    uu,
                    vv,
                    uv,
                    valid: if self.steps > 0 {
                        n / self.steps as f64
                    } else {
                        0.0
                    },
                }
            })
            .collect()
    }
}

/// Options of streaming PIV on pulses.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct StreamOptions {
    /// Options of the correlation.
    pub piv: PivOptions,
    /// How pulses' events become pseudo-images.
    pub pseudo: PseudoOptions,
    /// Frames per evaluation, `N_f` (≥ 2): pairs (k, k+1) summed.
    pub frames: usize,
    /// Pulses between evaluations; default `N_f − 1` (no pair used twice).
    pub step: usize,
}

/// A field measured from pulses `first_pulse … first_pulse + N_f − 1`.
#[derive(Debug, Clone)]
pub struct StepField {
    /// Index of the first pulse of the evaluation.
    pub first_pulse: i64,
    /// Centre time of the evaluated pulses (µs).
    pub t_us: f64,
    /// Displacement per pulse (px).
    pub field: VectorField,
}

/// Streaming PIV: feed pulses in order, get a field every `step` pulses.
pub(crate) struct PivStream {
    opts: StreamOptions,
    imager: PseudoImager,
    ring: FrameRing,
    grid: NodeGrid,
    timing: PulseTiming,
    pulse_hz: f64,
    since_eval: usize,
    /// Evaluations run together, in parallel ([`set_batch`](Self::set_batch)).
    batch: usize,
    /// Evaluations due but not yet run (at most `batch`).
    pending: Vec<PendingEval>,
    /// Running statistics (px/s) of the fields evaluated so far.
    pub stats: FieldStats,
}

/// An evaluation that is due: its first pulse and its `N_f` frames, shared
/// with the ring (no copy).
struct PendingEval {
    first_pulse: i64,
    frames: Vec<Arc<Image>>,
}

impl PivStream {
    /// A stream for a `width × height` px sensor with the given pulse
    /// timing; an error when `frames < 2`, `piv.pyramid ≥ frames`, `step`
    /// is 0, the pulse period is not positive, or the options do not suit
    /// the sensor (see [`node_grid`]).
    pub(crate) fn new(
        width: usize,
        height: usize,
        timing: PulseTiming,
        opts: StreamOptions,
    ) -> Result<Self> {
        if opts.frames < 2 {
            return Err(Error::param(
                "frames",
                format!("{}: multi-frame correlation needs N_f >= 2", opts.frames),
            ));
        }
        if opts.piv.pyramid >= opts.frames {
            return Err(Error::param(
                "pyramid",
                format!(
                    "largest frame separation {} needs more than {} frames (N_f)",
                    opts.piv.pyramid, opts.frames
                ),
            ));
        }
        if opts.step == 0 {
            return Err(Error::param("step", "must be at least 1 pulse"));
        }
        if !(timing.period_us.is_finite() && timing.period_us > 0.0) {
            return Err(Error::param(
                "period_us",
                format!("{}: pulse period must be positive", timing.period_us),
            ));
        }
        let grid = node_grid(width, height, &opts.piv)?;
        Ok(PivStream {
            imager: PseudoImager::new(width, height, opts.pseudo)?,
            ring: FrameRing::new(opts.frames),
            grid,
            timing,
            pulse_hz: 1e6 / timing.period_us,
            since_eval: 0,
            batch: 1,
            pending: Vec::new(),
            stats: FieldStats::new(grid),
            opts,
        })
    }

    pub(crate) fn grid(&self) -> &NodeGrid {
        &self.grid
    }

    /// Pulse frequency (Hz): displacement per pulse × this = px/s.
    pub(crate) fn pulse_hz(&self) -> f64 {
        self.pulse_hz
    }

    fn push_frame(&mut self, index: i64, events: Option<&crate::events::EventChunk>) {
        let mut buf = self.ring.take_buffer();
        match events {
            Some(ev) => self.imager.render(ev, &mut buf),
            None => self
                .imager
                .render(&crate::events::EventChunk::default(), &mut buf),
        }
        self.ring.push(index, buf);
        self.since_eval += 1;
    }

    /// Evaluate up to `n` time steps together, in parallel (rayon), when
    /// pulses are fed with [`feed`](Self::feed). Each evaluation is already
    /// parallel over its nodes; running several at once also keeps the
    /// cores busy through their sequential parts (validation, B-spline
    /// prefilter, pass barriers). Results do not depend on `n` or on the
    /// thread count: evaluations are independent and their fields are
    /// emitted, and added to the statistics, in time order. Memory: the
    /// frames of `n` evaluations (`n·step + N_f` pseudo-images at most) plus
    /// each running evaluation's deformed images.
    pub(crate) fn set_batch(&mut self, n: usize) -> Result<()> {
        if n == 0 {
            return Err(Error::param(
                "batch",
                "at least 1 evaluation at a time (1 = one after the other)",
            ));
        }
        self.batch = n;
        Ok(())
    }

    /// Ring bookkeeping for the next pulse: render it (and the empty
    /// frames of skipped pulses) and return the evaluation that became due.
    fn advance(&mut self, pe: &PulseEvents) -> Result<Option<PendingEval>> {
        if let Some(last) = self.ring.last_index() {
            if pe.index <= last {
                return Err(Error::analysis(format!(
                    "pulse {} after pulse {}: pulses must arrive in increasing order",
                    pe.index, last
                )));
            }
            let gap = (pe.index - last - 1) as usize;
            if gap >= self.opts.frames {
                self.ring.clear();
                self.since_eval = 0;
            } else {
                for k in 1..=gap as i64 {
                    self.push_frame(last + k, None);
                }
            }
        }
        self.push_frame(pe.index, Some(&pe.events));
        if !self.ring.is_full() {
            return Ok(None);
        }
        // A full ring has seen N_f >= step pushes since it (re)started, so the
        // first evaluation comes at once; then one every `step` pulses.
        if self.since_eval < self.opts.step {
            return Ok(None);
        }
        self.since_eval = 0;
        Ok(Some(PendingEval {
            first_pulse: self.ring.first_index().unwrap_or(0),
            frames: self.ring.shared_images(),
        }))
    }

    /// The field of one evaluation, added to the statistics.
    fn conclude(&mut self, first: i64, field: VectorField) -> StepField {
        self.stats.add(&field, self.pulse_hz);
        let mid = first as f64 + (self.opts.frames as f64 - 1.0) / 2.0;
        StepField {
            first_pulse: first,
            t_us: self.timing.first_pulse_us + mid * self.timing.period_us,
            field,
        }
    }

    #[cfg(feature = "testkit")]
    /// Add the events of the next pulse. Pulses skipped by the splitter
    /// (no events) become empty frames; a gap longer than `N_f` restarts the
    /// ring. Returns a field when one was evaluated (at once, whatever the
    /// batch; [`feed`](Self::feed) runs batches in parallel).
    pub(crate) fn push_pulse(&mut self, pe: &PulseEvents) -> Result<Option<StepField>> {
        if !self.pending.is_empty() {
            return Err(Error::analysis(
                "push_pulse after feed: flush the queued evaluations first",
            ));
        }
        match self.advance(pe)? {
            None => Ok(None),
            Some(job) => {
                let refs: Vec<&Image> = job.frames.iter().map(|f| &**f).collect();
                let field = piv_frames(&refs, &self.opts.piv)?;
                Ok(Some(self.conclude(job.first_pulse, field)))
            }
        }
    }

    /// Add the events of the next pulse (as [`push_pulse`](Self::push_pulse));
    /// due evaluations are queued and run in parallel once `batch` of them
    /// are waiting; each field is passed to `emit`, in time order. Call
    /// [`flush`](Self::flush) after the last pulse.
    pub(crate) fn feed(
        &mut self,
        pe: &PulseEvents,
        emit: &mut dyn FnMut(StepField) -> Result<()>,
    ) -> Result<()> {
        if let Some(job) = self.advance(pe)? {
            self.pending.push(job);
            if self.pending.len() >= self.batch {
                self.flush(emit)?;
            }
        }
        Ok(())
    }

    /// Run the queued evaluations (in parallel) and emit their fields in
    /// time order.
    pub(crate) fn flush(&mut self, emit: &mut dyn FnMut(StepField) -> Result<()>) -> Result<()> {
        if self.pending.is_empty() {
            return Ok(());
        }
        let jobs = std::mem::take(&mut self.pending);
        let piv = &self.opts.piv;
        let fields: Vec<Result<VectorField>> = jobs
            .par_iter()
            .map(|job| {
                let refs: Vec<&Image> = job.frames.iter().map(|f| &**f).collect();
                piv_frames(&refs, piv)
            })
            .collect();
        for (job, field) in jobs.into_iter().zip(fields) {
            let sf = self.conclude(job.first_pulse, field?);
            // Buffers no longer shared go back to the ring for reuse.
            job.frames.into_iter().for_each(|f| self.ring.recycle(f));
            emit(sf)?;
        }
        Ok(())
    }
}

#[cfg(feature = "testkit")]
pub(crate) mod tests;
