//! The shedding frequency of a recording ebptv did not make
//! (`../shared/data/dev/speeddev_shedding`, no trigger channel): tracked
//! with `--pulse-hz`, then `ebptv spectra` at a point on the wake's centre
//! line must report a significant peak within 1.5 Hz of the generator's
//! shedding frequency (`truth.json`: `flow.f_s`, `flow.yc`). Skipped when the
//! development recordings are absent.

use std::path::Path;
use std::process::Command;

fn run(cmd: &mut Command) {
    let out = cmd.output().expect("ebptv runs");
    assert!(
        out.status.success(),
        "{:?} failed: {}",
        cmd,
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
fn independent_wake_shedding_frequency_is_found_and_significant() {
    let rec = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/dev/speeddev_shedding");
    if !rec.join("events.raw").exists() {
        eprintln!("{} absent: skipped", rec.display());
        return;
    }
    let truth: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(rec.join("truth.json")).unwrap()).unwrap();
    let f_s = truth["flow"]["f_s"].as_f64().unwrap();
    let yc = truth["flow"]["yc"].as_f64().unwrap();
    let x = truth["width"].as_f64().unwrap() / 2.0;
    let pulse_hz = truth["f_p"].as_f64().unwrap();

    let dir = tempfile::tempdir().unwrap();
    let ptv = dir.path().join("ptv");
    let spec = dir.path().join("spectra");
    let bin = env!("CARGO_BIN_EXE_ebptv");
    run(Command::new(bin)
        .arg("track")
        .arg(rec.join("events.raw"))
        .args(["--pulse-hz", &pulse_hz.to_string(), "--out"])
        .arg(&ptv));
    run(Command::new(bin)
        .arg("spectra")
        .arg(ptv.join("tracks.parquet"))
        .args(["--point", &format!("{x},{yc}"), "--no-plots", "--out"])
        .arg(&spec));
    let s: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(spec.join("spectrum.json")).unwrap())
            .unwrap();
    assert_eq!(s["peak_significant"], true, "{s}");
    let peak = s["peak_hz"].as_f64().unwrap();
    assert!(
        (peak - f_s).abs() <= 1.5,
        "peak {peak} Hz, shedding {f_s} Hz"
    );
}
