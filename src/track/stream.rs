//! Recording → particles → tracks, streaming.
//!
//! The one entry point of the PTV stage for a recording:
//! [`track_recording`] runs the pulse analysis (one pass), then streams the
//! recording a second time through [`crate::pulses::split_pulses`], clusters
//! pulses in parallel batches (rayon, in [`crate::cluster::cluster_pulses`])
//! and feeds the particles, in pulse order, to the [`Tracker`] — the
//! clustering of one batch (on a scoped helper thread) overlapping the
//! tracking of the previous one on the caller's thread. Results go
//! to a [`PtvSink`] as they appear — particles per pulse, tracks when they
//! end — so memory is bounded by the batch and the active tracks, not by the
//! recording. What the sink does with them (write CSV, bin onto a grid,
//! score against truth) is the caller's business.
//!
//! Two passes instead of one because pulse timing (the period fitted over
//! the whole recording) must be known before the first event can be tied to
//! its pulse; reading a file twice from the page cache costs far less than
//! holding it.

use crate::cluster::{
    cluster_pulses, cluster_pulses_with_pixels, ClusterParams, Particle, ParticlePixels,
};
use crate::error::Result;
use crate::io::EventSource;
use crate::pulses::{self, PulseEvents, PulseOptions, PulseReport};

use super::slice::{SliceParams, SliceTracker};
use super::{Track, TrackParams, Tracker, TrackerStats};

/// The linking stage of a [`PtvStream`].
enum Linker {
    /// One [`Tracker`] over the whole stream.
    Sequential(Tracker),
    /// Independent trackers on time slices, joined at the seams.
    Sliced(SliceTracker),
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

/// Clustering and tracking fed pulse by pulse.
pub struct PtvStream {
    cluster: ClusterParams,
    linker: Linker,
    batch: Vec<PulseEvents>,
    /// The previous batch, clustered, waiting to be tracked while the
    /// current one is clustered (two-stage pipeline), with the pixel
    /// tables when the tracker splits merged images.
    clustered: Vec<(i64, f64, Vec<Particle>, Option<ParticlePixels>)>,
    /// Cluster with pixel tables (`TrackParams::split_merged`, sequential
    /// linker only).
    with_pixels: bool,
    batch_size: usize,
    events: u64,
}

impl PtvStream {
    /// `batch_size`: pulses clustered per parallel batch (≥ 1). Links
    /// with one sequential [`Tracker`].
    pub fn new(cluster: ClusterParams, track: TrackParams, batch_size: usize) -> Result<Self> {
        let with_pixels = track.split_merged;
        let linker = Linker::Sequential(Tracker::new(track)?);
        let mut s = Self::with_linker(cluster, linker, batch_size)?;
        s.with_pixels = with_pixels;
        Ok(s)
    }

    /// [`PtvStream::new`] linking with the parallel slice-and-stitch
    /// tracker ([`crate::track::slice`]).
    pub fn sliced(
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
            return Err(crate::Error::param("batch", "must be at least 1 pulse"));
        }
        Ok(PtvStream {
            cluster,
            linker,
            batch: Vec::with_capacity(batch_size),
            clustered: Vec::new(),
            with_pixels: false,
            batch_size,
            events: 0,
        })
    }

    /// Add the events of the next pulse (pulses in increasing order).
    pub fn push_pulse(&mut self, pulse: PulseEvents, sink: &mut dyn PtvSink) -> Result<()> {
        self.events += pulse.events.len() as u64;
        self.batch.push(pulse);
        if self.batch.len() >= self.batch_size {
            self.flush(sink)?;
        }
        Ok(())
    }

    /// Link already-detected particles of one pulse (e.g. read from a
    /// `particles.csv`); pulses in increasing order.
    pub fn push_particles(
        &mut self,
        pulse: i64,
        t_us: f64,
        particles: &[Particle],
        sink: &mut dyn PtvSink,
    ) -> Result<()> {
        sink.particles(pulse, t_us, particles)?;
        let done = match &mut self.linker {
            Linker::Sequential(tracker) => tracker.push(pulse, t_us, particles)?,
            Linker::Sliced(st) => unlinked(st.push(pulse, t_us, particles.to_vec())?),
        };
        sink.take_tracks(done)
    }

    /// Cluster the current batch (rayon, on a helper thread) while the
    /// previous, already clustered batch is tracked on this thread: the
    /// tracker is sequential, so this overlaps the two stages. Results are
    /// the same as clustering and tracking one after the other (pulses
    /// reach the tracker and the sink in order).
    fn flush(&mut self, sink: &mut dyn PtvSink) -> Result<()> {
        let batch = std::mem::take(&mut self.batch);
        let previous = std::mem::take(&mut self.clustered);
        let cluster = &self.cluster;
        let linker = &mut self.linker;
        let with_pixels = self.with_pixels;
        let (parts, tracked) = std::thread::scope(|scope| {
            let worker = (!batch.is_empty()).then(|| {
                scope.spawn(|| -> Result<Vec<(Vec<Particle>, Option<ParticlePixels>)>> {
                    Ok(if with_pixels {
                        cluster_pulses_with_pixels(&batch, cluster)?
                            .into_iter()
                            .map(|(p, px)| (p, Some(px)))
                            .collect()
                    } else {
                        cluster_pulses(&batch, cluster)?
                            .into_iter()
                            .map(|p| (p, None))
                            .collect()
                    })
                })
            });
            let tracked = track_batch(linker, previous, sink);
            let parts = match worker {
                Some(w) => w.join().unwrap_or_else(|e| std::panic::resume_unwind(e)),
                None => Ok(Vec::new()),
            };
            (parts, tracked)
        });
        tracked?;
        self.clustered = batch
            .iter()
            .zip(parts?)
            .map(|(pe, (ps, px))| (pe.index, pe.start_us, ps, px))
            .collect();
        self.batch = batch;
        self.batch.clear();
        Ok(())
    }

    /// Events handed over so far.
    pub fn events(&self) -> u64 {
        self.events
    }

    /// Particles seen and tracks active (for progress reports).
    pub fn progress(&self) -> (u64, usize) {
        match &self.linker {
            Linker::Sequential(t) => (t.stats().particles, t.active_tracks()),
            Linker::Sliced(t) => (t.stats().particles, t.active_tracks()),
        }
    }

    /// Cluster what is left, end all tracks, hand them to the sink.
    pub fn finish(mut self, sink: &mut dyn PtvSink) -> Result<TrackerStats> {
        self.flush(sink)?; // tracks the previous batch, clusters the last
        self.flush(sink)?; // tracks the last

        let (rest, stats) = match self.linker {
            Linker::Sequential(t) => t.finish(),
            Linker::Sliced(t) => t.finish()?,
        };
        sink.take_tracks(unlinked(rest))?;
        Ok(stats)
    }
}

fn unlinked(tracks: Vec<super::LinkedTrack>) -> Vec<Track> {
    tracks.into_iter().map(|t| t.track).collect()
}

/// Feed clustered pulses to the tracker and the sink, in order (per pulse
/// the sink gets the particles, then the tracks that ended).
/// The sliced linker keeps the particles until their slices are tracked,
/// so the sink gets a copy.
fn track_batch(
    linker: &mut Linker,
    clustered: Vec<(i64, f64, Vec<Particle>, Option<ParticlePixels>)>,
    sink: &mut dyn PtvSink,
) -> Result<()> {
    for (pulse, t_us, ps, px) in clustered {
        match linker {
            Linker::Sequential(tracker) => {
                let done = match &px {
                    Some(px) => tracker.push_with_pixels(pulse, t_us, &ps, px)?,
                    None => tracker.push(pulse, t_us, &ps)?,
                };
                sink.take_particles(pulse, t_us, ps)?;
                sink.take_tracks(done)?;
            }
            Linker::Sliced(st) => {
                sink.particles(pulse, t_us, &ps)?;
                let done = st.push(pulse, t_us, ps)?;
                sink.take_tracks(unlinked(done))?;
            }
        }
    }
    Ok(())
}

/// The whole PTV stage on a recording. `open` opens the recording afresh
/// (it is read twice: pulse analysis, then tracking); `on_pulse` is called
/// after each pulse for progress reports. Returns the pulse report, the
/// tracker's counters and the number of events not attributable to a pulse.
pub fn track_recording(
    open: &dyn Fn() -> Result<Box<dyn EventSource>>,
    pulse_options: &PulseOptions,
    stream: PtvStream,
    sink: &mut dyn PtvSink,
    on_pulse: &mut dyn FnMut(&PtvStream),
) -> Result<(PulseReport, TrackerStats, u64)> {
    let mut src = open()?;
    let report = pulses::analyze(&mut *src, pulse_options).map_err(|e| {
        crate::Error::analysis(format!(
            "finding the light pulses in {}: {e}",
            src.info().path.display()
        ))
    })?;
    let mut src = open()?;
    let mut stream = stream;
    let unassigned = pulses::split_pulses(&mut *src, &report.timing, &mut |p| {
        stream.push_pulse(p, sink)?;
        on_pulse(&stream);
        Ok(())
    })?;
    let stats = stream.finish(sink)?;
    Ok((report, stats, unassigned))
}

#[cfg(test)]
mod tests {
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
    #[test]
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
    /// tracking pulse by pulse on one thread gives: the parallel clustering
    /// and the parallel output fits change nothing. Short
    /// `max_track_length` so that segment hand-outs are exercised too.
    #[test]
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
            max_track_length: 44,
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
        for (threads, batch) in [(1, 64), (2, 64), (2, 5), (3, 1)] {
            let (sink, stats) = pool(threads).install(|| {
                let mut s = PtvStream::new(cparams.clone(), tparams.clone(), batch).unwrap();
                let mut sink = Collect::default();
                for sp in &scene {
                    s.push_pulse(sp.pulse.clone(), &mut sink).unwrap();
                }
                let stats = s.finish(&mut sink).unwrap();
                (sink, stats)
            });
            assert_eq!(stats, reference.1, "{threads} threads, batch {batch}");
            assert_eq!(sink.pulses, reference.0.pulses);
            assert_eq!(sink.particles, reference.0.particles);
            assert!(
                sink.tracks == reference.0.tracks,
                "{threads} threads, batch {batch}: tracks differ"
            );
        }
    }

    #[test]
    fn zero_batch_is_refused() {
        assert!(PtvStream::new(ClusterParams::default(), TrackParams::default(), 0).is_err());
    }
}
