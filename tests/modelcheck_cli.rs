//! `ebptv model-check` end to end: a recording simulated with a hidden
//! latency jitter, written as EVT 3.0 with triggers; the starting model is
//! the same scene without it.

use std::process::Command;

use ebptv::events::{Chunk, Geometry};
use ebptv::sim::scenario::{LatencyJitter, Scenario, Sensor};

#[test]
fn model_check_cli_names_a_hidden_latency_jitter() {
    let dir = tempfile::tempdir().unwrap();
    let mut sc = Scenario {
        name: "cli-check".into(),
        // 0.1 s (500 pulses): at 0.04 s the latency-vs-brightness profile is
        // too thin to tell jitter from intensity-dependent latency, and the
        // acceptance rule (a clear lead over the rival) rightly names nothing.
        duration_s: 0.1,
        sensor: Sensor {
            width: 160,
            height: 120,
            roi: None,
        },
        ..Scenario::default()
    };
    sc.seeding.ppp = 0.006;
    sc.light.energy = ebptv::sim::presets::WATER_ENERGY;
    std::fs::write(dir.path().join("model.toml"), sc.to_toml_string().unwrap()).unwrap();
    let mut measured = sc.clone();
    measured.pixel.latency_jitter = Some(LatencyJitter { spread_us: 10.0 });
    let out = ebptv::sim::simulate(&measured, 987_654).unwrap();
    let rec = dir.path().join("measured.raw");
    let mut w = ebptv::io::create(&rec, None, Geometry::new(160, 120)).unwrap();
    w.write_chunk(&Chunk {
        events: out.events.clone(),
        triggers: out.triggers.clone(),
    })
    .unwrap();
    w.finish().unwrap();

    let res = Command::new(env!("CARGO_BIN_EXE_ebptv"))
        .args(["model-check"])
        .arg(&rec)
        .arg("--model")
        .arg(dir.path().join("model.toml"))
        .arg("--out")
        .arg(dir.path().join("check"))
        .args([
            "--replicates",
            "4",
            "--evaluations",
            "10",
            "--max-effects",
            "1",
        ])
        .output()
        .unwrap();
    assert!(
        res.status.success(),
        "{}",
        String::from_utf8_lossy(&res.stderr)
    );
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dir.path().join("check/model_check.json")).unwrap())
            .unwrap();
    let effects = json["effects"].as_array().unwrap();
    assert!(!effects.is_empty(), "nothing named: {:#}", json["rounds"]);
    assert_eq!(effects[0]["name"], "latency_jitter", "{json:#}");
    let spread = effects[0]["parameters"]["spread_us"].as_f64().unwrap();
    assert!((spread - 10.0).abs() < 3.0, "spread {spread}");
    assert!(
        effects[0]["gap_after"].as_f64().unwrap()
            < 0.5 * effects[0]["gap_before"].as_f64().unwrap()
    );
    // The fitted model is a scenario the simulator accepts, with the effect on.
    let fitted = Scenario::from_toml_file(dir.path().join("check/model.toml")).unwrap();
    assert!(fitted.pixel.latency_jitter.is_some());
    let report = std::fs::read_to_string(dir.path().join("check/report.md")).unwrap();
    assert!(report.contains("latency_jitter"));
    assert!(dir.path().join("check/signature_latency.png").exists());

    // A missing file is a clear error, not a panic.
    let bad = Command::new(env!("CARGO_BIN_EXE_ebptv"))
        .args(["model-check", "/nonexistent.raw", "--out"])
        .arg(dir.path().join("bad"))
        .output()
        .unwrap();
    assert!(!bad.status.success());
    assert!(String::from_utf8_lossy(&bad.stderr).contains("nonexistent"));
}
