//! Each case is made inside the test from a real or development recording
//! (a header edit, one corrupted time word, random bytes) and run through
//! the `ebptv` binary.

use std::path::{Path, PathBuf};
use std::process::Output;

use crate::cli_common::ebptv;

fn shared(sub: &str) -> Option<PathBuf> {
    let p = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/data")
        .join(sub);
    p.exists().then_some(p)
}

fn run(args: &[&std::ffi::OsStr]) -> Output {
    ebptv().args(args).output().expect("starting ebptv")
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// Split a RAW file into its `% ` header lines and payload.
fn split_header(b: &[u8]) -> (Vec<u8>, Vec<u8>) {
    let mut i = 0;
    while b[i..].starts_with(b"% ") {
        match b[i..].iter().position(|&c| c == b'\n') {
            Some(j) => i += j + 1,
            None => break,
        }
    }
    (b[..i].to_vec(), b[i..].to_vec())
}

/// A failed run: exit 1, an `error:` line, no panic, nothing written.
fn assert_clean_failure(o: &Output, out: &Path, what: &str) {
    let e = stderr(o);
    assert_eq!(o.status.code(), Some(1), "{what}: {e}");
    assert!(
        e.contains("error:") && !e.contains("panicked"),
        "{what}: {e}"
    );
    assert!(!out.exists(), "{what}: {} was left behind", out.display());
}

/// None of the six real recordings has pulsed light: `pulses` and `track`
/// refuse each with exit 1 and write nothing (no output folder either).
#[test]
fn real_recordings_are_not_pulsed() {
    let Some(real) = shared("real") else { return };
    let dir = tempfile::tempdir().unwrap();
    let mut n = 0;
    for f in std::fs::read_dir(&real).unwrap() {
        let f = f.unwrap().path();
        if f.extension().is_some_and(|e| e == "md") {
            continue;
        }
        for stage in ["pulses", "track"] {
            let out = dir.path().join(format!("{stage}_out"));
            let o = run(&[
                stage.as_ref(),
                f.as_os_str(),
                "--out".as_ref(),
                out.as_os_str(),
            ]);
            assert_clean_failure(&o, &out, &format!("{stage} {}", f.display()));
            let e = stderr(&o);
            assert!(
                e.contains("no pulsed illumination") || e.contains("no pulses detectable"),
                "{e}"
            );
        }
        n += 1;
    }
    assert_eq!(n, 6);
    // The frame-exposure triggers of the DAVIS do not make it pulsed: the
    // error says what was measured and how to override.
    let davis = real.join("davis346_test.aedat4");
    let out = dir.path().join("davis");
    let o = run(&[
        "pulses".as_ref(),
        davis.as_os_str(),
        "--out".as_ref(),
        out.as_os_str(),
    ]);
    let e = stderr(&o);
    assert!(
        e.contains("trigger train of channel 3") && e.contains("--force-pulses"),
        "{e}"
    );
    // Forced, the same run goes through and says the verdict in pulses.json.
    let o = run(&[
        "pulses".as_ref(),
        davis.as_os_str(),
        "--force-pulses".as_ref(),
        "--out".as_ref(),
        out.as_os_str(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("pulses.json")).unwrap()).unwrap();
    assert_eq!(v["pulsed"]["pulsed"], false);
    assert!(v["pulsed"]["burst_contrast"].as_f64().unwrap() < 2.0);
}

/// The pulsed development recordings (independent generator) pass the test.
#[test]
fn dev_recordings_are_pulsed() {
    let Some(dev) = shared("dev") else { return };
    let dir = tempfile::tempdir().unwrap();
    for (name, extra) in [
        ("mcdev_latency_jitter", None),
        ("speeddev_shedding", Some("5000")),
    ] {
        let f = dev.join(name).join("events.raw");
        let out = dir.path().join(name);
        let mut args: Vec<&std::ffi::OsStr> = vec![
            "pulses".as_ref(),
            f.as_os_str(),
            "--out".as_ref(),
            out.as_os_str(),
        ];
        if let Some(hz) = extra {
            args.push(std::ffi::OsStr::new("--pulse-hz"));
            args.push(std::ffi::OsStr::new(hz));
        }
        let o = run(&args);
        assert!(o.status.success(), "{name}: {}", stderr(&o));
        let v: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out.join("pulses.json")).unwrap()).unwrap();
        assert_eq!(v["pulsed"]["pulsed"], true, "{name}");
    }
}

/// `% format EVT3;height=65535;width=65535` in front of a real EVT 3.0 file:
/// a warning, the geometry of the events, a bounded pixel map (this aborted
/// on a 4 GB allocation).
#[test]
fn absurd_stated_geometry_is_replaced() {
    let Some(real) = shared("real") else { return };
    let dir = tempfile::tempdir().unwrap();
    let src = std::fs::read(real.join("evt3_sample.raw")).unwrap();
    let f = dir.path().join("geom.raw");
    let mut b = b"% format EVT3;height=65535;width=65535\n".to_vec();
    b.extend_from_slice(&src);
    std::fs::write(&f, b).unwrap();
    let out = dir.path().join("out");
    let o = run(&[
        "pulses".as_ref(),
        f.as_os_str(),
        "--force-pulses".as_ref(),
        "--out".as_ref(),
        out.as_os_str(),
    ]);
    let e = stderr(&o);
    assert!(o.status.success(), "{e}");
    assert!(e.contains("65535x65535 is impossible"), "{e}");
    let v: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("pulses.json")).unwrap()).unwrap();
    let (w, h) = (
        v["rate_map"]["width"].as_u64().unwrap(),
        v["rate_map"]["height"].as_u64().unwrap(),
    );
    assert!(w <= 1280 && h <= 720, "{w}x{h}");
    // info says what was stated and that it was ignored.
    let o = run(&["info".as_ref(), f.as_os_str()]);
    let t = String::from_utf8_lossy(&o.stdout);
    assert!(
        t.contains("stated as 65535x65535, impossible: ignored"),
        "{t}"
    );
    assert!(t.contains("pulsed light       no"), "{t}");
}

/// One corrupted EVT 3.0 TIME_HIGH word in a pulsed recording moves the
/// clock by seconds for the events up to the next one: they are dropped
/// and counted, the pulses are found as before (this made millions of
/// empty pulses).
#[test]
fn one_corrupted_time_word_is_a_counted_glitch() {
    let Some(dev) = shared("dev") else { return };
    let dir = tempfile::tempdir().unwrap();
    let src = std::fs::read(dev.join("mcdev_null/events.raw")).unwrap();
    let (hdr, mut pay) = split_header(&src);
    // The TIME_HIGH words (type 0x8) of the middle of the file.
    let th: Vec<usize> = (0..pay.len() / 2)
        .map(|k| 2 * k)
        .filter(|&i| pay[i + 1] >> 4 == 0x8)
        .collect();
    let i = th[th.len() / 2];
    let w = u16::from_le_bytes([pay[i], pay[i + 1]]) ^ (1 << 11); // +8.4 s
    pay[i..i + 2].copy_from_slice(&w.to_le_bytes());
    let f = dir.path().join("jump.raw");
    std::fs::write(&f, [hdr, pay].concat()).unwrap();
    let out = dir.path().join("out");
    let o = run(&[
        "pulses".as_ref(),
        f.as_os_str(),
        "--out".as_ref(),
        out.as_os_str(),
    ]);
    let e = stderr(&o);
    assert!(o.status.success(), "{e}");
    assert!(e.contains("the clock jumped"), "{e}");
    let v: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("pulses.json")).unwrap()).unwrap();
    assert!(v["time_jumps"].as_u64().unwrap() >= 1);
    assert!(v["time_jump_events"].as_u64().unwrap() >= 1);
    assert!(
        v["duration_s"].as_f64().unwrap() < 1.0,
        "{}",
        v["duration_s"]
    );
    assert_eq!(v["pulsed"]["pulsed"], true);
}

/// A failed `track` leaves no output folder; a folder that existed stays,
/// with nothing new in it.
#[test]
fn failed_runs_leave_nothing() {
    let Some(real) = shared("real") else { return };
    let dir = tempfile::tempdir().unwrap();
    let f = real.join("evt3_sample.raw");
    let out = dir.path().join("a").join("b");
    let o = run(&[
        "track".as_ref(),
        f.as_os_str(),
        "--out".as_ref(),
        out.as_os_str(),
    ]);
    assert_clean_failure(&o, &dir.path().join("a"), "track");
    let keep = dir.path().join("existing");
    std::fs::create_dir(&keep).unwrap();
    std::fs::write(keep.join("mine.txt"), "x").unwrap();
    let o = run(&[
        "track".as_ref(),
        f.as_os_str(),
        "--out".as_ref(),
        keep.as_os_str(),
    ]);
    assert_eq!(o.status.code(), Some(1));
    let left: Vec<_> = std::fs::read_dir(&keep)
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(left, vec![std::ffi::OsString::from("mine.txt")]);
    // grid on a tracks file with an absurd position blames the extent,
    // and leaves no folder either.
    let tracks = dir.path().join("tracks.csv");
    std::fs::write(
        &tracks,
        "track_id,pulse,t_us,x,y,u,v\n1,0,0,10,10,1,1\n1,1,200,1e15,10,1,1\n",
    )
    .unwrap();
    let gout = dir.path().join("grid");
    let o = run(&[
        "grid".as_ref(),
        tracks.as_os_str(),
        "--out".as_ref(),
        gout.as_os_str(),
    ]);
    assert_clean_failure(&o, &gout, "grid");
    let e = stderr(&o);
    assert!(
        e.contains("extent") && e.contains("1000000000000000"),
        "{e}"
    );
}

/// Ctrl-C during `simulate`: the temporaries are removed, exit 130.
#[test]
fn interrupted_simulate_leaves_no_partial_file() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("sim");
    let mut child = ebptv()
        .args([
            "simulate",
            "--preset",
            "water_jet_5khz",
            "--seconds",
            "5",
            "--out",
        ])
        .arg(&out)
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    // Wait until the run writes, then interrupt.
    let t0 = std::time::Instant::now();
    while t0.elapsed().as_secs() < 20 {
        let partial = std::fs::read_dir(dir.path())
            .into_iter()
            .flatten()
            .chain(std::fs::read_dir(&out).into_iter().flatten())
            .any(|e| {
                e.unwrap()
                    .file_name()
                    .to_string_lossy()
                    .ends_with(".partial")
            });
        if partial || child.try_wait().unwrap().is_some() {
            break;
        }
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    unsafe {
        libc::kill(child.id() as i32, libc::SIGINT);
    }
    let status = child.wait().unwrap();
    let mut left = Vec::new();
    for d in [dir.path(), out.as_path()] {
        for e in std::fs::read_dir(d).into_iter().flatten() {
            let name = e.unwrap().file_name().to_string_lossy().into_owned();
            if name.ends_with(".partial") {
                left.push(name);
            }
        }
    }
    assert!(left.is_empty(), "{left:?} (exit {status:?})");
    if status.code() != Some(0) {
        assert_eq!(status.code(), Some(130));
    }
}

/// Small items: random bytes named .raw are refused; a `% format` line
/// contradicting `% evt` is refused (and read when --format names it);
/// `model-check --block-pulses 0` and absurd search budgets are refused;
/// convert lists anomalies in
/// words.
#[test]
fn small_items() {
    let dir = tempfile::tempdir().unwrap();
    let mut s: u64 = 99;
    let bytes: Vec<u8> = (0..200_000)
        .map(|_| {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (s >> 56) as u8
        })
        .collect();
    let f = dir.path().join("noise.raw");
    std::fs::write(&f, &bytes).unwrap();
    let o = run(&["info".as_ref(), f.as_os_str()]);
    assert_eq!(o.status.code(), Some(1), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("does not define") && stderr(&o).contains("noise.raw"),
        "{}",
        stderr(&o)
    );

    let o = run(&[
        "model-check".as_ref(),
        f.as_os_str(),
        "--block-pulses".as_ref(),
        "0".as_ref(),
        "--out".as_ref(),
        dir.path().join("mc").as_os_str(),
    ]);
    assert_eq!(o.status.code(), Some(1));
    assert!(
        stderr(&o).contains("block-pulses") && stderr(&o).contains("at least 20"),
        "{}",
        stderr(&o)
    );
    // A search budget that would run for days is refused up front too.
    for (opt, value) in [("--replicates", "1000000"), ("--evaluations", "100000000")] {
        let o = run(&[
            "model-check".as_ref(),
            f.as_os_str(),
            opt.as_ref(),
            value.as_ref(),
            "--out".as_ref(),
            dir.path().join("mc").as_os_str(),
        ]);
        assert_eq!(o.status.code(), Some(1));
        let e = stderr(&o);
        assert!(e.contains(&opt[2..]) && e.contains("at most"), "{e}");
        assert!(!dir.path().join("mc").exists());
    }

    let Some(real) = shared("real") else { return };
    let src = std::fs::read(real.join("evt3_sample.raw")).unwrap();
    let g = dir.path().join("contra.raw");
    std::fs::write(
        &g,
        [b"% format EVT2;height=720;width=1280\n".as_slice(), &src].concat(),
    )
    .unwrap();
    let o = run(&["info".as_ref(), g.as_os_str()]);
    assert_eq!(o.status.code(), Some(1));
    assert!(stderr(&o).contains("contradicts"), "{}", stderr(&o));
    let o = run(&[
        "info".as_ref(),
        g.as_os_str(),
        "--format".as_ref(),
        "evt2".as_ref(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));

    // A truncated copy: convert reports the tail in words.
    let t = dir.path().join("trunc.raw");
    std::fs::write(&t, &src[..src.len() - 1]).unwrap();
    let o = run(&[
        "convert".as_ref(),
        t.as_os_str(),
        dir.path().join("t.csv").as_os_str(),
    ]);
    let e = stderr(&o);
    assert!(!e.contains("Anomalies {"), "{e}");
}
