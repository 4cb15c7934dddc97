//! Named scenarios after the paper's experiments (Willert 2023), calibrated
//! so that a water flow gives ~2 and an air flow ~1.3 events per particle
//! per pulse, with the camera's latency, readout and noise effects on.

use super::scenario::*;
use ebptv_io::error::{Error, Result};

/// Preset names with a one-line description.
pub const PRESETS: [(&str, &str); 9] = [
    (
        "demo",
        "640x360, 0.05 s, Lamb–Oseen vortex, 0.01 ppp, 5 kHz: seconds end to end",
    ),
    ("water_jet_2khz", "water jet, full frame 1280x720, 2 kHz"),
    ("water_jet_4khz", "water jet, full frame 1280x720, 4 kHz"),
    ("water_jet_5khz", "water jet, full frame 1280x720, 5 kHz"),
    ("water_jet_10khz", "water jet, ROI 1280x360, 10 kHz"),
    (
        "laminar_bl",
        "laminar boundary layer (air), ROI 320x720, 5 kHz",
    ),
    (
        "turbulent_bl",
        "turbulent boundary layer (air), ROI 1280x320, 10 kHz",
    ),
    (
        "rib_wake",
        "square-rib wake (air), 1280x720, 5 kHz, shedding 35.4 Hz (St 0.145)",
    ),
    (
        "roi_burst",
        "water jet in a 1280x160 ROI at 10 kHz (short latency burst)",
    ),
];

/// Pulse energy giving ~2 events per particle per pulse (water: large,
/// bright particles).
#[ebptv_macros::testkit]
pub(crate) const WATER_ENERGY: f64 = 1.6;
/// Pulse energy giving ~1.3 events per particle per pulse (air: small
/// droplets).
pub(crate) const AIR_ENERGY: f64 = 1.0;

/// The camera's effects as calibrated against the paper (EVK2-HD).
pub(crate) fn camera_effects(s: &mut Scenario) {
    s.pixel.threshold_mismatch = Some(ThresholdMismatch { sigma: 0.1 });
    s.pixel.refractory = Some(Refractory { period_us: 30.0 });
    s.pixel.intensity_latency = Some(IntensityLatency {
        exponent: 0.5,
        reference: 3.0,
    });
    s.pixel.latency_jitter = Some(LatencyJitter { spread_us: 3.0 });
    s.readout.arbiter_saturation = Some(ArbiterSaturation {
        row_time_us: 0.005,
        event_time_us: 0.024,
    });
    s.noise.background_noise = Some(BackgroundNoise { rate_hz: 0.2 });
    s.light.pulse_streaks = Some(PulseStreaks { scale: 1.0 });
}

fn base(
    name: &str,
    width: u32,
    height: u32,
    roi: Option<Roi>,
    pulse_hz: f64,
    energy: f64,
) -> Scenario {
    let mut s = Scenario {
        name: name.into(),
        duration_s: 1.0,
        sensor: Sensor { width, height, roi },
        ..Scenario::default()
    };
    s.light.pulse_hz = pulse_hz;
    s.light.energy = energy;
    s.light.pulse_width_us = if pulse_hz > 6000.0 { 5.0 } else { 10.0 };
    s.light.sawtooth_depth = 0.15;
    s.light.first_pulse_us = 37.0;
    camera_effects(&mut s);
    s
}

fn water_jet(name: &str, pulse_hz: f64, roi: Option<Roi>) -> Scenario {
    let mut s = base(name, 1280, 720, roi, pulse_hz, WATER_ENERGY);
    // ~4 px per pulse on the jet axis at 5 kHz.
    s.flow = FlowSpec::Jet {
        u_center: 20_000.0,
        u_coflow: 1000.0,
        y_center: 360.0,
        half_width: 150.0,
        thickness: 30.0,
    };
    s.seeding = Seeding {
        ppp: 0.0036,
        sheet_thickness: 20.0,
        out_of_plane_rms: 500.0,
        brightness_spread: 0.4,
    };
    s.optics.particle_diameter_px = 1.5;
    s
}

/// The scenario of preset `name`.
pub fn preset(name: &str) -> Result<Scenario> {
    let air_seeding = Seeding {
        ppp: 0.006,
        sheet_thickness: 15.0,
        out_of_plane_rms: 300.0,
        brightness_spread: 0.5,
    };
    let s = match name {
        "demo" => {
            let mut s = base("demo", 640, 360, None, 5000.0, WATER_ENERGY);
            s.duration_s = 0.05;
            s.light.first_pulse_us = 37.0;
            // Peak swirl ~4 px per pulse at r ≈ 1.12 r_c.
            s.flow = FlowSpec::LambOseen {
                x0: 320.0,
                y0: 180.0,
                circulation: 1.2e7,
                core_radius: 60.0,
                u: 0.0,
                v: 0.0,
            };
            s.seeding = Seeding {
                ppp: 0.01,
                sheet_thickness: 20.0,
                out_of_plane_rms: 200.0,
                brightness_spread: 0.4,
            };
            s
        }
        "water_jet_2khz" => water_jet(name, 2000.0, None),
        "water_jet_4khz" => water_jet(name, 4000.0, None),
        "water_jet_5khz" => water_jet(name, 5000.0, None),
        "water_jet_10khz" => water_jet(
            name,
            10_000.0,
            Some(Roi {
                x: 0,
                y: 180,
                width: 1280,
                height: 360,
            }),
        ),
        "roi_burst" => {
            let mut s = water_jet(
                name,
                10_000.0,
                Some(Roi {
                    x: 0,
                    y: 280,
                    width: 1280,
                    height: 160,
                }),
            );
            s.seeding.ppp = 0.003;
            s
        }
        "laminar_bl" => {
            let mut s = base(
                name,
                1280,
                720,
                Some(Roi {
                    x: 480,
                    y: 0,
                    width: 320,
                    height: 720,
                }),
                5000.0,
                AIR_ENERGY,
            );
            s.flow = FlowSpec::BoundaryLayer {
                u_inf: 15_000.0,
                delta: 450.0,
                wall_y: 700.0,
            };
            s.seeding = air_seeding;
            s
        }
        "turbulent_bl" => {
            let mut s = base(
                name,
                1280,
                720,
                Some(Roi {
                    x: 0,
                    y: 200,
                    width: 1280,
                    height: 320,
                }),
                10_000.0,
                AIR_ENERGY,
            );
            s.flow = FlowSpec::Turbulent {
                u_mean: 25_000.0,
                v_mean: 0.0,
                shear: -20.0,
                y_ref: 360.0,
                rms: 2000.0,
                length_scale: 120.0,
                time_scale_s: 0.005,
                n_modes: 16,
                seed: 11,
            };
            s.seeding = air_seeding;
            s
        }
        "rib_wake" => {
            let mut s = base(name, 1280, 720, None, 5000.0, AIR_ENERGY);
            // f = St·U/h = 0.145 · 19 531 / 80 = 35.4 Hz.
            s.flow = FlowSpec::Shedding {
                u_inf: 19_531.0,
                obstacle_x: 0.0,
                y_center: 360.0,
                size: 80.0,
                strouhal: 0.145,
                amplitude: 0.25,
                deficit: 0.5,
                wake_width: 100.0,
            };
            s.seeding = Seeding {
                ppp: 0.004,
                ..air_seeding
            };
            s
        }
        other => {
            return Err(Error::param(
                "preset",
                format!(
                    "unknown preset `{other}`; known: {}",
                    PRESETS.iter().map(|p| p.0).collect::<Vec<_>>().join(", ")
                ),
            ))
        }
    };
    s.validate()?;
    Ok(s)
}

/// All preset names.
#[ebptv_macros::testkit]
pub(crate) fn names() -> Vec<&'static str> {
    PRESETS.iter().map(|p| p.0).collect()
}
