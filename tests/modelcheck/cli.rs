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

// ------------------------------------------------------------------
// The default check (no `--model`: a standard sensor calibrated to the
// measurement) on recordings ebptv's simulator did not make.

#[path = "../modelcheck_common/independent.rs"]
mod independent;

use std::path::{Path, PathBuf};

/// Run the default check; the parsed model_check.json.
fn standard_check(rec: &Path, out: &Path, extra: &[&str]) -> serde_json::Value {
    let res = Command::new(env!("CARGO_BIN_EXE_ebptv"))
        .arg("model-check")
        .arg(rec)
        .arg("--out")
        .arg(out)
        .args(extra)
        .output()
        .unwrap();
    assert!(
        res.status.success(),
        "{}: {}",
        rec.display(),
        String::from_utf8_lossy(&res.stderr)
    );
    serde_json::from_slice(&std::fs::read(out.join("model_check.json")).unwrap()).unwrap()
}

/// The first named effect and its gap ratio (after / before).
fn first_named(json: &serde_json::Value) -> Option<(String, f64)> {
    let e = json["effects"].as_array()?.first()?;
    let ratio = e["gap_after"].as_f64()? / e["gap_before"].as_f64()?;
    Some((e["name"].as_str()?.to_string(), ratio))
}

/// Options that keep one check on the small independent recordings to
/// well under a minute.
const SHORT: [&str; 6] = [
    "--block-pulses",
    "60",
    "--replicates",
    "3",
    "--evaluations",
    "8",
];

#[test]
fn standard_check_names_nothing_on_a_well_behaved_independent_sensor() {
    let dir = tempfile::tempdir().unwrap();
    let rec = dir.path().join("null.raw");
    independent::Recording::new(independent::Departure::None, 11).write(&rec);
    let json = standard_check(&rec, &dir.path().join("check"), &SHORT);
    assert!(
        json["effects"].as_array().unwrap().is_empty(),
        "named on a standard sensor: {:#}",
        json["rounds"]
    );
    assert_ne!(json["verdict"], "explained");
}

/// The check on one departure of the second generator: the first named
/// effect is `name`, with the gap halved.
fn names_departure(departure: independent::Departure, name: &str) {
    names_departure_of(independent::Recording::new(departure, 12), &[], name);
}

/// [`names_departure`] of `recording`, with `extra` options.
fn names_departure_of(recording: independent::Recording, extra: &[&str], name: &str) {
    let dir = tempfile::tempdir().unwrap();
    let rec = dir.path().join("measured.raw");
    recording.write(&rec);
    let args: Vec<&str> = SHORT.iter().chain(extra).copied().collect();
    let json = standard_check(&rec, &dir.path().join("check"), &args);
    let (first, ratio) =
        first_named(&json).unwrap_or_else(|| panic!("{name}: nothing named: {:#}", json["rounds"]));
    assert_eq!(first, name, "{:#}", json["rounds"]);
    assert!(ratio <= 0.5, "{name}: gap ratio {ratio}");
}

#[test]
fn standard_check_names_a_latency_jitter_of_an_independent_sensor() {
    names_departure(
        independent::Departure::LatencyJitter { scale_us: 30.0 },
        "latency_jitter",
    );
}

/// A dead time of 30 µs leaves the second generator's pixels no second
/// event within a burst (its repeats come 3–9 µs apart) and every event of
/// a pixel's next visit (a pulse period later). The recording has no
/// trigger channel: the check finds the pulses from the events
/// (`--pulse-hz`), and the latencies it compares count from the bursts'
/// leading edge.
#[test]
fn standard_check_names_a_refractory_period_of_an_independent_sensor_without_triggers() {
    let mut rec =
        independent::Recording::new(independent::Departure::Refractory { period_us: 30.0 }, 12);
    rec.triggers = false;
    let hz = format!("{}", 1e6 / rec.period_us);
    names_departure_of(rec, &["--pulse-hz", &hz], "refractory");
}

/// A recording without triggers whose events show no pulsed light (events
/// at random times) stops the check with the pulse analysis' reason,
/// naming the file, and leaves no output; so does a pulse frequency that
/// is not one.
#[test]
fn standard_check_without_pulsed_light_says_so() {
    use rand::{Rng, SeedableRng};
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("unpulsed.raw");
    let mut rng = rand_pcg::Pcg64::seed_from_u64(21);
    let mut t: Vec<i64> = (0..200_000).map(|_| rng.gen_range(0..40_000)).collect();
    t.sort_unstable();
    let mut events = ebptv::events::EventChunk::default();
    for t in t {
        events.push(t, rng.gen_range(0..320), rng.gen_range(0..180), 1);
    }
    let mut w = ebptv::io::create(&path, None, Geometry::new(320, 180)).unwrap();
    w.write_chunk(&Chunk {
        events,
        triggers: Vec::new(),
    })
    .unwrap();
    w.finish().unwrap();
    for (extra, want) in [
        (&[][..], "finding the light pulses in"),
        (&["--pulse-hz", "0"][..], "must be positive"),
    ] {
        let out = dir.path().join("check");
        let res = Command::new(env!("CARGO_BIN_EXE_ebptv"))
            .arg("model-check")
            .arg(&path)
            .arg("--out")
            .arg(&out)
            .args(extra)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&res.stderr);
        assert!(!res.status.success(), "{err}");
        assert!(err.contains(want), "{err}");
        if extra.is_empty() {
            assert!(err.contains("unpulsed.raw"), "{err}");
        }
        assert!(!out.exists(), "output left behind");
    }
}

/// The independent development recordings (`../shared/data/dev`, see its
/// README), skipped when absent.
fn dev_dir() -> Option<PathBuf> {
    let d = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/dev");
    if d.join("mcdev_null/events.raw").exists() {
        Some(d)
    } else {
        eprintln!("{} absent: skipped", d.display());
        None
    }
}

/// Did the check on `name` pass the way `../shared/eval/score_model_check.py`
/// scores it (first named effect = the sealed one, gap halved; nothing
/// named when the sealed effect is `none`)?
fn dev_passes(dev: &Path, name: &str, out: &Path, extra: &[&str]) -> (bool, String) {
    let sealed: serde_json::Value =
        serde_json::from_slice(&std::fs::read(dev.join(name).join("sealed.json")).unwrap())
            .unwrap();
    let want = sealed["effect"].as_str().unwrap().to_string();
    let json = standard_check(&dev.join(name).join("events.raw"), out, extra);
    let got = first_named(&json);
    let ok = match &got {
        None => want == "none",
        Some((n, ratio)) => *n == want && *ratio <= 0.5,
    };
    (ok, format!("{name}: sealed {want}, named {got:?}"))
}

/// One development recording through the standard check: the hidden
/// effect (or none) must be named first.
fn dev_recording_passes(name: &str) {
    let Some(dev) = dev_dir() else { return };
    let dir = tempfile::tempdir().unwrap();
    let (ok, what) = dev_passes(&dev, name, &dir.path().join(name), &[]);
    assert!(ok, "{what}");
}

// Four of the eight development recordings, one test each (so that the
// harness runs them side by side): nothing hidden, background noise, a
// refractory period, a latency that depends on brightness.
#[test]
fn standard_check_on_independent_dev_recording_null() {
    dev_recording_passes("mcdev_null");
}

/// The same recording with its trigger channel ignored and no pulse
/// frequency given: the pulses found from the events over the default
/// band, nothing named either.
#[test]
fn standard_check_on_independent_dev_recording_null_without_triggers() {
    let Some(dev) = dev_dir() else { return };
    let dir = tempfile::tempdir().unwrap();
    let extra = ["--ignore-triggers"];
    let (ok, what) = dev_passes(&dev, "mcdev_null", &dir.path().join("null"), &extra);
    assert!(ok, "{what}");
    let report = std::fs::read_to_string(dir.path().join("null/report.md")).unwrap();
    assert!(report.contains("found from the events"), "{report}");
}

#[test]
fn standard_check_on_independent_dev_recording_background_noise() {
    dev_recording_passes("mcdev_background_noise");
}

#[test]
fn standard_check_on_independent_dev_recording_refractory() {
    dev_recording_passes("mcdev_refractory");
}

/// Found by `latency_vs_yield` (a pixel that fires more events at a pulse
/// fires its first one sooner), with a seed other than the default: only
/// the check's own simulations change, and the effect must not hang on
/// them (its other rows lie ~2 z beyond the standard range, under the
/// threshold).
#[test]
fn standard_check_on_independent_dev_recording_intensity_latency() {
    let Some(dev) = dev_dir() else { return };
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("intensity");
    let (ok, what) = dev_passes(&dev, "mcdev_intensity_latency", &out, &["--seed", "4"]);
    assert!(ok, "{what}");
}

/// All eight development recordings with default options (several
/// minutes): `cargo test --release --test integration -- --ignored dev_recordings_all`.
#[test]
#[ignore]
fn standard_check_on_independent_dev_recordings_all() {
    let Some(dev) = dev_dir() else { return };
    let dir = tempfile::tempdir().unwrap();
    let mut lines = Vec::new();
    let mut passed = 0;
    for name in [
        "mcdev_null",
        "mcdev_arbiter_saturation",
        "mcdev_background_noise",
        "mcdev_hot_pixels",
        "mcdev_intensity_latency",
        "mcdev_latency_jitter",
        "mcdev_off_events",
        "mcdev_refractory",
    ] {
        let (ok, what) = dev_passes(&dev, name, &dir.path().join(name), &[]);
        passed += ok as usize;
        lines.push(format!("{} {what}", if ok { "PASS" } else { "FAIL" }));
    }
    eprintln!("{}", lines.join("\n"));
    assert!(passed == 8, "{passed} of 8:\n{}", lines.join("\n"));
}
