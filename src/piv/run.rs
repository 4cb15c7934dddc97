//! `ebptv piv` on a recording, without its files: pulse timing, then one
//! pass over the pulses with a field every `step` pulses handed to a
//! [`PivSink`], and the mean statistics at the end ([`run_recording`]).

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

use super::{MeanRow, NodeGrid};
use super::{PivOptions, PivStream, PixelMode, PseudoOptions, StepField, StreamOptions};
use crate::calib::Calibration;
use crate::error::{Error, Result};
use crate::io::EventSource;
use crate::pulses::{split_pulses, Analyzer, PulseOptions, PulseReport};
use crate::Cancel;

/// The options of `ebptv piv`; the defaults are the command's.
#[derive(Debug, Clone, PartialEq)]
pub struct PivRunOptions {
    /// Windows, spacing, passes, pyramid, clipping (`mask` is set from
    /// [`PivRunOptions::calibration`] and [`PivRunOptions::mask`]).
    pub correlation: PivOptions,
    /// Frames (pulses) per evaluation, `N_f`.
    pub frames: usize,
    /// Pulses between evaluations; `None`: `N_f − 1`.
    pub step: Option<usize>,
    /// The pseudo-images: binary or counts, polarities, blur.
    pub pseudo: PseudoOptions,
    /// Nominal pulse frequency (Hz) when the recording has no triggers.
    pub pulse_hz: Option<f64>,
    /// Time steps evaluated in parallel; `None`: the rayon thread count.
    pub batch: Option<usize>,
    /// Go on when the events show no bursts locked to pulses.
    pub force_pulses: bool,
    /// A `calib.toml`: its `[mask]` applies, and [`PivRun::calibration`]
    /// gives the physical columns.
    pub calibration: Option<PathBuf>,
    /// A mask image (PNG of the sensor's size, non-zero = not flow).
    pub mask: Option<PathBuf>,
}

impl Default for PivRunOptions {
    fn default() -> Self {
        PivRunOptions {
            correlation: PivOptions::sized(32, None, None),
            frames: 5,
            step: None,
            pseudo: PseudoOptions::default(),
            pulse_hz: None,
            batch: None,
            force_pulses: false,
            calibration: None,
            mask: None,
        }
    }
}

impl PivRunOptions {
    /// Pulses between evaluations: [`PivRunOptions::step`] or `N_f − 1`.
    pub(crate) fn step(&self) -> usize {
        self.step.unwrap_or(self.frames.saturating_sub(1).max(1))
    }

    /// Event counts (`true`) or binary pseudo-images.
    #[cfg_attr(not(feature = "python"), allow(dead_code))]
    pub(crate) fn counts(&self) -> bool {
        self.pseudo.mode == PixelMode::Counts
    }
}

/// The two passes over the recording.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PivStage {
    /// Finding the pulse times.
    PulseTiming,
    /// Pseudo-images and correlation.
    Correlation,
}

/// What [`run_recording`] reports to its progress callback as it goes.
#[derive(Clone, Copy, Debug)]
#[non_exhaustive]
pub enum PivProgress<'a> {
    /// A pass over the recording starts; `file_size` in bytes when known.
    Stage {
        /// The pass that starts.
        stage: PivStage,
        /// Size of the recording (bytes), when known.
        file_size: Option<u64>,
    },
    /// After each chunk read: bytes read and events decoded in this pass,
    /// and the fields so far.
    Read {
        /// The pass under way.
        stage: PivStage,
        /// Bytes read in this pass.
        bytes: u64,
        /// Events decoded in this pass.
        events: u64,
        /// Fields evaluated so far.
        fields: u64,
    },
    /// A reader's warning about the recording.
    Warning(&'a str),
}

/// Where [`run_recording`] hands its fields.
pub trait PivSink {
    /// Before the first field: the node grid and the pulse frequency (Hz;
    /// a field's displacement per pulse × `pulse_hz` = px/s).
    fn start(&mut self, grid: &NodeGrid, pulse_hz: f64) -> Result<()>;
    /// Each field, in time order. An error stops the run.
    fn field(&mut self, field: &StepField) -> Result<()>;
}

/// What [`run_recording`] found besides the fields it handed its sink.
#[derive(Debug, Clone)]
pub struct PivRun {
    /// The pulse analysis (`pulses.json`).
    pub pulses: PulseReport,
    /// The node grid of every field.
    pub grid: NodeGrid,
    /// Pulse frequency (Hz): displacement per pulse × this = px/s.
    pub pulse_hz: f64,
    /// `(first_pulse, t_us)` of every field (`piv_steps.csv`).
    pub steps: Vec<(i64, f64)>,
    /// The mean statistics per node, rows by y then x (the `piv_mean` table).
    pub mean: Vec<MeanRow>,
    /// The calibration of [`PivRunOptions::calibration`].
    pub calibration: Option<Calibration>,
    /// A mask (image or the calibration's) applied.
    pub masked: bool,
}

impl PivRun {
    /// Nodes masked or never valid (the mean is NaN and `valid` 0).
    pub(crate) fn nodes_without_vector(&self) -> usize {
        self.mean
            .iter()
            .filter(|r| r.valid == 0.0 && r.u.is_nan())
            .count()
    }
}

/// `ebptv piv RECORDING` in memory: the pulse timing, then a field every
/// `step` pulses (to `sink`), then the mean statistics. The recording is
/// read twice. The run stops with an error when `cancel` is set (it looks
/// before each chunk read and each field) or the sink returns one. Errors
/// name the file.
pub fn run_recording(
    path: &Path,
    opts: &PivRunOptions,
    sink: &mut dyn PivSink,
    on_progress: &(dyn Fn(PivProgress<'_>) + Sync),
    cancel: &Cancel,
) -> Result<PivRun> {
    let src = crate::io::open_for_analysis(path)?;
    for w in src.warnings() {
        on_progress(PivProgress::Warning(&w));
    }
    let geom = src.info().geometry.ok_or_else(|| {
        Error::analysis(format!(
            "{}: the sensor size is not stated in the file; PIV needs it for the pseudo-images",
            path.display()
        ))
    })?;
    let fields = AtomicU64::new(0);
    let mut src = observed(src, PivStage::PulseTiming, on_progress, &fields, cancel)?;
    let pulses = {
        let mut an = Analyzer::new(
            PulseOptions {
                pulse_hz: opts.pulse_hz,
                require_pulsed: !opts.force_pulses,
                ..Default::default()
            },
            src.info().geometry,
        )?;
        let mut chunk = crate::Chunk::default();
        while src.next_chunk(&mut chunk)? {
            an.push(&chunk)?;
        }
        an.finish()?
    };
    let (calibration, mask) =
        crate::calib::load(opts.calibration.as_deref(), opts.mask.as_deref())?;
    let mut piv = opts.correlation.clone();
    if let Some(m) = &mask {
        if let Some(p) = &opts.mask {
            let (mw, mh) = crate::calib::PixelMask::from_png(p)?.size();
            if (mw, mh) != (geom.width as u32, geom.height as u32) {
                return Err(Error::analysis(format!(
                    "{}: mask of {mw} x {mh} pixels, the sensor has {} x {}",
                    p.display(),
                    geom.width,
                    geom.height
                )));
            }
        }
        let (w, h) = (geom.width as u32, geom.height as u32);
        piv.mask = Some(
            (0..h)
                .flat_map(|y| (0..w).map(move |x| (x, y)))
                .map(|(x, y)| m.is_masked_px(x, y))
                .collect(),
        );
    }
    let stream_opts = StreamOptions {
        piv,
        pseudo: opts.pseudo,
        frames: opts.frames,
        step: opts.step(),
    };
    let (w, h) = (geom.width as usize, geom.height as usize);
    let mut stream = PivStream::new(w, h, pulses.timing, stream_opts)?;
    let grid = *stream.grid();
    let pulse_hz = stream.pulse_hz();
    sink.start(&grid, pulse_hz)?;
    stream.set_batch(opts.batch.unwrap_or_else(rayon::current_num_threads))?;
    // Second pass: the pulses, one field every `step`.
    let mut src = observed(
        crate::io::open_for_analysis(path)?,
        PivStage::Correlation,
        on_progress,
        &fields,
        cancel,
    )?;
    let mut steps = Vec::new();
    let mut emit = |f: StepField| -> Result<()> {
        cancel.check()?;
        sink.field(&f)?;
        steps.push((f.first_pulse, f.t_us));
        fields.store(steps.len() as u64, Ordering::Relaxed);
        Ok(())
    };
    split_pulses(&mut src, &pulses.timing, &mut |pe| {
        stream.feed(&pe, &mut emit)
    })?;
    stream.flush(&mut emit)?;
    if steps.is_empty() {
        return Err(Error::analysis(format!(
            "{}: no PIV field: fewer than {} consecutive pulses with events",
            path.display(),
            opts.frames
        )));
    }
    Ok(PivRun {
        pulses,
        grid,
        pulse_hz,
        steps,
        mean: stream.stats.rows(),
        calibration,
        masked: mask.is_some(),
    })
}

/// `inner`, reporting its reading as `stage` and looking at the cancel
/// flag before the first chunk and after each one.
fn observed<'a>(
    inner: Box<dyn EventSource>,
    stage: PivStage,
    on_progress: &'a (dyn Fn(PivProgress<'_>) + Sync),
    fields: &'a AtomicU64,
    cancel: &'a Cancel,
) -> Result<impl EventSource + 'a> {
    on_progress(PivProgress::Stage {
        stage,
        file_size: inner.info().file_size,
    });
    cancel.check()?;
    Ok(crate::io::Observed::new(inner, move |r| {
        cancel.check()?;
        on_progress(PivProgress::Read {
            stage,
            bytes: r.bytes,
            events: r.events,
            fields: fields.load(Ordering::Relaxed),
        });
        Ok(())
    }))
}
