//! The streaming pass that measures a recording's signatures
//! ([`SignatureAccumulator`]): per-pixel state, the binned histograms and
//! their integer fast paths, fed one event chunk at a time and turned into
//! [`Signatures`] at the end.

use super::*;

/// Streaming computation of [`Signatures`].
///
/// Fast path ([`reference::ReferenceAccumulator`] is the plain
/// version the tests compare it with, signature for signature): the
/// per-pixel state is one 32-byte record per pixel (`PixelState`), so
/// an event touches one cache line instead of eight arrays of the sensor
/// size (a 640x360 sensor's state does not fit in cache, and the events of
/// a burst land all over it); every histogram fed per event or per pixel
/// counts integers per bin and bins through a lookup table or the uniform
/// spacing (`IntBins`, `UniformBins`) instead of a binary search per
/// value. Counts are exact integers either way, so the signatures are
/// identical, not just close.
pub(crate) struct SignatureAccumulator {
    pub(super) cfg: SignatureConfig,
    pub(super) latency: UniformBins,
    pub(super) latency_counts: Vec<u64>,
    /// Per latency bin: is its centre outside the burst window (only with
    /// a fixed window)?
    pub(super) latency_outside: Option<Vec<bool>>,
    /// Folded time of OFF events (same bins as `latency`).
    pub(super) off_latency_counts: Vec<u64>,
    /// Events per pulse: the pulse being counted and its count so far.
    pub(super) pulse_now: i64,
    pub(super) pulse_count: u64,
    pub(super) pulse_counts: Vec<u64>,
    /// The pulse the even/odd flag was taken for, and whether it lies in
    /// an even block.
    pub(super) block_pulse: i64,
    pub(super) block_even: bool,
    pub(super) pix: Vec<PixelState>,
    /// Visits per number of events (index: events, saturating at 16 and
    /// above, which share the last bin).
    pub(super) visit_yield: Vec<u64>,
    /// Σ of the visits' first-event latencies (quarter µs,
    /// [`quarter_us`]) per index of `visit_yield`.
    pub(super) visit_first_sum: Vec<u64>,
    pub(super) n_events: u64,
    pub(super) n_on: u64,
    pub(super) n_outside: u64,
    pub(super) t_min: i64,
    pub(super) t_max: i64,
    // (row, timestamp) grouping over runs of equal timestamps.
    pub(super) run_t: i64,
    pub(super) run_rows: Vec<u16>,
    /// Groups per size (index: size).
    pub(super) group_sizes: Vec<u64>,
    pub(super) shared_events: u64,
    pub(super) tick_events: ProfileAcc,
    /// The last tick seen: (timestamp, distinct rows, events, whether the
    /// tick before it had events too).
    pub(super) last_tick: Option<(i64, usize, usize, bool)>,
    /// The last busy tick and the (groups, events) of the busy ticks up to
    /// it (at most a window's worth, all consecutive).
    pub(super) busy_last: i64,
    pub(super) busy_ticks: std::collections::VecDeque<(usize, usize)>,
    /// Σ over busy windows of (1, G, E, G², G·E).
    pub(super) window_sums: [f64; 5],
    /// Per pixel, the visits (pulses) with events outside the burst
    /// window and the pulse of the last one (only with a fixed window;
    /// apart from [`PixelState`]: it is touched only by the few events
    /// outside the burst).
    pub(super) count_off_burst: Option<Vec<(u32, i64)>>,
    /// (events, first latency, extent x, extent y) per particle.
    pub(super) particles: Vec<(u32, f32, f32, f32)>,
    pub(super) elongation: Option<ProfileAcc>,
    pub(super) track_lengths: Vec<u32>,
}

/// Everything the accumulator keeps per pixel, in one record.
///
/// The pixel's current visit (the pulse of its last event) is not stored:
/// it is the pulse of `last_t`, recomputed (a division costs less than the
/// cache line another 8 bytes per pixel would spill into).
#[derive(Debug, Clone, Copy)]
#[repr(C, align(32))]
pub(super) struct PixelState {
    /// Time of the last event (`NO_TIME`: none yet).
    pub(super) last_t: i64,
    /// Smallest interval between two events, µs, capped at
    /// `u32::MAX - 1` (far inside the last `min_iei` bin, which starts at
    /// 10⁷ µs); `u32::MAX`: no interval yet.
    pub(super) min_dt: u32,
    pub(super) count_even: u32,
    pub(super) count_odd: u32,
    pub(super) visits_even: u32,
    pub(super) visits_odd: u32,
    /// Events in the current visit (saturating).
    pub(super) visit_events: u16,
    /// Folded latency of the current visit's first event ([`quarter_us`]).
    pub(super) visit_first: u16,
}

pub(super) const NO_INTERVAL: u32 = u32::MAX;

impl PixelState {
    pub(super) const EMPTY: PixelState = PixelState {
        last_t: NO_TIME,
        min_dt: NO_INTERVAL,
        count_even: 0,
        count_odd: 0,
        visits_even: 0,
        visits_odd: 0,
        visit_events: 0,
        visit_first: 0,
    };
}

/// Binning of a histogram with uniformly spaced edges (the folded latency):
/// the bin from the spacing, corrected against the edges so that it is the
/// bin [`Histogram::bin_of`] finds.
#[derive(Debug, Clone)]
pub(super) struct UniformBins {
    pub(super) hist: Histogram,
    pub(super) inv_width: f64,
}

impl UniformBins {
    pub(super) fn new(hist: Histogram) -> Self {
        let n = hist.n_bins();
        let inv_width = n as f64 / (hist.edges[n] - hist.edges[0]);
        UniformBins { hist, inv_width }
    }

    /// Same as `self.hist.bin_of(v)`.
    #[inline]
    pub(super) fn bin_of(&self, v: f64) -> Option<usize> {
        if v.is_nan() {
            return None;
        }
        let e = &self.hist.edges;
        let n = e.len() - 1;
        let guess = (v - e[0]) * self.inv_width;
        // `as usize` saturates (and maps a negative guess to 0).
        let mut k = (guess as usize).min(n - 1);
        while k > 0 && e[k] > v {
            k -= 1;
        }
        while k + 1 < n && e[k + 1] <= v {
            k += 1;
        }
        Some(k)
    }

    /// The histogram with `counts` in its bins.
    pub(super) fn with_counts(&self, counts: &[u64]) -> Histogram {
        let mut h = self.hist.clone();
        for (c, &n) in h.counts.iter_mut().zip(counts) {
            *c = n as f64;
        }
        h
    }
}

/// Binning of non-negative integers (counts, intervals in µs) on any
/// edges: a table of [`Histogram::bin_of`] for the small values, which
/// are nearly all of them, the binary search beyond.
#[derive(Debug, Clone)]
pub(super) struct IntBins {
    pub(super) hist: Histogram,
    pub(super) table: Vec<u16>,
    pub(super) counts: Vec<u64>,
}

/// Values binned by table in [`IntBins`].
pub(super) const INT_TABLE: usize = 4096;

impl IntBins {
    pub(super) fn new(hist: Histogram) -> Self {
        let table = (0..INT_TABLE)
            .map(|v| hist.bin_of(v as f64).expect("not NaN") as u16)
            .collect();
        let counts = vec![0; hist.n_bins()];
        IntBins {
            hist,
            table,
            counts,
        }
    }

    #[inline]
    pub(super) fn add(&mut self, v: u64) {
        let k = match self.table.get(v as usize) {
            Some(&k) => k as usize,
            None => self.hist.bin_of(v as f64).expect("not NaN"),
        };
        self.counts[k] += 1;
    }

    pub(super) fn finish(mut self) -> Histogram {
        for (c, &n) in self.hist.counts.iter_mut().zip(&self.counts) {
            *c = n as f64;
        }
        self.hist
    }
}

/// Events ahead whose pixel record [`SignatureAccumulator::add_events`]
/// prefetches: enough to cover a memory latency with the work of the
/// events between.
pub(super) const PREFETCH_AHEAD: usize = 12;

/// Hint the cache to fetch `*r` (no effect on results; a no-op off x86-64).
#[inline(always)]
pub(super) fn prefetch<T>(r: &T) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        // SAFETY: a prefetch never faults, and the address is a live reference.
        unsafe { _mm_prefetch::<_MM_HINT_T0>(r as *const T as *const i8) };
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = r;
}

/// `x.floor() as i64` without the libm call (the baseline x86-64 target
/// has no rounding instruction): truncation, one down for negative
/// non-integers; saturating as `as` does, 0 for NaN.
#[inline(always)]
pub(super) fn floor_i64(x: f64) -> i64 {
    let q = x as i64;
    if (q as f64) > x {
        q.saturating_sub(1)
    } else {
        q
    }
}

pub(super) const NO_TIME: i64 = i64::MIN;

/// Ticks per busy window of `busy_window_slope`: long enough
/// that the grants cut by the window's edges (about one per edge) are a
/// small part of it, short enough for a few windows per burst.
pub(crate) const BUSY_WINDOW_TICKS: usize = 8;

/// Upper end of the per-pixel count binning (the last bin is "≥ this").
/// Fixed, never taken from the data, so every data set shares the bins.
pub(super) const MAX_COUNT_EDGE: f64 = (1u64 << 24) as f64;

/// Bins of `visit_yield` and `events_per_cluster`: 1, 2, …, 16 and more.
pub(super) fn yield_edges() -> Vec<f64> {
    (1..=17).map(|k| k as f64).collect()
}

impl SignatureAccumulator {
    /// An empty accumulator for `cfg`. Fails when `cfg` is invalid.
    pub(crate) fn new(cfg: SignatureConfig) -> Result<Self> {
        cfg.validate()?;
        let latency = UniformBins::new(Histogram::new(cfg.latency_edges(), BinScale::Linear)?);
        let n_lat = latency.hist.n_bins();
        let period = cfg.timing.period_us;
        let latency_outside = cfg.burst_window_us.map(|w| {
            latency
                .hist
                .edges
                .windows(2)
                .map(|e| outside_window(0.5 * (e[0] + e[1]), w, period))
                .collect()
        });
        let n = cfg.geometry.pixels();
        Ok(SignatureAccumulator {
            latency,
            latency_counts: vec![0; n_lat],
            latency_outside,
            off_latency_counts: vec![0; n_lat],
            pulse_now: NO_TIME,
            pulse_count: 0,
            pulse_counts: Vec::new(),
            block_pulse: NO_TIME,
            block_even: true,
            pix: vec![PixelState::EMPTY; n],
            visit_yield: vec![0; 17],
            visit_first_sum: vec![0; 17],
            n_events: 0,
            n_on: 0,
            n_outside: 0,
            t_min: i64::MAX,
            t_max: i64::MIN,
            run_t: NO_TIME,
            run_rows: Vec::new(),
            group_sizes: Vec::new(),
            shared_events: 0,
            tick_events: ProfileAcc::new(count_edges(65536.0)[1..].to_vec())?,
            last_tick: None,
            busy_last: NO_TIME,
            busy_ticks: Default::default(),
            window_sums: [0.0; 5],
            count_off_burst: cfg.burst_window_us.map(|_| vec![(0, NO_TIME); n]),
            particles: Vec::new(),
            elongation: None,
            track_lengths: Vec::new(),
            cfg,
        })
    }

    /// Add a chunk of events (chunks in stream order).
    pub(crate) fn add_events(&mut self, ev: &EventChunk) {
        let g = self.cfg.geometry;
        let width = g.width as usize;
        let period = self.cfg.timing.period_us;
        let first = self.cfg.timing.first_pulse_us;
        let block = self.cfg.block_pulses as i64;
        for i in 0..ev.len() {
            // The events of a burst land all over the sensor: ask for the
            // pixel record of an event a few ahead while this one is done.
            if let Some(j) = i.checked_add(PREFETCH_AHEAD).filter(|&j| j < ev.len()) {
                if g.contains(ev.x[j], ev.y[j]) {
                    prefetch(&self.pix[ev.y[j] as usize * width + ev.x[j] as usize]);
                }
            }
            let (t, x, y, p) = (ev.t[i], ev.x[i], ev.y[i], ev.p[i]);
            if !g.contains(x, y) {
                self.n_outside += 1;
                continue;
            }
            self.n_events += 1;
            self.n_on += (p == ON) as u64;
            self.t_min = self.t_min.min(t);
            self.t_max = self.t_max.max(t);

            let rel = t as f64 - first;
            let folded = rel.rem_euclid(period);
            let lat_bin = self.latency.bin_of(folded);
            if let Some(k) = lat_bin {
                self.latency_counts[k] += 1;
                if p != ON {
                    self.off_latency_counts[k] += 1;
                }
            }
            let pulse = floor_i64(rel / period);
            if pulse != self.pulse_now {
                if self.pulse_count > 0 {
                    self.pulse_counts.push(self.pulse_count);
                }
                self.pulse_now = pulse;
                self.pulse_count = 0;
            }
            self.pulse_count += 1;
            if pulse != self.block_pulse {
                self.block_pulse = pulse;
                self.block_even = pulse.div_euclid(block) % 2 == 0;
            }
            let pix = y as usize * width + x as usize;
            let s = &mut self.pix[pix];
            let last = s.last_t;
            // A new visit unless the pixel's last event is in this pulse
            // (its pulse computed exactly as this event's).
            if last == NO_TIME || floor_i64((last as f64 - first) / period) != pulse {
                if last != NO_TIME {
                    let v = (s.visit_events as usize).min(16);
                    self.visit_yield[v] += 1;
                    self.visit_first_sum[v] += s.visit_first as u64;
                }
                s.visit_events = 0;
                s.visit_first = quarter_us(folded);
                if self.block_even {
                    s.visits_even += 1;
                } else {
                    s.visits_odd += 1;
                }
            }
            s.visit_events = s.visit_events.saturating_add(1);
            if self.block_even {
                s.count_even += 1;
            } else {
                s.count_odd += 1;
            }
            if last != NO_TIME {
                // Readers never reorder time; a backwards step is data, and
                // its size is still an interval between two events.
                let dt = (t - last).unsigned_abs().min(NO_INTERVAL as u64 - 1) as u32;
                s.min_dt = s.min_dt.min(dt);
            }
            s.last_t = t;
            if let (Some(out), Some(c), Some(k)) = (
                self.latency_outside.as_ref(),
                self.count_off_burst.as_mut(),
                lat_bin,
            ) {
                // Folded time, binned as the latency histogram bins it, so
                // that a pixel counts where `off_burst_rate` counts its
                // events; one count per visit.
                let c = &mut c[pix];
                if out[k] && c.1 != pulse {
                    *c = (c.0 + 1, pulse);
                }
            }

            if t != self.run_t {
                self.flush_run();
                self.run_t = t;
            }
            self.run_rows.push(y);
        }
    }

    pub(super) fn flush_run(&mut self) {
        if self.run_rows.is_empty() {
            return;
        }
        self.run_rows.sort_unstable();
        let rows = std::mem::take(&mut self.run_rows);
        let distinct = rows.chunk_by(|a, b| a == b).count();
        // Only ticks inside a busy period (the ticks before and after have
        // events too): there the server never idles, and R·row_time +
        // E·event_time fills the tick.
        let t = self.run_t;
        let mut after_busy = false;
        if let Some((pt, r, e, before)) = self.last_tick {
            after_busy = pt == t - 1;
            if before && after_busy {
                self.tick_events.add(r as f64, e as f64);
                self.add_busy_tick(pt, r, e);
            }
        }
        self.last_tick = Some((t, distinct, rows.len(), after_busy));
        for group in rows.chunk_by(|a, b| a == b) {
            let s = group.len() as u32;
            let s = s as usize;
            if self.group_sizes.len() <= s {
                self.group_sizes.resize(s + 1, 0);
            }
            self.group_sizes[s] += 1;
            if s >= 2 {
                self.shared_events += s as u64;
            }
        }
        self.run_rows = rows;
        self.run_rows.clear();
    }

    /// A tick inside a busy period extends the current run of busy ticks
    /// (or starts one when it does not follow the last); every window of
    /// [`BUSY_WINDOW_TICKS`] consecutive busy ticks (sliding: overlapping
    /// windows use every phase of the grants against the tick grid) adds
    /// its (groups, events) point to the regression sums.
    pub(super) fn add_busy_tick(&mut self, t: i64, groups: usize, events: usize) {
        if self.busy_last != NO_TIME && t != self.busy_last + 1 {
            self.busy_ticks.clear();
        }
        self.busy_last = t;
        self.busy_ticks.push_back((groups, events));
        if self.busy_ticks.len() > BUSY_WINDOW_TICKS {
            self.busy_ticks.pop_front();
        }
        if self.busy_ticks.len() == BUSY_WINDOW_TICKS {
            let (g, e) = self
                .busy_ticks
                .iter()
                .fold((0usize, 0usize), |a, b| (a.0 + b.0, a.1 + b.1));
            let (g, e) = (g as f64, e as f64);
            for (s, v) in self.window_sums.iter_mut().zip([1.0, g, e, g * g, g * e]) {
                *s += v;
            }
        }
    }

    /// Add clustered particles (any order).
    pub(crate) fn add_particles(&mut self, particles: &[Particle]) {
        self.particles.extend(
            particles
                .iter()
                .map(|p| (p.n_events, p.first_latency_us, p.extent_x, p.extent_y)),
        );
    }

    /// Add tracks, with the particles they were built from (for the
    /// elongation of each tracked particle image). A particle is matched to
    /// the track point at the same pulse nearest to it, within 2 px.
    pub(crate) fn add_tracks(&mut self, tracks: &[Track], particles: &[Particle]) -> Result<()> {
        if self.elongation.is_none() {
            self.elongation =
                Some(ProfileAcc::new(self.cfg.speed_edges.clone()).map_err(|_| {
                    Error::param(
                        "speed_edges",
                        "need ≥ 2 finite, strictly increasing edges (px/s)",
                    )
                })?);
        }
        self.track_lengths
            .extend(tracks.iter().map(|t| t.points.len() as u32));
        let mut by_pulse: HashMap<i64, Vec<(f64, f64, f64, f64)>> = HashMap::new();
        for tr in tracks {
            for pt in &tr.points {
                if !pt.interpolated {
                    by_pulse
                        .entry(pt.pulse)
                        .or_default()
                        .push((pt.x, pt.y, pt.u, pt.v));
                }
            }
        }
        let acc = self.elongation.as_mut().expect("set above");
        for p in particles {
            let Some(cands) = by_pulse.get(&p.pulse) else {
                continue;
            };
            let best = cands
                .iter()
                .map(|c| ((c.0 - p.x).powi(2) + (c.1 - p.y).powi(2), c))
                .min_by(|a, b| a.0.total_cmp(&b.0));
            if let Some((d2, &(_, _, u, v))) = best {
                if d2 <= 4.0 {
                    let (ex, ey) = (p.extent_x as f64, p.extent_y as f64);
                    let along_minus_across = if u.abs() >= v.abs() { ex - ey } else { ey - ex };
                    acc.add(u.hypot(v), along_minus_across);
                }
            }
        }
        Ok(())
    }

    /// Finish: all signatures. Errors when no event fell inside the sensor.
    pub(crate) fn finish(mut self) -> Result<Signatures> {
        self.flush_run();
        if self.n_events == 0 {
            return Err(Error::analysis(
                "no events inside the sensor geometry: no signatures",
            ));
        }
        let duration_us = (self.t_max - self.t_min) as f64;
        let seconds = (duration_us.max(self.cfg.timing.period_us)) * 1e-6;
        let n_pix = self.cfg.geometry.pixels() as f64;
        let mut items = Vec::new();
        let mut push = |name: &str, description: &str, value: SignatureValue| {
            items.push(Signature {
                name: name.into(),
                description: description.into(),
                value,
            })
        };

        let latency = self.latency.with_counts(&self.latency_counts);
        push(
            "latency",
            "events per folded time bin, (t - first pulse) mod period (us)",
            SignatureValue::Histogram(latency.clone()),
        );
        push(
            "event_rate",
            "events per second",
            SignatureValue::Scalar {
                value: self.n_events as f64 / seconds,
            },
        );
        push(
            "on_fraction",
            "fraction of ON events",
            SignatureValue::Scalar {
                value: self.n_on as f64 / self.n_events as f64,
            },
        );

        // One pass over the pixels for every per-pixel histogram; the
        // yields of pixels visited in both halves in pixel order (the
        // correlation sums in that order, as the reference does).
        let edges = count_edges(MAX_COUNT_EDGE);
        let mut pixel_count = IntBins::new(Histogram::new(edges.clone(), BinScale::Index)?);
        let mut split_min = IntBins::new(Histogram::new(edges, BinScale::Index)?);
        let mut iei = IntBins::new(Histogram::new(interval_edges(), BinScale::Index)?);
        let mut visit_yield = self.visit_yield.clone();
        let mut visit_first_sum = self.visit_first_sum.clone();
        let (mut ye, mut yo) = (Vec::new(), Vec::new());
        let (mut sum_even, mut sum_odd) = (0u64, 0u64);
        for s in &self.pix {
            let (a, b) = (s.count_even, s.count_odd);
            pixel_count.add((a + b) as u64);
            split_min.add(a.min(b) as u64);
            sum_even += a as u64;
            sum_odd += b as u64;
            if s.min_dt != NO_INTERVAL {
                iei.add(s.min_dt as u64);
            }
            if s.last_t != NO_TIME {
                let v = (s.visit_events as usize).min(16);
                visit_yield[v] += 1;
                visit_first_sum[v] += s.visit_first as u64;
            }
            let (ve, vo) = (s.visits_even, s.visits_odd);
            if ve > 0 && vo > 0 {
                ye.push(a as f64 / ve as f64);
                yo.push(b as f64 / vo as f64);
            }
        }
        push(
            "pixel_count",
            "pixels per bin of events per pixel",
            SignatureValue::Histogram(pixel_count.finish()),
        );
        push(
            "split_half_min",
            "pixels per bin of min(even-block, odd-block) event count",
            SignatureValue::Histogram(split_min.finish()),
        );
        push(
            "split_half_correlation",
            "Pearson r of per-pixel counts in even vs odd pulse blocks",
            SignatureValue::Scalar {
                value: pixel_pearson(&self.pix, sum_even, sum_odd),
            },
        );

        let window = match self.cfg.burst_window_us {
            Some(w) => w,
            None => burst_window(&latency, 0.95)?,
        };
        let period = self.cfg.timing.period_us;
        let off: f64 = latency
            .positions()
            .iter()
            .zip(&latency.counts)
            .filter(|(c, _)| outside_window(**c, window, period))
            .map(|(_, n)| n)
            .sum();
        push(
            "off_burst_rate",
            "events per pixel per second outside the burst window",
            SignatureValue::Scalar {
                value: off / n_pix / seconds,
            },
        );

        if let Some(c) = &self.count_off_burst {
            let mut hist = IntBins::new(Histogram::new(
                count_edges(MAX_COUNT_EDGE)[1..].to_vec(),
                BinScale::Index,
            )?);
            let mut active = 0usize;
            for &(k, _) in c.iter().filter(|c| c.0 > 0) {
                hist.add(k as u64);
                active += 1;
            }
            push(
                "off_burst_pixels",
                "fraction of pixels with an event outside the burst window",
                SignatureValue::Scalar {
                    value: active as f64 / n_pix,
                },
            );
            push(
                "off_burst_pixel_count",
                "pixels per bin of their visits (pulses) with events outside the burst window (pixels with any)",
                SignatureValue::Histogram(hist.finish()),
            );
        }

        push(
            "shared_fraction",
            "fraction of events sharing (row, timestamp) with another event",
            SignatureValue::Scalar {
                value: self.shared_events as f64 / self.n_events as f64,
            },
        );
        let mut groups = Histogram::new(count_edges(65536.0)[1..].to_vec(), BinScale::Index)?;
        for (s, &n) in self.group_sizes.iter().enumerate() {
            if n > 0 {
                groups.add_weighted(s as f64, n as f64);
            }
        }
        push(
            "group_size",
            "(row, timestamp) groups per bin of group size",
            SignatureValue::Histogram(groups),
        );

        push(
            "tick_events_vs_rows",
            "mean events per timestamp tick per bin of distinct rows in the tick",
            SignatureValue::Profile(self.tick_events.finish()),
        );

        push(
            "busy_window_slope",
            "least-squares slope of events on (row, timestamp) groups over windows of 8 busy ticks",
            SignatureValue::Scalar {
                value: regression_slope(&self.window_sums),
            },
        );

        push(
            "min_iei",
            "pixels per bin of their minimum inter-event interval (us)",
            SignatureValue::Histogram(iei.finish()),
        );
        push(
            "burst_repeat_share",
            "log10 share of pixels with an interval whose shortest is under half a pulse period",
            SignatureValue::Scalar {
                value: super::burst_repeat_share(
                    self.pix
                        .iter()
                        .filter(|s| s.min_dt != NO_INTERVAL)
                        .map(|s| s.min_dt as f64),
                    self.cfg.timing.period_us,
                ),
            },
        );

        push(
            "off_latency",
            "OFF events per folded time bin (us)",
            SignatureValue::Histogram(self.latency.with_counts(&self.off_latency_counts)),
        );
        if self.pulse_count > 0 {
            self.pulse_counts.push(self.pulse_count);
        }
        let mut per_pulse = IntBins::new(Histogram::new(
            count_edges(MAX_COUNT_EDGE)[1..].to_vec(),
            BinScale::Index,
        )?);
        for &c in &self.pulse_counts {
            per_pulse.add(c);
        }
        push(
            "events_per_pulse",
            "pulse periods per bin of their events (periods with any)",
            SignatureValue::Histogram(per_pulse.finish()),
        );
        let mut yields = Histogram::new(yield_edges(), BinScale::Index)?;
        for (v, &n) in visit_yield.iter().enumerate() {
            if n > 0 {
                yields.add_weighted(v as f64, n as f64);
            }
        }
        push(
            "visit_yield",
            "(pixel, pulse) visits per number of events in them",
            SignatureValue::Histogram(yields),
        );
        push(
            "yield_split_correlation",
            "Pearson r of per-pixel events per visit in even vs odd pulse blocks (pixels visited in both)",
            SignatureValue::Scalar {
                value: pearson_f64(&ye, &yo),
            },
        );
        // Visits of 1, 2, 3 and 4 or more events (`LATENCY_YIELD_EDGES`):
        // the integer sums of a bin (quarter µs: exact in f64 as well).
        let bins = LATENCY_YIELD_EDGES.len() - 1;
        let (mut sums, mut counts) = (vec![0.0; bins], vec![0.0; bins]);
        for b in 0..bins {
            let lo = LATENCY_YIELD_EDGES[b] as usize;
            let hi = LATENCY_YIELD_EDGES[b + 1] as usize;
            sums[b] = visit_first_sum[lo..hi].iter().sum::<u64>() as f64 * 0.25;
            counts[b] = visit_yield[lo..hi].iter().sum::<u64>() as f64;
        }
        push(
            "latency_vs_yield",
            "mean folded latency (us) of a visit's first event per events in the visit, less the mean over all visits",
            SignatureValue::Profile(latency_yield_profile(&sums, &counts)),
        );

        if !self.particles.is_empty() {
            let mut epc = Histogram::new((1..=17).map(|k| k as f64).collect(), BinScale::Index)?;
            let mut lat = ProfileAcc::new(vec![1.0, 2.0, 3.0, 4.0, 5.0, 7.0, 10.0, 16.0])?;
            let extent_edges: Vec<f64> = (1..=13).map(|k| k as f64).collect();
            let mut ext_x = Histogram::new(extent_edges.clone(), BinScale::Index)?;
            let mut ext_y = Histogram::new(extent_edges, BinScale::Index)?;
            // Integer differences at the bin centres, ±6 px and beyond in
            // the end bins.
            let mut elongation =
                Histogram::new((-6..=7).map(|k| k as f64 - 0.5).collect(), BinScale::Linear)?;
            for &(n, l, ex, ey) in &self.particles {
                epc.add(n as f64);
                lat.add(n as f64, l as f64);
                ext_x.add(ex as f64);
                ext_y.add(ey as f64);
                elongation.add(ex as f64 - ey as f64);
            }
            push(
                "extent_x",
                "particles per bounding-box extent along x (px)",
                SignatureValue::Histogram(ext_x),
            );
            push(
                "extent_y",
                "particles per bounding-box extent along y (px)",
                SignatureValue::Histogram(ext_y),
            );
            push(
                "elongation",
                "particles per bounding-box extent x minus extent y (px)",
                SignatureValue::Histogram(elongation),
            );
            push(
                "events_per_cluster",
                "particles per number of events",
                SignatureValue::Histogram(epc),
            );
            push(
                "latency_vs_brightness",
                "mean first-event latency (us) per events-per-cluster bin",
                SignatureValue::Profile(lat.finish()),
            );
        }
        if let Some(el) = &self.elongation {
            push(
                "elongation_vs_speed",
                "mean extent along minus across the motion (px) per speed bin (px/s)",
                SignatureValue::Profile(el.finish()),
            );
            let mut tl = Histogram::new(
                vec![
                    1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0, 15.0, 20.0, 30.0, 50.0, 100.0, 200.0,
                ],
                BinScale::Index,
            )?;
            for &n in &self.track_lengths {
                tl.add(n as f64);
            }
            push(
                "track_length",
                "tracks per number of points",
                SignatureValue::Histogram(tl),
            );
        }

        Ok(Signatures {
            items,
            n_events: self.n_events,
            n_outside: self.n_outside,
            duration_us,
        })
    }
}
