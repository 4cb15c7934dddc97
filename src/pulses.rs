//! Light pulses: timing from triggers or from the events, event-to-pulse
//! assignment, latency and readout-saturation diagnostics.
//!
//! (Design notes to be written with the implementation.)

use serde::{Deserialize, Serialize};

use crate::events::EventChunk;

/// Where the pulse times came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PulseSource {
    Trigger,
    Estimated,
}

/// A regular pulse train: pulse k starts at `first_pulse_us + k * period_us`
/// (sensor clock, µs). Events of pulse k are those in
/// `[start_k + window_offset_us, start_k + window_offset_us + period_us)`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct PulseTiming {
    pub period_us: f64,
    pub first_pulse_us: f64,
    /// Offset of the assignment window from the pulse start (µs); the window
    /// boundary sits where the folded histogram is lowest. May be negative.
    pub window_offset_us: f64,
    pub source: PulseSource,
    /// Pulse width (µs) when known (falling triggers, or the scenario).
    pub pulse_width_us: Option<f64>,
}

impl PulseTiming {
    /// Start time of pulse `k` (µs).
    #[inline]
    pub fn pulse_start(&self, k: i64) -> f64 {
        self.first_pulse_us + k as f64 * self.period_us
    }

    /// Pulse index of an event at time `t_us`, or `None` before pulse 0.
    #[inline]
    pub fn assign(&self, t_us: i64) -> Option<i64> {
        let rel = (t_us as f64 - self.first_pulse_us - self.window_offset_us) / self.period_us;
        if rel < 0.0 {
            None
        } else {
            Some(rel.floor() as i64)
        }
    }
}

/// The events of one pulse, gathered while streaming.
#[derive(Debug, Clone, Default)]
pub struct PulseEvents {
    pub index: i64,
    /// Start of the light pulse (µs, sensor clock).
    pub start_us: f64,
    pub events: EventChunk,
}

/// Options of [`analyze`].
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
pub struct PulseOptions {
    /// Nominal pulse frequency (Hz) when estimating from events.
    pub pulse_hz: Option<f64>,
    /// Search range (Hz) when the frequency is not known exactly.
    pub pulse_hz_range: Option<(f64, f64)>,
    /// Trigger channel to use; `None` = the one carrying a regular train.
    pub trigger_channel: Option<u8>,
    /// Ignore triggers even when present (estimate from events).
    pub ignore_triggers: bool,
}

/// Result of the pulse stage (serialised as `pulses.json`).
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PulseReport {
    pub timing: PulseTiming,
    pub latency_peak_us: f64,
    pub latency_fwhm_us: f64,
    pub saturated: bool,
    /// Fraction of events sharing (row, timestamp) with others.
    pub saturation_shared_fraction: f64,
}

/// One streaming pass over `source`: pulse timing and diagnostics.
pub fn analyze(
    source: &mut dyn crate::io::EventSource,
    opts: &PulseOptions,
) -> crate::Result<PulseReport> {
    let _ = (source, opts);
    Err(crate::Error::analysis("pulse analysis not implemented yet"))
}

/// Stream `source` and hand the events of each pulse, in pulse order, to
/// `on_pulse`. Returns the number of events that could not be attributed.
pub fn split_pulses(
    source: &mut dyn crate::io::EventSource,
    timing: &PulseTiming,
    on_pulse: &mut dyn FnMut(PulseEvents) -> crate::Result<()>,
) -> crate::Result<u64> {
    let _ = (source, timing, on_pulse);
    Err(crate::Error::analysis(
        "pulse splitting not implemented yet",
    ))
}
