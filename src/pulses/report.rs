//! What the pulse analysis reports ([`PulseReport`] and its parts): trigger
//! and estimate results, the pulse's time window, saturation, particle images,
//! the rate map and the pulsed-illumination verdict.

use super::*;

/// How the trigger channels looked and how the train fitted.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct TriggerReport {
    /// Every trigger channel seen, sorted by channel id.
    pub channels: Vec<timing::ChannelSummary>,
    /// The fit of the channel used (absent when pulses were estimated).
    pub fit: Option<timing::TriggerFit>,
}

/// How the period was estimated from events.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct EstimateReport {
    /// Band of pulse frequencies searched (Hz, low, high).
    pub search_hz: (f64, f64),
    /// Warm-up estimate (periodogram + epoch folding).
    pub warmup: Periodicity,
    /// Blocks whose phase entered the final fit.
    pub blocks_used: usize,
    /// RMS of block phases about the fitted line (µs).
    pub phase_residual_rms_us: f64,
    /// The known onset latency subtracted from the leading edge
    /// (`onset_latency_us`; 0 when not given).
    pub onset_latency_subtracted_us: f64,
}

/// One time block of the recording.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct TimeWindow {
    /// Start of the block (µs, sensor clock).
    pub t_start_us: i64,
    /// End of the block (µs, sensor clock).
    pub t_end_us: i64,
    /// Events in the block.
    pub events: u64,
    /// Event rate in the block (ev/s).
    pub rate_hz: f64,
    /// Events in runs sharing (row, timestamp), any size ≥ 2.
    pub shared_fraction: f64,
    /// Events in runs of ≥ LARGE_GROUP sharing (row, timestamp).
    pub large_group_fraction: f64,
    /// Events above the random floor of this block's latency histogram.
    pub burst_fraction: f64,
    /// The block is flagged as readout-saturated: many large (row, timestamp)
    /// runs and a burst fraction well below the recording's median.
    pub saturated: bool,
}

/// Readout-saturation measures.
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
pub struct SaturationReport {
    /// Number of runs of each size (index = events sharing one (row, t);
    /// the last bin collects larger runs).
    pub group_sizes: Vec<u64>,
    /// Fraction of all events in runs of ≥ LARGE_GROUP sharing (row, timestamp).
    pub large_group_fraction: f64,
    /// Fraction of events in flagged time windows.
    pub saturated_event_fraction: f64,
    /// The time blocks, in order.
    pub windows: Vec<TimeWindow>,
}

/// Particle-image statistics from per-pulse pseudo-images (paper App. A).
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
pub struct ParticleImageReport {
    /// Pulses whose events were imaged.
    pub pulses_sampled: u64,
    /// Connected-pixel clusters per sensor pixel per pulse.
    pub ppp: f64,
    /// sqrt(mean cluster area) (px).
    pub mean_image_size_px: f64,
    /// Events per cluster per pulse (noise events form clusters too).
    pub events_per_particle: f64,
}

/// Event-rate map and hot pixels.
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
pub struct RateMapReport {
    /// Sensor width (px).
    pub width: u16,
    /// Sensor height (px).
    pub height: u16,
    /// Mean over pixels with at least one event (ev/(pixel·s)).
    pub mean_active_rate_hz: f64,
    /// Highest pixel rate (ev/(pixel·s)).
    pub max_rate_hz: f64,
    /// Rate above which a pixel counts as hot (ev/(pixel·s)).
    pub hot_threshold_hz: f64,
    /// The hottest pixels, by rate, highest first (a bounded list).
    pub hot_pixels: Vec<diagnostics::HotPixel>,
    /// Events per pixel per second, row-major `height × width` (not in JSON;
    /// written as `rate_map.npy` / `.csv` by the CLI).
    #[serde(skip)]
    pub rate: Vec<f32>,
}

/// Is the recording pulsed at all? The test behind the verdict.
///
/// A pulsed light sheet makes the particles fire within a latency window
/// that is a fraction of the period, every pulse; events of anything else
/// (noise, a scene under steady light) fall anywhere in the period. So, in
/// the latency histogram (events folded on the pulse train, from triggers
/// or estimated):
///
/// 1. **Contrast** ≥ `MIN_PULSED_CONTRAST`: the event density inside the
///    burst window (the shortest interval holding 95 % of the excess over
///    the floor) is at least twice that outside, i.e. inside the window the
///    events locked to the pulses at least equal the random ones. A scene
///    without pulsed light folded on any period (the best one of a search
///    included) gives 1.0–1.3: its excess is spread over most of the period.
/// 2. **Significance** ≥ `MIN_PULSED_Z`: the excess in the window exceeds
///    the Poisson spread of the random count expected there by that many
///    standard deviations (few events cannot pass by chance).
/// 3. **Locked in time** ≥ `MIN_LOCKED_SHARE`: at least half of the events
///    lie in time blocks (of ≥ 100 events) whose own burst fraction reaches
///    half of the recording's; one flash of the scene folded into the
///    histogram makes a peak, but only in its own block.
///
/// A trigger channel alone does not make a recording pulsed: with triggers
/// the same test runs on the events folded on the trigger train (a
/// camera's frame-exposure triggers are regular, but the events are not
/// locked to them). A saturated readout also fails (its timing no longer
/// follows the pulses) — the error then names the saturation measure.
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
pub struct PulsedVerdict {
    /// The recording passes all three tests.
    pub pulsed: bool,
    /// Event density inside the burst window over that outside (test 1).
    pub burst_contrast: f64,
    /// Burst excess over the random floor in Poisson standard deviations (test 2).
    pub excess_z: f64,
    /// Share of events in time blocks showing the burst (test 3, 0–1).
    pub locked_share: f64,
    /// What failed (empty when pulsed).
    pub reason: String,
}

impl PulsedVerdict {
    /// Apply the test to a latency histogram and the time blocks' burst
    /// fractions (`(events, burst fraction)` per block).
    pub(crate) fn judge(stats: &diagnostics::LatencyStats, blocks: &[(u64, f64)]) -> PulsedVerdict {
        let h = &stats.histogram;
        let n = h.len();
        let total: f64 = h.iter().sum();
        let (w0, w1) = stats.window95_us;
        let (w0, wl) = (w0.max(0.0) as usize, ((w1 - w0).max(0.0) as usize).min(n));
        let inside: f64 = (w0..w0 + wl).map(|i| h[i % n.max(1)]).sum();
        let outside = (total - inside).max(0.0);
        let expected = if wl < n {
            outside / (n - wl) as f64 * wl as f64
        } else {
            inside
        };
        let excess_z = (inside - expected) / expected.max(1.0).sqrt();
        let global = stats.burst_fraction;
        let (mut all, mut locked) = (0u64, 0u64);
        for &(events, burst) in blocks {
            if events >= 100 {
                all += events;
                if burst >= 0.5 * global {
                    locked += events;
                }
            }
        }
        let locked_share = if all > 0 {
            locked as f64 / all as f64
        } else {
            1.0
        };
        let contrast = stats.burst_contrast;
        let mut why = Vec::new();
        if !(contrast >= MIN_PULSED_CONTRAST) {
            why.push(format!(
                "burst contrast {contrast:.2} < {MIN_PULSED_CONTRAST} (events in the burst window per µs against those outside)"
            ));
        }
        if !(excess_z >= MIN_PULSED_Z) {
            why.push(format!(
                "burst excess {excess_z:.1} σ < {MIN_PULSED_Z} σ over the random floor"
            ));
        }
        if !(locked_share >= MIN_LOCKED_SHARE) {
            why.push(format!(
                "only {:.0} % of the events in time blocks showing the burst (< {:.0} %)",
                100.0 * locked_share,
                100.0 * MIN_LOCKED_SHARE
            ));
        }
        PulsedVerdict {
            pulsed: why.is_empty(),
            burst_contrast: contrast,
            excess_z,
            locked_share,
            reason: why.join("; "),
        }
    }
}

/// Result of the pulse stage, serialised flat as `pulses.json`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct PulseReport {
    /// The pulse train (period, first pulse, window offset, source).
    #[serde(flatten)]
    pub timing: PulseTiming,
    /// Peak of the latency histogram (µs after the pulse start).
    pub latency_peak_us: f64,
    /// Full width at half maximum of the latency peak (µs).
    pub latency_fwhm_us: f64,
    /// Shortest latency interval holding 95 % of the burst events (µs, start, end).
    pub latency_window95_us: (f64, f64),
    /// Event density inside the 95 % window over that outside.
    pub burst_contrast: f64,
    /// Fraction of events on the random floor of the latency histogram.
    pub random_event_fraction: f64,
    /// min/max of the smoothed latency histogram: 1 = flat (no pulse structure).
    pub histogram_flatness: f64,
    /// The readout is judged saturated (its timing no longer follows the pulses).
    pub saturated: bool,
    /// Fraction of events sharing (row, timestamp) with others.
    pub saturation_shared_fraction: f64,
    /// Events in the recording.
    pub events: u64,
    /// Fraction of events with ON polarity.
    pub on_fraction: f64,
    /// Time of the first event (µs, sensor clock).
    pub t_first_us: i64,
    /// Time of the last event (µs, sensor clock).
    pub t_last_us: i64,
    /// Duration from first to last event (s).
    pub duration_s: f64,
    /// Mean event rate (ev/s).
    pub event_rate_hz: f64,
    /// Pulses from pulse 0 to the one holding the last event.
    pub pulses: u64,
    /// Events before the window of pulse 0.
    pub unattributed_events: u64,
    /// Trigger channels and the trigger fit.
    pub triggers: TriggerReport,
    /// How the period was estimated (absent when triggers gave the timing).
    pub estimate: Option<EstimateReport>,
    /// The latency histogram (events folded on the pulse train) and its measures.
    pub latency: diagnostics::LatencyStats,
    /// Readout-saturation measures.
    pub saturation: SaturationReport,
    /// Particle-image statistics.
    pub particles: ParticleImageReport,
    /// Event-rate map and hot pixels.
    pub rate_map: RateMapReport,
    /// Event counts per 1 µs from `rate_trace_t0_us` over the first pulses
    /// (figure of the rate with pulse marks).
    pub rate_trace: Vec<u32>,
    /// Time of the first bin of `rate_trace` (µs, sensor clock).
    pub rate_trace_t0_us: i64,
    /// Is the recording pulsed at all ([`PulsedVerdict`]).
    #[serde(default)]
    pub pulsed: PulsedVerdict,
    /// Events with x or y beyond any sensor (damaged data): not in the map.
    #[serde(default)]
    pub off_sensor_events: u64,
    /// Clock jumps met by the caller's [`crate::io::guard::TimeGuard`]
    /// (filled in by the caller; 0 without one).
    #[serde(default)]
    pub time_jumps: u64,
    /// Events and triggers dropped with those jumps.
    #[serde(default)]
    pub time_jump_events: u64,
}

impl PulseReport {
    /// The error of a recording without pulsed light: what was measured,
    /// and how to go on anyway.
    pub(crate) fn not_pulsed_error(&self) -> Error {
        let v = &self.pulsed;
        let how = match self.timing.source {
            PulseSource::Trigger => format!(
                "events folded on the trigger train of channel {} ({:.3} Hz)",
                self.triggers.fit.as_ref().map_or(0, |f| f.channel),
                1e6 / self.timing.period_us
            ),
            PulseSource::Estimated => format!(
                "events folded on the best period found, {:.3} Hz",
                1e6 / self.timing.period_us
            ),
        };
        let sat = if self.saturation.large_group_fraction > SATURATION_GROUP_FRACTION {
            format!(
                "; or the readout saturated ({:.0} % of events in row groups)",
                100.0 * self.saturation.large_group_fraction
            )
        } else {
            String::new()
        };
        Error::analysis(format!(
            "no pulsed illumination: the events show no bursts locked to pulses ({how}: {}){sat}. If the light was pulsed, give its frequency (--pulse-hz, or --trigger-channel for the laser's trigger), or go on anyway with --force-pulses",
            v.reason
        ))
    }
}
