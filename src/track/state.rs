//! The tracker's state and the life cycle of a track: the output types
//! ([`Track`], [`TrackPoint`], [`LinkedTrack`]), the detections and active
//! tracks the [`Tracker`] holds, one pulse's step ([`Tracker::push`]: checks,
//! prediction and assignment, gap repair, initialisation, stitching,
//! hand-out), the four-frame initialisation of new tracks (stage 4 of the
//! module doc) and the whole-set entry points [`link`] and [`link_linked`].

use super::*;

/// One point of a track: the track's fitted state at one pulse.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct TrackPoint {
    /// Index of the pulse.
    pub pulse: i64,
    /// Time of the pulse (µs).
    pub t_us: f64,
    /// Fitted position (px).
    pub x: f64,
    /// Fitted position y (px).
    pub y: f64,
    /// Fitted velocity (px/s).
    pub u: f64,
    /// Fitted velocity along y (px/s).
    pub v: f64,
    /// Fitted acceleration (px/s²).
    pub ax: f64,
    /// Fitted acceleration along y (px/s²).
    pub ay: f64,
    /// True where the point bridges a gap (no detection at this pulse).
    pub interpolated: bool,
}

/// A Lagrangian track.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Track {
    /// Track id, unique within a run.
    pub id: u64,
    /// The points, one per pulse in increasing pulse order.
    pub points: Vec<TrackPoint>,
}

/// A track with, for each point, the serial number of the detection it was
/// built from (`None` on bridged gaps). Serial numbers count the particles
/// in the order they were pushed, from 0 — for [`link`] the index into its
/// (pulse-sorted) input. Used to score links against ground truth.
#[derive(Debug, Clone, PartialEq)]
#[ebptv_macros::testkit]
pub(crate) struct LinkedTrack {
    /// The track.
    pub track: Track,
    /// Per point, the serial number of its detection (`None` on bridged gaps).
    pub detections: Vec<Option<u64>>,
}

/// A mean-flow prior for track initialisation: velocity (px/s) at a
/// position (px). Build one from a closure, a uniform flow or a grid.
#[derive(Clone)]
pub struct FlowPrior(pub Arc<dyn Fn(f64, f64) -> (f64, f64) + Send + Sync>);

impl std::fmt::Debug for FlowPrior {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("FlowPrior(..)")
    }
}

impl FlowPrior {
    pub(crate) fn from_fn(f: impl Fn(f64, f64) -> (f64, f64) + Send + Sync + 'static) -> Self {
        FlowPrior(Arc::new(f))
    }
    pub(crate) fn uniform(u: f64, v: f64) -> Self {
        Self::from_fn(move |_, _| (u, v))
    }
    #[cfg(feature = "testkit")]
    /// A gridded field: node `(i, j)` at `(x0 + i·dx, y0 + j·dy)`, row-major
    /// `u[j·nx + i]`; bilinear inside, clamped to the border outside.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn grid(
        x0: f64,
        y0: f64,
        dx: f64,
        dy: f64,
        nx: usize,
        ny: usize,
        u: Vec<f64>,
        v: Vec<f64>,
    ) -> Result<Self> {
        if nx == 0 || ny == 0 || u.len() != nx * ny || v.len() != nx * ny || !(dx > 0.0 && dy > 0.0)
        {
            return Err(Error::param(
                "prior",
                "grid needs nx·ny values per component and positive spacing",
            ));
        }
        if u.iter().chain(&v).any(|a| !a.is_finite()) {
            return Err(Error::param("prior", "grid velocities must be finite"));
        }
        Ok(Self::from_fn(move |x, y| {
            let fi = ((x - x0) / dx).clamp(0.0, (nx - 1) as f64);
            let fj = ((y - y0) / dy).clamp(0.0, (ny - 1) as f64);
            let (i0, j0) = (fi.floor() as usize, fj.floor() as usize);
            let (i1, j1) = ((i0 + 1).min(nx - 1), (j0 + 1).min(ny - 1));
            let (a, b) = (fi - i0 as f64, fj - j0 as f64);
            let bil = |f: &Vec<f64>| {
                (1.0 - a) * (1.0 - b) * f[j0 * nx + i0]
                    + a * (1.0 - b) * f[j0 * nx + i1]
                    + (1.0 - a) * b * f[j1 * nx + i0]
                    + a * b * f[j1 * nx + i1]
            };
            (bil(&u), bil(&v))
        }))
    }
}

/// Cell size (px) of the local flow grid of the ghost test: the flow is
/// averaged over 3 × 3 cells (48 px), a few particle spacings at ppp 0.01.
pub(super) const FLOW_CELL: f64 = 16.0;

/// Time constant (pulses) of the local flow's memory.
pub(super) const FLOW_MEMORY: f64 = 8.0;

/// Detections a track must hold before its links feed the local flow
/// (longer than any track the ghost test judges).
pub(super) const FLOW_MIN_DETECTIONS: usize = 6;

/// Detections a new track has room for before its first reallocation.
pub(super) const NEW_TRACK_CAPACITY: usize = 64;

/// Frames (pulses) a new track's initialisation chain spans.
pub(crate) const INIT_FRAMES: usize = 4;

#[derive(Debug, Clone, Copy)]
pub(super) struct Det {
    pub(super) serial: u64,
    pub(super) pulse: i64,
    pub(super) t_us: f64,
    pub(super) x: f64,
    pub(super) y: f64,
}

#[derive(Debug, Clone)]
pub(super) struct ActiveTrack {
    /// Identity for the frames' owner lists (kept through stitching and
    /// cuts; `NO_OWNER` for handed-out segments).
    pub(super) uid: u64,
    pub(super) dets: Vec<Det>,
    /// Leading detections that only give context (the predictor and the
    /// fit) because an earlier segment of the track already handed them
    /// out (see `TrackParams::max_track_length`).
    pub(super) context: usize,
}

impl ActiveTrack {
    pub(super) fn last(&self) -> &Det {
        self.dets.last().expect("tracks are never empty")
    }
}

/// Owner of a particle no track took.
pub(super) const NO_OWNER: u64 = u64::MAX;

/// Detections on each side of the repaired pulse that its two-sided fit
/// uses at most (before it; after it there are `repair_lag`).
pub(super) const REPAIR_WINDOW: i64 = 8;

/// Most detections the backward extension fits (its predictor window).
pub(super) const BACK_FIT_WINDOW: usize = 16;

/// What [`Tracker::extend_active`] did with the particles of a pulse.
pub(super) struct FrameLinks {
    pub(super) used: Vec<bool>,
    pub(super) owner: Vec<u64>,
    pub(super) hungry: Vec<u64>,
    /// The scratch grid does not hold this pulse's particles.
    pub(super) grid_stale: bool,
}

/// Particles of one recent pulse with their "already used" flags.
pub(super) struct Frame {
    pub(super) pulse: i64,
    pub(super) t_us: f64,
    /// Serial of the pulse's first particle (the next serial if none).
    pub(super) first_serial: u64,
    /// The track (uid) each particle went to (`NO_OWNER`: none).
    pub(super) owner: Vec<u64>,
    /// Tracks (uids) that found no particle at this pulse.
    pub(super) hungry: Vec<u64>,
    /// Grid over `dets` (chain starts, the delayed repair and the backward
    /// extension search it; used particles are skipped by their flags).
    pub(super) grid: GridIndex,
    pub(super) dets: Vec<Det>,
    pub(super) used: Vec<bool>,
}

impl Frame {
    /// Index in `dets` of the detection with this serial.
    pub(super) fn index_of(&self, serial: u64) -> Option<usize> {
        let i = serial.checked_sub(self.first_serial)? as usize;
        (i < self.dets.len()).then_some(i)
    }
}

/// Counters of what the tracker did (for `summary.json`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct TrackerStats {
    /// Pulses pushed.
    pub pulses: u64,
    /// Particles (detections) pushed.
    pub particles: u64,
    /// Tracks initialised.
    pub tracks_started: u64,
    /// Ended tracks joined to a new chain across a gap.
    pub tracks_stitched: u64,
    /// Tracks kept (written out).
    pub tracks_kept: u64,
    /// Tracks dropped with fewer than `min_length` detections.
    pub tracks_rejected_short: u64,
    /// Tracks dropped with a fit residual above `max_fit_residual`.
    pub tracks_rejected_rough: u64,
    /// Detections on kept tracks.
    pub particles_on_tracks: u64,
    /// Always 0: the tracker takes the images as clustering made them
    /// (clustering splits wide ones, `ClusterParams::split_extent`); the
    /// key stays in `summary.json` for its readers.
    #[serde(default)]
    pub images_split: u64,
    /// Short tracks dropped as ghosts by the local-flow test
    /// (`TrackParams::ghost_check_length`).
    #[serde(default)]
    pub tracks_rejected_ghost: u64,
    /// Tracks below `min_length` kept because they agree with the local flow.
    #[serde(default)]
    pub tracks_kept_by_flow: u64,
    /// Ended tracks cut at a step (`TrackParams::step_split`), per cut.
    #[serde(default)]
    pub tracks_cut_at_steps: u64,
}

impl TrackerStats {
    /// Add the counters that [`Finaliser::finalise`] keeps (the fits'
    /// verdicts: kept, short, ghost, rough, kept by flow, particles on
    /// tracks, step cuts) from `fits`; the linking counters stay this one's.
    pub(crate) fn add_fit_counters(&mut self, fits: &TrackerStats) {
        self.tracks_kept += fits.tracks_kept;
        self.tracks_rejected_short += fits.tracks_rejected_short;
        self.tracks_rejected_ghost += fits.tracks_rejected_ghost;
        self.tracks_rejected_rough += fits.tracks_rejected_rough;
        self.tracks_kept_by_flow += fits.tracks_kept_by_flow;
        self.particles_on_tracks += fits.particles_on_tracks;
        self.tracks_cut_at_steps += fits.tracks_cut_at_steps;
    }
}

/// Streaming multi-frame tracker: feed pulses in increasing order with
/// `Tracker::push`, collect finished tracks as they come out, and call
/// [`Tracker::finish`] at the end.
#[ebptv_macros::testkit]
pub(crate) struct Tracker {
    pub(super) params: TrackParams,
    pub(super) active: Vec<ActiveTrack>,
    pub(super) frames: VecDeque<Frame>,
    /// The `back_extend` pulses before `frames` (oldest first), for the
    /// backward extension of new tracks.
    pub(super) back_frames: VecDeque<Frame>,
    /// Ended tracks waiting for a possible stitch.
    pub(super) pool: Vec<ActiveTrack>,
    pub(super) next_serial: u64,
    pub(super) next_uid: u64,
    /// Sum and count of squared normalised innovations (px², per axis),
    /// seeded with `sigma_floor` as a prior worth a few dozen links.
    pub(super) innov_sum: f64,
    pub(super) innov_n: f64,
    pub(super) last_pulse: Option<i64>,
    pub(super) stats: TrackerStats,
    /// Predictor weights for gap-free windows (see [`PredictWeights`]).
    pub(super) weights: Vec<PredictWeights>,
    /// Index in `weights` of the last used entry.
    pub(super) weights_hint: usize,
    /// Fits, validates and numbers ended tracks (the output fit's
    /// curvature prior, its copy of the local flow and the track ids live
    /// there).
    pub(super) finaliser: Finaliser,
    /// Ended tracks waiting for [`Tracker::take_ended`] instead of being
    /// fitted here ([`Tracker::defer_fits`]).
    pub(super) deferred: Option<Vec<EndedTracks>>,
    /// Displacements of the established tracks' links, for the ghost test
    /// of new chains (and, replayed, of short ended tracks).
    pub(super) flow: local_flow::LocalFlow,
    /// The samples added to `flow` since the last batch of ended tracks:
    /// they travel with the next batch, and the [`Finaliser`] replays them
    /// into its own copy of the flow, so that a deferred fit sees the flow
    /// exactly as it was when its tracks ended.
    pub(super) flow_log: Vec<local_flow::FlowSample>,
    /// Reused buffers of [`Tracker::extend_active`] and
    /// [`Tracker::initialise`] (no allocation per pulse in steady state).
    pub(super) scratch: Scratch,
    /// First steps (p0→p1 pairs) the initialisation has expanded.
    pub(super) chains_enumerated: u64,
}

#[derive(Default)]
pub(super) struct Scratch {
    pub(super) grid: GridIndex,
    pub(super) near: Vec<(u32, f64)>,
    pub(super) near2: Vec<(u32, f64)>,
    pub(super) near3: Vec<(u32, f64)>,
    /// (track, detection, normalised cost) candidate pairs, grouped by track.
    pub(super) edges: Vec<(usize, usize, f64)>,
    pub(super) edge_d2: Vec<f64>,
    pub(super) row_start: Vec<usize>,
    pub(super) leverage: Vec<f64>,
    pub(super) miss: Vec<f64>,
}

impl Tracker {
    /// A tracker with these parameters; an error when a parameter is out of range.
    #[ebptv_macros::testkit]
    pub(crate) fn new(params: TrackParams) -> Result<Self> {
        params.validate()?;
        let floor2 = params.gates.sigma_floor.powi(2);
        Ok(Tracker {
            params: params.clone(),
            active: Vec::new(),
            frames: VecDeque::new(),
            back_frames: VecDeque::new(),
            pool: Vec::new(),
            next_serial: 0,
            next_uid: 0,
            innov_sum: floor2 * 30.0,
            innov_n: 30.0,
            last_pulse: None,
            stats: TrackerStats::default(),
            weights: Vec::new(),
            weights_hint: 0,
            finaliser: Finaliser::new(params.clone()),
            deferred: None,
            flow: local_flow::LocalFlow::new(FLOW_CELL, FLOW_MEMORY),
            flow_log: Vec::new(),
            scratch: Scratch::default(),
            chains_enumerated: 0,
        })
    }

    pub(crate) fn stats(&self) -> &TrackerStats {
        &self.stats
    }

    /// Number of tracks currently being extended.
    pub(crate) fn active_tracks(&self) -> usize {
        self.active.len()
    }

    /// Feed the particles of one pulse; returns the tracks that finished.
    pub(crate) fn push(
        &mut self,
        pulse: i64,
        t_us: f64,
        particles: &[Particle],
    ) -> Result<Vec<Track>> {
        Ok(self
            .push_linked(pulse, t_us, particles)?
            .into_iter()
            .map(|t| t.track)
            .collect())
    }

    /// `Tracker::push`, keeping the detection serial numbers.
    #[ebptv_macros::testkit]
    pub(crate) fn push_linked(
        &mut self,
        pulse: i64,
        t_us: f64,
        particles: &[Particle],
    ) -> Result<Vec<LinkedTrack>> {
        if let Some(last) = self.last_pulse {
            if pulse <= last {
                return Err(Error::param(
                    "pulse",
                    format!("pulses must increase: got {pulse} after {last}"),
                ));
            }
        }
        if !t_us.is_finite() {
            return Err(Error::param(
                "t_us",
                format!("pulse {pulse}: time is not finite"),
            ));
        }
        if let Some(bad) = particles
            .iter()
            .find(|p| !(p.x.is_finite() && p.y.is_finite()))
        {
            return Err(Error::param(
                "particles",
                format!("pulse {pulse}: non-finite position ({}, {})", bad.x, bad.y),
            ));
        }
        self.last_pulse = Some(pulse);
        self.stats.pulses += 1;
        self.stats.particles += particles.len() as u64;
        let first_serial = self.next_serial;
        let dets: Vec<Det> = particles
            .iter()
            .map(|p| {
                let d = Det {
                    serial: self.next_serial,
                    pulse,
                    t_us,
                    x: p.x,
                    y: p.y,
                };
                self.next_serial += 1;
                d
            })
            .collect();

        // Tracks that missed too many pulses end (and wait for a stitch).
        // Removal keeps the order: active tracks stay sorted by uid (new
        // tracks get the next uids, revived ones are inserted in place), so
        // the order is deterministic and the delayed repair finds tracks
        // by binary search.
        let max_gap = self.params.max_gap as i64;
        let mut kept = 0;
        for i in 0..self.active.len() {
            // A short loop body: the misses need more lead than in
            // `extend_active`.
            if let Some(ahead) = self.active.get(i + 4 * PREFETCH_AHEAD) {
                prefetch_window(&ahead.dets, 1);
            }
            if pulse - self.active[i].last().pulse - 1 > max_gap {
                let t = std::mem::replace(
                    &mut self.active[i],
                    ActiveTrack {
                        uid: NO_OWNER,
                        dets: Vec::new(),
                        context: 0,
                    },
                );
                self.pool.push(t);
            } else {
                self.active.swap(kept, i);
                kept += 1;
            }
        }
        self.active.truncate(kept);
        debug_assert!(self.active.windows(2).all(|w| w[0].uid < w[1].uid));

        let links = self.extend_active(&dets, pulse);
        let segments = self.cut_long_tracks();
        let mut grid = std::mem::take(&mut self.scratch.grid);
        if links.grid_stale {
            grid.rebuild(dets.iter().map(|d| (d.x, d.y)));
        }
        self.frames.push_back(Frame {
            pulse,
            t_us,
            first_serial,
            dets,
            used: links.used,
            owner: links.owner,
            hungry: links.hungry,
            grid,
        });
        if self.params.gates.repair_lag > 0 {
            self.repair(pulse - self.params.gates.repair_lag as i64);
        }
        let kept_frames = INIT_FRAMES + self.params.init.init_gap as usize;
        // A frame's grid goes back to the scratch for reuse when the frame
        // is dropped (the backward extension searches the older frames'
        // grids).
        while self.frames.len() > kept_frames {
            let mut old = self.frames.pop_front().expect("more frames than kept");
            if self.params.init.back_extend > 0 {
                self.back_frames.push_back(old);
            } else {
                self.scratch.grid = std::mem::take(&mut old.grid);
            }
        }
        while self.back_frames.len() > self.params.init.back_extend {
            let mut old = self.back_frames.pop_front().expect("more frames than kept");
            self.scratch.grid = std::mem::take(&mut old.grid);
        }
        self.initialise();

        // Pool entries no new chain can reach any more are final.
        let horizon = pulse - (INIT_FRAMES as i64 - 1) - self.params.stitch.stitch_gap as i64 - 1;
        let (done, keep): (Vec<_>, Vec<_>) = std::mem::take(&mut self.pool)
            .into_iter()
            .partition(|t| t.last().pulse < horizon);
        self.pool = keep;
        let mut out = self.finalise(segments);
        out.extend(self.finalise(done));
        Ok(out)
    }

    /// Hand out the detections of tracks that reached `max_track_length`
    /// as a finished segment and continue each such track with its last
    /// few detections as context, so that memory does not grow with the
    /// life of a particle that stays in view.
    pub(super) fn cut_long_tracks(&mut self) -> Vec<ActiveTrack> {
        let max = self.params.gates.max_track_length;
        let keep = self
            .params
            .gates
            .predict_window
            .max(self.params.fit.fit_window);
        let mut segments = Vec::new();
        for t in &mut self.active {
            if t.dets.len() >= max {
                let tail = t.dets[t.dets.len() - keep..].to_vec();
                let seg = std::mem::replace(&mut t.dets, tail);
                segments.push(ActiveTrack {
                    uid: NO_OWNER,
                    dets: seg,
                    context: t.context,
                });
                t.context = keep;
            }
        }
        segments
    }

    /// End every track and return the rest.
    #[ebptv_macros::testkit]
    pub(crate) fn finish(mut self) -> (Vec<LinkedTrack>, TrackerStats) {
        let mut all = std::mem::take(&mut self.pool);
        all.append(&mut self.active);
        all.sort_unstable_by_key(|t| t.dets[0].serial);
        let out = self.finalise(all);
        (out, self.stats)
    }

    #[cfg(feature = "testkit")]
    /// First steps (pairs of a first and a second particle) the four-frame
    /// initialisation has expanded into chains so far: its work, for
    /// comparing search strategies (`TrackParams::gap_first_step`).
    pub(crate) fn chains_enumerated(&self) -> u64 {
        self.chains_enumerated
    }

    /// Position noise per axis (px) estimated from the innovations of all
    /// accepted links so far (a few per-track residuals are too noisy to
    /// set a gate), within `[sigma_floor, sigma_ceiling]`.
    #[ebptv_macros::testkit]
    pub(crate) fn position_sigma(&self) -> f64 {
        (self.innov_sum / self.innov_n)
            .sqrt()
            .min(self.params.gates.sigma_ceiling)
            .max(self.params.gates.sigma_floor)
    }

    /// The output fit's prior rms acceleration per axis (px/pulse²) for
    /// the next tracks: `fit_accel_rms` if set, else the estimate from the
    /// tracks kept so far (0 until there are enough; after
    /// `Tracker::defer_fits` the estimate lives in the `Finaliser`).
    #[ebptv_macros::testkit]
    pub(crate) fn fit_accel_rms(&self) -> f64 {
        self.params
            .fit
            .fit_accel_rms
            .unwrap_or_else(|| self.finaliser.accel_prior.accel_rms(self.position_sigma()))
    }

    /// From now on, tracks that end are not fitted on this thread: they
    /// wait, unfitted, for [`Tracker::take_ended`] (and `push*` return no
    /// tracks), and the returned [`Finaliser`] — the fits' state so far:
    /// curvature prior, track numbering — fits them elsewhere, in the
    /// order they are taken. Outputs are those of the synchronous path
    /// (`stream::parallel_stream_equals_sequential_tracking`); only the
    /// counters of the fits ([`TrackerStats::add_fit_counters`]) are then
    /// the finaliser's, not [`Tracker::stats`]'s.
    pub(crate) fn defer_fits(&mut self) -> Finaliser {
        self.deferred.get_or_insert_with(Vec::new);
        std::mem::replace(&mut self.finaliser, Finaliser::new(self.params.clone()))
    }

    /// The ended tracks waiting since the last call (after
    /// [`Tracker::defer_fits`]), one entry per batch the tracker would
    /// have fitted at once, in order.
    pub(crate) fn take_ended(&mut self) -> Vec<EndedTracks> {
        self.deferred
            .as_mut()
            .map(std::mem::take)
            .unwrap_or_default()
    }

    /// [`Tracker::finish`] for a tracker that defers its fits (after
    /// [`Tracker::defer_fits`]): end every track and return all that wait
    /// unfitted.
    pub(crate) fn finish_unfitted(mut self) -> (Vec<EndedTracks>, TrackerStats) {
        self.deferred.get_or_insert_with(Vec::new);
        let mut all = std::mem::take(&mut self.pool);
        all.append(&mut self.active);
        all.sort_unstable_by_key(|t| t.dets[0].serial);
        self.finalise(all);
        (self.take_ended(), self.stats)
    }
}

impl Tracker {
    /// Four-frame initialisation over the unused particles of the last
    /// [`INIT_FRAMES`] pulses (and, with `init_gap`, chains of four
    /// detections over the last five pulses that skip one of the three
    /// middle pulses), then backward extension and stitching of the new
    /// chains to ended tracks.
    pub(super) fn initialise(&mut self) {
        let n = self.frames.len();
        if n < INIT_FRAMES {
            return;
        }
        let consecutive = |frames: &VecDeque<Frame>, from: usize| {
            (from + 1..n).all(|k| frames[k].pulse == frames[k - 1].pulse + 1)
        };
        let mut new_tracks: Vec<ActiveTrack> = Vec::new();
        let last: [usize; INIT_FRAMES] = std::array::from_fn(|k| n - INIT_FRAMES + k);
        if consecutive(&self.frames, n - INIT_FRAMES) {
            self.start_chains(last, &mut new_tracks);
        }
        if self.params.init.init_gap && n == INIT_FRAMES + 1 && consecutive(&self.frames, 0) {
            // A particle missed once in its first pulses (5 % of the
            // images are lost, and merged ones are taken by a neighbour)
            // starts here instead of waiting for four clean pulses in a row.
            for skip in 1..INIT_FRAMES {
                let idx: Vec<usize> = (0..=INIT_FRAMES).filter(|&k| k != skip).collect();
                self.start_chains([idx[0], idx[1], idx[2], idx[3]], &mut new_tracks);
            }
        }
        self.stats.tracks_started += new_tracks.len() as u64;
        self.next_uid += new_tracks.len() as u64;
        self.extend_backward(&mut new_tracks);
        let new_tracks = self.stitch(new_tracks);
        for t in &new_tracks {
            self.set_owner(t);
        }
        self.active.extend(new_tracks);
    }

    /// Chains of unused particles through the frames `idx` (indices into
    /// `frames`, increasing pulses, any spacing): p0→p1 within `max_disp`
    /// per pulse (or around the prior's prediction), →p2 and →p3 within
    /// the gate of the constant-velocity prediction from the previous two.
    /// A chain's cost is the sum of its two prediction errors, each
    /// divided by its variance factor (6 on consecutive pulses: a
    /// prediction from two noisy positions errs by √6 σ per axis); chains
    /// are accepted best-first without sharing particles and appended to
    /// `out` (uids after `next_uid + out.len()`), their particles marked used.
    pub(super) fn start_chains(&mut self, idx: [usize; INIT_FRAMES], out: &mut Vec<ActiveTrack>) {
        let f = &self.frames;
        let p = &self.params;
        let sigma = self.position_sigma();
        let dt = |a: usize, b: usize| f[idx[b]].t_us - f[idx[a]].t_us;
        let span = |a: usize, b: usize| (f[idx[b]].pulse - f[idx[a]].pulse) as f64;
        // Variance factor of the prediction of frame k from frames k-2, k-1.
        let var = |k: usize| {
            let a = span(k - 1, k) / span(k - 2, k - 1);
            (1.0 + a).powi(2) + a * a + 1.0
        };
        let (var2, var3) = (var(2), var(3));
        // `max_disp` bounds the gate even below `init_radius` (a slow
        // flow): no track looks further than the user allows.
        let gate = |v: f64| {
            (p.gates.n_sigma * sigma * v.sqrt())
                .max(p.init.init_radius)
                .min(p.max_disp)
        };
        let (gate2, gate3) = (gate(var2), gate(var3));
        // The unused particles of frames 1..3 near a point: each frame's
        // grid holds all its particles (built once, when the pulse was
        // linked), and the used ones are skipped here. (Grids of the
        // unused particles alone, rebuilt for every chain start, cost
        // more than the used particles' distance tests they saved.)
        let mut sc = std::mem::take(&mut self.scratch);
        let near = |k: usize, x: f64, y: f64, r: f64, out: &mut Vec<(u32, f64)>| {
            let fk = &f[idx[k]];
            out.clear();
            fk.grid.within(x, y, r, out);
            out.retain(|e| !fk.used[e.0 as usize]);
        };
        let (mut n1, mut n2, mut n3) = (
            std::mem::take(&mut sc.near),
            std::mem::take(&mut sc.near2),
            std::mem::take(&mut sc.near3),
        );
        let (f0, f1, f2, f3) = (&f[idx[0]], &f[idx[1]], &f[idx[2]], &f[idx[3]]);
        let check = p.init.ghost_check_init && p.init.ghost_check_length > 0;
        // A chain that skips a pulse must show that it moves with the
        // local flow (an unknown flow is no excuse): it is the likelier
        // ghost (wider first steps, one image fewer per span).
        let gappy = span(0, INIT_FRAMES - 1) > (INIT_FRAMES - 1) as f64;
        // Its first step can be held to the flow at once
        // (`gap_first_step`): the pulse and Σ(τ − τ̄)² of the ghost test's
        // line fit, for its flow tolerance.
        let first_step_flow = gappy && check && p.init.gap_first_step;
        let taus: [f64; INIT_FRAMES] = std::array::from_fn(|k| span(0, k));
        let tau_mean = taus.iter().sum::<f64>() / INIT_FRAMES as f64;
        let stt: f64 = taus.iter().map(|t| (t - tau_mean).powi(2)).sum();
        let t_mid = (f0.pulse as f64 + tau_mean).round() as i64;
        let s2 = sigma * sigma;
        // (cost, [i0, i1, i2, i3])
        let mut chains: Vec<(f64, [usize; 4])> = Vec::new();
        for (i0, d0) in f0.dets.iter().enumerate() {
            if f0.used[i0] {
                continue;
            }
            let (cx, cy, r1) = match &p.prior {
                Some(prior) => {
                    let (u, v) = (prior.0)(d0.x, d0.y);
                    let s = dt(0, 1) * 1e-6;
                    (d0.x + u * s, d0.y + v * s, p.init.prior_radius * span(0, 1))
                }
                None => (d0.x, d0.y, p.max_disp * span(0, 1)),
            };
            if first_step_flow {
                let flow = match self.flow.at(t_mid, d0.x, d0.y) {
                    Some(e) if e.weight >= local_flow::MIN_FLOW_WEIGHT => e,
                    _ => continue,
                };
                // The ghost test's tolerance of the chain's velocity, and
                // three σ of the first step's own noise (√2 σ per axis)
                // plus 1 px for its difference from the chain's fitted
                // velocity (curvature over two pulses).
                let variation = (flow.spread2 - 2.0 * s2).max(0.0);
                let tol =
                    p.init.ghost_sigma * (variation + s2 / stt + flow.spread2 / flow.weight).sqrt();
                let s01 = span(0, 1);
                let r = (s01 * tol + 3.0 * std::f64::consts::SQRT_2 * sigma + 1.0).min(r1);
                near(1, d0.x + flow.u * s01, d0.y + flow.v * s01, r, &mut n1);
                // Within the plain first-step disc too.
                n1.retain(|&(i1, _)| {
                    let d1 = &f1.dets[i1 as usize];
                    (d1.x - cx).powi(2) + (d1.y - cy).powi(2) <= r1 * r1
                });
            } else {
                near(1, cx, cy, r1, &mut n1);
            }
            self.chains_enumerated += n1.len() as u64;
            for &(i1, _) in &n1 {
                let i1 = i1 as usize;
                let d1 = &f1.dets[i1];
                let (v1x, v1y) = ((d1.x - d0.x) / dt(0, 1), (d1.y - d0.y) / dt(0, 1));
                let (p2x, p2y) = (d1.x + v1x * dt(1, 2), d1.y + v1y * dt(1, 2));
                near(2, p2x, p2y, gate2, &mut n2);
                for &(i2, _) in &n2 {
                    let i2 = i2 as usize;
                    let d2 = &f2.dets[i2];
                    let (v2x, v2y) = ((d2.x - d1.x) / dt(1, 2), (d2.y - d1.y) / dt(1, 2));
                    let (p3x, p3y) = (d2.x + v2x * dt(2, 3), d2.y + v2y * dt(2, 3));
                    near(3, p3x, p3y, gate3, &mut n3);
                    for &(i3, _) in &n3 {
                        let i3 = i3 as usize;
                        let d3 = &f3.dets[i3];
                        let e2 = (d2.x - p2x).powi(2) + (d2.y - p2y).powi(2);
                        let e3 = (d3.x - p3x).powi(2) + (d3.y - p3y).powi(2);
                        chains.push((e2 / var2 + e3 / var3, [i0, i1, i2, i3]));
                    }
                }
            }
        }
        sc.near = n1;
        sc.near2 = n2;
        sc.near3 = n3;
        self.scratch = sc;
        let f = &self.frames;
        chains.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        let mut taken: Vec<Vec<bool>> = idx.iter().map(|&k| f[k].used.clone()).collect();
        for (_, ids) in chains {
            if (0..INIT_FRAMES).any(|k| taken[k][ids[k]]) {
                continue;
            }
            if check {
                let xy: [(i64, f64, f64); INIT_FRAMES] = std::array::from_fn(|k| {
                    let d = &f[idx[k]].dets[ids[k]];
                    (d.pulse, d.x, d.y)
                });
                match local_flow::flow_consistent(&xy, &self.flow, sigma, p.init.ghost_sigma) {
                    local_flow::FlowCheck::Ghost => continue,
                    local_flow::FlowCheck::Unknown if gappy => continue,
                    _ => {}
                }
            }
            for k in 0..INIT_FRAMES {
                taken[k][ids[k]] = true;
            }
            // Room for the track's first dozens of links: a track grows
            // a detection per pulse, and growing from four by doubling
            // cost ~1 400 instructions per step on the linking thread
            // (~8 000 per track; the allocator, copies).
            let mut dets = Vec::with_capacity(NEW_TRACK_CAPACITY);
            dets.extend((0..INIT_FRAMES).map(|k| f[idx[k]].dets[ids[k]]));
            out.push(ActiveTrack {
                uid: self.next_uid + out.len() as u64,
                dets,
                context: 0,
            });
        }
        for (k, t) in idx.iter().zip(taken) {
            self.frames[*k].used = t;
        }
    }
}

/// Link a whole set of particles (any order; grouped by pulse, pulses in
/// increasing order) into tracks. The detection serials of the returned
/// tracks index the particles sorted by `(pulse, input order)`; the second
/// value is that sorted order as indices into `particles`.
#[ebptv_macros::testkit]
pub(crate) fn link_linked(
    particles: &[Particle],
    params: &TrackParams,
) -> Result<(Vec<LinkedTrack>, Vec<usize>, TrackerStats)> {
    let mut order: Vec<usize> = (0..particles.len()).collect();
    order.sort_by_key(|&i| particles[i].pulse); // stable: keeps input order within a pulse
    let sorted: Vec<Particle> = order.iter().map(|&i| particles[i]).collect();
    let mut tracker = Tracker::new(params.clone())?;
    let mut out = Vec::new();
    let mut s = 0;
    while s < sorted.len() {
        let mut e = s;
        while e < sorted.len() && sorted[e].pulse == sorted[s].pulse {
            e += 1;
        }
        out.extend(tracker.push_linked(sorted[s].pulse, sorted[s].t_us, &sorted[s..e])?);
        s = e;
    }
    let (rest, stats) = tracker.finish();
    out.extend(rest);
    Ok((out, order, stats))
}

/// Link particles into tracks (see `link_linked`).
pub fn link(particles: &[Particle], params: &TrackParams) -> Result<Vec<Track>> {
    Ok(link_linked(particles, params)?
        .0
        .into_iter()
        .map(|t| t.track)
        .collect())
}
