//! The scenario: everything the simulator needs, as one serde/TOML value.
//!
//! Sections mirror the physical chain: `sensor` (geometry, ROI) → `flow` →
//! `seeding` → `light` → `optics` → `pixel` → `readout` → `noise`, plus the
//! recording (`duration_s`, `triggers`). Every section has defaults, so a
//! scenario file only states what differs from the calibrated defaults.
//!
//! Sensor and readout effects that the model-check workflow searches over are
//! `Option`s: `None` means the effect is exactly absent (not "small"). They
//! live in the section where the physics happens, and are also reachable by
//! name through [`Scenario::effect_params`] / [`Scenario::set_effect`] so a
//! fitting loop need not know the layout:
//!
//! | name                 | section  | parameters                          |
//! |----------------------|----------|-------------------------------------|
//! | `hot_pixels`         | noise    | `count`, `rate_hz`                  |
//! | `background_noise`   | noise    | `rate_hz` (per pixel)               |
//! | `latency_jitter`     | pixel    | `spread_us`                         |
//! | `intensity_latency`  | pixel    | `exponent`, `reference`             |
//! | `refractory`         | pixel    | `period_us`                         |
//! | `threshold_mismatch` | pixel    | `sigma`                             |
//! | `off_events`         | pixel    | `threshold`, `tau_us`               |
//! | `arbiter_saturation` | readout  | `row_time_us`, `event_time_us`      |
//! | `rate_limiter`       | readout  | `max_rate_ev_s`, `window_us`        |
//! | `pulse_streaks`      | light    | `scale`                             |
//! | `clock_drift`        | light    | `ppm`, `wander_ppm`, `wander_period_s` |

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use ebptv_io::error::{Error, Result};

/// The most particles a scenario may seed. A simulation holds ~1.8 KB per
/// particle (state, random stream, images, events and truth of the pulse in
/// flight; measured: 2.2 GB for 1.26 M particles), so this caps it at
/// ~3.5 GB. A 2048 x 2048 sensor reaches it at ~0.3 particles per pixel,
/// far denser than PTV images are.
pub(crate) const MAX_PARTICLES: usize = 2_000_000;

/// Most noise events (background and hot pixels) of one simulated block,
/// which are drawn at once: 10^10 events/s at the usual 2 ms blocks, ten
/// times what the fastest event sensors read out.
const MAX_NOISE_PER_BLOCK: f64 = 2e7;

/// A complete simulation scenario.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Scenario {
    /// Free-text name (presets use their preset name).
    pub name: String,
    /// Recording length (s).
    pub duration_s: f64,
    /// Sensor geometry and region of interest.
    pub sensor: Sensor,
    /// The velocity field.
    pub flow: FlowSpec,
    /// Particle seeding.
    pub seeding: Seeding,
    /// The pulsed light sheet.
    pub light: Light,
    /// Imaging optics.
    pub optics: Optics,
    /// The event pixel.
    pub pixel: Pixel,
    /// Readout effects.
    pub readout: Readout,
    /// Noise sources.
    pub noise: Noise,
    /// Trigger recording.
    pub triggers: Triggers,
}

/// Sensor geometry and region of interest.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Sensor {
    /// Full sensor size (px); the file geometry.
    pub width: u32,
    /// Full sensor height (px).
    pub height: u32,
    /// Active region; `None` = full frame. Events only come from here, and
    /// the readout's load (and so its latency) scales with its row count.
    pub roi: Option<Roi>,
}

/// A rectangular region of the sensor (px).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Roi {
    /// Left column.
    pub x: u32,
    /// Top row.
    pub y: u32,
    /// Width.
    pub width: u32,
    /// Height.
    pub height: u32,
}

/// The velocity field. All lengths in px, velocities in px/s, time in s.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case", deny_unknown_fields)]
pub enum FlowSpec {
    /// u = (u, v) everywhere.
    Uniform {
        /// x velocity (px/s).
        u: f64,
        /// y velocity (px/s).
        v: f64,
    },
    /// Lamb–Oseen vortex (steady core) at (x0, y0) on a uniform background.
    LambOseen {
        /// Core centre x (px).
        x0: f64,
        /// Core centre y (px).
        y0: f64,
        /// Circulation Γ (px²/s); positive = counter-clockwise in (x, y).
        circulation: f64,
        /// Core radius r_c (px): u_θ = Γ/(2πr)·(1 − exp(−r²/r_c²)).
        core_radius: f64,
        /// Background x velocity (px/s).
        #[serde(default)]
        u: f64,
        /// Background y velocity (px/s).
        #[serde(default)]
        v: f64,
    },
    /// Plane Poiseuille channel along x between walls y = y0 and y0 + width.
    Poiseuille {
        /// Centre-line velocity (px/s).
        u_max: f64,
        /// Lower wall y (px).
        y0: f64,
        /// Channel width (px).
        width: f64,
    },
    /// Laminar boundary layer (Pohlhausen quartic profile) along x, wall at
    /// y = wall_y, fluid at y < wall_y (above the wall in the image).
    BoundaryLayer {
        /// Free-stream velocity (px/s).
        u_inf: f64,
        /// Layer thickness (px).
        delta: f64,
        /// Wall position y (px).
        wall_y: f64,
    },
    /// Random divergence-free Fourier modes (stream function) on a mean
    /// shear flow u = u_mean + shear·(y − y_ref), v = v_mean. The modes are
    /// drawn from `seed`; their exact Reynolds stresses are known.
    Turbulent {
        /// Mean x velocity at `y_ref` (px/s).
        u_mean: f64,
        /// Mean y velocity (px/s).
        v_mean: f64,
        /// Mean shear du/dy (1/s).
        #[serde(default)]
        shear: f64,
        /// Reference y of the mean shear (px).
        #[serde(default)]
        y_ref: f64,
        /// sqrt((uu + vv)/2) of the fluctuations (px/s).
        rms: f64,
        /// Typical wavelength (px).
        length_scale: f64,
        /// Decorrelation time of the modes in the convected frame (s).
        time_scale_s: f64,
        /// Number of Fourier modes.
        n_modes: u32,
        /// Seed of the modes.
        seed: u64,
    },
    /// Plane jet-like shear layers: u = u_coflow + (u_center − u_coflow)·
    /// ½(1 + tanh((half_width − |y − y_center|)/thickness)).
    Jet {
        /// Centre-line velocity (px/s).
        u_center: f64,
        /// Co-flow velocity (px/s).
        u_coflow: f64,
        /// Jet axis y (px).
        y_center: f64,
        /// Half width (px).
        half_width: f64,
        /// Shear-layer thickness (px).
        thickness: f64,
    },
    /// Periodic vortex shedding behind an obstacle of size `size` at
    /// (obstacle_x, y_center): f = St·u_inf/size, a wake deficit and a
    /// travelling wave of the stream function (divergence-free, exact).
    Shedding {
        /// Free-stream velocity (px/s).
        u_inf: f64,
        /// Obstacle x (px).
        obstacle_x: f64,
        /// Wake centre line y (px).
        y_center: f64,
        /// Obstacle size (px).
        size: f64,
        /// Strouhal number St.
        strouhal: f64,
        /// Peak cross-stream velocity of the wave, as a fraction of u_inf.
        amplitude: f64,
        /// Relative velocity deficit on the wake centre line.
        deficit: f64,
        /// Gaussian half-width of the wake (px).
        wake_width: f64,
    },
    /// A user's steady field on a regular grid: CSV with header `x,y,u,v`
    /// (px, px/s), bilinear interpolation, edge values outside.
    Gridded {
        /// The CSV file.
        path: PathBuf,
        /// Multiplies u and v (unit conversion).
        #[serde(default = "one")]
        scale: f64,
    },
}

fn one() -> f64 {
    1.0
}

/// Particles.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Seeding {
    /// Particles in the light sheet per ROI pixel.
    pub ppp: f64,
    /// Light-sheet thickness (px-equivalent units, same as out-of-plane
    /// motion). Particles live in a slab 1.5 sheet thicknesses deep.
    pub sheet_thickness: f64,
    /// Out-of-plane velocity spread (std dev, px/s): particles leave and
    /// enter the sheet.
    pub out_of_plane_rms: f64,
    /// Log-normal spread (σ of ln) of particle brightness (median 1).
    pub brightness_spread: f64,
}

/// Pulsed light sheet.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Light {
    /// Pulse repetition rate (Hz).
    pub pulse_hz: f64,
    /// Width of the pulse between half-rise and half-fall (µs).
    pub pulse_width_us: f64,
    /// Rise time (µs).
    pub rise_us: f64,
    /// Fall time (µs).
    pub fall_us: f64,
    /// Peak-to-peak relative saw-tooth modulation of the laser power.
    pub sawtooth_depth: f64,
    /// Frequency of the saw-tooth modulation (Hz).
    pub sawtooth_hz: f64,
    /// Signal of a median particle fully on one pixel, relative to the
    /// pixel's background (dimensionless; sets events per particle).
    pub energy: f64,
    /// Start of pulse 0 (µs).
    pub first_pulse_us: f64,
    /// Particle motion during the pulse smears the image (effect
    /// `pulse_streaks`); `None` = image at the pulse start position.
    pub pulse_streaks: Option<PulseStreaks>,
    /// The laser's clock runs at a different rate from the camera's
    /// (effect `clock_drift`); `None` = one common clock.
    pub clock_drift: Option<ClockDrift>,
}

/// Laser clock against camera clock. The laser fires pulse k at
/// τ_k = k·period on its own clock; in camera time (events, triggers,
/// truth) it starts at `first_pulse_us + τ_k + δ(τ_k)` with
/// δ(τ) = 10⁻⁶·(ppm·τ + wander_ppm·P/2π·(1 − cos 2πτ/P)), P the wander
/// period: a constant rate offset plus a slow sinusoidal wander of the
/// rate (±wander_ppm), as two free-running crystal oscillators do. The
/// pulse period seen by the camera is period·(1 + 10⁻⁶·ppm) on average.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ClockDrift {
    /// Constant rate offset (parts per million; positive = laser slow).
    pub ppm: f64,
    /// Amplitude of the rate's sinusoidal wander (ppm).
    pub wander_ppm: f64,
    /// Period of the wander (s).
    pub wander_period_s: f64,
}

impl ClockDrift {
    /// δ(τ) (µs) for laser time τ (µs since pulse 0).
    pub(crate) fn offset_us(&self, tau_us: f64) -> f64 {
        let p = self.wander_period_s * 1e6;
        let wander = self.wander_ppm * p / std::f64::consts::TAU
            * (1.0 - (std::f64::consts::TAU * tau_us / p).cos());
        1e-6 * (self.ppm * tau_us + wander)
    }
}

/// Particle streaks during each pulse.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PulseStreaks {
    /// Multiplies the physical streak length (1 = physical).
    pub scale: f64,
}

/// Imaging optics.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Optics {
    /// e⁻² diameter of the Gaussian particle image (px).
    pub particle_diameter_px: f64,
}

/// The event pixel (log-intensity contrast detector).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Pixel {
    /// ON contrast threshold (log-intensity step).
    pub contrast_threshold: f64,
    /// Fixed part of the latency (comparator, handshake) (µs).
    pub latency_us: f64,
    /// Photoreceptor time constant at the reference signal (µs).
    pub tau_us: f64,
    /// Cap on ON events of one pixel per pulse.
    pub max_events_per_pulse: u32,
    /// Per-pixel threshold scatter (fixed pattern); `None` = off.
    pub threshold_mismatch: Option<ThresholdMismatch>,
    /// Refractory period after each event; `None` = off.
    pub refractory: Option<Refractory>,
    /// Latency growing at low intensity; `None` = off.
    pub intensity_latency: Option<IntensityLatency>,
    /// Random latency jitter; `None` = off.
    pub latency_jitter: Option<LatencyJitter>,
    /// OFF events as the light decays; `None` = off.
    pub off_events: Option<OffEvents>,
}

/// Per-pixel threshold scatter.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ThresholdMismatch {
    /// Relative std dev of the per-pixel threshold (fixed pattern).
    pub sigma: f64,
}

/// Refractory period.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Refractory {
    /// A pixel cannot fire again within this time after an event (µs).
    pub period_us: f64,
}

/// Intensity-dependent latency.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct IntensityLatency {
    /// τ = tau_us·(reference / signal)^exponent.
    pub exponent: f64,
    /// Signal-to-background ratio at which τ = tau_us.
    pub reference: f64,
}

/// Random latency jitter: one Gaussian delay per visit (a pixel's events of
/// one polarity at one pulse), shared by the visit's events.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LatencyJitter {
    /// Std dev of the Gaussian delay added to each visit's events (µs).
    pub spread_us: f64,
}

/// OFF events after each pulse.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OffEvents {
    /// OFF contrast threshold.
    pub threshold: f64,
    /// Decay time constant after the pulse (µs).
    pub tau_us: f64,
}

/// Readout effects.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Readout {
    /// Row-arbiter saturation; `None` = off.
    pub arbiter_saturation: Option<ArbiterSaturation>,
    /// Event-rate limiter; `None` = off.
    pub rate_limiter: Option<RateLimiter>,
}

/// Row-arbiter saturation.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ArbiterSaturation {
    /// Time to grant one row (µs).
    pub row_time_us: f64,
    /// Time to read one event of a granted row (µs).
    pub event_time_us: f64,
}

/// Event-rate limiter.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RateLimiter {
    /// Events per second allowed; the excess of each window is dropped.
    pub max_rate_ev_s: f64,
    /// Window length (µs).
    pub window_us: f64,
}

/// Noise sources.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Noise {
    /// Hot pixels; `None` = off.
    pub hot_pixels: Option<HotPixels>,
    /// Background activity; `None` = off.
    pub background_noise: Option<BackgroundNoise>,
}

/// Hot pixels.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HotPixels {
    /// Number of hot pixels (random positions in the ROI, fixed by the seed).
    pub count: u32,
    /// Event rate of each hot pixel (Hz), ON polarity.
    pub rate_hz: f64,
}

/// Background activity.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BackgroundNoise {
    /// Background-activity rate per pixel (Hz), ON and OFF equally.
    pub rate_hz: f64,
}

/// External-trigger recording of the laser TTL (both edges).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Triggers {
    /// Whether trigger events are recorded.
    pub enabled: bool,
    /// Trigger channel id.
    pub channel: u8,
}

impl Default for Sensor {
    fn default() -> Self {
        Sensor {
            width: 1280,
            height: 720,
            roi: None,
        }
    }
}
impl Default for FlowSpec {
    fn default() -> Self {
        FlowSpec::Uniform {
            u: 10_000.0,
            v: 0.0,
        }
    }
}
impl Default for Seeding {
    fn default() -> Self {
        Seeding {
            ppp: 0.005,
            sheet_thickness: 20.0,
            out_of_plane_rms: 0.0,
            brightness_spread: 0.4,
        }
    }
}
impl Default for Light {
    fn default() -> Self {
        Light {
            pulse_hz: 5000.0,
            pulse_width_us: 10.0,
            rise_us: 3.0,
            fall_us: 3.0,
            sawtooth_depth: 0.0,
            sawtooth_hz: 50_000.0,
            energy: 6.0,
            first_pulse_us: 50.0,
            pulse_streaks: None,
            clock_drift: None,
        }
    }
}
impl Default for Optics {
    fn default() -> Self {
        Optics {
            particle_diameter_px: 1.3,
        }
    }
}
impl Default for Pixel {
    fn default() -> Self {
        Pixel {
            contrast_threshold: 0.25,
            latency_us: 12.0,
            tau_us: 6.0,
            max_events_per_pulse: 4,
            threshold_mismatch: None,
            refractory: None,
            intensity_latency: None,
            latency_jitter: None,
            off_events: None,
        }
    }
}
impl Default for Triggers {
    fn default() -> Self {
        Triggers {
            enabled: true,
            channel: 1,
        }
    }
}
impl Default for Scenario {
    fn default() -> Self {
        Scenario {
            name: "custom".into(),
            duration_s: 0.1,
            sensor: Sensor::default(),
            flow: FlowSpec::default(),
            seeding: Seeding::default(),
            light: Light::default(),
            optics: Optics::default(),
            pixel: Pixel::default(),
            readout: Readout::default(),
            noise: Noise::default(),
            triggers: Triggers::default(),
        }
    }
}

/// Names of the switchable effects, in catalogue order.
/// One table of the switchable effects (name, where it lives in the
/// scenario, its parameters) from which both [`Scenario::effect_params`]
/// and [`Scenario::set_effect`] are generated, so the two cannot drift.
macro_rules! effect_table {
    ($($name:literal => $sec:ident . $field:ident : $ty:ident { $($p:ident),+ }),+ $(,)?) => {
        /// Parameters of effect `name` (`None` when it is off). Errors on an
        /// unknown name.
        pub fn effect_params(&self, name: &str) -> Result<Option<BTreeMap<String, f64>>> {
            Ok(match name {
                $($name => self.$sec.$field.as_ref().map(|e| {
                    let mut m = BTreeMap::new();
                    $(m.insert(stringify!($p).to_string(), EffectParam::to_f64(e.$p));)+
                    m
                }),)+
                other => return Err(unknown_effect(other)),
            })
        }

        /// Switch effect `name` on with `params` (every parameter required),
        /// or off with `None`. Does not validate the values (call `validate`).
        pub fn set_effect(&mut self, name: &str, params: Option<&BTreeMap<String, f64>>) -> Result<()> {
            let get = |k: &str| -> Result<f64> {
                params
                    .and_then(|p| p.get(k).copied())
                    .ok_or_else(|| Error::param(format!("{name}.{k}"), "missing parameter"))
            };
            match name {
                $($name => {
                    self.$sec.$field = match params {
                        Some(_) => Some($ty { $($p: EffectParam::from_f64(get(stringify!($p))?)),+ }),
                        None => None,
                    };
                })+
                other => return Err(unknown_effect(other)),
            }
            Ok(())
        }
    };
}

/// Names of the optional effects a scenario can switch on.
pub const EFFECT_NAMES: [&str; 11] = [
    "hot_pixels",
    "background_noise",
    "latency_jitter",
    "intensity_latency",
    "arbiter_saturation",
    "refractory",
    "pulse_streaks",
    "threshold_mismatch",
    "rate_limiter",
    "off_events",
    "clock_drift",
];

fn check(ok: bool, name: &str, why: impl FnOnce() -> String) -> Result<()> {
    if ok {
        Ok(())
    } else {
        Err(Error::param(name, why()))
    }
}

fn positive(v: f64, name: &str) -> Result<()> {
    check(v.is_finite() && v > 0.0, name, || {
        format!("must be a positive number, got {v}")
    })
}

fn non_negative(v: f64, name: &str) -> Result<()> {
    check(v.is_finite() && v >= 0.0, name, || {
        format!("must be zero or positive, got {v}")
    })
}

fn finite(v: f64, name: &str) -> Result<()> {
    check(v.is_finite(), name, || {
        format!("must be a finite number, got {v}")
    })
}

impl Scenario {
    /// An ideal sensor: the scenario with every effect switched off.
    pub fn without_effects(&self) -> Scenario {
        let mut s = self.clone();
        for name in EFFECT_NAMES {
            s.set_effect(name, None).expect("known effect name");
        }
        s
    }

    /// The active region (the full frame when no ROI is set).
    pub fn roi(&self) -> Roi {
        self.sensor.roi.unwrap_or(Roi {
            x: 0,
            y: 0,
            width: self.sensor.width,
            height: self.sensor.height,
        })
    }

    /// The pulse period (µs).
    pub fn period_us(&self) -> f64 {
        1e6 / self.light.pulse_hz
    }

    /// Start of pulse `k` in camera time (µs): `first_pulse_us + k·period`,
    /// moved by the `clock_drift` effect when it is on.
    pub(crate) fn pulse_start_us(&self, k: u64) -> f64 {
        let tau = k as f64 * self.period_us();
        let drift = self.light.clock_drift.map_or(0.0, |c| c.offset_us(tau));
        self.light.first_pulse_us + tau + drift
    }

    /// Number of pulses starting within the recording (pulse starts
    /// increase with k: validation keeps the drift's rate change far
    /// below 100 %).
    pub fn pulse_count(&self) -> u64 {
        let end = self.duration_s * 1e6;
        if self.light.first_pulse_us >= end {
            return 0;
        }
        let mut n = ((end - self.light.first_pulse_us) / self.period_us()).ceil() as u64;
        while n > 0 && self.pulse_start_us(n - 1) >= end {
            n -= 1;
        }
        while self.pulse_start_us(n) < end {
            n += 1;
        }
        n
    }

    /// Refuse impossible values, naming the field.
    pub fn validate(&self) -> Result<()> {
        positive(self.duration_s, "duration_s")?;
        check(self.duration_s <= 3600.0, "duration_s", || {
            format!("{} s is beyond one hour", self.duration_s)
        })?;
        let s = &self.sensor;
        check(s.width > 0 && s.width <= 4096, "sensor.width", || {
            format!("must be in 1..=4096, got {}", s.width)
        })?;
        check(s.height > 0 && s.height <= 4096, "sensor.height", || {
            format!("must be in 1..=4096, got {}", s.height)
        })?;
        if let Some(r) = s.roi {
            check(r.width > 0, "sensor.roi.width", || {
                "must be positive".into()
            })?;
            check(r.height > 0, "sensor.roi.height", || {
                "must be positive".into()
            })?;
            check(r.x + r.width <= s.width, "sensor.roi", || {
                format!(
                    "x {} + width {} exceeds sensor width {}",
                    r.x, r.width, s.width
                )
            })?;
            check(r.y + r.height <= s.height, "sensor.roi", || {
                format!(
                    "y {} + height {} exceeds sensor height {}",
                    r.y, r.height, s.height
                )
            })?;
        }
        self.validate_flow()?;
        let sd = &self.seeding;
        check(
            sd.ppp.is_finite() && sd.ppp > 0.0 && sd.ppp <= 1.0,
            "seeding.ppp",
            || format!("particles per pixel must be in (0, 1], got {}", sd.ppp),
        )?;
        positive(sd.sheet_thickness, "seeding.sheet_thickness")?;
        non_negative(sd.out_of_plane_rms, "seeding.out_of_plane_rms")?;
        check(
            sd.brightness_spread.is_finite() && (0.0..=3.0).contains(&sd.brightness_spread),
            "seeding.brightness_spread",
            || format!("must be in [0, 3], got {}", sd.brightness_spread),
        )?;
        let l = &self.light;
        check(
            l.pulse_hz.is_finite() && l.pulse_hz > 0.0 && l.pulse_hz <= 1e6,
            "light.pulse_hz",
            || format!("pulse frequency must be in (0, 1 MHz], got {}", l.pulse_hz),
        )?;
        positive(l.pulse_width_us, "light.pulse_width_us")?;
        non_negative(l.rise_us, "light.rise_us")?;
        non_negative(l.fall_us, "light.fall_us")?;
        let period = self.period_us();
        check(
            l.pulse_width_us + 0.5 * (l.rise_us + l.fall_us) < period,
            "light.pulse_width_us",
            || {
                format!(
                "pulse ({} µs plus rise/fall) is not shorter than the pulse period ({:.3} µs at {} Hz)",
                l.pulse_width_us, period, l.pulse_hz
            )
            },
        )?;
        check(l.rise_us <= 2.0 * l.pulse_width_us, "light.rise_us", || {
            "rise time longer than twice the pulse width".into()
        })?;
        check(l.fall_us <= 2.0 * l.pulse_width_us, "light.fall_us", || {
            "fall time longer than twice the pulse width".into()
        })?;
        check(
            l.sawtooth_depth.is_finite() && (0.0..=1.0).contains(&l.sawtooth_depth),
            "light.sawtooth_depth",
            || format!("must be in [0, 1], got {}", l.sawtooth_depth),
        )?;
        positive(l.sawtooth_hz, "light.sawtooth_hz")?;
        positive(l.energy, "light.energy")?;
        non_negative(l.first_pulse_us, "light.first_pulse_us")?;
        if let Some(ps) = l.pulse_streaks {
            non_negative(ps.scale, "light.pulse_streaks.scale")?;
        }
        if let Some(c) = l.clock_drift {
            // Crystal oscillators are within ~±100 ppm; 1000 ppm bounds
            // anything that is still a drift.
            check(
                c.ppm.is_finite() && c.ppm.abs() <= 1000.0,
                "light.clock_drift.ppm",
                || format!("must be within ±1000 ppm, got {}", c.ppm),
            )?;
            check(
                c.wander_ppm.is_finite() && c.wander_ppm.abs() <= 1000.0,
                "light.clock_drift.wander_ppm",
                || format!("must be within ±1000 ppm, got {}", c.wander_ppm),
            )?;
            positive(c.wander_period_s, "light.clock_drift.wander_period_s")?;
        }
        check(
            self.optics.particle_diameter_px.is_finite()
                && self.optics.particle_diameter_px >= 0.1
                && self.optics.particle_diameter_px <= 20.0,
            "optics.particle_diameter_px",
            || {
                format!(
                    "must be in [0.1, 20] px, got {}",
                    self.optics.particle_diameter_px
                )
            },
        )?;
        let n = crate::seeding::particle_count_bound(self);
        check(n <= MAX_PARTICLES as f64, "seeding.ppp", || {
            let r = self.roi();
            format!(
                "{} particles per pixel on {}x{} px seed up to {n:.0} particles, more than {MAX_PARTICLES} (~1.8 KB of memory each); lower the density or the sensor's region",
                self.seeding.ppp, r.width, r.height
            )
        })?;
        let p = &self.pixel;
        check(
            p.contrast_threshold.is_finite()
                && p.contrast_threshold > 0.0
                && p.contrast_threshold < 5.0,
            "pixel.contrast_threshold",
            || format!("must be in (0, 5), got {}", p.contrast_threshold),
        )?;
        non_negative(p.latency_us, "pixel.latency_us")?;
        positive(p.tau_us, "pixel.tau_us")?;
        check(
            p.max_events_per_pulse >= 1 && p.max_events_per_pulse <= 64,
            "pixel.max_events_per_pulse",
            || format!("must be in 1..=64, got {}", p.max_events_per_pulse),
        )?;
        if let Some(m) = p.threshold_mismatch {
            check(
                m.sigma.is_finite() && (0.0..1.0).contains(&m.sigma),
                "pixel.threshold_mismatch.sigma",
                || format!("must be in [0, 1), got {}", m.sigma),
            )?;
        }
        if let Some(r) = p.refractory {
            non_negative(r.period_us, "pixel.refractory.period_us")?;
        }
        if let Some(il) = p.intensity_latency {
            check(
                il.exponent.is_finite() && (0.0..=3.0).contains(&il.exponent),
                "pixel.intensity_latency.exponent",
                || format!("must be in [0, 3], got {}", il.exponent),
            )?;
            positive(il.reference, "pixel.intensity_latency.reference")?;
        }
        if let Some(j) = p.latency_jitter {
            non_negative(j.spread_us, "pixel.latency_jitter.spread_us")?;
        }
        if let Some(o) = p.off_events {
            positive(o.threshold, "pixel.off_events.threshold")?;
            positive(o.tau_us, "pixel.off_events.tau_us")?;
        }
        if let Some(a) = self.readout.arbiter_saturation {
            non_negative(a.row_time_us, "readout.arbiter_saturation.row_time_us")?;
            non_negative(a.event_time_us, "readout.arbiter_saturation.event_time_us")?;
            check(
                a.row_time_us + a.event_time_us > 0.0,
                "readout.arbiter_saturation",
                || "row_time_us and event_time_us cannot both be zero".into(),
            )?;
        }
        if let Some(r) = self.readout.rate_limiter {
            positive(r.max_rate_ev_s, "readout.rate_limiter.max_rate_ev_s")?;
            positive(r.window_us, "readout.rate_limiter.window_us")?;
        }
        if let Some(h) = self.noise.hot_pixels {
            let n = self.roi().width as u64 * self.roi().height as u64;
            check((h.count as u64) <= n, "noise.hot_pixels.count", || {
                format!("{} hot pixels exceed the {} ROI pixels", h.count, n)
            })?;
            non_negative(h.rate_hz, "noise.hot_pixels.rate_hz")?;
        }
        if let Some(b) = self.noise.background_noise {
            non_negative(b.rate_hz, "noise.background_noise.rate_hz")?;
        }
        // The noise events of a block (~2 ms of pulses, or one period when
        // longer) are drawn at once: background at 10^6 Hz per pixel on
        // 640x360 (4.6·10^8 events per block) aborted on the allocation.
        let npix = self.roi().width as f64 * self.roi().height as f64;
        let background = self
            .noise
            .background_noise
            .map_or(0.0, |b| b.rate_hz * npix);
        let hot = self
            .noise
            .hot_pixels
            .map_or(0.0, |h| h.rate_hz * h.count as f64);
        let period = self.period_us();
        let block_s = ((crate::BLOCK_US / period).round().max(1.0) * period) * 1e-6;
        for (name, rate) in [
            ("noise.background_noise.rate_hz", background),
            ("noise.hot_pixels.rate_hz", hot),
            ("noise", background + hot),
        ] {
            check(rate * block_s <= MAX_NOISE_PER_BLOCK, name, || {
                format!(
                    "{rate:.3e} noise events/s are {:.3e} per simulated block of {:.0} µs, more than {MAX_NOISE_PER_BLOCK:.0e} (~16 bytes each in memory)",
                    rate * block_s,
                    block_s * 1e6
                )
            })?;
        }
        Ok(())
    }

    fn validate_flow(&self) -> Result<()> {
        match &self.flow {
            FlowSpec::Uniform { u, v } => {
                finite(*u, "flow.u")?;
                finite(*v, "flow.v")
            }
            FlowSpec::LambOseen {
                x0,
                y0,
                circulation,
                core_radius,
                u,
                v,
            } => {
                finite(*x0, "flow.x0")?;
                finite(*y0, "flow.y0")?;
                finite(*circulation, "flow.circulation")?;
                positive(*core_radius, "flow.core_radius")?;
                finite(*u, "flow.u")?;
                finite(*v, "flow.v")
            }
            FlowSpec::Poiseuille { u_max, y0, width } => {
                finite(*u_max, "flow.u_max")?;
                finite(*y0, "flow.y0")?;
                positive(*width, "flow.width")
            }
            FlowSpec::BoundaryLayer {
                u_inf,
                delta,
                wall_y,
            } => {
                finite(*u_inf, "flow.u_inf")?;
                positive(*delta, "flow.delta")?;
                finite(*wall_y, "flow.wall_y")
            }
            FlowSpec::Turbulent {
                u_mean,
                v_mean,
                shear,
                y_ref,
                rms,
                length_scale,
                time_scale_s,
                n_modes,
                ..
            } => {
                finite(*u_mean, "flow.u_mean")?;
                finite(*v_mean, "flow.v_mean")?;
                finite(*shear, "flow.shear")?;
                finite(*y_ref, "flow.y_ref")?;
                non_negative(*rms, "flow.rms")?;
                positive(*length_scale, "flow.length_scale")?;
                positive(*time_scale_s, "flow.time_scale_s")?;
                check(*n_modes >= 1 && *n_modes <= 4096, "flow.n_modes", || {
                    format!("must be in 1..=4096, got {n_modes}")
                })
            }
            FlowSpec::Jet {
                u_center,
                u_coflow,
                y_center,
                half_width,
                thickness,
            } => {
                finite(*u_center, "flow.u_center")?;
                finite(*u_coflow, "flow.u_coflow")?;
                finite(*y_center, "flow.y_center")?;
                positive(*half_width, "flow.half_width")?;
                positive(*thickness, "flow.thickness")
            }
            FlowSpec::Shedding {
                u_inf,
                obstacle_x,
                y_center,
                size,
                strouhal,
                amplitude,
                deficit,
                wake_width,
            } => {
                positive(*u_inf, "flow.u_inf")?;
                finite(*obstacle_x, "flow.obstacle_x")?;
                finite(*y_center, "flow.y_center")?;
                positive(*size, "flow.size")?;
                positive(*strouhal, "flow.strouhal")?;
                non_negative(*amplitude, "flow.amplitude")?;
                check(
                    deficit.is_finite() && (0.0..=1.5).contains(deficit),
                    "flow.deficit",
                    || format!("must be in [0, 1.5], got {deficit}"),
                )?;
                positive(*wake_width, "flow.wake_width")
            }
            FlowSpec::Gridded { path, scale } => {
                check(!path.as_os_str().is_empty(), "flow.path", || {
                    "empty path".into()
                })?;
                finite(*scale, "flow.scale")
            }
        }
    }

    /// Read and validate a TOML scenario file. A relative `flow.path` is
    /// taken relative to the scenario file's directory.
    pub fn from_toml_file(path: impl AsRef<Path>) -> Result<Scenario> {
        let path = path.as_ref();
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let mut s = Scenario::from_toml_str(&text).map_err(|e| match e {
            Error::InvalidParameter { name, why } => Error::Config {
                path: path.to_path_buf(),
                why: format!("invalid parameter `{name}`: {why}"),
            },
            Error::Config { why, .. } => Error::Config {
                path: path.to_path_buf(),
                why,
            },
            other => other,
        })?;
        if let FlowSpec::Gridded { path: p, .. } = &mut s.flow {
            if p.is_relative() {
                if let Some(dir) = path.parent() {
                    *p = dir.join(&*p);
                }
            }
        }
        Ok(s)
    }

    /// Parse and validate TOML text.
    #[ebptv_macros::testkit]
    pub(crate) fn from_toml_str(text: &str) -> Result<Scenario> {
        let s: Scenario = toml::from_str(text).map_err(|e| Error::Config {
            path: PathBuf::from("<scenario>"),
            why: e.to_string(),
        })?;
        s.validate()?;
        Ok(s)
    }

    /// The scenario as TOML (the format scenario files use).
    pub fn to_toml_string(&self) -> Result<String> {
        toml::to_string_pretty(self)
            .map_err(|e| Error::analysis(format!("cannot serialise scenario: {e}")))
    }

    effect_table! {
        "hot_pixels" => noise.hot_pixels: HotPixels { count, rate_hz },
        "background_noise" => noise.background_noise: BackgroundNoise { rate_hz },
        "latency_jitter" => pixel.latency_jitter: LatencyJitter { spread_us },
        "intensity_latency" => pixel.intensity_latency: IntensityLatency { exponent, reference },
        "arbiter_saturation" => readout.arbiter_saturation: ArbiterSaturation { row_time_us, event_time_us },
        "refractory" => pixel.refractory: Refractory { period_us },
        "pulse_streaks" => light.pulse_streaks: PulseStreaks { scale },
        "threshold_mismatch" => pixel.threshold_mismatch: ThresholdMismatch { sigma },
        "rate_limiter" => readout.rate_limiter: RateLimiter { max_rate_ev_s, window_us },
        "off_events" => pixel.off_events: OffEvents { threshold, tau_us },
        "clock_drift" => light.clock_drift: ClockDrift { ppm, wander_ppm, wander_period_s },
    }
}

fn unknown_effect(name: &str) -> Error {
    Error::param(
        "effect",
        format!(
            "unknown effect `{name}`; known: {}",
            EFFECT_NAMES.join(", ")
        ),
    )
}

/// An effect parameter as the fitting code sees it: a real number. Counts
/// round to the nearest non-negative integer on the way in.
trait EffectParam: Copy {
    fn to_f64(self) -> f64;
    fn from_f64(v: f64) -> Self;
}

impl EffectParam for f64 {
    fn to_f64(self) -> f64 {
        self
    }
    fn from_f64(v: f64) -> Self {
        v
    }
}

impl EffectParam for u32 {
    fn to_f64(self) -> f64 {
        self as f64
    }
    fn from_f64(v: f64) -> Self {
        v.round().max(0.0) as u32
    }
}
