//! The reference implementation of [`super::SignatureAccumulator`]: one
//! array per per-pixel quantity, every histogram binned by its binary
//! search. It is the plain accumulator, kept unchanged so that tests can compare the fast one with it
//! (`tests/modelcheck_signatures.rs`: equal signatures on simulated
//! recordings with every effect on). Not used by the workflow.

use std::collections::HashMap;

use super::{
    burst_window, count_edges, interval_edges, latency_yield_profile, outside_window, pearson,
    pearson_f64, quarter_us, regression_slope, BinScale, Histogram, ProfileAcc, Signature,
    SignatureConfig, SignatureValue, Signatures, BUSY_WINDOW_TICKS, LATENCY_YIELD_EDGES,
    MAX_COUNT_EDGE, NO_TIME,
};
use crate::cluster::Particle;
use crate::error::{Error, Result};
use crate::events::{EventChunk, ON};
use crate::track::Track;

/// Streaming computation of [`Signatures`].
pub(crate) struct ReferenceAccumulator {
    cfg: SignatureConfig,
    latency: Histogram,
    /// Folded time of OFF events (same bins as `latency`).
    off_latency: Histogram,
    /// Events per pulse: the pulse being counted and its count so far.
    pulse_now: i64,
    pulse_count: u64,
    pulse_counts: Vec<u64>,
    /// Per pixel: the pulse of its current visit (events in one pulse)
    /// and the events in it so far; visits in even / odd blocks.
    visit_pulse: Vec<i64>,
    visit_events: Vec<u16>,
    visits_even: Vec<u32>,
    visits_odd: Vec<u32>,
    /// Folded latency of the first event of each pixel's current visit
    /// (quarter µs).
    visit_first: Vec<u16>,
    /// Visits per bin of their events.
    visit_yield: Histogram,
    /// Mean first-event latency of the visits per bin of their events.
    latency_yield: ProfileAcc,
    count_even: Vec<u32>,
    count_odd: Vec<u32>,
    last_t: Vec<i64>,
    min_dt: Vec<i64>,
    n_events: u64,
    n_on: u64,
    n_outside: u64,
    t_min: i64,
    t_max: i64,
    // (row, timestamp) grouping over runs of equal timestamps.
    run_t: i64,
    run_rows: Vec<u16>,
    group_sizes: HashMap<u32, u64>,
    shared_events: u64,
    tick_events: ProfileAcc,
    /// The last tick seen: (timestamp, distinct rows, events, whether the
    /// tick before it had events too).
    last_tick: Option<(i64, usize, usize, bool)>,
    /// The last busy tick and the (groups, events) of the busy ticks up to
    /// it (at most a window's worth, all consecutive).
    busy_last: i64,
    busy_ticks: std::collections::VecDeque<(usize, usize)>,
    /// Σ over busy windows of (1, G, E, G², G·E).
    window_sums: [f64; 5],
    /// Events per pixel outside the burst window (only with a fixed window).
    /// Per pixel: visits with events outside the burst window, and the
    /// pulse of the last one.
    count_off_burst: Option<Vec<(u32, i64)>>,
    /// (events, first latency, extent x, extent y) per particle.
    particles: Vec<(u32, f32, f32, f32)>,
    elongation: Option<ProfileAcc>,
    track_lengths: Vec<u32>,
}

impl ReferenceAccumulator {
    /// An empty accumulator for `cfg`. Fails when `cfg` is invalid.
    pub(crate) fn new(cfg: SignatureConfig) -> Result<Self> {
        cfg.validate()?;
        let latency = Histogram::new(cfg.latency_edges(), BinScale::Linear)?;
        let n = cfg.geometry.pixels();
        Ok(ReferenceAccumulator {
            latency,
            off_latency: Histogram::new(cfg.latency_edges(), BinScale::Linear)?,
            pulse_now: NO_TIME,
            pulse_count: 0,
            pulse_counts: Vec::new(),
            visit_pulse: vec![NO_TIME; n],
            visit_events: vec![0; n],
            visits_even: vec![0; n],
            visits_odd: vec![0; n],
            visit_first: vec![0; n],
            visit_yield: Histogram::new((1..=17).map(|k| k as f64).collect(), BinScale::Index)?,
            latency_yield: ProfileAcc::new(LATENCY_YIELD_EDGES.to_vec())?,
            count_even: vec![0; n],
            count_odd: vec![0; n],
            last_t: vec![NO_TIME; n],
            min_dt: vec![i64::MAX; n],
            n_events: 0,
            n_on: 0,
            n_outside: 0,
            t_min: i64::MAX,
            t_max: i64::MIN,
            run_t: NO_TIME,
            run_rows: Vec::new(),
            group_sizes: HashMap::new(),
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
        let period = self.cfg.timing.period_us;
        let first = self.cfg.timing.first_pulse_us;
        let block = self.cfg.block_pulses as i64;
        let window = self.cfg.burst_window_us;
        for i in 0..ev.len() {
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
            self.latency.add(folded);
            let pulse = (rel / period).floor() as i64;
            if p != ON {
                self.off_latency.add(folded);
            }
            if pulse != self.pulse_now {
                if self.pulse_count > 0 {
                    self.pulse_counts.push(self.pulse_count);
                }
                self.pulse_now = pulse;
                self.pulse_count = 0;
            }
            self.pulse_count += 1;
            let pix = y as usize * g.width as usize + x as usize;
            if self.visit_pulse[pix] != pulse {
                if self.visit_pulse[pix] != NO_TIME {
                    let n = self.visit_events[pix] as f64;
                    self.visit_yield.add(n);
                    self.latency_yield
                        .add(n, self.visit_first[pix] as f64 * 0.25);
                }
                self.visit_pulse[pix] = pulse;
                self.visit_events[pix] = 0;
                self.visit_first[pix] = quarter_us(folded);
                if pulse.div_euclid(block) % 2 == 0 {
                    self.visits_even[pix] += 1;
                } else {
                    self.visits_odd[pix] += 1;
                }
            }
            self.visit_events[pix] = self.visit_events[pix].saturating_add(1);
            if let (Some(w), Some(c)) = (window, self.count_off_burst.as_mut()) {
                // Folded time, binned as the latency histogram bins it, so
                // that a pixel counts where `off_burst_rate` counts its
                // events; one count per visit.
                if outside_window(self.latency.bin_centre(folded), w, period) && c[pix].1 != pulse {
                    c[pix] = (c[pix].0 + 1, pulse);
                }
            }
            if pulse.div_euclid(block) % 2 == 0 {
                self.count_even[pix] += 1;
            } else {
                self.count_odd[pix] += 1;
            }
            let last = self.last_t[pix];
            if last != NO_TIME {
                // Readers never reorder time; a backwards step is data, and
                // its size is still an interval between two events.
                let dt = (t - last).abs();
                self.min_dt[pix] = self.min_dt[pix].min(dt);
            }
            self.last_t[pix] = t;

            if t != self.run_t {
                self.flush_run();
                self.run_t = t;
            }
            self.run_rows.push(y);
        }
    }

    fn flush_run(&mut self) {
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
            *self.group_sizes.entry(s).or_insert(0) += 1;
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
    fn add_busy_tick(&mut self, t: i64, groups: usize, events: usize) {
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

        push(
            "latency",
            "events per folded time bin, (t - first pulse) mod period (us)",
            SignatureValue::Histogram(self.latency.clone()),
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

        let edges = count_edges(MAX_COUNT_EDGE);
        let mut pixel_count = Histogram::new(edges.clone(), BinScale::Index)?;
        let mut split_min = Histogram::new(edges, BinScale::Index)?;
        for (&a, &b) in self.count_even.iter().zip(&self.count_odd) {
            pixel_count.add((a + b) as f64);
            split_min.add(a.min(b) as f64);
        }
        push(
            "pixel_count",
            "pixels per bin of events per pixel",
            SignatureValue::Histogram(pixel_count),
        );
        push(
            "split_half_min",
            "pixels per bin of min(even-block, odd-block) event count",
            SignatureValue::Histogram(split_min),
        );
        push(
            "split_half_correlation",
            "Pearson r of per-pixel counts in even vs odd pulse blocks",
            SignatureValue::Scalar {
                value: pearson(&self.count_even, &self.count_odd),
            },
        );

        let window = match self.cfg.burst_window_us {
            Some(w) => w,
            None => burst_window(&self.latency, 0.95)?,
        };
        let period = self.cfg.timing.period_us;
        let off: f64 = self
            .latency
            .positions()
            .iter()
            .zip(&self.latency.counts)
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
            let mut hist =
                Histogram::new(count_edges(MAX_COUNT_EDGE)[1..].to_vec(), BinScale::Index)?;
            let mut active = 0usize;
            for &(k, _) in c.iter().filter(|c| c.0 > 0) {
                hist.add(k as f64);
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
                SignatureValue::Histogram(hist),
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
        for (&s, &n) in &self.group_sizes {
            groups.add_weighted(s as f64, n as f64);
        }
        push(
            "group_size",
            "(row, timestamp) groups per bin of group size",
            SignatureValue::Histogram(groups),
        );

        let mut iei = Histogram::new(interval_edges(), BinScale::Index)?;
        for &d in &self.min_dt {
            if d != i64::MAX {
                iei.add(d as f64);
            }
        }
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
            SignatureValue::Histogram(iei),
        );
        push(
            "burst_repeat_share",
            "log10 share of pixels with an interval whose shortest is under half a pulse period",
            SignatureValue::Scalar {
                value: super::burst_repeat_share(
                    self.min_dt
                        .iter()
                        .filter(|&&d| d != i64::MAX)
                        .map(|&d| d as f64),
                    self.cfg.timing.period_us,
                ),
            },
        );

        push(
            "off_latency",
            "OFF events per folded time bin (us)",
            SignatureValue::Histogram(self.off_latency.clone()),
        );
        if self.pulse_count > 0 {
            self.pulse_counts.push(self.pulse_count);
        }
        let mut per_pulse =
            Histogram::new(count_edges(MAX_COUNT_EDGE)[1..].to_vec(), BinScale::Index)?;
        for &c in &self.pulse_counts {
            per_pulse.add(c as f64);
        }
        push(
            "events_per_pulse",
            "pulse periods per bin of their events (periods with any)",
            SignatureValue::Histogram(per_pulse),
        );
        let mut visit_yield = self.visit_yield.clone();
        let mut latency_yield = self.latency_yield.clone();
        let (mut ye, mut yo) = (Vec::new(), Vec::new());
        for pix in 0..self.visit_pulse.len() {
            if self.visit_pulse[pix] != NO_TIME {
                let n = self.visit_events[pix] as f64;
                visit_yield.add(n);
                latency_yield.add(n, self.visit_first[pix] as f64 * 0.25);
            }
            let (ve, vo) = (self.visits_even[pix], self.visits_odd[pix]);
            if ve > 0 && vo > 0 {
                ye.push(self.count_even[pix] as f64 / ve as f64);
                yo.push(self.count_odd[pix] as f64 / vo as f64);
            }
        }
        push(
            "visit_yield",
            "(pixel, pulse) visits per number of events in them",
            SignatureValue::Histogram(visit_yield),
        );
        push(
            "yield_split_correlation",
            "Pearson r of per-pixel events per visit in even vs odd pulse blocks (pixels visited in both)",
            SignatureValue::Scalar {
                value: pearson_f64(&ye, &yo),
            },
        );
        push(
            "latency_vs_yield",
            "mean folded latency (us) of a visit's first event per events in the visit, less the mean over all visits",
            SignatureValue::Profile(latency_yield_profile(
                &latency_yield.sum,
                &latency_yield.bins.counts,
            )),
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
