//! A recording (or a `particles` table) into an output directory:
//! [`track_to_dir`] runs pulses → particles → tracks and writes the
//! `particles` and `tracks` tables (`.parquet`, `.csv` or `.npy`:
//! `run.table_format`), `tracks.npy` (when `run.npy`),
//! `pulses.json` (from a recording), `summary.json`, `tracks.png` and
//! `params.toml`; [`FileSink`] is the [`PtvSink`] behind it, for a caller
//! that drives its own [`PtvStream`].
//!
//! The files are formatted on a thread of their own: formatting ~10⁶ rows
//! per second of recording is about a fifth of the work of a full-frame
//! run, and on a second core it overlaps tracking. Every file appears at
//! the end, atomically; a run that fails leaves none behind.

use std::collections::HashSet;
use std::path::Path;

use crate::cluster::Particle;
use crate::error::{Error, Result};
use crate::io::atomic::{create_output_dir, AtomicFile};
use crate::io::EventSource;
use crate::pulses::{PulseOptions, PulseReport};
use crate::Geometry;

use super::{
    read_particles, track_recording, write_summary_json, Linker, ParticlesWriter, PtvSink,
    PtvStream, RunParams, Summary, SummaryAcc, Track, TrackConfig, TrackerStats, TracksNpyWriter,
    TracksWriter,
};
use crate::table::TableFormat;

/// Which pass over the input a [`TrackProgress`] report is about.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TrackStage {
    /// The first pass over a recording: finding the pulse times.
    PulseTiming,
    /// The second pass: clustering and linking.
    Tracking,
}

/// What [`track_to_dir`] reports to its progress callback as it goes.
#[derive(Clone, Copy, Debug)]
#[non_exhaustive]
pub enum TrackProgress<'a> {
    /// A pass over the input starts; `file_size` is its size in bytes when
    /// known.
    Stage {
        /// The pass that starts.
        stage: TrackStage,
        /// Size of the input (bytes), when known.
        file_size: Option<u64>,
    },
    /// After each chunk read: the bytes read and events decoded so far in
    /// this pass; `done` on the last chunk.
    Read {
        /// The pass under way.
        stage: TrackStage,
        /// Bytes read so far in this pass.
        bytes: u64,
        /// Events decoded so far in this pass.
        events: u64,
        /// True on the pass's last chunk.
        done: bool,
    },
    /// After each pulse tracked: particles found so far and tracks active.
    Pulse {
        /// Particles found so far.
        particles: u64,
        /// Tracks currently active.
        active_tracks: usize,
    },
    /// A reader's warning about the input (e.g. a header it could not use).
    Warning(&'a str),
    /// Tracking is done; the output files are being committed.
    Writing,
}

/// What [`track_to_dir`] did, besides writing its files.
#[derive(Clone, Debug)]
pub struct DirRun {
    /// The run's `summary.json`.
    pub summary: Summary,
    /// The pulse analysis (`pulses.json`); `None` for a `particles` table
    /// input.
    pub pulses: Option<PulseReport>,
    /// Events that fell outside every pulse window.
    pub unassigned_events: u64,
}

/// Track `input` (a recording in any supported event format, or a
/// `particles` table in any [`TableFormat`]: then linking only) with `config` and write the outputs
/// into `out` (created if missing). `on_progress` receives
/// [`TrackProgress`] reports, from the reading threads too.
///
/// A `config.run.hot_pixels` file is read into `config.cluster.hot_pixels`
/// (the written `params.toml` then holds the pixels themselves).
pub fn track_to_dir(
    input: &Path,
    config: &TrackConfig,
    out: &Path,
    on_progress: &(dyn Fn(TrackProgress<'_>) + Sync),
) -> Result<DirRun> {
    track_to_dir_with(input, config, out, on_progress, &[])
}

/// [`track_to_dir`] whose outputs record `command_line` (what the user
/// typed; empty for a library call) in their provenance
/// ([`crate::provenance`]): `provenance.json`, the `"provenance"` key of
/// `summary.json` and the Parquet tables' metadata, with the run's full
/// parameters, the input's fingerprint and the pulse source.
pub fn track_to_dir_with(
    input: &Path,
    config: &TrackConfig,
    out: &Path,
    on_progress: &(dyn Fn(TrackProgress<'_>) + Sync),
    command_line: &[String],
) -> Result<DirRun> {
    let mut prov =
        crate::provenance::Provenance::new(command_line.iter().cloned()).with_parameters(config)?;
    if input.is_file() {
        prov = prov.with_input(input)?;
    }
    let config = resolve_config(config)?;
    let stream = stream_of(&config)?;
    create_output_dir(out)?;
    // Written with the other outputs, once tracking succeeded.
    let params_toml = config.to_toml()?;
    let write_params = || AtomicFile::write_all_to(out.join("params.toml"), params_toml.as_bytes());
    let calib = config
        .run
        .calibration
        .as_deref()
        .map(crate::calib::Calibration::from_file)
        .transpose()?;
    let mut sink = FileSink::create_calibrated(out, &config.run, calib)?;
    let run = track_into(
        TrackInput::of_path(input),
        &config,
        stream,
        &mut sink,
        on_progress,
        &crate::Cancel::new(),
    )?;
    on_progress(TrackProgress::Writing);
    if let Some(pulses) = &run.pulses {
        let json = serde_json::to_vec_pretty(pulses)
            .map_err(|e| Error::analysis(format!("pulses.json: {e}")))?;
        AtomicFile::write_all_to(out.join("pulses.json"), &json)?;
    }
    write_params()?;
    // The run's mask travels with its tracks (`ebptv grid` reads it).
    if let Some(m) = &config.cluster.mask {
        m.write_png(&out.join("mask.png"))?;
    }
    prov = prov.with_pulse_source(match &run.pulses {
        Some(p) => format!("{:?}", p.timing.source).to_lowercase(),
        None => "particles table".into(),
    });
    prov.write_to_dir(out)?;
    sink.provenance = Some(prov);
    let summary = sink.finish(
        &run.stats,
        run.geometry.map(|g| (g.width as f64, g.height as f64)),
    )?;
    Ok(DirRun {
        summary,
        pulses: run.pulses,
        unassigned_events: run.unassigned_events,
    })
}

/// What a tracking run reads: [`track_into`]'s input.
#[derive(Debug)]
pub enum TrackInput<'a> {
    /// A recording in any supported event format.
    Recording(&'a Path),
    /// A particles table, Parquet, CSV or .npy (linking only).
    ParticlesTable(&'a Path),
    /// Particles in memory (linking only), in any order.
    Particles(Vec<Particle>),
}

impl TrackInput<'_> {
    /// A recording, or a particles table (any format) when it has a
    /// `pulse` column (what `ebptv track` decides).
    pub(crate) fn of_path(path: &Path) -> TrackInput<'_> {
        if is_particles_table(path) {
            TrackInput::ParticlesTable(path)
        } else {
            TrackInput::Recording(path)
        }
    }
}

/// What [`track_into`] found besides the particles and tracks it handed
/// to its sink.
#[derive(Clone, Debug)]
pub struct SinkRun {
    /// The tracker's counters.
    pub stats: TrackerStats,
    /// The pulse analysis (`pulses.json`); `None` for particles.
    pub pulses: Option<PulseReport>,
    /// Events that fell outside every pulse window.
    pub unassigned_events: u64,
    /// The sensor's geometry when the recording states it.
    pub geometry: Option<Geometry>,
}

/// The options as a run uses them: a `run.hot_pixels` file read into
/// `cluster.hot_pixels`, and without the ghost test no check of new chains
/// against the flow. [`track_to_dir`] writes this set to `params.toml`.
pub fn resolve_config(config: &TrackConfig) -> Result<TrackConfig> {
    let mut config = config.clone();
    if let Some([u, v]) = config.run.prior {
        if !(u.is_finite() && v.is_finite()) {
            return Err(Error::param(
                "run.prior",
                format!("the mean flow must be finite (px/s), got [{u}, {v}]"),
            ));
        }
    }
    if let Some(p) = config.run.hot_pixels.take() {
        config.cluster.hot_pixels.extend(read_hot_pixels(&p)?);
    }
    // The calibration and the mask (the image of run.mask joined with the
    // calibration file's polygons or image): masked events are ignored,
    // masked regions never stitched across.
    let (_, mask) = crate::calib::load(
        config.run.calibration.as_deref(),
        config.run.mask.as_deref(),
    )?;
    if let Some(m) = &mask {
        config.cluster.mask = Some(m.clone());
        config.track.mask = Some(m.clone());
    }
    // Without the ghost test there is no flow to check new chains against.
    if config.track.init.ghost_check_length == 0 {
        config.track.init.ghost_check_init = false;
        config.track.init.init_gap = false;
    }
    Ok(config)
}

/// The tracker stream of a run set up with `config` (from
/// [`resolve_config`]): its linker, prior and batch size.
pub fn stream_of(config: &TrackConfig) -> Result<PtvStream> {
    let TrackConfig {
        run,
        cluster,
        track: mut tparams,
    } = config.clone();
    if let Some([u, v]) = run.prior {
        tparams.prior = Some(super::FlowPrior::uniform(u, v));
    }
    match run.linker {
        Linker::Sequential => PtvStream::new(cluster, tparams, run.batch),
        Linker::Sliced => PtvStream::sliced(cluster, tparams, run.slicing(), run.batch)
            .map_err(|e| Error::analysis(format!("run.slice_pulses / run.slice_overlap: {e}"))),
    }
}

/// The run of [`track_to_dir`] with its results handed to `sink` instead
/// of files: `config` from [`resolve_config`], `stream` from
/// [`stream_of`]. The run stops with an error when `cancel` is set (it
/// looks after each chunk read and each pulse) or a sink returns an error.
pub fn track_into(
    input: TrackInput<'_>,
    config: &TrackConfig,
    mut stream: PtvStream,
    sink: &mut dyn PtvSink,
    on_progress: &(dyn Fn(TrackProgress<'_>) + Sync),
    cancel: &crate::Cancel,
) -> Result<SinkRun> {
    let run = &config.run;
    let particles = match input {
        TrackInput::Recording(path) => {
            return track_recording_into(path, run, stream, sink, on_progress, cancel)
        }
        TrackInput::ParticlesTable(path) => {
            on_progress(TrackProgress::Stage {
                stage: TrackStage::Tracking,
                file_size: std::fs::metadata(path).ok().map(|m| m.len()),
            });
            read_particles(path)?
        }
        TrackInput::Particles(particles) => {
            on_progress(TrackProgress::Stage {
                stage: TrackStage::Tracking,
                file_size: None,
            });
            particles
        }
    };
    let mut order: Vec<usize> = (0..particles.len()).collect();
    order.sort_by_key(|&i| particles[i].pulse);
    let sorted: Vec<Particle> = order.iter().map(|&i| particles[i]).collect();
    let mut s = 0;
    while s < sorted.len() {
        let mut e = s;
        while e < sorted.len() && sorted[e].pulse == sorted[s].pulse {
            e += 1;
        }
        cancel.check()?;
        stream.push_particles(sorted[s].pulse, sorted[s].t_us, &sorted[s..e], sink)?;
        let (particles, active_tracks) = stream.progress();
        on_progress(TrackProgress::Pulse {
            particles,
            active_tracks,
        });
        s = e;
    }
    let stats = stream.finish(sink)?;
    Ok(SinkRun {
        stats,
        pulses: None,
        unassigned_events: 0,
        geometry: None,
    })
}

/// [`track_into`] on a recording: pulse timing, then tracking.
fn track_recording_into(
    input: &Path,
    run: &RunParams,
    stream: PtvStream,
    sink: &mut dyn PtvSink,
    on_progress: &(dyn Fn(TrackProgress<'_>) + Sync),
    cancel: &crate::Cancel,
) -> Result<SinkRun> {
    let opts = PulseOptions {
        pulse_hz: run.pulse_hz,
        ignore_triggers: run.ignore_triggers,
        require_pulsed: !run.force_pulses,
        ..Default::default()
    };
    let geometry = {
        let src = crate::io::open(input)?;
        for w in src.warnings() {
            on_progress(TrackProgress::Warning(&w));
        }
        src.info().geometry
    };
    if let (Some(p), Some(g)) = (&run.mask, geometry) {
        let (w, h) = crate::calib::PixelMask::from_png(p)?.size();
        if (w, h) != (g.width as u32, g.height as u32) {
            return Err(Error::Config {
                path: p.clone(),
                why: format!(
                    "mask of {w} x {h} pixels, the sensor has {} x {}",
                    g.width, g.height
                ),
            });
        }
    }
    // The recording is read twice: pulse timing, then tracking.
    let passes = std::sync::atomic::AtomicUsize::new(0);
    let open = || -> Result<Box<dyn EventSource + '_>> {
        let inner = crate::io::open_for_analysis(input)?;
        let stage = match passes.fetch_add(1, std::sync::atomic::Ordering::Relaxed) {
            0 => TrackStage::PulseTiming,
            _ => TrackStage::Tracking,
        };
        on_progress(TrackProgress::Stage {
            stage,
            file_size: inner.info().file_size,
        });
        cancel.check()?;
        Ok(Box::new(crate::io::Observed::new(inner, move |r| {
            cancel.check()?;
            on_progress(TrackProgress::Read {
                stage,
                bytes: r.bytes,
                events: r.events,
                done: r.done,
            });
            Ok(())
        })))
    };
    let run_result = track_recording(&open, &opts, stream, sink, &mut |s| {
        let (particles, active_tracks) = s.progress();
        on_progress(TrackProgress::Pulse {
            particles,
            active_tracks,
        });
    })?;
    Ok(SinkRun {
        stats: run_result.stats,
        pulses: Some(run_result.pulses),
        unassigned_events: run_result.unassigned_events,
        geometry,
    })
}

/// Reads pixels to ignore from `path`: one `x,y` per line (a header line
/// and blank lines are skipped).
pub(crate) fn read_hot_pixels(path: &Path) -> Result<HashSet<(u16, u16)>> {
    let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
    let mut set = HashSet::new();
    for (i, line) in text.lines().enumerate() {
        let f: Vec<&str> = line.split(',').map(|s| s.trim()).collect();
        if f.len() < 2 || line.trim().is_empty() {
            continue;
        }
        match (f[0].parse::<u16>(), f[1].parse::<u16>()) {
            (Ok(x), Ok(y)) => {
                set.insert((x, y));
            }
            _ if i == 0 => {} // header
            _ => {
                return Err(Error::analysis(format!(
                    "{}: line {}: expected `x,y` pixel coordinates, got `{line}`",
                    path.display(),
                    i + 1
                )))
            }
        }
    }
    Ok(set)
}

/// True when the file is a table (Parquet, `.npy` or CSV) with a `pulse`
/// column: a particles table (event files have no such column). Missing
/// columns are then reported by the particles reader.
fn is_particles_table(path: &Path) -> bool {
    crate::table::column_names(path).is_some_and(|c| c.iter().any(|c| c == "pulse"))
}

/// What the tracking thread hands to the writer thread.
enum Output {
    /// A pulse's index and particles.
    Particles(i64, Vec<Particle>),
    Tracks(Vec<Track>),
}

/// The outputs of one run, on their own thread ([`FileSink`] feeds it):
/// the CSV/NPY writers, the summary and the figure's polylines.
struct Writer {
    particles_out: ParticlesWriter,
    tracks_out: TracksWriter,
    npy_out: Option<TracksNpyWriter>,
    summary: SummaryAcc,
    first_pulse: Option<i64>,
    plot_pulses: i64,
    plot_lines: Vec<Vec<(f64, f64)>>,
    plot_speeds: Vec<f64>,
    width: f64,
    height: f64,
    /// px/s → m/s for the figure's colour scale, when calibrated.
    speed_to_m_s: Option<f64>,
}

impl Writer {
    fn create(
        out: &Path,
        format: TableFormat,
        npy: bool,
        plot_pulses: i64,
        calib: Option<crate::calib::Calibration>,
    ) -> Result<Self> {
        let speed_to_m_s = calib.as_ref().map(|c| c.velocity_px_s_to_m_s(1.0, 0.0).0);
        Ok(Writer {
            speed_to_m_s,
            particles_out: ParticlesWriter::create(out, format)?,
            tracks_out: TracksWriter::create_calibrated(out, format, calib)?,
            // tracks.npy is the tracks table itself in the npy format.
            npy_out: (npy && format != TableFormat::Npy)
                .then(|| TracksNpyWriter::create(&out.join("tracks.npy")))
                .transpose()?,
            summary: SummaryAcc::default(),
            first_pulse: None,
            plot_pulses,
            plot_lines: Vec::new(),
            plot_speeds: Vec::new(),
            width: 0.0,
            height: 0.0,
        })
    }

    /// Write everything that arrives until the channel closes.
    fn run(mut self, rx: std::sync::mpsc::Receiver<Output>) -> Result<Self> {
        for msg in rx {
            match msg {
                Output::Particles(pulse, ps) => self.particles(pulse, &ps)?,
                Output::Tracks(ts) => self.tracks(&ts)?,
            }
        }
        Ok(self)
    }

    fn particles(&mut self, pulse: i64, ps: &[Particle]) -> Result<()> {
        self.first_pulse.get_or_insert(pulse);
        for p in ps {
            self.width = self.width.max(p.x + 1.0);
            self.height = self.height.max(p.y + 1.0);
        }
        self.particles_out.write(ps)
    }

    fn tracks(&mut self, tracks: &[Track]) -> Result<()> {
        self.tracks_out.write(tracks)?;
        if let Some(npy) = &mut self.npy_out {
            npy.write(tracks)?;
        }
        self.summary.add(tracks);
        let end = self.first_pulse.unwrap_or(0) + self.plot_pulses;
        for t in tracks {
            let pts: Vec<(f64, f64)> = t
                .points
                .iter()
                .filter(|p| p.pulse < end)
                .map(|p| (p.x, p.y))
                .collect();
            if pts.len() >= 2 {
                let speed =
                    t.points.iter().map(|p| p.u.hypot(p.v)).sum::<f64>() / t.points.len() as f64;
                self.plot_lines.push(pts);
                self.plot_speeds.push(speed);
            }
        }
        Ok(())
    }

    /// Commits the files, writes summary.json and tracks.png (`size`: the
    /// sensor's, else the extent of the particles).
    fn finish(
        mut self,
        stats: &TrackerStats,
        out: &Path,
        size: Option<(f64, f64)>,
        provenance: Option<&crate::provenance::Provenance>,
    ) -> Result<Summary> {
        let mut summary = self.summary.summary(stats);
        if let Some(p) = provenance {
            let json = p.to_json();
            let text = json.to_string();
            self.particles_out
                .add_metadata(crate::provenance::PARQUET_KEY, &text);
            self.tracks_out
                .add_metadata(crate::provenance::PARQUET_KEY, &text);
            summary.provenance = Some(json);
        }
        // The big files' commits wait for the disk (their sync) and the
        // figure is CPU work: nothing else runs at this point, so they run
        // side by side instead of one after another.
        let Writer {
            particles_out,
            tracks_out,
            npy_out,
            first_pulse,
            plot_pulses,
            plot_lines,
            plot_speeds,
            width: seen_width,
            height: seen_height,
            speed_to_m_s,
            ..
        } = self;
        let (plot_speeds, speed_label) = match speed_to_m_s {
            Some(k) => (plot_speeds.iter().map(|v| v * k).collect(), "speed (m/s)"),
            None => (plot_speeds, "speed (px/s)"),
        };
        let (width, height) = size.unwrap_or((seen_width.max(1.0), seen_height.max(1.0)));
        std::thread::scope(|scope| -> Result<()> {
            let particles = scope.spawn(move || particles_out.finish());
            let tracks = scope.spawn(move || tracks_out.finish());
            let npy = npy_out.map(|npy| scope.spawn(move || npy.finish()));
            let rest = write_summary_json(&out.join("summary.json"), &summary).and_then(|()| {
                crate::plot::polylines(
                    &out.join("tracks.png"),
                    &crate::plot::Polylines {
                        title: &format!(
                            "tracks, pulses {}..{}",
                            first_pulse.unwrap_or(0),
                            first_pulse.unwrap_or(0) + plot_pulses
                        ),
                        width,
                        height,
                        lines: &plot_lines,
                        values: &plot_speeds,
                        colorbar_label: speed_label,
                    },
                )
            });
            let join = |h: std::thread::ScopedJoinHandle<'_, Result<()>>| {
                h.join().unwrap_or_else(|e| std::panic::resume_unwind(e))
            };
            // Every commit is waited for; the first error is reported.
            let particles = join(particles);
            let tracks = join(tracks);
            let npy = npy.map(join).unwrap_or(Ok(()));
            particles?;
            tracks?;
            npy?;
            rest
        })?;
        Ok(summary)
    }
}

/// Track points per message to the writer (×128 messages in the channel:
/// ~40 MB at most waiting).
const MESSAGE_POINTS: usize = 4096;

/// A [`PtvSink`] that writes a run's files into a directory: the
/// `particles` and `tracks` tables in `run.table_format`, `tracks.npy`
/// (when `run.npy`), and at
/// `FileSink::finish` `summary.json` and `tracks.png`. Results go to a
/// writer thread through a bounded channel, so a slow disk holds the
/// tracker back instead of filling memory. Dropped without `finish` (an
/// error on the way), it writes no file.
pub(crate) struct FileSink {
    out: std::path::PathBuf,
    /// Recorded in `summary.json` and the Parquet tables when set.
    pub provenance: Option<crate::provenance::Provenance>,
    tx: Option<std::sync::mpsc::SyncSender<Output>>,
    writer: Option<std::thread::JoinHandle<Result<Writer>>>,
}

impl FileSink {
    /// [`FileSink::create`] whose tracks table also has the physical
    /// columns of `calib`.
    pub(crate) fn create_calibrated(
        out: &Path,
        run: &RunParams,
        calib: Option<crate::calib::Calibration>,
    ) -> Result<Self> {
        let writer = Writer::create(out, run.table_format, run.npy, run.plot_pulses, calib)?;
        let (tx, rx) = std::sync::mpsc::sync_channel(128);
        let handle = std::thread::Builder::new()
            .name("ebptv-track-writer".into())
            .spawn(move || writer.run(rx))
            .map_err(|e| Error::analysis(format!("starting the output writer thread: {e}")))?;
        Ok(FileSink {
            out: out.to_path_buf(),
            provenance: None,
            tx: Some(tx),
            writer: Some(handle),
        })
    }

    fn send(&mut self, msg: Output) -> Result<()> {
        let Some(tx) = self.tx.as_ref() else {
            return Err(Error::analysis("the output writer stopped early"));
        };
        if tx.send(msg).is_ok() {
            return Ok(());
        }
        // The writer stopped: it failed; report its error.
        self.tx = None;
        match self.join() {
            Err(e) => Err(e),
            Ok(_) => Err(Error::analysis("the output writer stopped early")),
        }
    }

    fn join(&mut self) -> Result<Writer> {
        let Some(handle) = self.writer.take() else {
            return Err(Error::analysis("the output writer stopped early"));
        };
        handle
            .join()
            .unwrap_or_else(|e| std::panic::resume_unwind(e))
    }

    /// Commits the files and writes `summary.json` (from `stats`, the
    /// tracker's counters) and `tracks.png`, drawn over `size` (the
    /// sensor's width and height; `None`: the extent of the particles).
    pub(crate) fn finish(
        mut self,
        stats: &TrackerStats,
        size: Option<(f64, f64)>,
    ) -> Result<Summary> {
        self.tx = None; // closes the channel: the writer drains it and returns
        let writer = self.join()?;
        writer.finish(stats, &self.out, size, self.provenance.as_ref())
    }
}

/// On an error the run ends without `finish`: close the channel and wait
/// for the writer, whose uncommitted files then remove themselves (no
/// temporary files left behind).
impl Drop for FileSink {
    fn drop(&mut self) {
        self.tx = None;
        if let Some(handle) = self.writer.take() {
            let _ = handle.join();
        }
    }
}

impl PtvSink for FileSink {
    fn particles(&mut self, pulse: i64, t_us: f64, ps: &[Particle]) -> Result<()> {
        self.take_particles(pulse, t_us, ps.to_vec())
    }

    fn take_particles(&mut self, pulse: i64, _t_us: f64, ps: Vec<Particle>) -> Result<()> {
        self.send(Output::Particles(pulse, ps))
    }

    fn tracks(&mut self, tracks: &[Track]) -> Result<()> {
        self.take_tracks(tracks.to_vec())
    }

    /// Large hand-outs (the sliced linker's come a group of slices at a
    /// time) go in messages of at most `MESSAGE_POINTS` points, so the
    /// bounded channel bounds the memory waiting for the writer.
    fn take_tracks(&mut self, tracks: Vec<Track>) -> Result<()> {
        let mut chunk = Vec::new();
        let mut points = 0;
        for t in tracks {
            points += t.points.len();
            chunk.push(t);
            if points >= MESSAGE_POINTS {
                self.send(Output::Tracks(std::mem::take(&mut chunk)))?;
                points = 0;
            }
        }
        if chunk.is_empty() {
            return Ok(());
        }
        self.send(Output::Tracks(chunk))
    }
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;
    use std::sync::atomic::{AtomicU64, Ordering};

    /// Two particles crossing the field at constant speed, 12 pulses.
    fn write_particles(path: &Path) {
        let mut text = String::from("pulse,t_us,x,y,n_events\n");
        for k in 0..12 {
            let t = 200.0 * k as f64;
            let k = k as f64;
            text.push_str(&format!("{k},{t},{},{},2\n", 20.0 + 3.0 * k, 30.0));
            text.push_str(&format!("{k},{t},{},{},2\n", 60.0, 80.0 - 2.0 * k));
        }
        std::fs::write(path, text).unwrap();
    }

    #[ebptv_macros::unit_test]
    fn particles_csv_into_a_directory() {
        let dir = tempfile::tempdir().unwrap();
        let input = dir.path().join("particles.csv");
        write_particles(&input);
        let out = dir.path().join("out");
        let pulses = AtomicU64::new(0);
        let writing = AtomicU64::new(0);
        let run = track_to_dir(&input, &TrackConfig::default(), &out, &|p| match p {
            TrackProgress::Pulse { .. } => {
                pulses.fetch_add(1, Ordering::Relaxed);
            }
            TrackProgress::Writing => {
                writing.fetch_add(1, Ordering::Relaxed);
            }
            _ => {}
        })
        .unwrap();
        assert_eq!(pulses.load(Ordering::Relaxed), 12);
        assert_eq!(writing.load(Ordering::Relaxed), 1);
        assert!(run.pulses.is_none());
        assert_eq!(run.summary.pulses, 12);
        assert_eq!(run.summary.particles, 24);
        assert_eq!(run.summary.tracks, 2);
        for f in [
            "particles.parquet",
            "tracks.parquet",
            "summary.json",
            "tracks.png",
            "params.toml",
            "provenance.json",
        ] {
            assert!(out.join(f).is_file(), "{f} missing");
        }
        // A library call records an empty command line, the parameters,
        // the input and the pulse source.
        let prov = crate::provenance::Provenance::read_from_dir(&out)
            .unwrap()
            .unwrap();
        assert!(prov.command_line.is_empty());
        assert_eq!(prov.pulse_source.as_deref(), Some("particles table"));
        assert_eq!(prov.inputs.len(), 1);
        assert!(prov.parameters.unwrap().get("track").is_some());
        assert!(!out.join("tracks.npy").exists());
        let tracks = super::super::read_tracks(&out.join("tracks.parquet")).unwrap();
        assert_eq!(tracks.len(), 2);

        // The run's particles table, in each format, relinks to the same
        // tracks, written in each format.
        for fmt in [TableFormat::Csv, TableFormat::Npy, TableFormat::Parquet] {
            let mut config = TrackConfig::default();
            config.run.table_format = fmt;
            let again = dir.path().join(format!("again_{}", fmt.ext()));
            track_to_dir(&out.join("particles.parquet"), &config, &again, &|_| {}).unwrap();
            let relinked = dir.path().join(format!("relinked_{}", fmt.ext()));
            track_to_dir(
                &again.join(fmt.file_name("particles")),
                &TrackConfig::default(),
                &relinked,
                &|_| {},
            )
            .unwrap();
            assert!(!again.join("tracks.parquet").exists() || fmt == TableFormat::Parquet);
            let a = super::super::read_tracks(&again.join(fmt.file_name("tracks"))).unwrap();
            let b = super::super::read_tracks(&relinked.join("tracks.parquet")).unwrap();
            assert_eq!(a.len(), 2, "{fmt:?}");
            for (a, b) in a.iter().zip(&b).chain(a.iter().zip(&tracks)) {
                assert_eq!(a.id, b.id);
                assert_eq!(a.points.len(), b.points.len());
                for (p, q) in a.points.iter().zip(&b.points) {
                    // CSV keeps 4 decimals of positions, 3 of velocities.
                    assert_eq!(p.pulse, q.pulse);
                    assert!((p.x - q.x).abs() < 2e-4 && (p.y - q.y).abs() < 2e-4);
                    assert!(
                        (p.u - q.u).abs() < 1.0 && (p.v - q.v).abs() < 1.0,
                        "{p:?} {q:?}"
                    );
                }
            }
        }
    }

    #[ebptv_macros::unit_test]
    fn a_failed_run_leaves_no_files() {
        let dir = tempfile::tempdir().unwrap();
        let input = dir.path().join("missing.raw");
        let out = dir.path().join("out");
        let err = track_to_dir(&input, &TrackConfig::default(), &out, &|_| {}).unwrap_err();
        assert!(err.to_string().contains("missing.raw"), "{err}");
        let left: Vec<_> = std::fs::read_dir(&out)
            .map(|d| d.filter_map(|e| e.ok()).map(|e| e.file_name()).collect())
            .unwrap_or_default();
        assert!(left.is_empty(), "{left:?}");
    }
}
