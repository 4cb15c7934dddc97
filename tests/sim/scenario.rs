//! Scenario files: presets, TOML round trip, refusal of impossible values
//! with the field named.

use ebptv::sim::presets;
use ebptv::sim::scenario::*;

fn refused(s: &Scenario, field: &str) {
    let e = s
        .validate()
        .expect_err(&format!("{field} should be refused"))
        .to_string();
    assert!(e.contains(field), "error `{e}` does not name `{field}`");
}

#[test]
fn impossible_values_are_refused_naming_the_field() {
    let ok = Scenario::default();
    ok.validate().unwrap();
    let mut s = ok.clone();
    s.light.pulse_hz = -5000.0;
    refused(&s, "light.pulse_hz");
    let mut s = ok.clone();
    s.light.pulse_width_us = 250.0; // period is 200 µs at 5 kHz
    refused(&s, "light.pulse_width_us");
    let mut s = ok.clone();
    s.seeding.ppp = 1.5;
    refused(&s, "seeding.ppp");
    // A dense seeding on a large sensor: 6.3 M particles (~11 GB) are
    // refused before anything is allocated; 0.1 per pixel there is fine.
    let mut s = ok.clone();
    (s.sensor.width, s.sensor.height) = (2048, 2048);
    s.seeding.ppp = 1.0;
    refused(&s, "seeding.ppp");
    s.seeding.ppp = 0.1;
    s.validate().unwrap();
    // Noise no readout delivers (10^6 Hz per pixel: 2.3·10^11 events/s on
    // 640x360) aborted on its allocation; a busy sensor's 100 Hz per pixel
    // (2.3·10^7 events/s) is fine. One hot pixel at 10^12 Hz is refused too.
    let mut s = ok.clone();
    s.noise.background_noise = Some(BackgroundNoise { rate_hz: 1e6 });
    refused(&s, "noise.background_noise.rate_hz");
    s.noise.background_noise = Some(BackgroundNoise { rate_hz: 100.0 });
    s.validate().unwrap();
    let mut s = ok.clone();
    s.noise.hot_pixels = Some(HotPixels {
        count: 1,
        rate_hz: 1e12,
    });
    refused(&s, "noise.hot_pixels.rate_hz");
    // A low pulse rate makes a block one long period: 9·10^7 events/s of
    // noise (allowed at 5 kHz) in a block of 1 s are refused.
    let mut s = ok.clone();
    s.noise.background_noise = Some(BackgroundNoise { rate_hz: 400.0 });
    s.validate().unwrap();
    s.light.pulse_hz = 1.0;
    s.light.pulse_width_us = 10.0;
    refused(&s, "noise.background_noise.rate_hz");
    let mut s = ok.clone();
    s.duration_s = 0.0;
    refused(&s, "duration_s");
    let mut s = ok.clone();
    s.sensor.roi = Some(Roi {
        x: 1000,
        y: 0,
        width: 400,
        height: 100,
    });
    refused(&s, "sensor.roi");
    let mut s = ok.clone();
    s.optics.particle_diameter_px = f64::NAN;
    refused(&s, "optics.particle_diameter_px");
    let mut s = ok.clone();
    s.flow = FlowSpec::LambOseen {
        x0: 0.0,
        y0: 0.0,
        circulation: 1.0,
        core_radius: -1.0,
        u: 0.0,
        v: 0.0,
    };
    refused(&s, "flow.core_radius");
    let mut s = ok.clone();
    s.pixel.refractory = Some(Refractory { period_us: -1.0 });
    refused(&s, "pixel.refractory.period_us");
    let mut s = ok.clone();
    s.noise.hot_pixels = Some(HotPixels {
        count: 10_000_000,
        rate_hz: 1.0,
    });
    refused(&s, "noise.hot_pixels.count");
    let mut s = ok.clone();
    s.readout.arbiter_saturation = Some(ArbiterSaturation {
        row_time_us: 0.0,
        event_time_us: 0.0,
    });
    refused(&s, "readout.arbiter_saturation");
    // The simulator refuses too, before doing anything.
    let mut s = ok;
    s.light.pulse_hz = 0.0;
    assert!(ebptv::sim::simulate(&s, 0).is_err());
}

#[test]
fn presets_validate_and_round_trip_through_toml() {
    assert!(presets::names().len() >= 9);
    for name in presets::names() {
        let s = presets::preset(name).unwrap();
        s.validate().unwrap();
        let text = s.to_toml_string().unwrap();
        let back = Scenario::from_toml_str(&text).unwrap();
        assert_eq!(back, s, "{name}");
    }
    let e = presets::preset("nope").unwrap_err().to_string();
    assert!(e.contains("preset") && e.contains("demo"), "{e}");
}

#[test]
fn toml_errors_name_the_file_and_the_field() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("bad.toml");
    std::fs::write(
        &p,
        "duration_s = 0.1\n[light]\npulse_hz = 5000\npulse_widht_us = 10\n",
    )
    .unwrap();
    let e = Scenario::from_toml_file(&p).unwrap_err().to_string();
    assert!(
        e.contains("bad.toml") && e.contains("pulse_widht_us"),
        "{e}"
    );
    std::fs::write(&p, "[seeding]\nppp = 2.0\n").unwrap();
    let e = Scenario::from_toml_file(&p).unwrap_err().to_string();
    assert!(e.contains("bad.toml") && e.contains("seeding.ppp"), "{e}");
    let e = Scenario::from_toml_file(dir.path().join("missing.toml"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("missing.toml"), "{e}");
}

#[test]
fn minimal_toml_takes_defaults_and_gridded_paths_are_relative_to_the_file() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("field.csv"),
        "x,y,u,v\n0,0,1,0\n100,0,1,0\n0,100,1,0\n100,100,1,0\n",
    )
    .unwrap();
    let p = dir.path().join("s.toml");
    std::fs::write(
        &p,
        "[flow]\nkind = \"gridded\"\npath = \"field.csv\"\n[pixel.refractory]\nperiod_us = 20\n",
    )
    .unwrap();
    let s = Scenario::from_toml_file(&p).unwrap();
    assert_eq!(s.light, Light::default());
    assert_eq!(
        s.effect_params("refractory").unwrap().unwrap()["period_us"],
        20.0
    );
    match &s.flow {
        FlowSpec::Gridded { path, scale } => {
            assert_eq!(path, &dir.path().join("field.csv"));
            assert_eq!(*scale, 1.0);
        }
        f => panic!("{f:?}"),
    }
    ebptv::sim::Flow::build(&s.flow).unwrap();
}

#[test]
fn example_scenario_files_parse() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("data/scenarios");
    let mut n = 0;
    for entry in std::fs::read_dir(&dir).unwrap() {
        let p = entry.unwrap().path();
        if p.extension().and_then(|e| e.to_str()) == Some("toml") {
            let s = Scenario::from_toml_file(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
            if !matches!(s.flow, FlowSpec::Gridded { .. }) {
                ebptv::sim::Flow::build(&s.flow).unwrap();
            }
            n += 1;
        }
    }
    assert!(n >= 2, "{n} example scenarios");
}

#[test]
fn every_effect_can_be_set_and_cleared_by_name() {
    let full = presets::preset("demo").unwrap();
    let mut s = Scenario::default();
    for name in EFFECT_NAMES {
        let p = full.effect_params(name).unwrap().unwrap_or_else(|| {
            // Effects the demo leaves off: give plausible parameters.
            let pairs: &[(&str, f64)] = match name {
                "hot_pixels" => &[("count", 3.0), ("rate_hz", 100.0)],
                "rate_limiter" => &[("max_rate_ev_s", 1e7), ("window_us", 100.0)],
                "off_events" => &[("threshold", 0.3), ("tau_us", 20.0)],
                "clock_drift" => &[("ppm", 40.0), ("wander_ppm", 5.0), ("wander_period_s", 2.0)],
                _ => panic!("{name}"),
            };
            pairs.iter().map(|(k, v)| (k.to_string(), *v)).collect()
        });
        s.set_effect(name, Some(&p)).unwrap();
        assert_eq!(s.effect_params(name).unwrap(), Some(p.clone()));
        s.validate().unwrap();
        let mut partial = p.clone();
        let k = partial.keys().next().unwrap().clone();
        partial.remove(&k);
        let e = s
            .clone()
            .set_effect(name, Some(&partial))
            .unwrap_err()
            .to_string();
        assert!(e.contains(&k), "{e}");
    }
    assert_eq!(s.without_effects(), Scenario::default());
}

/// Every experiment the issue names has a preset with the stated geometry
/// and pulse rate.
#[test]
fn the_issues_experiments_are_presets() {
    use ebptv::sim::scenario::FlowSpec;
    let roi = |s: &ebptv::sim::Scenario| (s.roi().width, s.roi().height);
    for (name, hz) in [
        ("water_jet_2khz", 2000.0),
        ("water_jet_4khz", 4000.0),
        ("water_jet_5khz", 5000.0),
        ("water_jet_10khz", 10_000.0),
    ] {
        let s = presets::preset(name).unwrap();
        assert_eq!(s.light.pulse_hz, hz, "{name}");
        assert!(matches!(s.flow, FlowSpec::Jet { .. }), "{name}");
        assert_eq!((s.sensor.width, s.sensor.height), (1280, 720), "{name}");
    }
    let lbl = presets::preset("laminar_bl").unwrap();
    assert_eq!((roi(&lbl), lbl.light.pulse_hz), ((320, 720), 5000.0));
    assert!(matches!(lbl.flow, FlowSpec::BoundaryLayer { .. }));
    let tbl = presets::preset("turbulent_bl").unwrap();
    assert_eq!(roi(&tbl), (1280, 320));
    assert!(matches!(tbl.flow, FlowSpec::Turbulent { .. }));
    let rib = presets::preset("rib_wake").unwrap();
    assert_eq!((roi(&rib), rib.light.pulse_hz), ((1280, 720), 5000.0));
    let FlowSpec::Shedding {
        u_inf,
        size,
        strouhal,
        ..
    } = rib.flow
    else {
        panic!("rib_wake is not a shedding flow")
    };
    assert_eq!(strouhal, 0.145);
    assert!((strouhal * u_inf / size - 35.4).abs() < 0.05);
    let roi_burst = presets::preset("roi_burst").unwrap();
    assert_eq!(roi(&roi_burst), (1280, 160));
}
