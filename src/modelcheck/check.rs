//! The whole `ebptv model-check` run: read the measured recording, build
//! the starting model, fit on one half and judge on the other, write
//! `model_check.json`, `model.toml` and the figures into the output folder.

use std::path::Path;

use crate::cluster::ClusterParams;
use crate::error::{Error, Result};
use crate::events::{Chunk, Edge, EventChunk, Geometry};
use crate::modelcheck::baseline::{baseline_from_measurement, BaselineOptions, PulseTrain};
use crate::modelcheck::report::write_outputs;
use crate::modelcheck::scene::{
    active_effects, median_event_latency, particles_of, timing_of, SceneSimulator,
};
use crate::modelcheck::signatures::{burst_window, quiet_complement};
use crate::modelcheck::standard::{
    check as standard_check, standard_effects, StandardOptions, StandardSensor,
};
use crate::modelcheck::workflow::{
    run as run_check, signatures_of, ModelCheckResult, Recording, WorkflowOptions,
};
use crate::sim::scenario::Scenario;

/// Fewest pulses per fit / held-out block: fewer hold too few events per
/// pixel for the signatures.
pub(crate) const MIN_BLOCK_PULSES: u64 = 20;

/// Options of [`check_recording`]; the defaults are those of
/// `ebptv model-check`.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelCheckOptions {
    /// Starting model (scenario TOML); `None`: the standard sensor
    /// calibrated to the measurement.
    pub model: Option<std::path::PathBuf>,
    /// Base seed of every simulation.
    pub seed: u64,
    /// Replicate simulations per assessment.
    pub replicates: usize,
    /// Objective evaluations per parameter and fit stage.
    pub evaluations: usize,
    /// Most effects to add.
    pub max_effects: usize,
    /// Pulses per fit and per held-out block (at most half the recording).
    pub block_pulses: u64,
    /// Nominal pulse frequency (Hz). Without a trigger channel (or with
    /// `ignore_triggers`) the pulse train is found from the events, as
    /// `ebptv pulses` finds it: around this frequency when given, over
    /// 500–50 000 Hz otherwise. Unused with a `model`.
    pub pulse_hz: Option<f64>,
    /// Find the pulse train from the events even when the recording has
    /// triggers.
    pub ignore_triggers: bool,
}

impl Default for ModelCheckOptions {
    fn default() -> Self {
        ModelCheckOptions {
            model: None,
            seed: 1,
            replicates: 5,
            evaluations: 12,
            max_effects: 3,
            block_pulses: 100,
            pulse_hz: None,
            ignore_triggers: false,
        }
    }
}

/// What [`check_recording`] found (also written to `model_check.json`).
#[derive(Debug, Clone)]
pub struct ModelCheckRun {
    /// The model check's outcome: effects found, verdict, tables, rounds.
    pub result: ModelCheckResult,
    /// What the run did along the way (starting model, baseline estimates), one line each.
    pub notes: Vec<String>,
}

/// `ebptv model-check MEASURED --out OUT`: the check of a measured
/// recording against the simulator, its outputs written into `out`.
pub fn check_recording(
    measured: &Path,
    out: &Path,
    a: &ModelCheckOptions,
) -> Result<ModelCheckRun> {
    check_recording_with(measured, out, a, &crate::Cancel::new())
}

/// [`check_recording`] that stops with an error once `cancel` is set (it
/// looks after each chunk read and before each simulation).
pub(crate) fn check_recording_with(
    measured: &Path,
    out: &Path,
    a: &ModelCheckOptions,
    cancel: &crate::Cancel,
) -> Result<ModelCheckRun> {
    check_recording_capped(measured, out, a, cancel, MAX_EVENTS)
}

/// The most events a model check holds: ~13 B each (~0.65 GB), plus the
/// two blocks cut from them. Of a longer recording it reads this many
/// around the middle, and the notes say so.
const MAX_EVENTS: usize = 50_000_000;

/// What a model check reads of a recording.
struct Measured {
    events: EventChunk,
    /// Rising trigger edges among them (µs).
    rising: Vec<i64>,
    geometry_hint: Option<Geometry>,
    /// Which part of a longer recording was read.
    note: Option<String>,
}

/// The events of `path` a model check works on: the whole recording when
/// it has at most `max_events`; of a longer one a stretch of about
/// `max_events` around its middle, found in two passes (the first counts
/// the events and their span, the second keeps the stretch). The middle,
/// not the start: a recording's first moments (a flow starting, a laser
/// warming up) need not be what the rest of it is.
fn read_measured(path: &Path, cancel: &crate::Cancel, max_events: usize) -> Result<Measured> {
    let first = read_pass(path, cancel, max_events, None)?;
    if first.seen <= max_events as u64 {
        return Ok(Measured {
            events: first.events,
            rising: first.rising,
            geometry_hint: first.geometry_hint,
            note: None,
        });
    }
    drop(first.events);
    // Span of the stretch: the cap's share of the recording's duration,
    // with a margin for an uneven event rate (the second pass still stops
    // at the cap).
    let (t0, t1) = (first.t_min as f64, first.t_max as f64);
    let share = 0.95 * max_events as f64 / first.seen as f64;
    let half = 0.5 * share * (t1 - t0);
    let mid = 0.5 * (t0 + t1);
    let window = ((mid - half).floor() as i64, (mid + half).ceil() as i64);
    let second = read_pass(path, cancel, max_events, Some(window))?;
    let note = format!(
        "read {} events around the middle of a recording of {} (t = {}..{} us of {}..{} us; the check's memory bound is {max_events} events)",
        second.events.len(),
        first.seen,
        window.0,
        window.1,
        first.t_min,
        first.t_max
    );
    Ok(Measured {
        events: second.events,
        rising: second.rising,
        geometry_hint: second.geometry_hint,
        note: Some(note),
    })
}

/// One pass of [`read_measured`].
struct Pass {
    /// Events kept (at most the cap).
    events: EventChunk,
    rising: Vec<i64>,
    geometry_hint: Option<Geometry>,
    /// Events in the recording (whole pass), and their time span.
    seen: u64,
    t_min: i64,
    t_max: i64,
}

/// Read `path`, keeping the events with `t` in `window` (all without one)
/// up to `max_events`. Without a window the pass goes on to the end,
/// counting what it no longer keeps; with one it stops at the first chunk
/// that starts after the window.
fn read_pass(
    path: &Path,
    cancel: &crate::Cancel,
    max_events: usize,
    window: Option<(i64, i64)>,
) -> Result<Pass> {
    let mut src = crate::io::open(path)?;
    let geometry_hint = src.info().geometry;
    let (lo, hi) = window.unwrap_or((i64::MIN, i64::MAX));
    let mut pass = Pass {
        events: EventChunk::default(),
        rising: Vec::new(),
        geometry_hint,
        seen: 0,
        t_min: i64::MAX,
        t_max: i64::MIN,
    };
    let mut chunk = Chunk::default();
    while src.next_chunk(&mut chunk)? {
        cancel.check()?;
        let ev = &chunk.events;
        pass.seen += ev.len() as u64;
        for &t in &ev.t {
            pass.t_min = pass.t_min.min(t);
            pass.t_max = pass.t_max.max(t);
        }
        if window.is_some() && ev.t.iter().min().is_some_and(|&t| t >= hi) {
            break;
        }
        let room = max_events - pass.events.len();
        if room == 0 {
            if window.is_some() {
                break;
            }
            continue; // counting only
        }
        let mut kept = 0;
        let mut t_last = i64::MIN;
        for e in ev.iter() {
            if kept == room {
                break;
            }
            if e.t >= lo && e.t < hi {
                pass.events.push(e.t, e.x, e.y, e.p);
                t_last = t_last.max(e.t);
                kept += 1;
            }
        }
        // The triggers of the stretch kept, up to its last event once full.
        let full = pass.events.len() == max_events;
        pass.rising.extend(
            chunk
                .triggers
                .iter()
                .filter(|t| {
                    t.edge == Edge::Rising && t.t >= lo && t.t < hi && (!full || t.t <= t_last)
                })
                .map(|t| t.t),
        );
    }
    Ok(pass)
}

/// The pulse train of a check without a starting model: the trigger
/// channel's when it has one (and `ignore_triggers` is off), else found
/// from the events by the pulse analysis of `ebptv pulses` (around
/// `pulse_hz` when given, over the default band otherwise), run on the
/// events the check read.
fn pulse_train(
    measured: &Path,
    events: &EventChunk,
    rising: &[i64],
    geometry: Geometry,
    a: &ModelCheckOptions,
) -> Result<PulseTrain> {
    if let Some(hz) = a.pulse_hz {
        if !(hz.is_finite() && hz > 0.0) {
            return Err(Error::param("pulse-hz", format!("{hz}: must be positive")));
        }
    }
    if !a.ignore_triggers && rising.len() >= 3 {
        return PulseTrain::from_triggers(rising);
    }
    let opts = crate::pulses::PulseOptions {
        pulse_hz: a.pulse_hz,
        ignore_triggers: true,
        require_pulsed: true,
        ..Default::default()
    };
    let mut an = crate::pulses::Analyzer::new(opts, Some(geometry))?;
    let mut chunk = Chunk::default();
    let n = events.len();
    let mut i = 0;
    while i < n {
        let j = (i + ANALYSIS_CHUNK).min(n);
        chunk.clear();
        chunk.events.t.extend_from_slice(&events.t[i..j]);
        chunk.events.x.extend_from_slice(&events.x[i..j]);
        chunk.events.y.extend_from_slice(&events.y[i..j]);
        chunk.events.p.extend_from_slice(&events.p[i..j]);
        an.push(&chunk)?;
        i = j;
    }
    let report = an.finish().map_err(|e| {
        Error::analysis(format!(
            "finding the light pulses in {}: {e}",
            measured.display()
        ))
    })?;
    Ok(PulseTrain::estimated(&report.timing, a.pulse_hz))
}

/// Events per chunk fed to the pulse analysis (as a reader hands them).
const ANALYSIS_CHUNK: usize = 1 << 20;

/// [`check_recording_with`] reading at most `max_events` events.
pub(crate) fn check_recording_capped(
    measured: &Path,
    out: &Path,
    a: &ModelCheckOptions,
    cancel: &crate::Cancel,
    max_events: usize,
) -> Result<ModelCheckRun> {
    if a.block_pulses < MIN_BLOCK_PULSES {
        return Err(Error::param(
            "block-pulses",
            format!(
                "{}: must be at least {MIN_BLOCK_PULSES} (fewer pulses hold too few events for the signatures)",
                a.block_pulses
            ),
        ));
    }
    crate::modelcheck::workflow::check_budget(a.replicates, a.evaluations)?;
    let Measured {
        events,
        rising,
        geometry_hint,
        note,
    } = read_measured(measured, cancel, max_events)?;
    if events.len() < 1000 {
        return Err(Error::analysis(format!(
            "{}: only {} events, too few for a model check",
            measured.display(),
            events.len()
        )));
    }
    let t0 = *events.t.iter().min().unwrap_or(&0);
    let t1 = *events.t.iter().max().unwrap_or(&0);
    let geometry = geometry_hint.unwrap_or_else(|| {
        let w = events.x.iter().max().copied().unwrap_or(0) + 1;
        let h = events.y.iter().max().copied().unwrap_or(0) + 1;
        Geometry::new(w, h)
    });

    let mut notes: Vec<String> = note.into_iter().collect();
    let scenario = match &a.model {
        Some(p) => {
            notes.push(format!("starting model: {}", p.display()));
            Scenario::from_toml_file(p)?
        }
        None => {
            let train = pulse_train(measured, &events, &rising, geometry, a)?;
            crate::io::atomic::create_output_dir(out)?;
            let b = baseline_from_measurement(
                &events,
                &train,
                geometry,
                // Absolute: the fitted model.toml names it, and a relative
                // path there would be read relative to that file.
                &std::fs::canonicalize(out)
                    .map_err(|e| Error::io(out, e))?
                    .join("flow_baseline.csv"),
                &BaselineOptions {
                    seed: a.seed,
                    ..BaselineOptions::default()
                },
            )?;
            notes.extend(b.notes);
            b.scenario
        }
    };
    // Fit on the first half, judge on the second; the simulator makes
    // recordings as long as one half.
    let timing = timing_of(&scenario);
    let half_pulses = (((t1 - t0) as f64 / 2.0) / timing.period_us).floor();
    if half_pulses < 20.0 {
        return Err(Error::analysis(format!(
            "{}: recording shorter than 40 pulses",
            measured.display()
        )));
    }
    let split = timing.first_pulse_us
        + (timing.assign(t0).unwrap_or(0) as f64 + half_pulses) * timing.period_us;
    // Every objective evaluation simulates one block: its length is what
    // the search costs, so it is capped (`--block-pulses`).
    let block_pulses = half_pulses.min(a.block_pulses as f64);
    let block_us = block_pulses * timing.period_us;
    // The two blocks in one pass, without a copy of the whole recording.
    let (mut fit_ev, mut hold_ev) = (EventChunk::default(), EventChunk::default());
    for e in events.iter() {
        let t = e.t as f64;
        if t >= split - block_us && t < split {
            fit_ev.push(e.t, e.x, e.y, e.p);
        } else if t >= split && t < split + block_us {
            hold_ev.push(e.t, e.x, e.y, e.p);
        }
    }
    drop(events);
    notes.push(format!(
        "fit on {block_pulses} pulses before t = {split:.0} us, judged on the {block_pulses} after"
    ));
    let mut sc = scenario.clone();
    sc.duration_s = (block_us + timing.first_pulse_us) * 1e-6;
    let standard = a.model.is_none();
    let mut start_model = active_effects(&sc);
    let mut sim = SceneSimulator::new(sc.without_effects())?.with_cancel(cancel.clone());
    // Against the standard sensor: the measured rate scales its noise, and
    // every simulation is moved to the measured median latency.
    let event_rate_hz = fit_ev.len() as f64 / (block_us * 1e-6);
    let pixels = geometry.width as f64 * geometry.height as f64;
    if standard {
        let median = median_event_latency(&fit_ev, &timing);
        sim = sim.with_latency_median(Some(median));
        start_model = standard_effects(&StandardSensor::default(), event_rate_hz, pixels);
        notes.push(format!(
            "standard sensor: latency spread {:.0} us, background noise {:.1} % of events; median latency {:.1} us refitted with every simulation",
            StandardSensor::default().latency_spread_us,
            100.0 * StandardSensor::default().noise_fraction,
            median
        ));
    }
    let cluster = ClusterParams {
        radius: ClusterParams::radius_for_image_diameter(sc.optics.particle_diameter_px),
        ..ClusterParams::default()
    };
    let recording = |ev: EventChunk| -> Result<Recording> {
        let particles = particles_of(&ev, &timing, &cluster)?;
        Ok(Recording {
            events: ev,
            particles,
            tracks: None,
        })
    };
    cancel.check()?;
    let fit = recording(fit_ev)?;
    let hold = recording(hold_ev)?;
    let mut cfg = sim.signature_config();
    let lat = signatures_of(&cfg, &fit)?;
    let lat = lat
        .histogram("latency")
        .ok_or_else(|| Error::analysis("latency signature"))?;
    cfg.burst_window_us = Some(if standard {
        // Off-burst = the quietest quarter of the period: background and
        // hot pixels, not the tails of the latency distribution.
        quiet_complement(lat, 0.25)?
    } else {
        burst_window(lat, 0.95)?
    });

    let opts = WorkflowOptions {
        replicates: a.replicates,
        max_evaluations: a.evaluations,
        max_effects: a.max_effects,
        seed: a.seed,
        ..WorkflowOptions::default()
    };
    let result = if standard {
        let sopts = StandardOptions {
            replicates: a.replicates,
            evaluations: a.evaluations,
            max_effects: a.max_effects,
            seed: a.seed,
            ..StandardOptions::default()
        };
        standard_check(
            &sim,
            &cfg,
            &fit,
            &hold,
            &start_model,
            event_rate_hz,
            pixels,
            &sopts,
        )?
    } else {
        run_check(&sim, &cfg, &fit, &hold, &start_model, &opts)?
    };
    write_outputs(
        out,
        &sim,
        &cfg,
        &hold,
        &start_model,
        &result,
        &notes,
        a.seed ^ 0xA5A5,
    )?;
    Ok(ModelCheckRun { result, notes })
}
