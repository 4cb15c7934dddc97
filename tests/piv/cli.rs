//! End-to-end runs of `ebptv piv-images` and `ebptv compare`.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use ebptv::piv::images::save_png16;
use ebptv::piv::synth::{particle_frames, SynthOptions};

fn ebptv() -> Command {
    Command::new(env!("CARGO_BIN_EXE_ebptv"))
}

/// `frames` synthetic frames of `width`×`height` moving by `shift`, saved
/// as 16-bit PNGs `f0.png`, `f1.png`, … in `dir`.
fn png_frames(
    dir: &Path,
    width: usize,
    height: usize,
    frames: usize,
    shift: (f64, f64),
    full_scale: f32,
) -> Vec<PathBuf> {
    let so = SynthOptions {
        width,
        height,
        frames,
        seed: 3,
        ..Default::default()
    };
    let images = particle_frames(&so, &|_, _| shift);
    images
        .iter()
        .enumerate()
        .map(|(k, im)| {
            let path = dir.join(format!("f{k}_{width}x{height}.png"));
            save_png16(&path, im, full_scale).unwrap();
            path
        })
        .collect()
}

/// `ebptv --table-format csv piv-images IMAGES… OPTIONS… --out OUT`.
fn piv_images(images: &[&Path], options: &[&str], out: &Path) -> Output {
    let mut cmd = ebptv();
    cmd.args(["--table-format", "csv", "piv-images"])
        .args(images)
        .args(options)
        .arg("--out")
        .arg(out);
    cmd.output().unwrap()
}

/// The run failed and its error message mentions `what`.
fn assert_refused(r: &Output, what: &str) {
    let err = String::from_utf8_lossy(&r.stderr);
    assert!(
        !r.status.success(),
        "expected a failure mentioning {what:?}"
    );
    assert!(err.contains(what), "{err}");
}

#[test]
fn piv_images_on_png_pair_recovers_the_shift() {
    let dir = tempfile::tempdir().unwrap();
    let f = png_frames(dir.path(), 128, 96, 2, (2.4, -1.2), 20000.0);
    let out = dir.path().join("out");
    let st = piv_images(
        &[&f[0], &f[1]],
        &["--window", "32", "--spacing", "16"],
        &out,
    )
    .status;
    assert!(st.success());
    let csv = std::fs::read_to_string(out.join("vectors_00000.csv")).unwrap();
    let mut lines = csv.lines();
    assert_eq!(lines.next().unwrap(), "x,y,u,v,flag");
    let mut n = 0;
    for l in lines {
        let f: Vec<f64> = l.split(',').map(|s| s.parse().unwrap()).collect();
        if f[4] == 0.0 {
            assert!((f[2] - 2.4).abs() < 0.1 && (f[3] + 1.2).abs() < 0.1, "{l}");
            n += 1;
        }
    }
    assert!(n >= 32, "{n} of 35 vectors valid");
}

#[test]
fn piv_images_rejects_different_sizes_and_big_windows() {
    let dir = tempfile::tempdir().unwrap();
    let a = &png_frames(dir.path(), 64, 64, 1, (0.0, 0.0), 1000.0)[0];
    let b = &png_frames(dir.path(), 48, 64, 1, (0.0, 0.0), 1000.0)[0];
    let out = dir.path().join("o");
    assert_refused(&piv_images(&[a, b], &[], &out), "same size");
    assert_refused(
        &piv_images(&[a, a], &["--window", "128"], &out),
        "larger than",
    );
    assert_refused(&piv_images(&[a, a], &["--spacing", "0"], &out), "spacing");
}

#[test]
fn compare_writes_json_with_known_differences() {
    let dir = tempfile::tempdir().unwrap();
    let mut piv = String::from("x,y,u,v,uu,vv,uv,valid\n");
    for j in 0..5 {
        for i in 0..5 {
            let (x, y) = (16.0 * i as f64, 16.0 * j as f64);
            piv.push_str(&format!("{x},{y},{},{},1,1,0,1\n", 100.0 + x, -y));
        }
    }
    let mut ptv = String::from("x,y,count,u,v,uu,vv,uv\n");
    for j in 0..8 {
        for i in 0..8 {
            let (x, y) = (4.0 + 8.0 * i as f64, 4.0 + 8.0 * j as f64);
            ptv.push_str(&format!("{x},{y},5,{},{},1,1,0\n", 100.0 + x + 2.0, -y));
        }
    }
    std::fs::write(dir.path().join("piv_mean.csv"), piv).unwrap();
    std::fs::write(dir.path().join("grid.csv"), ptv).unwrap();
    let out = dir.path().join("cmp");
    let st = ebptv()
        .args([
            "compare",
            "--ptv",
            dir.path().join("grid.csv").to_str().unwrap(),
            "--piv",
            dir.path().join("piv_mean.csv").to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ])
        .status()
        .unwrap();
    assert!(st.success());
    let j: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("compare.json")).unwrap()).unwrap();
    assert!(
        (j["u"]["mean_diff"].as_f64().unwrap() - 2.0).abs() < 1e-9,
        "{j}"
    );
    assert!(j["v"]["rms_diff"].as_f64().unwrap() < 1e-9);
    assert_eq!(j["compared_bins"].as_u64().unwrap(), 64);
}

/// A recording without a pulse train (events at random times, as under
/// continuous illumination): `ebptv piv` must say there are no pulses and
/// write nothing.
#[test]
fn piv_on_a_recording_without_pulses_is_a_clear_error() {
    use ebptv::events::{Chunk, Geometry};
    use rand::{Rng, SeedableRng};
    let dir = tempfile::tempdir().unwrap();
    let rec = dir.path().join("continuous.raw");
    let mut w = ebptv::io::create(
        &rec,
        None,
        Geometry {
            width: 128,
            height: 96,
        },
    )
    .unwrap();
    let mut rng = rand_pcg::Pcg64::seed_from_u64(4);
    let mut chunk = Chunk::default();
    let mut t = 0i64;
    for _ in 0..40_000 {
        t += rng.gen_range(0..6);
        chunk
            .events
            .push(t, rng.gen_range(0..128), rng.gen_range(0..96), 1);
    }
    w.write_chunk(&chunk).unwrap();
    w.finish().unwrap();
    let out = dir.path().join("o");
    let r = ebptv()
        .args(["piv", rec.to_str().unwrap(), "--out", out.to_str().unwrap()])
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&r.stderr);
    assert!(!r.status.success());
    assert!(err.contains("no pulse"), "{err}");
    assert!(!out.join("piv_mean.parquet").exists());
}

/// The pyramid depth is checked against the frames before any work.
#[test]
fn piv_images_rejects_a_pyramid_deeper_than_the_frames() {
    let dir = tempfile::tempdir().unwrap();
    let f = png_frames(dir.path(), 64, 64, 2, (1.0, 0.0), 1000.0);
    let out = dir.path().join("o");
    assert_refused(
        &piv_images(&[&f[0], &f[1]], &["--pyramid", "2"], &out),
        "pyramid",
    );
}
