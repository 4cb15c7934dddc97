//! Live monitor: while a recording is being written, summarise each
//! interval of recording time (event rate, burst contrast, FWHM, a
//! saturation warning) so the operator can turn the laser or the seeding
//! down before data is lost.
//!
//! Each interval gets its own `Analyzer` (the pulse period is re-found in
//! every interval, or taken from the triggers), so a change of conditions
//! shows at once. Following a growing file relies on the source returning
//! `Ok(false)` at the current end and delivering new data on a later call
//! (`io::live`): the monitor sleeps and polls again until
//! `stop` is set (Ctrl-C) or, with an idle timeout, until the file has not
//! grown for that long.
//!
//! Intervals are in *recording* time: interval k covers
//! `[t₀ + k·Δ, t₀ + (k + 1)·Δ)` of event time, t₀ the first event's time,
//! and is reported when the first event at or past its end arrives (or at
//! the end of the data, as a shorter last interval). How the bytes arrive
//! (read chunks, a writer that pauses) does not change the intervals, so
//! following a growing file reports exactly what reading the finished file
//! does; a pause only delays the report. Triggers go with the interval of
//! their time.

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::{Duration, Instant};

use serde::Serialize;

use super::{Analyzer, PulseOptions};
use crate::error::Result;
use crate::events::Chunk;
use crate::io::EventSource;

/// What the monitor prints for one interval.
#[derive(Debug, Clone, Serialize, PartialEq)]
#[ebptv_macros::testkit]
pub(crate) struct IntervalSummary {
    /// Start of the interval (µs, sensor clock).
    pub t_start_us: i64,
    /// End of the interval (µs, sensor clock).
    pub t_end_us: i64,
    /// Events in the interval.
    pub events: u64,
    /// Event rate in the interval (ev/s).
    pub rate_hz: f64,
    /// Event density inside the burst window over that outside.
    pub burst_contrast: f64,
    /// Full width at half maximum of the latency peak (µs).
    pub fwhm_us: f64,
    /// Fraction of events above the random floor (tied to pulses).
    pub burst_fraction: f64,
    /// Fraction of events in large runs sharing (row, timestamp).
    pub large_group_fraction: f64,
    /// The interval is judged readout-saturated.
    pub saturated: bool,
    /// Why no pulse statistics could be computed, when so.
    pub note: Option<String>,
}

impl std::fmt::Display for IntervalSummary {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "t={:.3} s  {:7.2} Mev/s",
            self.t_start_us as f64 * 1e-6,
            self.rate_hz * 1e-6
        )?;
        if let Some(n) = &self.note {
            return write!(f, "  ({n})");
        }
        write!(
            f,
            "  contrast {:6.1}  FWHM {:6.1} µs  burst {:5.1} %",
            self.burst_contrast,
            self.fwhm_us,
            100.0 * self.burst_fraction
        )?;
        if self.saturated {
            write!(f, "  WARNING: readout saturated ({:.0} % of events in row groups) — reduce laser power or seeding", 100.0 * self.large_group_fraction)?;
        }
        Ok(())
    }
}

fn summarize(an: Analyzer, t0: i64, t1: i64, events: u64) -> IntervalSummary {
    let dur = ((t1 - t0).max(1) as f64) * 1e-6;
    let mut s = IntervalSummary {
        t_start_us: t0,
        t_end_us: t1,
        events,
        rate_hz: events as f64 / dur,
        burst_contrast: 0.0,
        fwhm_us: 0.0,
        burst_fraction: 0.0,
        large_group_fraction: 0.0,
        saturated: false,
        note: None,
    };
    match an.finish() {
        Ok(r) => {
            s.burst_contrast = r.burst_contrast;
            s.fwhm_us = r.latency_fwhm_us;
            s.burst_fraction = 1.0 - r.random_event_fraction;
            s.large_group_fraction = r.saturation.large_group_fraction;
            s.saturated = r.saturated;
        }
        Err(e) => s.note = Some(e.to_string()),
    }
    s
}

/// How the monitor treats the end of the data.
#[derive(Debug, Clone, Copy, PartialEq)]
#[ebptv_macros::testkit]
pub(crate) enum Follow {
    /// The first end of the data ends the monitor (a finished file, a pipe).
    No,
    /// Keep polling a growing file until `stop` is set.
    UntilStopped,
    /// Keep polling until `stop`, or until no new data came for this long.
    UntilIdle(Duration),
}

/// Run the monitor over `source`, one summary per `interval_us` of
/// recording time. When following, `Ok(false)` from the source means "no
/// data yet": sleep and poll again (see [`Follow`]). Returns the number of
/// intervals reported.
#[ebptv_macros::testkit]
pub(crate) fn run(
    source: &mut dyn EventSource,
    opts: &PulseOptions,
    interval_us: i64,
    follow: Follow,
    stop: &AtomicBool,
    on_interval: &mut dyn FnMut(&IntervalSummary),
) -> Result<u64> {
    if interval_us <= 0 {
        return Err(crate::error::Error::param(
            "interval",
            format!("{interval_us} µs: must be positive"),
        ));
    }
    opts.validate()?;
    let geometry = source.info().geometry;
    let mut chunk = Chunk::default();
    let mut an = Analyzer::new(opts.clone(), geometry)?;
    // The interval in progress: [start, end) of recording time.
    let mut interval: Option<(i64, i64)> = None;
    let mut t_last = 0i64;
    let mut events = 0u64;
    let mut reported = 0u64;
    let poll = Duration::from_millis(100);
    let mut idle_since = Instant::now();
    // Triggers not yet handed to an interval (in stream order).
    let mut triggers: Vec<crate::Trigger> = Vec::new();
    while !stop.load(Ordering::Relaxed) {
        if !source.next_chunk(&mut chunk)? {
            match follow {
                Follow::No => break,
                Follow::UntilIdle(limit) if idle_since.elapsed() >= limit => break,
                _ => {}
            }
            std::thread::sleep(poll);
            continue;
        }
        idle_since = Instant::now();
        triggers.extend_from_slice(&chunk.triggers);
        // Split the chunk where events reach the end of the interval.
        let ev = &chunk.events;
        let mut start = 0;
        for i in 0..ev.len() {
            let t = ev.t[i];
            let (s, e) = *interval.get_or_insert((t, t + interval_us));
            if t >= e {
                let part = slice_chunk(&chunk, start, i, &mut triggers, e);
                an.push(&part)?;
                events += (i - start) as u64;
                let done = std::mem::replace(&mut an, Analyzer::new(opts.clone(), geometry)?);
                on_interval(&summarize(done, s, e, events));
                reported += 1;
                events = 0;
                start = i;
                // The next interval of the grid holding t (empty ones skipped).
                let s = s + (t - s) / interval_us * interval_us;
                interval = Some((s, s + interval_us));
            }
            t_last = t_last.max(t);
        }
        // Triggers past the interval's end wait for their interval.
        let end = interval.map_or(i64::MAX, |(_, e)| e);
        let rest = slice_chunk(&chunk, start, ev.len(), &mut triggers, end);
        an.push(&rest)?;
        events += (ev.len() - start) as u64;
    }
    if events > 0 {
        let rest = Chunk {
            triggers,
            ..Chunk::default()
        };
        an.push(&rest)?;
        let s = interval.map_or(0, |(s, _)| s);
        on_interval(&summarize(an, s, t_last + 1, events));
        reported += 1;
    }
    Ok(reported)
}

/// Events `a..b` of `c`, with the leading `triggers` before `t_end`
/// (removed from `triggers`).
fn slice_chunk(
    c: &Chunk,
    a: usize,
    b: usize,
    triggers: &mut Vec<crate::Trigger>,
    t_end: i64,
) -> Chunk {
    let mut out = Chunk::default();
    let n = triggers.iter().take_while(|tr| tr.t < t_end).count();
    out.triggers.extend(triggers.drain(..n));
    out.events.t.extend_from_slice(&c.events.t[a..b]);
    out.events.x.extend_from_slice(&c.events.x[a..b]);
    out.events.y.extend_from_slice(&c.events.y[a..b]);
    out.events.p.extend_from_slice(&c.events.p[a..b]);
    out
}
