//! The bridge from the model-check search to ebptv's simulator: a base
//! [`Scenario`] whose switchable effects are the candidates, and the same
//! processing (pulse split by the scenario's timing, per-pulse clustering)
//! that the measurement goes through.

use super::signatures::SignatureConfig;
use super::workflow::{EffectSetting, EffectSpec, ParamSpec, Recording, Simulator};
use crate::cluster::{cluster_pulses, ClusterParams, Particle};
use crate::error::{Error, Result};
use crate::events::{EventChunk, Geometry};
use crate::pulses::{PulseEvents, PulseSource, PulseTiming};
use crate::sim::Scenario;

/// The catalogue searched by default, with parameter ranges wide enough for
/// the EVK2-class sensors the project targets. Ranges are in the units of
/// the scenario file (see `crate::sim::scenario`).
pub(crate) fn default_catalogue(base: &Scenario) -> Vec<EffectSpec> {
    let roi = base.roi();
    let pixels = roi.width as f64 * roi.height as f64;
    let p = |name: &str, lo: f64, hi: f64, log: bool| ParamSpec {
        name: name.into(),
        lo,
        hi,
        log,
    };
    let e = |name: &str, params: Vec<ParamSpec>| EffectSpec {
        name: name.into(),
        params,
    };
    vec![
        e(
            "hot_pixels",
            vec![
                p("count", 1.0, (0.02 * pixels).max(2.0), true),
                p("rate_hz", 20.0, 20_000.0, true),
            ],
        ),
        e("background_noise", vec![p("rate_hz", 0.05, 100.0, true)]),
        e("latency_jitter", vec![p("spread_us", 0.5, 60.0, true)]),
        e(
            "intensity_latency",
            vec![
                p("exponent", 0.05, 2.0, false),
                p("reference", 0.5, 20.0, true),
            ],
        ),
        e(
            "arbiter_saturation",
            vec![
                p("row_time_us", 0.001, 0.5, true),
                p("event_time_us", 0.002, 1.0, true),
            ],
        ),
        e("refractory", vec![p("period_us", 1.0, 300.0, true)]),
        e("pulse_streaks", vec![p("scale", 1.0, 100.0, true)]),
        e("threshold_mismatch", vec![p("sigma", 0.02, 0.6, true)]),
        e(
            "rate_limiter",
            vec![
                p("max_rate_ev_s", 1e5, 1e9, true),
                p("window_us", 1.0, 1000.0, true),
            ],
        ),
        e(
            "off_events",
            vec![
                p("threshold", 0.05, 2.0, true),
                p("tau_us", 1.0, 300.0, true),
            ],
        ),
        // The constant rate offset only: the wander (a slow sinusoid of the
        // rate) stays off (see [`NEUTRAL_PARAMETERS`]); over one
        // 100-pulse block it is indistinguishable from an offset.
        e("clock_drift", vec![p("ppm", -500.0, 500.0, false)]),
    ]
}

/// Values of effect parameters that a catalogue entry does not search:
/// the value at which that part of the effect is absent. Filled in by
/// [`SceneSimulator::scenario_with`] when a setting leaves them out.
pub(crate) const NEUTRAL_PARAMETERS: &[(&str, &str, f64)] = &[
    ("clock_drift", "wander_ppm", 0.0),
    ("clock_drift", "wander_period_s", 1.0),
];

/// `set` with the parameters it leaves out taken from
/// [`NEUTRAL_PARAMETERS`].
pub(crate) fn with_neutral_parameters(set: &EffectSetting) -> EffectSetting {
    let mut out = set.clone();
    for &(effect, name, value) in NEUTRAL_PARAMETERS {
        if effect == set.name {
            out.parameters.entry(name.to_string()).or_insert(value);
        }
    }
    out
}

/// Drives `crate::sim` for the search.
pub(crate) struct SceneSimulator {
    base: Scenario,
    catalogue: Vec<EffectSpec>,
    cluster: ClusterParams,
    /// Median event latency (µs after the pulse start) every simulated
    /// recording is moved to; `None` leaves the simulator's own.
    latency_median_us: Option<f64>,
    /// Set: every simulation stops with an error.
    cancel: crate::Cancel,
    /// The particle motions of the scene's seeds: the search simulates
    /// one scene with one seed hundreds of times, only the sensor changed
    /// (`crate::sim::MotionCache`).
    motion: std::sync::Arc<crate::sim::MotionCache>,
}

impl SceneSimulator {
    /// `base` is validated; its effects stay on as the starting model's
    /// fixed part (use `Scenario::without_effects` for an ideal sensor).
    pub(crate) fn new(base: Scenario) -> Result<Self> {
        base.validate()?;
        let cluster = ClusterParams {
            radius: ClusterParams::radius_for_image_diameter(base.optics.particle_diameter_px),
            ..ClusterParams::default()
        };
        Ok(SceneSimulator {
            catalogue: default_catalogue(&base),
            base,
            cluster,
            latency_median_us: None,
            cancel: crate::Cancel::new(),
            motion: Default::default(),
        })
    }

    /// Simulations fail (`cancelled`) once `cancel` is set: a long search
    /// stops at its next simulation.
    pub(crate) fn with_cancel(mut self, cancel: crate::Cancel) -> Self {
        self.cancel = cancel;
        self
    }

    /// Refit the median latency with every simulation: each simulated
    /// recording is moved in time so that the median latency of its events
    /// (µs after their pulse's start) is `median_us`.
    ///
    /// The median latency is a nuisance of every recording (bias settings,
    /// ROI height, readout load), not an effect; but an effect can move it
    /// (a saturated arbiter delays the whole burst, an intensity-dependent
    /// latency delays the faint part). Refitting it with each candidate
    /// keeps it from absorbing the candidate's first-order signature in the
    /// baseline. A common shift of all event times is the same as a change
    /// of the fixed latency: the readout is time-invariant, and the noise
    /// is uniform in time.
    pub(crate) fn with_latency_median(mut self, median_us: Option<f64>) -> Self {
        self.latency_median_us = median_us.filter(|m| m.is_finite());
        self
    }

    /// The scenario-only variant of this simulator (same catalogue, same
    /// latency refit) over another base scenario.
    pub(crate) fn with_base(&self, base: Scenario) -> Result<Self> {
        let mut s = SceneSimulator::new(base)?;
        // The measurement's processing stays the same for every variant.
        s.cluster = self.cluster.clone();
        Ok(s.with_catalogue(self.catalogue.clone())
            .with_latency_median(self.latency_median_us)
            .with_cancel(self.cancel.clone()))
    }

    /// Restrict or reorder the catalogue (names must be known effects).
    pub(crate) fn with_catalogue(mut self, catalogue: Vec<EffectSpec>) -> Self {
        self.catalogue = catalogue;
        self
    }

    pub(crate) fn base(&self) -> &Scenario {
        &self.base
    }

    /// The scenario with `effects` switched on (validated).
    pub(crate) fn scenario_with(&self, effects: &[EffectSetting]) -> Result<Scenario> {
        let mut sc = self.base.clone();
        for e in effects {
            let e = with_neutral_parameters(e);
            sc.set_effect(&e.name, Some(&e.parameters))?;
        }
        sc.validate()?;
        Ok(sc)
    }

    /// Pulse timing of the scenario (the simulator's own clock).
    pub(crate) fn timing(&self) -> PulseTiming {
        timing_of(&self.base)
    }

    /// Signature configuration for this scene (geometry and timing).
    pub(crate) fn signature_config(&self) -> SignatureConfig {
        let g = Geometry::new(
            self.base.sensor.width as u16,
            self.base.sensor.height as u16,
        );
        SignatureConfig::new(g, self.timing())
    }
}

/// The effects switched on in `sc`, as settings.
pub(crate) fn active_effects(sc: &Scenario) -> Vec<EffectSetting> {
    crate::sim::EFFECT_NAMES
        .iter()
        .filter_map(|name| {
            sc.effect_params(name)
                .ok()
                .flatten()
                .map(|parameters| EffectSetting {
                    name: name.to_string(),
                    parameters,
                })
        })
        .collect()
}

/// Pulse timing of a scenario.
pub(crate) fn timing_of(sc: &Scenario) -> PulseTiming {
    PulseTiming {
        period_us: sc.period_us(),
        first_pulse_us: sc.light.first_pulse_us,
        window_offset_us: 0.0,
        source: PulseSource::Trigger,
        pulse_width_us: Some(sc.light.pulse_width_us),
    }
}

/// Split time-ordered events into pulses by `timing` (pulses without
/// events are left out).
///
/// The events of a pulse are copied a run at a time (a run: consecutive
/// events of one pulse), not one by one: the same pulses and events as
/// `pulses_of_reference` (unit tests), which the tests compare it with.
pub(crate) fn pulses_of(events: &EventChunk, timing: &PulseTiming) -> Result<Vec<PulseEvents>> {
    fn copy_run(pulses: &mut [PulseEvents], events: &EventChunk, a: usize, b: usize) {
        let p = &mut pulses.last_mut().expect("a run belongs to a pulse").events;
        p.t.extend_from_slice(&events.t[a..b]);
        p.x.extend_from_slice(&events.x[a..b]);
        p.y.extend_from_slice(&events.y[a..b]);
        p.p.extend_from_slice(&events.p[a..b]);
    }
    let mut pulses: Vec<PulseEvents> = Vec::new();
    // The current run: its first event and its pulse.
    let mut run: Option<(usize, i64)> = None;
    for i in 0..events.len() {
        let k = timing.assign(events.t[i]);
        if let (Some((_, kr)), Some(k)) = (run, k) {
            if kr == k {
                continue;
            }
        }
        if let Some((a, _)) = run.take() {
            copy_run(&mut pulses, events, a, i);
        }
        let Some(k) = k else {
            continue;
        };
        open_pulse(&mut pulses, k, timing)?;
        run = Some((i, k));
    }
    if let Some((a, _)) = run {
        copy_run(&mut pulses, events, a, events.len());
    }
    Ok(pulses)
}

/// Makes pulse `k` the last of `pulses` (events arrive in time order, so
/// a pulse is only ever appended; an earlier one means disorder).
fn open_pulse(pulses: &mut Vec<PulseEvents>, k: i64, timing: &PulseTiming) -> Result<()> {
    if pulses.last().map(|p| p.index) == Some(k) {
        return Ok(());
    }
    if pulses.last().is_some_and(|p| p.index > k) {
        return Err(Error::analysis(
            "events are not in time order: cannot split them into pulses",
        ));
    }
    pulses.push(PulseEvents {
        index: k,
        start_us: timing.pulse_start(k),
        events: EventChunk::default(),
    });
    Ok(())
}

/// [`pulses_of`] event by event: the reference it is tested against
/// (unit tests).
#[cfg(feature = "testkit")]
pub(crate) fn pulses_of_reference(
    events: &EventChunk,
    timing: &PulseTiming,
) -> Result<Vec<PulseEvents>> {
    let mut pulses: Vec<PulseEvents> = Vec::new();
    for i in 0..events.len() {
        let Some(k) = timing.assign(events.t[i]) else {
            continue;
        };
        open_pulse(&mut pulses, k, timing)?;
        let p = pulses.last_mut().expect("pushed above");
        p.events
            .push(events.t[i], events.x[i], events.y[i], events.p[i]);
    }
    Ok(pulses)
}

/// Split time-ordered events into pulses by `timing` and cluster them.
pub(crate) fn particles_of(
    events: &EventChunk,
    timing: &PulseTiming,
    params: &ClusterParams,
) -> Result<Vec<Particle>> {
    let pulses = pulses_of(events, timing)?;
    Ok(cluster_pulses(&pulses, params)?
        .into_iter()
        .flatten()
        .collect())
}

impl Simulator for SceneSimulator {
    fn catalogue(&self) -> Vec<EffectSpec> {
        self.catalogue.clone()
    }

    fn simulate(&self, effects: &[EffectSetting], seed: u64) -> Result<Recording> {
        self.cancel.check()?;
        let sc = self.scenario_with(effects)?;
        let out = crate::sim::simulate_with(&sc, seed, &self.motion)?;
        let timing = timing_of(&sc);
        let mut particles = particles_of(&out.events, &timing, &self.cluster)?;
        let mut events = out.events;
        if let Some(target) = self.latency_median_us {
            let m = median_event_latency(&events, &timing);
            if m.is_finite() {
                let shift = (target - m).round() as i64;
                events.t.iter_mut().for_each(|t| *t += shift);
                particles
                    .iter_mut()
                    .for_each(|p| p.first_latency_us += shift as f32);
            }
        }
        Ok(Recording {
            events,
            particles,
            tracks: None,
        })
    }
}

/// Median time of the events after the start of their pulse (µs); NaN
/// without events inside a pulse.
pub(crate) fn median_event_latency(events: &EventChunk, timing: &PulseTiming) -> f64 {
    let mut l: Vec<f64> = events
        .t
        .iter()
        .filter_map(|&t| timing.assign(t).map(|k| t as f64 - timing.pulse_start(k)))
        .collect();
    if l.is_empty() {
        return f64::NAN;
    }
    let mid = l.len() / 2;
    *l.select_nth_unstable_by(mid, f64::total_cmp).1
}
