//! `ebptv simulate` end to end.

use std::process::Command;

fn ebptv() -> Command {
    Command::new(env!("CARGO_BIN_EXE_ebptv"))
}

#[test]
fn simulate_writes_recording_truth_scenario_and_summary() {
    for format in ["csv", "evt3"] {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("sim");
        // The truth table as CSV with CSV events, Parquet (the default)
        // otherwise.
        let tables: &[&str] = if format == "csv" {
            &["--table-format", "csv"]
        } else {
            &[]
        };
        let r = ebptv()
            .args(tables)
            .args([
                "simulate",
                "--preset",
                "demo",
                "--seconds",
                "0.004",
                "--seed",
                "3",
                "--format",
                format,
                "--out",
            ])
            .arg(&out)
            .output()
            .unwrap();
        let stderr = String::from_utf8_lossy(&r.stderr);
        if !r.status.success() && stderr.contains("not implemented yet") {
            // The io writers land separately; until then the run must fail
            // cleanly and leave no output file behind.
            let left: Vec<_> = std::fs::read_dir(&out)
                .map(|d| d.map(|e| e.unwrap().file_name()).collect())
                .unwrap_or_default();
            assert!(left.is_empty(), "partial outputs left: {left:?}");
            eprintln!(
                "skip: {format} writer not available yet ({})",
                stderr.trim()
            );
            continue;
        }
        assert!(r.status.success(), "{stderr}");
        let summary: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap())
                .unwrap();
        let events = summary["events"].as_u64().unwrap();
        assert!(events > 10_000, "{summary}");
        assert_eq!(summary["pulses"].as_u64().unwrap(), 20);
        let epp = summary["events_per_particle_per_pulse"].as_f64().unwrap();
        assert!((1.5..2.5).contains(&epp), "{epp}");
        let truth_rows = if format == "csv" {
            assert!(!out.join("truth_particles.parquet").exists());
            let truth = std::fs::read_to_string(out.join("truth_particles.csv")).unwrap();
            let mut lines = truth.lines();
            assert_eq!(lines.next().unwrap(), "pulse,t_us,particle_id,x,y,u,v");
            lines.count()
        } else {
            assert!(!out.join("truth_particles.csv").exists());
            let t = ebptv::compare::read_table(&out.join("truth_particles.parquet"), &[]).unwrap();
            assert_eq!(
                t.names,
                ["pulse", "t_us", "particle_id", "x", "y", "u", "v"]
            );
            t.rows()
        };
        assert_eq!(
            truth_rows as u64,
            summary["truth_samples"].as_u64().unwrap()
        );
        let sc = ebptv::sim::Scenario::from_toml_file(out.join("scenario.toml")).unwrap();
        let mut expect = ebptv::sim::presets::preset("demo").unwrap();
        expect.duration_s = 0.004;
        assert_eq!(sc, expect);
        let rec = out.join(summary["recording"].as_str().unwrap());
        match ebptv::io::open(&rec) {
            Ok(mut src) => {
                let mut chunk = ebptv::Chunk::default();
                let (mut n, mut trig) = (0u64, 0u64);
                while src.next_chunk(&mut chunk).unwrap() {
                    n += chunk.events.len() as u64;
                    trig += chunk.triggers.len() as u64;
                }
                assert_eq!(n, events);
                if format == "evt3" {
                    assert_eq!(trig, 40, "both edges of 20 pulses");
                }
            }
            Err(e) => eprintln!("skip reading back {}: {e}", rec.display()),
        }
    }
}

#[test]
fn simulate_refuses_bad_input_naming_it() {
    let dir = tempfile::tempdir().unwrap();
    let r = ebptv()
        .args(["simulate", "--preset", "nope", "--out"])
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(!r.status.success());
    assert!(String::from_utf8_lossy(&r.stderr).contains("preset"));
    let cfg = dir.path().join("bad.toml");
    std::fs::write(&cfg, "[seeding]\nppp = 3.0\n").unwrap();
    let r = ebptv()
        .args(["simulate", "--config"])
        .arg(&cfg)
        .arg("--out")
        .arg(dir.path().join("o"))
        .output()
        .unwrap();
    assert!(!r.status.success());
    let e = String::from_utf8_lossy(&r.stderr);
    assert!(e.contains("seeding.ppp") && e.contains("bad.toml"), "{e}");
    let r = ebptv()
        .args(["simulate", "--preset", "demo", "--seconds=-1", "--out"])
        .arg(dir.path().join("o"))
        .output()
        .unwrap();
    assert!(!r.status.success());
    assert!(String::from_utf8_lossy(&r.stderr).contains("duration_s"));
    assert!(
        !dir.path().join("o").exists(),
        "nothing written for refused input"
    );
}
