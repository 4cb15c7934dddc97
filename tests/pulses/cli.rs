//! `ebptv pulses` and `ebptv monitor` end to end on a simulated RAW file.
use crate::cli_common;

use cli_common::{ebptv, run_ok};

use ebptv::sim::{presets::preset, simulate};

fn write_demo(dir: &std::path::Path) -> std::path::PathBuf {
    let mut sc = preset("demo").unwrap();
    sc.triggers.enabled = true;
    let out = simulate(&sc, 5).unwrap();
    let path = dir.join("demo.raw");
    let mut w = ebptv::io::create(&path, None, out.geometry.unwrap()).unwrap();
    let mut chunk = ebptv::Chunk::default();
    chunk.events = out.events;
    chunk.triggers = out.triggers;
    w.write_chunk(&chunk).unwrap();
    w.finish().unwrap();
    path
}

#[test]
fn pulses_writes_json_npy_and_figures() {
    let dir = tempfile::tempdir().unwrap();
    let raw = write_demo(dir.path());
    let out = dir.path().join("out");
    run_ok(ebptv().args([
        "pulses",
        raw.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]));
    let v: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("pulses.json")).unwrap()).unwrap();
    assert_eq!(v["source"], "trigger");
    assert!((v["period_us"].as_f64().unwrap() - 200.0).abs() < 0.01);
    assert!((v["first_pulse_us"].as_f64().unwrap() - 37.0).abs() < 1.0);
    assert_eq!(v["saturated"], false);
    for f in [
        "rate_map.npy",
        "latency.csv",
        "latency_histogram.png",
        "latency_cumulative.png",
        "rate_trace.png",
        "rate_map.png",
    ] {
        assert!(out.join(f).exists(), "{f} missing");
    }
    // Triggers asked on a channel that has none: a clear refusal, no outputs.
    let out2 = dir.path().join("out2");
    let st = ebptv()
        .args([
            "pulses",
            raw.to_str().unwrap(),
            "--trigger-channel",
            "7",
            "--out",
            out2.to_str().unwrap(),
        ])
        .output()
        .unwrap();
    assert!(!st.status.success());
    let msg = String::from_utf8_lossy(&st.stderr);
    assert!(msg.contains("channel 7"), "{msg}");
    assert!(!out2.join("pulses.json").exists());
}

#[test]
fn monitor_reports_intervals() {
    let dir = tempfile::tempdir().unwrap();
    let raw = write_demo(dir.path());
    let st = run_ok(ebptv().args(["monitor", raw.to_str().unwrap(), "--interval-s", "0.01"]));
    let text = String::from_utf8_lossy(&st.stdout);
    let lines: Vec<&str> = text.lines().filter(|l| l.contains("Mev/s")).collect();
    assert!(lines.len() >= 4, "{text}");
    assert!(
        lines.iter().filter(|l| l.contains("FWHM")).count() >= 4,
        "{text}"
    );
}
