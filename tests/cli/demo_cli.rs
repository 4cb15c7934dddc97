//! `ebptv demo` end to end on a short recording: every stage runs from the
//! command line and the scores against the simulator's truth stay where the
//! full demo puts them (with margins for the shorter recording).

use std::process::Command;

#[test]
fn demo_runs_every_stage_and_scores_against_truth() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("demo");
    let status = Command::new(env!("CARGO_BIN_EXE_ebptv"))
        .args(["demo", "--seconds", "0.02", "--seed", "3", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(
        status.status.success(),
        "demo failed: {}",
        String::from_utf8_lossy(&status.stderr)
    );
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("demo_report.json")).unwrap())
            .unwrap();
    let f = |ptr: &str| {
        report
            .pointer(ptr)
            .and_then(|v| v.as_f64())
            .unwrap_or_else(|| panic!("{ptr} missing in {report}"))
    };
    // Triggers are recorded: timing must be exact to well below 1 µs.
    assert!(f("/pulses/period_error_us").abs() < 0.01);
    assert!(f("/pulses/first_pulse_error_us").abs() < 1.0);
    // Detection and linking against truth (full demo: 0.99 / 0.91 / 0.987).
    assert!(f("/particles/precision") > 0.97, "{report}");
    assert!(f("/particles/recall") > 0.85, "{report}");
    assert!(f("/tracks/link_precision") > 0.97, "{report}");
    assert!(f("/tracks/velocity_rms_px_per_pulse") < 0.06, "{report}");
    // Eulerian means within a few percent of the largest speed.
    assert!(f("/grid/rms_error_of_max_speed") < 0.03, "{report}");
    assert!(f("/piv/rms_error_of_max_speed") < 0.04, "{report}");
    for step in [
        "sim/recording.raw",
        "ptv/tracks.parquet",
        "sim/truth_particles.parquet",
        "grid/grid.parquet",
        "grid/grid_extra.parquet",
        "piv/piv_mean.parquet",
        "piv/piv_steps.parquet",
        "compare/compare.json",
    ] {
        assert!(out.join(step).exists(), "{step} missing");
    }
    // A steady vortex: no frequency in the flow, so no significant peak
    // (particles crossing the bin make a bump above the resolved band).
    let sp: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("spectra/spectrum.json")).unwrap())
            .unwrap();
    assert_eq!(sp["peak_significant"], false, "{sp}");
    assert!(sp["peak_hz"].is_null(), "{sp}");
    assert!(sp["peak_false_alarm"].as_f64().unwrap() > 0.01, "{sp}");
}

/// `--config` runs the same chain on a scenario file, and the report says
/// which file it was.
#[test]
fn demo_runs_on_a_scenario_file() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("demo");
    let scene = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/data/scenarios/vortex_small.toml"
    );
    let run = Command::new(env!("CARGO_BIN_EXE_ebptv"))
        .args(["demo", "--config", scene, "--seconds", "0.01", "--out"])
        .arg(&out)
        .output()
        .unwrap();
    assert!(
        run.status.success(),
        "demo failed: {}",
        String::from_utf8_lossy(&run.stderr)
    );
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("demo_report.json")).unwrap())
            .unwrap();
    assert_eq!(report["config"].as_str(), Some(scene), "{report}");
    assert!(report["preset"].is_null(), "{report}");
    let used = std::fs::read_to_string(out.join("sim/scenario.toml")).unwrap();
    assert!(used.contains("vortex_small"), "{used}");
    let precision = report["tracks"]["link_precision"].as_f64().unwrap();
    assert!(precision > 0.9, "{report}");
}

/// A scenario file that cannot be read fails before anything runs: the
/// error names the file, and no step leaves output behind.
#[test]
fn demo_refuses_a_bad_scenario_file_by_name() {
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("bad_scene.toml");
    std::fs::write(&bad, "name = \"x\"\n[light]\npulse_hz = -5.0\n").unwrap();
    let out = dir.path().join("demo");
    let run = Command::new(env!("CARGO_BIN_EXE_ebptv"))
        .args(["demo", "--config"])
        .arg(&bad)
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    assert!(!run.status.success());
    let err = String::from_utf8_lossy(&run.stderr);
    assert!(err.contains("bad_scene.toml"), "{err}");
    assert!(!out.exists(), "output was written: {err}");
    // --preset and --config together are refused by the parser.
    let both = Command::new(env!("CARGO_BIN_EXE_ebptv"))
        .args(["demo", "--preset", "demo", "--config"])
        .arg(&bad)
        .output()
        .unwrap();
    assert!(!both.status.success());
}
