//! Slice-and-stitch parallel tracking.
//!
//! # Why
//! [`Tracker`] is sequential by nature: each pulse's links depend on the
//! tracks of all earlier pulses (and its noise gate on all earlier links).
//! On a full-frame recording its linking and the output fits of its tracks
//! are most of the work, so one tracker caps the run at one core.
//!
//! # How
//! The pulse stream is cut into consecutive **slices** of
//! [`SliceParams::slice_pulses`] pulses, counted by position in the stream
//! (the n-th pulse pushed), so the cut does not depend on the thread count.
//! Every slice is tracked by its own fresh [`Tracker`], which also sees
//! [`SliceParams::overlap`] pulses before its own (warm-up: tracks are
//! initialised and their predictors filled by the time the slice's first
//! own pulse comes) and after them (look-ahead: the output fit near the end
//! has its full window, and tracks are not cut short there). Slices are
//! tracked in parallel (rayon), a group of [`SliceParams::in_flight`]
//! slices at a time.
//!
//! # The seam join
//! Every output point belongs to the slice that owns its pulse; the points
//! a slice's tracker made for its neighbours' pulses are dropped. A piece
//! of track in slice k+1 continues the joined track whose last own
//! detection (made by slice k, or earlier) is the detection that slice
//! k+1's tracker linked just before the piece's first own point — the link
//! across the seam is made by the tracker that owns the later pulse, with
//! its whole warm-up window as context, as every other link. Each detection
//! is the last of at most one joined track and the predecessor of at most
//! one piece, so the join is one-to-one without any search; where the two
//! trackers disagree about the seam the track breaks there (a missed link,
//! never a wrong one).
//!
//! Joined tracks are validated again (fewer than `min_length` detections,
//! or `min_length_flow` with the ghost test, see `TrackParams::min_kept_length`:
//! rejected; leading and trailing bridged points trimmed) and cut into
//! segments of at most `max_track_length` points with fresh ids, as the
//! sequential tracker does. Results depend only on the pulses and the
//! parameters — not on the thread count nor on `in_flight` — and memory on
//! `in_flight · slice_pulses + 2 · overlap` pulses of particles plus the
//! joined tracks crossing the current seam.
//!
//! # Statistics
//! `pulses`, `particles`, `tracks_kept` and `particles_on_tracks` count the
//! joined output; `tracks_started` counts joined tracks started (not
//! continued across a seam); `tracks_stitched` and `tracks_rejected_rough`
//! sum what the slices' trackers counted (pulses in an overlap are seen by
//! two trackers); `tracks_rejected_short` adds the joined tracks rejected
//! as short to the slices' counts.

use std::collections::{HashMap, VecDeque};

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::{LinkedTrack, Track, TrackParams, TrackPoint, Tracker, TrackerStats};
use crate::cluster::Particle;
use crate::error::{Error, Result};

/// How the pulse stream is cut for [`SliceTracker`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub(crate) struct SliceParams {
    /// Pulses each slice owns (≥ 1).
    pub slice_pulses: usize,
    /// Pulses a slice's tracker also sees on each side of its own.
    pub overlap: usize,
    /// Slices tracked together; 0 = the rayon threads (at least 2).
    /// Changes memory and load balance, never the result.
    pub in_flight: usize,
}

impl Default for SliceParams {
    fn default() -> Self {
        SliceParams {
            slice_pulses: 256,
            overlap: 24,
            in_flight: 0,
        }
    }
}

impl SliceParams {
    pub(crate) fn validate(&self) -> Result<()> {
        if self.slice_pulses == 0 {
            return Err(Error::param("slice_pulses", "must be at least 1 pulse"));
        }
        Ok(())
    }

    fn group(&self) -> usize {
        if self.in_flight > 0 {
            self.in_flight
        } else {
            rayon::current_num_threads().max(2)
        }
    }
}

/// One buffered pulse: its particles and the serial number of the first.
struct BufferedPulse {
    pulse: i64,
    t_us: f64,
    particles: Vec<Particle>,
    first_serial: u64,
}

/// A track being joined across seams.
struct Joined {
    points: Vec<TrackPoint>,
    detections: Vec<Option<u64>>,
    /// The last detection of the track so far (also after a segment cut).
    last_detection: Option<u64>,
    /// The pulse of the track's last point (also after a segment cut).
    last_pulse: Option<i64>,
    /// A later segment of a track already handed out in part: not checked
    /// against `min_length` (as the sequential tracker's segments).
    continuation: bool,
}

impl Joined {
    /// Append the points after the track's last one.
    fn append(&mut self, points: &[TrackPoint], detections: &[Option<u64>]) {
        let skip = match self.last_pulse {
            Some(last) => points.iter().take_while(|p| p.pulse <= last).count(),
            None => 0,
        };
        let (points, detections) = (&points[skip..], &detections[skip..]);
        self.points.extend_from_slice(points);
        self.detections.extend_from_slice(detections);
        if let Some(d) = detections.iter().rev().flatten().next() {
            self.last_detection = Some(*d);
        }
        if let Some(p) = points.last() {
            self.last_pulse = Some(p.pulse);
        }
    }
}

/// What one slice's tracker produced.
struct SliceOutput {
    tracks: Vec<LinkedTrack>,
    stats: TrackerStats,
}

/// Parallel slice-and-stitch tracker (module docs). Feed pulses in
/// increasing order with `SliceTracker::push`; tracks come out, joined,
/// as whole groups of slices are tracked.
pub(crate) struct SliceTracker {
    params: TrackParams,
    slicing: SliceParams,
    /// Pulses from stream position `buffer_start` on.
    buffer: VecDeque<BufferedPulse>,
    buffer_start: usize,
    pulses_seen: usize,
    next_serial: u64,
    /// The next slice to track.
    next_slice: usize,
    /// Joined tracks the last tracked slice continued (candidates for the
    /// next seam), in a deterministic order.
    open: Vec<Joined>,
    next_id: u64,
    last_pulse: Option<i64>,
    stats: TrackerStats,
}

impl SliceTracker {
    /// A slice tracker with these tracking and slicing parameters; an
    /// error when a parameter is out of range.
    pub(crate) fn new(params: TrackParams, slicing: SliceParams) -> Result<Self> {
        params.validate()?;
        slicing.validate()?;
        Ok(SliceTracker {
            params,
            slicing,
            buffer: VecDeque::new(),
            buffer_start: 0,
            pulses_seen: 0,
            next_serial: 0,
            next_slice: 0,
            open: Vec::new(),
            next_id: 0,
            last_pulse: None,
            stats: TrackerStats::default(),
        })
    }

    /// Counters so far (final after [`SliceTracker::finish`]).
    pub(crate) fn stats(&self) -> &TrackerStats {
        &self.stats
    }

    /// Tracks crossing the last tracked seam.
    pub(crate) fn active_tracks(&self) -> usize {
        self.open.len()
    }

    /// Add the particles of the next pulse; returns tracks that are final.
    pub(crate) fn push(
        &mut self,
        pulse: i64,
        t_us: f64,
        particles: Vec<Particle>,
    ) -> Result<Vec<LinkedTrack>> {
        if let Some(last) = self.last_pulse {
            if pulse <= last {
                return Err(Error::param(
                    "pulse",
                    format!("pulses must increase: got {pulse} after {last}"),
                ));
            }
        }
        self.last_pulse = Some(pulse);
        self.stats.pulses += 1;
        self.stats.particles += particles.len() as u64;
        let n = particles.len() as u64;
        self.buffer.push_back(BufferedPulse {
            pulse,
            t_us,
            particles,
            first_serial: self.next_serial,
        });
        self.next_serial += n;
        self.pulses_seen += 1;
        let (s, o) = (self.slicing.slice_pulses, self.slicing.overlap);
        let group = self.slicing.group();
        // The group's last slice is complete once its look-ahead arrived.
        if self.pulses_seen >= (self.next_slice + group) * s + o {
            self.track_slices(self.next_slice + group)
        } else {
            Ok(Vec::new())
        }
    }

    /// Track what is left and end every track.
    pub(crate) fn finish(mut self) -> Result<(Vec<LinkedTrack>, TrackerStats)> {
        let s = self.slicing.slice_pulses;
        let slices = self.pulses_seen.div_ceil(s);
        let mut out = self.track_slices(slices)?;
        for j in std::mem::take(&mut self.open) {
            self.emit(j, &mut out);
        }
        Ok((out, self.stats))
    }

    /// Track slices `next_slice..end` in parallel, join them in order,
    /// drop the pulses no later slice needs.
    fn track_slices(&mut self, end: usize) -> Result<Vec<LinkedTrack>> {
        let (s, o) = (self.slicing.slice_pulses, self.slicing.overlap);
        let first = self.next_slice;
        let seen = self.pulses_seen;
        let buffer = &self.buffer;
        let buffer_start = self.buffer_start;
        let params = &self.params;
        let owned: Vec<(i64, i64)> = (first..end)
            .map(|k| {
                let lo = self.pulse_at(k * s).expect("slice start is buffered");
                (lo, self.pulse_at((k + 1) * s).unwrap_or(i64::MAX))
            })
            .collect();
        let outputs: Vec<Result<SliceOutput>> = (first..end)
            .into_par_iter()
            .with_max_len(1)
            .map(|k| {
                let lo = (k * s).saturating_sub(o);
                let hi = ((k + 1) * s + o).min(seen);
                let range = (lo - buffer_start)..(hi - buffer_start);
                track_slice(params, buffer.range(range), owned[k - first])
            })
            .collect();
        let mut done = Vec::new();
        for ((owned_lo, owned_hi), output) in owned.into_iter().zip(outputs) {
            self.join(output?, owned_lo, owned_hi, &mut done);
        }
        self.next_slice = end;
        let keep_from = (end * s).saturating_sub(o).min(seen);
        while self.buffer_start < keep_from {
            self.buffer.pop_front();
            self.buffer_start += 1;
        }
        Ok(done)
    }

    fn pulse_at(&self, position: usize) -> Option<i64> {
        position
            .checked_sub(self.buffer_start)
            .and_then(|i| self.buffer.get(i))
            .map(|p| p.pulse)
    }

    /// Join one slice's tracks (its own pulses `owned_lo..owned_hi`) onto
    /// the open tracks; tracks the slice did not continue are final.
    fn join(
        &mut self,
        output: SliceOutput,
        owned_lo: i64,
        owned_hi: i64,
        done: &mut Vec<LinkedTrack>,
    ) {
        let st = &output.stats;
        self.stats.tracks_stitched += st.tracks_stitched;
        self.stats.tracks_rejected_rough += st.tracks_rejected_rough;
        self.stats.tracks_rejected_ghost += st.tracks_rejected_ghost;
        self.stats.tracks_rejected_short += st.tracks_rejected_short;

        let mut previous: Vec<Option<Joined>> = std::mem::take(&mut self.open)
            .into_iter()
            .map(Some)
            .collect();
        let by_last: HashMap<u64, usize> = previous
            .iter()
            .enumerate()
            .filter_map(|(i, j)| Some((j.as_ref()?.last_detection?, i)))
            .collect();
        let mut open = Vec::new();
        for t in output.tracks {
            let pts = &t.track.points;
            let Some(a) = pts.iter().position(|p| p.pulse >= owned_lo) else {
                continue;
            };
            let b = pts[a..]
                .iter()
                .position(|p| p.pulse >= owned_hi)
                .map_or(pts.len(), |e| a + e);
            if a == b {
                continue;
            }
            let before = t.detections[..a].iter().rposition(Option::is_some);
            let joined = before
                .and_then(|i| by_last.get(&t.detections[i]?))
                .and_then(|&i| previous[i].take());
            let joined = match joined {
                // The seam's bridged points (if any) come with the link.
                Some(mut j) => {
                    let from = before.map_or(a, |i| i + 1);
                    j.append(&pts[from..b], &t.detections[from..b]);
                    j
                }
                None => {
                    self.stats.tracks_started += 1;
                    let mut j = Joined {
                        points: Vec::new(),
                        detections: Vec::new(),
                        last_detection: None,
                        last_pulse: None,
                        continuation: false,
                    };
                    j.append(&pts[a..b], &t.detections[a..b]);
                    j
                }
            };
            open.push(joined);
        }
        for j in previous.into_iter().flatten() {
            self.emit(j, done);
        }
        // Long tracks go out in segments, as the sequential tracker's.
        for j in &mut open {
            if j.points.len() >= self.params.gates.max_track_length {
                let segment = Joined {
                    points: std::mem::take(&mut j.points),
                    detections: std::mem::take(&mut j.detections),
                    last_detection: j.last_detection,
                    last_pulse: j.last_pulse,
                    continuation: j.continuation,
                };
                j.continuation = true;
                self.emit(segment, done);
            }
        }
        self.open = open;
    }

    /// Validate a finished joined track and hand it out.
    fn emit(&mut self, mut j: Joined, done: &mut Vec<LinkedTrack>) {
        // A track starts and ends on detections.
        let first = j.detections.iter().position(Option::is_some);
        let last = j.detections.iter().rposition(Option::is_some);
        let (Some(first), Some(last)) = (first, last) else {
            if !j.continuation && !j.points.is_empty() {
                self.stats.tracks_rejected_short += 1;
            }
            return;
        };
        j.points.truncate(last + 1);
        j.detections.truncate(last + 1);
        if !j.continuation {
            j.points.drain(..first);
            j.detections.drain(..first);
        }
        let n = j.detections.iter().flatten().count();
        if !j.continuation && n < self.params.min_kept_length() {
            self.stats.tracks_rejected_short += 1;
            return;
        }
        self.stats.tracks_kept += 1;
        self.stats.particles_on_tracks += n as u64;
        done.push(LinkedTrack {
            track: Track {
                id: self.next_id,
                points: j.points,
            },
            detections: j.detections,
        });
        self.next_id += 1;
    }
}

/// One slice through a fresh tracker; detection serials made global. Of
/// each track only what the join needs is kept (memory): the points of the
/// slice's own pulses `owned.0..owned.1`, preceded by the last detection
/// before them.
fn track_slice<'a>(
    params: &TrackParams,
    pulses: impl Iterator<Item = &'a BufferedPulse>,
    owned: (i64, i64),
) -> Result<SliceOutput> {
    let mut tracker = Tracker::new(params.clone())?;
    let mut tracks = Vec::new();
    let mut base = None;
    let mut keep = |done: Vec<LinkedTrack>, base: u64| {
        for t in done {
            if let Some(t) = trim_to_owned(t, owned, base) {
                tracks.push(t);
            }
        }
    };
    for p in pulses {
        let base = *base.get_or_insert(p.first_serial);
        keep(tracker.push_linked(p.pulse, p.t_us, &p.particles)?, base);
    }
    let (rest, stats) = tracker.finish();
    keep(rest, base.unwrap_or(0));
    Ok(SliceOutput { tracks, stats })
}

/// The part of a slice's track that [`SliceTracker::join`] uses, serials
/// offset by `base`; `None` when the track has no point in `owned`.
fn trim_to_owned(mut t: LinkedTrack, owned: (i64, i64), base: u64) -> Option<LinkedTrack> {
    let pts = &t.track.points;
    let a = pts.iter().position(|p| p.pulse >= owned.0)?;
    let b = pts[a..]
        .iter()
        .position(|p| p.pulse >= owned.1)
        .map_or(pts.len(), |e| a + e);
    if a == b {
        return None;
    }
    let from = t.detections[..a]
        .iter()
        .rposition(Option::is_some)
        .unwrap_or(a);
    t.track.points.truncate(b);
    t.detections.truncate(b);
    t.track.points.drain(..from);
    t.detections.drain(..from);
    for d in t.detections.iter_mut().flatten() {
        *d += base;
    }
    Some(t)
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;

    fn particle(pulse: i64, x: f64, y: f64) -> Particle {
        Particle {
            pulse,
            t_us: pulse as f64 * 200.0,
            x,
            y,
            n_events: 2,
            n_pixels: 2,
            extent_x: 1.0,
            extent_y: 1.0,
            first_latency_us: 1.0,
        }
    }

    /// Three particles crossing many seams: each must come out as one
    /// track over all pulses, with every detection in order.
    #[ebptv_macros::unit_test]
    fn tracks_cross_seams_whole() {
        let slicing = SliceParams {
            slice_pulses: 7,
            overlap: 6,
            in_flight: 2,
        };
        let mut st = SliceTracker::new(TrackParams::default(), slicing).unwrap();
        let mut out = Vec::new();
        for k in 0..60i64 {
            let ps: Vec<Particle> = (0..3)
                .map(|i| {
                    particle(
                        k,
                        20.0 + 40.0 * i as f64 + 1.5 * k as f64,
                        30.0 + 0.5 * k as f64,
                    )
                })
                .collect();
            out.extend(st.push(k, k as f64 * 200.0, ps).unwrap());
        }
        let (rest, stats) = st.finish().unwrap();
        out.extend(rest);
        assert_eq!(out.len(), 3, "{stats:?}");
        for t in &out {
            assert_eq!(t.track.points.len(), 60);
            let dets: Vec<u64> = t.detections.iter().map(|d| d.unwrap()).collect();
            let i = dets[0];
            assert!(dets.iter().enumerate().all(|(k, &d)| d == i + 3 * k as u64));
        }
        assert_eq!(stats.tracks_kept, 3);
        assert_eq!(stats.particles_on_tracks, 180);
        assert_eq!(stats.pulses, 60);
    }

    #[ebptv_macros::unit_test]
    fn bad_parameters_and_order_are_refused() {
        let zero = SliceParams {
            slice_pulses: 0,
            ..Default::default()
        };
        assert!(SliceTracker::new(TrackParams::default(), zero).is_err());
        let mut st = SliceTracker::new(TrackParams::default(), SliceParams::default()).unwrap();
        st.push(5, 1000.0, Vec::new()).unwrap();
        assert!(st.push(5, 1000.0, Vec::new()).is_err());
    }
}
