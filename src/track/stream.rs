//! Recording → particles → tracks, streaming.
//!
//! The one entry point of the PTV stage for a recording:
//! [`track_recording`] runs the pulse analysis (one pass), then streams the
//! recording a second time through [`crate::pulses::split_pulses`] into a
//! [`PtvStream`]. Results go to a [`PtvSink`] as they appear — particles
//! per pulse, tracks when they end — so memory is bounded by the batches
//! in flight and the active tracks, not by the recording. What the sink
//! does with them (write CSV, bin onto a grid, score against truth) is the
//! caller's business.
//!
//! **A pipeline of four stages** keeps every core busy:
//!
//! ```text
//! caller's thread          cluster stage            tracker stage     fit stage
//! decode + split ──batch─▶ cluster (rayon pool) ──▶ link ──ended────▶ output fits
//!   ▲ (bounded, 1)          (bounded, 1)              (bounded, 1)     (global pool)
//!   └──────────── particles, fitted tracks, progress ◀──────────────────────┘
//!   sink calls (in pulse order)
//! ```
//!
//! Each stage runs on its own thread; the channels between them hold at
//! most one batch each, so a slow stage holds the earlier ones back
//! instead of filling memory. The results flow back to the caller's
//! thread, which calls the sink — the sink need not be `Send`, and its
//! calls come in exactly the order of the sequential loop (per pulse the
//! particles, then the tracks that ended), only later. That channel is
//! drained at every [`PtvStream::push_pulse`]; it can only hold what the
//! bounded stages passed on while the caller waited for room, so it stays
//! bounded too.
//!
//! **The output fits have a stage of their own**: linking is
//! the longest serial chain of the run, and while the tracker waited for
//! the fits of each batch of ended tracks it stood still. The tracker now
//! hands its ended tracks over unfitted ([`Tracker::defer_fits`]), with
//! the position noise and outlier gate of the moment they ended; the fit
//! stage fits them batch by batch, in the order they ended, with the
//! [`Finaliser`] the tracker would have used — the curvature prior of the
//! tracks kept before each batch, the same numbering — so the result is
//! the synchronous tracker's, bit for bit. Only the batches follow one
//! another; the tracks of a batch are fitted in parallel, as before.
//!
//! The clustering runs in a rayon pool of its own (as many threads as the
//! caller's pool), the output fits in the global pool: in one shared pool
//! the fits queued behind a whole batch of clustering jobs. (Run from
//! inside a rayon pool, the tracker and fit stages get pools of their own
//! too, so that their work never waits for workers that may be blocked
//! feeding the stream.) Neither the batch size nor any thread count
//! changes a result: clustering is per pulse, the tracker sees the pulses
//! in order, and its fits are numbered in order
//! (`parallel_stream_equals_sequential_tracking` checks 1–4 threads and
//! the global pool).
//!
//! Two passes over the file instead of one because pulse timing (the
//! period fitted over the whole recording) must be known before the first
//! event can be tied to its pulse; reading a file twice from the page
//! cache costs far less than holding it.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{self, Receiver, Sender, SyncSender, TryRecvError};
use std::sync::Arc;
use std::thread::JoinHandle;

use crate::cluster::{cluster_pulses, ClusterParams, Particle};
use crate::error::{Error, Result};
use crate::io::EventSource;
use crate::pulses::{self, PulseEvents, PulseOptions, PulseReport};

use super::slice::{SliceParams, SliceTracker};
use super::{EndedTracks, Finaliser, Track, TrackParams, Tracker, TrackerStats};

/// The linking stage of a [`PtvStream`].
#[allow(clippy::large_enum_variant)]
enum Linker {
    /// One [`Tracker`] over the whole stream.
    Sequential(Tracker),
    /// Independent trackers on time slices, joined at the seams.
    Sliced(SliceTracker),
}

impl Linker {
    /// Particles seen and tracks active.
    fn progress(&self) -> (u64, usize) {
        match self {
            Linker::Sequential(t) => (t.stats().particles, t.active_tracks()),
            Linker::Sliced(t) => (t.stats().particles, t.active_tracks()),
        }
    }

    /// Link one clustered pulse; the particles, then the tracks that
    /// ended, go to `out` (the order the sink sees them in).
    fn push(
        &mut self,
        pulse: i64,
        t_us: f64,
        ps: Vec<Particle>,
        out: &mut dyn FnMut(Output),
    ) -> Result<()> {
        match self {
            Linker::Sequential(tracker) => {
                // The tracker defers its fits (`Stages::start`): `done` is
                // empty, the ended tracks wait in `take_ended`.
                let done = tracker.push(pulse, t_us, &ps)?;
                out(Output::Particles(pulse, t_us, ps));
                if !done.is_empty() {
                    out(Output::Tracks(done));
                }
                for ended in tracker.take_ended() {
                    out(Output::Ended(ended));
                }
            }
            Linker::Sliced(st) => {
                // It keeps the particles until their slices are tracked.
                out(Output::Particles(pulse, t_us, ps.clone()));
                let done = st.push(pulse, t_us, ps)?;
                out(Output::Tracks(unlinked(done)));
            }
        }
        Ok(())
    }

    /// End all tracks (in the pipeline: the sequential tracker's
    /// unfitted, as [`Output::Ended`]).
    fn finish_into(self, out: &mut dyn FnMut(Output)) -> Result<TrackerStats> {
        match self {
            Linker::Sequential(t) => {
                let (ended, stats) = t.finish_unfitted();
                for e in ended {
                    out(Output::Ended(e));
                }
                Ok(stats)
            }
            Linker::Sliced(t) => {
                let (rest, stats) = t.finish()?;
                out(Output::Tracks(unlinked(rest)));
                Ok(stats)
            }
        }
    }

    /// End all tracks.
    fn finish(self) -> Result<(Vec<Track>, TrackerStats)> {
        let (rest, stats) = match self {
            Linker::Sequential(t) => t.finish(),
            Linker::Sliced(t) => t.finish()?,
        };
        Ok((unlinked(rest), stats))
    }
}

/// Receives the PTV stage's results while streaming.
pub trait PtvSink {
    /// The particles of one pulse (called in pulse order, also for pulses
    /// without particles).
    fn particles(&mut self, pulse: i64, t_us: f64, particles: &[Particle]) -> Result<()>;
    /// Tracks that have ended (final: they will not grow any more).
    fn tracks(&mut self, tracks: &[Track]) -> Result<()>;
    /// [`PtvSink::tracks`] handing over ownership (what the stream
    /// calls): a sink that sends tracks to another thread takes them
    /// without a copy. Defaults to [`PtvSink::tracks`].
    fn take_tracks(&mut self, tracks: Vec<Track>) -> Result<()> {
        self.tracks(&tracks)
    }
    /// [`PtvSink::particles`] handing over ownership (what the stream
    /// calls for recordings). Defaults to [`PtvSink::particles`].
    fn take_particles(&mut self, pulse: i64, t_us: f64, particles: Vec<Particle>) -> Result<()> {
        self.particles(pulse, t_us, &particles)
    }
}

/// What the tracker stage sends on to the fit stage, and the fit stage
/// back to the caller's thread.
enum Output {
    Particles(i64, f64, Vec<Particle>),
    Tracks(Vec<Track>),
    /// Tracks that ended together, still to be fitted (tracker → fit
    /// stage only).
    Ended(EndedTracks),
    /// Particles seen and tracks active after a batch.
    Progress(u64, usize),
    /// The stage stopped on this error.
    Failed(Error),
    /// All tracks ended and handed out (after their `Tracks`).
    Finished(TrackerStats),
}

/// A clustered batch: per pulse its index, start time and particles.
type Clustered = Vec<(i64, f64, Vec<Particle>)>;

/// The running stages of a [`PtvStream`].
struct Stages {
    /// Batches to the cluster stage (`None` once closed).
    to_cluster: Option<SyncSender<Vec<PulseEvents>>>,
    /// Results from the tracker stage.
    outputs: Receiver<Output>,
    /// Asks both stages to drop what is queued (the stream was dropped
    /// without `finish`, or failed).
    cancel: Arc<AtomicBool>,
    threads: Vec<JoinHandle<()>>,
}

impl Stages {
    /// Start the cluster, tracker and fit threads; the clustering gets
    /// a rayon pool of `threads` threads.
    fn start(cluster: ClusterParams, mut linker: Linker, threads: usize) -> Result<Self> {
        let pool = |name: &'static str| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .thread_name(move |i| format!("ebptv-{name}-{i}"))
                .build()
                .map_err(|e| Error::analysis(format!("starting the {name} threads: {e}")))
        };
        let cluster_pool = pool("cluster")?;
        // The sequential tracker hands its ended tracks over unfitted; the
        // fit stage continues its fits' state (prior, numbering).
        let finaliser = match &mut linker {
            Linker::Sequential(t) => Some(t.defer_fits()),
            Linker::Sliced(_) => None,
        };
        let (to_cluster, batches) = mpsc::sync_channel::<Vec<PulseEvents>>(1);
        let (to_track, clustered) = mpsc::sync_channel::<Result<Clustered>>(1);
        let (to_fit, linked) = mpsc::sync_channel::<Vec<Output>>(FIT_QUEUE_PULSES);
        let (to_caller, outputs) = mpsc::channel::<Output>();
        let cancel = Arc::new(AtomicBool::new(false));
        let spawn = |name: &str, f: Box<dyn FnOnce() + Send>| {
            std::thread::Builder::new()
                .name(name.into())
                .spawn(f)
                .map_err(|e| Error::analysis(format!("starting the {name} thread: {e}")))
        };
        let stop = cancel.clone();
        let clusterer = spawn(
            "ebptv-cluster",
            Box::new(move || {
                cluster_pool.install(|| cluster_stage(&cluster, batches, to_track, &stop))
            }),
        )?;
        let mut stages = Stages {
            to_cluster: Some(to_cluster),
            outputs,
            cancel,
            threads: vec![clusterer],
        };
        // On a failure below `stages` drops: the threads started see their
        // input (or output) closed and end.
        // The tracker's and the fits' parallel work (the sliced linker's
        // slices, the output fits) goes to the global pool — unless the
        // stream is driven from inside a rayon pool: the caller's thread
        // may then be one of the global workers, blocked on a channel, and
        // the work must not depend on them (each stage then runs inside a
        // pool of its own and takes part in its work).
        let own_pools = rayon::current_thread_index().is_some();
        let track_pool = if own_pools {
            Some(pool("track")?)
        } else {
            None
        };
        let fit_pool = if own_pools { Some(pool("fit")?) } else { None };
        let stop = stages.cancel.clone();
        stages.threads.push(spawn(
            "ebptv-track",
            Box::new(move || match track_pool {
                Some(p) => p.install(|| track_stage(linker, clustered, to_fit, &stop)),
                None => track_stage(linker, clustered, to_fit, &stop),
            }),
        )?);
        let stop = stages.cancel.clone();
        stages.threads.push(spawn(
            "ebptv-fit",
            Box::new(move || match fit_pool {
                Some(p) => p.install(|| fit_stage(finaliser, linked, to_caller, &stop)),
                None => fit_stage(finaliser, linked, to_caller, &stop),
            }),
        )?);
        Ok(stages)
    }

    /// Close the input, wait for both threads; a panic in one is resumed
    /// here.
    fn join(&mut self) {
        self.to_cluster = None;
        let mut panic = None;
        for h in self.threads.drain(..) {
            if let Err(e) = h.join() {
                panic.get_or_insert(e);
            }
        }
        if let Some(e) = panic {
            // Not while unwinding already (a drop on the way out).
            if !std::thread::panicking() {
                std::panic::resume_unwind(e);
            }
        }
    }
}

/// Cluster batches until the input closes (or the tracker stage stops).
fn cluster_stage(
    params: &ClusterParams,
    batches: Receiver<Vec<PulseEvents>>,
    to_track: SyncSender<Result<Clustered>>,
    cancel: &AtomicBool,
) {
    for batch in batches {
        if cancel.load(Ordering::Relaxed) {
            return;
        }
        let clustered = cluster_pulses(&batch, params).map(|parts| {
            batch
                .iter()
                .zip(parts)
                .map(|(pe, ps)| (pe.index, pe.start_us, ps))
                .collect()
        });
        drop(batch); // free the events before waiting for room
        let failed = clustered.is_err();
        if to_track.send(clustered).is_err() || failed {
            return;
        }
    }
}

/// Link clustered batches in order until the input closes, then end all
/// tracks; everything goes on to the fit stage as [`Output`]s, one pulse
/// at a time (the channel holds [`FIT_QUEUE_PULSES`]: a batch at a time,
/// the fit stage would hold a whole batch's particles and ended tracks
/// more, ~20 MB at full frame).
fn track_stage(
    mut linker: Linker,
    clustered: Receiver<Result<Clustered>>,
    to_fit: SyncSender<Vec<Output>>,
    cancel: &AtomicBool,
) {
    // A send fails only when the fit stage is gone: nothing left to do then.
    for batch in clustered {
        if cancel.load(Ordering::Relaxed) {
            return;
        }
        let batch = match batch {
            Ok(b) => b,
            Err(e) => {
                let _ = to_fit.send(vec![Output::Failed(e)]);
                return;
            }
        };
        for (pulse, t_us, ps) in batch {
            let mut outs = Vec::with_capacity(3);
            if let Err(e) = linker.push(pulse, t_us, ps, &mut |o| outs.push(o)) {
                outs.push(Output::Failed(e));
                let _ = to_fit.send(outs);
                return;
            }
            if to_fit.send(outs).is_err() {
                return;
            }
        }
        let (particles, active) = linker.progress();
        if to_fit
            .send(vec![Output::Progress(particles, active)])
            .is_err()
        {
            return;
        }
    }
    if cancel.load(Ordering::Relaxed) {
        return;
    }
    let mut outs = Vec::new();
    match linker.finish_into(&mut |o| outs.push(o)) {
        Ok(stats) => outs.push(Output::Finished(stats)),
        Err(e) => outs.push(Output::Failed(e)),
    }
    let _ = to_fit.send(outs);
}

/// Pulses of linked output queued between the tracker and the fit stage.
const FIT_QUEUE_PULSES: usize = 16;

/// Largest `run.batch` accepted (pulses): 4096 pulses of a 20 Mev/s
/// recording at 5 kHz are ~0.3 GB of events per batch in flight.
const MAX_BATCH_PULSES: usize = 4096;

/// Fit the sequential tracker's ended tracks ([`Output::Ended`]) in the
/// order they ended, each batch in parallel (rayon, the pool this runs
/// in), and pass everything on to the caller's thread in order. Off the
/// tracker's thread, the fits no longer hold the linking up; the result
/// is the synchronous tracker's: the same batches, fitted with the same
/// prior, numbered in the same order.
fn fit_stage(
    mut finaliser: Option<Finaliser>,
    linked: Receiver<Vec<Output>>,
    to_caller: Sender<Output>,
    cancel: &AtomicBool,
) {
    // The fits' counters, added to the tracker's at the end.
    let mut fit_stats = TrackerStats::default();
    for outs in linked {
        for o in outs {
            if cancel.load(Ordering::Relaxed) {
                return;
            }
            let o = match o {
                Output::Ended(ended) => match &mut finaliser {
                    Some(f) => Output::Tracks(unlinked(f.finalise(ended, &mut fit_stats))),
                    None => Output::Failed(Error::analysis(
                        "unfitted tracks from a linker that fits its own",
                    )),
                },
                Output::Finished(mut stats) => {
                    stats.add_fit_counters(&fit_stats);
                    Output::Finished(stats)
                }
                o => o,
            };
            // A send fails only when the caller is gone.
            if to_caller.send(o).is_err() {
                return;
            }
        }
    }
}

/// Where a [`PtvStream`] stands.
enum State {
    /// No batch handed on yet: clustering and linking could still run on
    /// the caller's thread ([`PtvStream::push_particles`]).
    Idle(Box<(ClusterParams, Linker)>),
    /// The stage threads run.
    Running(Stages),
    /// Finished or failed.
    Stopped,
}

/// Clustering and tracking fed pulse by pulse (module docs: a pipeline of
/// threads; the sink is called on the caller's thread, in pulse order).
pub struct PtvStream {
    state: State,
    batch: Vec<PulseEvents>,
    batch_size: usize,
    events: u64,
    /// Particles seen and tracks active, as last reported by the tracker.
    progress: (u64, usize),
    stats: Option<TrackerStats>,
}

impl PtvStream {
    /// `batch_size`: pulses clustered per parallel batch (≥ 1). Links
    /// with one sequential [`Tracker`].
    #[ebptv_macros::testkit]
    pub(crate) fn new(
        cluster: ClusterParams,
        track: TrackParams,
        batch_size: usize,
    ) -> Result<Self> {
        let linker = Linker::Sequential(Tracker::new(track)?);
        Self::with_linker(cluster, linker, batch_size)
    }

    /// [`PtvStream::new`] linking with the parallel slice-and-stitch
    /// tracker ([`crate::track::slice`]).
    pub(crate) fn sliced(
        cluster: ClusterParams,
        track: TrackParams,
        slicing: SliceParams,
        batch_size: usize,
    ) -> Result<Self> {
        let linker = Linker::Sliced(SliceTracker::new(track, slicing)?);
        Self::with_linker(cluster, linker, batch_size)
    }

    fn with_linker(cluster: ClusterParams, linker: Linker, batch_size: usize) -> Result<Self> {
        cluster.validate()?;
        if batch_size == 0 {
            return Err(Error::param("batch", "must be at least 1 pulse"));
        }
        if batch_size > MAX_BATCH_PULSES {
            // Up to three batches of events are in flight at once.
            return Err(Error::param(
                "batch",
                format!(
                    "at most {MAX_BATCH_PULSES} pulses (each stage holds a batch of events in memory), got {batch_size}"
                ),
            ));
        }
        Ok(PtvStream {
            state: State::Idle(Box::new((cluster, linker))),
            batch: Vec::with_capacity(batch_size),
            batch_size,
            events: 0,
            progress: (0, 0),
            stats: None,
        })
    }

    /// Add the events of the next pulse (pulses in increasing order).
    /// Results of earlier pulses reach the sink here, as they come out of
    /// the pipeline.
    #[ebptv_macros::testkit]
    pub(crate) fn push_pulse(&mut self, pulse: PulseEvents, sink: &mut dyn PtvSink) -> Result<()> {
        self.events += pulse.events.len() as u64;
        self.batch.push(pulse);
        if self.batch.len() >= self.batch_size {
            self.hand_on(sink)?;
        }
        self.drain(sink, false)
    }

    /// Link already-detected particles of one pulse (e.g. read from a
    /// `particles.csv`) on the caller's thread; pulses in increasing
    /// order. Not after [`PtvStream::push_pulse`] started the pipeline.
    pub(crate) fn push_particles(
        &mut self,
        pulse: i64,
        t_us: f64,
        particles: &[Particle],
        sink: &mut dyn PtvSink,
    ) -> Result<()> {
        let State::Idle(idle) = &mut self.state else {
            return Err(Error::param(
                "particles",
                "a stream fed with events cannot also link particles",
            ));
        };
        sink.particles(pulse, t_us, particles)?;
        let done = match &mut idle.1 {
            Linker::Sequential(tracker) => tracker.push(pulse, t_us, particles)?,
            Linker::Sliced(st) => unlinked(st.push(pulse, t_us, particles.to_vec())?),
        };
        self.progress = idle.1.progress();
        sink.take_tracks(done)
    }

    /// Hand the current batch to the cluster stage (starting the stages
    /// on the first one); waits while the stage still holds a batch.
    fn hand_on(&mut self, sink: &mut dyn PtvSink) -> Result<()> {
        if self.batch.is_empty() {
            return Ok(());
        }
        if matches!(self.state, State::Idle(_)) {
            let State::Idle(idle) = std::mem::replace(&mut self.state, State::Stopped) else {
                unreachable!("checked above");
            };
            let (cluster, linker) = *idle;
            let threads = rayon::current_num_threads().max(1);
            self.state = State::Running(Stages::start(cluster, linker, threads)?);
        }
        let State::Running(stages) = &mut self.state else {
            return Err(Error::analysis("the tracking stream has stopped"));
        };
        let batch = std::mem::replace(&mut self.batch, Vec::with_capacity(self.batch_size));
        let sent = stages
            .to_cluster
            .as_ref()
            .is_some_and(|tx| tx.send(batch).is_ok());
        if sent {
            Ok(())
        } else {
            // A stage stopped: its error is in the outputs.
            self.drain(sink, true)?;
            Err(Error::analysis("the tracking stages stopped early"))
        }
    }

    /// Pass the results that came out of the pipeline to the sink; with
    /// `to_end`, wait for all of them (the input must be closed). On an
    /// error (the stages' or the sink's) the stages are stopped.
    fn drain(&mut self, sink: &mut dyn PtvSink, to_end: bool) -> Result<()> {
        let State::Running(stages) = &mut self.state else {
            return Ok(());
        };
        loop {
            let out = if to_end {
                match stages.outputs.recv() {
                    Ok(o) => o,
                    Err(_) => break,
                }
            } else {
                match stages.outputs.try_recv() {
                    Ok(o) => o,
                    Err(TryRecvError::Empty | TryRecvError::Disconnected) => break,
                }
            };
            let r = match out {
                Output::Particles(pulse, t_us, ps) => sink.take_particles(pulse, t_us, ps),
                Output::Tracks(ts) => sink.take_tracks(ts),
                Output::Progress(particles, active) => {
                    self.progress = (particles, active);
                    Ok(())
                }
                Output::Failed(e) => Err(e),
                Output::Ended(_) => Err(Error::analysis("unfitted tracks passed the fit stage")),
                Output::Finished(stats) => {
                    self.stats = Some(stats);
                    Ok(())
                }
            };
            if let Err(e) = r {
                self.stop();
                return Err(e);
            }
        }
        Ok(())
    }

    /// Stop the stages (dropping what they still hold) and join them.
    fn stop(&mut self) {
        if let State::Running(mut stages) = std::mem::replace(&mut self.state, State::Stopped) {
            stages.cancel.store(true, Ordering::Relaxed);
            stages.join();
        }
    }

    /// Particles seen and tracks active (for progress reports; from the
    /// tracker stage's last report while the pipeline runs).
    pub(crate) fn progress(&self) -> (u64, usize) {
        match &self.state {
            State::Idle(idle) => idle.1.progress(),
            _ => self.progress,
        }
    }

    /// Cluster and track what is left, end all tracks, hand everything to
    /// the sink.
    #[ebptv_macros::testkit]
    pub(crate) fn finish(mut self, sink: &mut dyn PtvSink) -> Result<TrackerStats> {
        self.hand_on(sink)?;
        match std::mem::replace(&mut self.state, State::Stopped) {
            State::Idle(idle) => {
                let (rest, stats) = idle.1.finish()?;
                sink.take_tracks(rest)?;
                Ok(stats)
            }
            State::Running(mut stages) => {
                // Close the input; the stages end after the last batch.
                stages.to_cluster = None;
                self.state = State::Running(stages);
                self.drain(sink, true)?;
                self.stop();
                self.stats
                    .take()
                    .ok_or_else(|| Error::analysis("the tracking stage ended without its result"))
            }
            State::Stopped => Err(Error::analysis("the tracking stream has stopped")),
        }
    }
}

/// Dropped without [`PtvStream::finish`] (an error on the way): the stages
/// drop what they hold and end.
impl Drop for PtvStream {
    fn drop(&mut self) {
        self.stop();
    }
}

fn unlinked(tracks: Vec<super::LinkedTrack>) -> Vec<Track> {
    tracks.into_iter().map(|t| t.track).collect()
}

/// What [`track_recording`] found besides the tracks it handed to its sink.
#[derive(Clone, Debug)]
#[ebptv_macros::testkit]
pub(crate) struct TrackingRun {
    /// The pulse analysis (timing, lock-in test), as in `pulses.json`.
    pub pulses: PulseReport,
    /// The tracker's counters.
    pub stats: TrackerStats,
    /// Events that fell outside every pulse window.
    pub unassigned_events: u64,
}

/// The whole PTV stage on a recording. `open` opens the recording afresh
/// (it is read twice: pulse analysis, then tracking); `on_pulse` is called
/// after each pulse for progress reports.
#[ebptv_macros::testkit]
pub(crate) fn track_recording<'a>(
    open: &dyn Fn() -> Result<Box<dyn EventSource + 'a>>,
    pulse_options: &PulseOptions,
    stream: PtvStream,
    sink: &mut dyn PtvSink,
    on_pulse: &mut dyn FnMut(&PtvStream),
) -> Result<TrackingRun> {
    let mut src = open()?;
    let path = (*src).info().path.clone();
    let report = pulses::analyze_pipelined(&mut *src, pulse_options).map_err(|e| {
        crate::Error::analysis(format!(
            "finding the light pulses in {}: {e}",
            path.display()
        ))
    })?;
    drop(src);
    let mut src = open()?;
    let mut stream = stream;
    let unassigned = pulses::split_pulses(&mut *src, &report.timing, &mut |p| {
        stream.push_pulse(p, sink)?;
        on_pulse(&stream);
        Ok(())
    })?;
    let stats = stream.finish(sink)?;
    Ok(TrackingRun {
        pulses: report,
        stats,
        unassigned_events: unassigned,
    })
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;
    use crate::events::EventChunk;

    #[derive(Default)]
    struct Collect {
        pulses: Vec<i64>,
        particles: usize,
        tracks: Vec<Track>,
    }

    impl PtvSink for Collect {
        fn particles(&mut self, pulse: i64, _t: f64, ps: &[Particle]) -> Result<()> {
            self.pulses.push(pulse);
            self.particles += ps.len();
            Ok(())
        }
        fn tracks(&mut self, tracks: &[Track]) -> Result<()> {
            self.tracks.extend_from_slice(tracks);
            Ok(())
        }
    }

    /// Three particles moving uniformly, two events each per pulse: the
    /// stream must give one track per particle with the true velocity,
    /// whatever the batch size.
    #[ebptv_macros::unit_test]
    fn batches_do_not_change_the_result() {
        let period = 200.0;
        let pulses: Vec<PulseEvents> = (0..30)
            .map(|k| {
                let mut ev = EventChunk::default();
                for (i, (x0, y0)) in [(20.0, 20.0), (60.0, 40.0), (100.0, 70.0)]
                    .iter()
                    .enumerate()
                {
                    let x = x0 + 2.0 * k as f64;
                    let y = y0 + 1.0 * k as f64 + i as f64 * 0.0;
                    let t = (k as f64 * period) as i64 + 50;
                    ev.push(t, x as u16, y as u16, 1);
                    ev.push(t + 1, x as u16 + 1, y as u16, 1);
                }
                PulseEvents {
                    index: k,
                    start_us: k as f64 * period,
                    events: ev,
                }
            })
            .collect();
        let run = |batch: usize| {
            let mut s =
                PtvStream::new(ClusterParams::default(), TrackParams::default(), batch).unwrap();
            let mut sink = Collect::default();
            for p in pulses.iter().cloned() {
                s.push_pulse(p, &mut sink).unwrap();
            }
            s.finish(&mut sink).unwrap();
            sink
        };
        let a = run(1);
        let b = run(7);
        assert_eq!(a.pulses, (0..30).collect::<Vec<_>>());
        assert_eq!(a.pulses, b.pulses);
        assert_eq!(a.particles, 90);
        assert_eq!(a.tracks.len(), 3);
        assert_eq!(a.tracks, b.tracks);
        for t in &a.tracks {
            let mid = &t.points[t.points.len() / 2];
            // 2 px and 1 px per 200 µs pulse interval.
            assert!((mid.u - 10_000.0).abs() < 1.0, "u = {}", mid.u);
            assert!((mid.v - 5_000.0).abs() < 1.0, "v = {}", mid.v);
        }
    }

    /// A paper-like synthetic scene (ppp 0.01, ~1.6 events per particle,
    /// 1 % noise) through the stream in rayon pools of 1, 2 and 3 threads
    /// and with different batch sizes must give exactly what clustering and
    /// tracking pulse by pulse on one thread gives: the parallel clustering,
    /// the output fits on their own stage (the tracker's ended tracks
    /// fitted later, on another thread, with the curvature prior of the
    /// tracks kept before them) and in parallel change nothing. Short
    /// `max_track_length` so that segment hand-outs are exercised too.
    #[ebptv_macros::unit_test]
    fn parallel_stream_equals_sequential_tracking() {
        use crate::cluster::cluster_pulse;
        use crate::track::synth::{generate, SynthParams};
        let scene = generate(&SynthParams {
            width: 200,
            height: 200,
            pulses: 120,
            ..Default::default()
        });
        let cparams = ClusterParams::default();
        let tparams = TrackParams {
            gates: crate::track::GateParams {
                max_track_length: 44,
                ..Default::default()
            },
            ..Default::default()
        };
        let pool = |n: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .build()
                .unwrap()
        };
        let reference = pool(1).install(|| {
            let mut tracker = Tracker::new(tparams.clone()).unwrap();
            let mut sink = Collect::default();
            for sp in &scene {
                let ps = cluster_pulse(&sp.pulse, &cparams);
                sink.particles(sp.pulse.index, sp.pulse.start_us, &ps)
                    .unwrap();
                let done = tracker
                    .push(sp.pulse.index, sp.pulse.start_us, &ps)
                    .unwrap();
                sink.tracks(&done).unwrap();
            }
            // The fits used the curvature prior (the order of the fits
            // matters).
            assert!(tracker.fit_accel_rms() > 0.0);
            let (rest, stats) = tracker.finish();
            sink.tracks.extend(rest.into_iter().map(|t| t.track));
            (sink, stats)
        });
        assert!(
            reference.0.tracks.len() > 100,
            "{}",
            reference.0.tracks.len()
        );
        assert!(reference.1.tracks_kept > 100 && reference.1.particles_on_tracks > 20_000);
        let run = |batch: usize| {
            let mut s = PtvStream::new(cparams.clone(), tparams.clone(), batch).unwrap();
            let mut sink = Collect::default();
            for sp in &scene {
                s.push_pulse(sp.pulse.clone(), &mut sink).unwrap();
            }
            let stats = s.finish(&mut sink).unwrap();
            (sink, stats)
        };
        // Thread count 0: driven from outside any rayon pool (as the
        // CLI is), the fits run in the global pool.
        for (threads, batch) in [(1, 64), (2, 64), (2, 5), (3, 1), (4, 3), (0, 2), (0, 17)] {
            let (sink, stats) = match threads {
                0 => run(batch),
                n => pool(n).install(|| run(batch)),
            };
            assert_eq!(stats, reference.1, "{threads} threads, batch {batch}");
            assert_eq!(sink.pulses, reference.0.pulses);
            assert_eq!(sink.particles, reference.0.particles);
            assert!(
                sink.tracks == reference.0.tracks,
                "{threads} threads, batch {batch}: tracks differ"
            );
        }
    }

    /// Pulses of the uniform-motion scene of
    /// `batches_do_not_change_the_result`, `n` of them.
    fn moving_pulses(n: i64) -> Vec<PulseEvents> {
        (0..n)
            .map(|k| {
                let mut ev = EventChunk::default();
                for (x0, y0) in [(20, 20), (60, 40), (100, 70)] {
                    let t = k * 200 + 50;
                    ev.push(t, x0 + 2 * k as u16, y0 + k as u16, 1);
                }
                PulseEvents {
                    index: k,
                    start_us: k as f64 * 200.0,
                    events: ev,
                }
            })
            .collect()
    }

    /// A sink that fails on the `fail_at`-th pulse of particles.
    struct Failing {
        seen: usize,
        fail_at: usize,
    }

    impl PtvSink for Failing {
        fn particles(&mut self, _: i64, _: f64, _: &[Particle]) -> Result<()> {
            self.seen += 1;
            if self.seen == self.fail_at {
                return Err(Error::analysis("disk full"));
            }
            Ok(())
        }
        fn tracks(&mut self, _: &[Track]) -> Result<()> {
            Ok(())
        }
    }

    /// Pushes pulses until one is refused, else finishes: the error the
    /// stream must report.
    fn feed_until_error(
        mut s: PtvStream,
        pulses: impl Iterator<Item = PulseEvents>,
        sink: &mut impl PtvSink,
    ) -> Error {
        for p in pulses {
            if let Err(e) = s.push_pulse(p, sink) {
                return e;
            }
        }
        s.finish(sink).unwrap_err()
    }

    /// Errors of the sink, of the tracker stage (pulses out of order) and
    /// a stream dropped half-way: each ends the pipeline's threads and
    /// reaches the caller (the test would hang otherwise).
    #[ebptv_macros::unit_test]
    fn errors_and_drops_end_the_pipeline() {
        let pulses = moving_pulses(40);
        let s = PtvStream::new(ClusterParams::default(), TrackParams::default(), 3).unwrap();
        let mut sink = Failing {
            seen: 0,
            fail_at: 10,
        };
        let err = feed_until_error(s, pulses.iter().cloned(), &mut sink);
        assert!(err.to_string().contains("disk full"), "{err}");

        // Pulse 5 twice: the tracker refuses it.
        let s = PtvStream::new(ClusterParams::default(), TrackParams::default(), 2).unwrap();
        let mut sink = Collect::default();
        let err = feed_until_error(
            s,
            pulses[..6].iter().chain(&pulses[5..20]).cloned(),
            &mut sink,
        );
        assert!(err.to_string().contains("pulses must increase"), "{err}");
        assert_eq!(sink.pulses, (0..6).collect::<Vec<_>>());

        let mut s = PtvStream::new(ClusterParams::default(), TrackParams::default(), 2).unwrap();
        let mut sink = Collect::default();
        for p in pulses.iter().cloned() {
            s.push_pulse(p, &mut sink).unwrap();
        }
        drop(s);
        // Linking particles after events is refused, not mixed in.
        let mut s = PtvStream::new(ClusterParams::default(), TrackParams::default(), 1).unwrap();
        s.push_pulse(pulses[0].clone(), &mut sink).unwrap();
        assert!(s.push_particles(1, 200.0, &[], &mut sink).is_err());
    }

    #[ebptv_macros::unit_test]
    fn zero_batch_is_refused() {
        assert!(PtvStream::new(ClusterParams::default(), TrackParams::default(), 0).is_err());
    }
}
