//! End to end on the simulator: a Lamb–Oseen vortex recorded by the
//! simulated event camera (latency, noise, refractory period, …) →
//! `ebptv piv` → mean field against the analytic truth.
use crate::cli_common;

use cli_common::{ebptv, run_ok};

#[test]
fn simulated_vortex_recording_mean_field_within_2_percent() {
    let dir = tempfile::tempdir().unwrap();
    let scen = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/data/scenarios/vortex_small.toml"
    ))
    .unwrap();
    // 40 pulses (9 PIV fields) on a 32 px node spacing keep the test short.
    let scen = scen.replace("duration_s = 0.05", "duration_s = 0.008");
    assert!(
        scen.contains("duration_s = 0.008"),
        "scenario changed: update this test"
    );
    let cfg = dir.path().join("s.toml");
    std::fs::write(&cfg, scen).unwrap();
    let sim = dir.path().join("sim");
    run_ok(ebptv().args([
        "simulate",
        "--config",
        cfg.to_str().unwrap(),
        "--out",
        sim.to_str().unwrap(),
    ]));
    let out = dir.path().join("piv");
    run_ok(ebptv().args([
        "--table-format",
        "csv",
        "piv",
        sim.join("recording.raw").to_str().unwrap(),
        "--window",
        "32",
        "--spacing",
        "32",
        "--frames",
        "5",
        "--out",
        out.to_str().unwrap(),
    ]));
    for f in [
        "piv_u.npy",
        "piv_v.npy",
        "piv_flag.npy",
        "piv_steps.csv",
        "piv_u.png",
    ] {
        assert!(out.join(f).exists(), "{f} missing");
    }
    let csv = std::fs::read_to_string(out.join("piv_mean.csv")).unwrap();
    let mut lines = csv.lines();
    assert_eq!(lines.next().unwrap(), "x,y,u,v,uu,vv,uv,valid");
    // The scenario's vortex: centre (320, 180), Γ = 1.2e7 px²/s, r_c = 60 px.
    let (cx, cy, gamma, rc) = (320.0, 180.0, 1.2e7, 60.0);
    let truth = |x: f64, y: f64| {
        let (dx, dy) = (x - cx, y - cy);
        let r2 = dx * dx + dy * dy;
        let ut = gamma / (2.0 * std::f64::consts::PI * r2.sqrt()) * (1.0 - (-r2 / (rc * rc)).exp());
        (-ut * dy / r2.sqrt(), ut * dx / r2.sqrt())
    };
    let (mut se, mut n, mut vmax, mut valid) = (0.0, 0.0, 0.0f64, 0.0);
    let mut nodes = 0.0;
    for l in lines {
        let f: Vec<f64> = l.split(',').map(|s| s.parse().unwrap()).collect();
        let (tu, tv) = truth(f[0], f[1]);
        vmax = vmax.max(tu.hypot(tv));
        nodes += 1.0;
        valid += f[7];
        if f[7] > 0.5 {
            se += (f[2] - tu).powi(2) + (f[3] - tv).powi(2);
            n += 1.0;
        }
    }
    let rel = (se / n).sqrt() / vmax;
    eprintln!(
        "simulated vortex: mean-field rms error {:.2} % of peak, mean valid fraction {:.3}",
        rel * 100.0,
        valid / nodes
    );
    assert!(rel < 0.02, "rms error {rel} of peak speed");
    assert!(valid / nodes > 0.9);

    // Time steps in parallel: the same files, byte for byte, with one
    // thread evaluating one step at a time and with two threads running
    // batches of 3 steps (the run above: the default batch).
    for (threads, batch) in [("1", "1"), ("2", "3")] {
        let again = dir.path().join(format!("piv_{threads}_{batch}"));
        run_ok(ebptv().env("RAYON_NUM_THREADS", threads).args([
            "--table-format",
            "csv",
            "piv",
            sim.join("recording.raw").to_str().unwrap(),
            "--window",
            "32",
            "--spacing",
            "32",
            "--frames",
            "5",
            "--batch",
            batch,
            "--out",
            again.to_str().unwrap(),
        ]));
        for f in [
            "piv_u.npy",
            "piv_v.npy",
            "piv_flag.npy",
            "piv_steps.csv",
            "piv_mean.csv",
        ] {
            assert!(
                std::fs::read(out.join(f)).unwrap() == std::fs::read(again.join(f)).unwrap(),
                "{f} differs with {threads} thread(s), batch {batch}"
            );
        }
    }
}
