//! `ebptv track` on a particles.csv: outputs, contracts and bad input.
use crate::cli_common;

use cli_common::{ebptv, run_ok};

use ebptv::cluster::{cluster_pulse, ClusterParams};
use ebptv::track::synth::{generate, SynthParams};

/// A synthetic 128×128 scene of `pulses` pulses, clustered with the
/// defaults and written as `dir/particles.csv` (its path and particles).
fn synthetic_particles_csv(
    dir: &std::path::Path,
    pulses: usize,
) -> (std::path::PathBuf, Vec<ebptv::cluster::Particle>) {
    let scene = generate(&SynthParams {
        pulses,
        width: 128,
        height: 128,
        ..Default::default()
    });
    let particles: Vec<_> = scene
        .iter()
        .flat_map(|s| cluster_pulse(&s.pulse, &ClusterParams::default()))
        .collect();
    let input = dir.join("particles.csv");
    ebptv::track::write_particles_csv(&input, &particles).unwrap();
    (input, particles)
}

#[test]
fn links_a_particles_csv() {
    let dir = tempfile::tempdir().unwrap();
    let (input, particles) = synthetic_particles_csv(dir.path(), 30);
    let out = dir.path().join("out");
    let params = dir.path().join("npy.toml");
    std::fs::write(&params, "[run]\nnpy = true\n").unwrap();
    run_ok(
        ebptv()
            .arg("track")
            .arg(&input)
            .arg("--out")
            .arg(&out)
            .arg("--params")
            .arg(&params),
    );
    let tracks = ebptv::track::read_tracks(&out.join("tracks.parquet")).unwrap();
    assert!(tracks.len() > 50, "{} tracks", tracks.len());
    for t in &tracks {
        // min_length 5, or 4 for tracks that agree with the local flow.
        assert!(t.points.len() >= 4);
        assert!(t.points.windows(2).all(|w| w[1].pulse == w[0].pulse + 1));
    }
    let back = ebptv::track::read_particles(&out.join("particles.parquet")).unwrap();
    assert_eq!(back.len(), particles.len());
    let summary: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("summary.json")).unwrap()).unwrap();
    assert_eq!(summary["tracks"].as_u64().unwrap(), tracks.len() as u64);
    assert_eq!(
        summary["particles"].as_u64().unwrap(),
        particles.len() as u64
    );
    let f = summary["fraction_on_tracks"].as_f64().unwrap();
    assert!(f > 0.5 && f <= 1.0, "{f}");
    assert!(out.join("tracks.png").exists());
    let npy = std::fs::read(out.join("tracks.npy")).unwrap();
    let h = ebptv::io::npy::parse_npy_header(&npy).unwrap();
    assert!(
        h.descr.contains("track_id") && h.descr.contains("'v'"),
        "{}",
        h.descr
    );
    let rows: usize = tracks.iter().map(|t| t.points.len()).sum();
    assert_eq!(h.shape, vec![rows]);
    // Streamed records: 56 bytes each, the last one the last CSV row.
    assert_eq!(npy.len(), h.data_offset + 56 * rows);
    let last = &npy[npy.len() - 56..];
    let (t, p) = (
        tracks.last().unwrap(),
        tracks.last().unwrap().points.last().unwrap(),
    );
    assert_eq!(u64::from_le_bytes(last[..8].try_into().unwrap()), t.id);
    assert_eq!(i64::from_le_bytes(last[8..16].try_into().unwrap()), p.pulse);
    let x = f64::from_le_bytes(last[24..32].try_into().unwrap());
    assert!((x - p.x).abs() <= 5e-5, "{x} vs {}", p.x);
    // Nothing but the outputs in the directory (no temporary files).
    let mut names: Vec<String> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    assert_eq!(
        names,
        [
            "params.toml",
            "particles.parquet",
            "provenance.json",
            "summary.json",
            "tracks.npy",
            "tracks.parquet",
            "tracks.png"
        ]
    );
}

/// `ebptv track ARGS… INPUT --out OUT`: its exit code and its stderr.
fn track_status(
    args: &[&str],
    input: &std::path::Path,
    out: &std::path::Path,
) -> (Option<i32>, String) {
    let st = ebptv()
        .arg("track")
        .args(args)
        .arg(input)
        .arg("--out")
        .arg(out)
        .output()
        .unwrap();
    (
        st.status.code(),
        String::from_utf8_lossy(&st.stderr).into_owned(),
    )
}

#[test]
fn bad_input_gives_clear_errors_and_no_outputs() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("particles.csv");
    let out = dir.path().join("out");
    std::fs::write(&input, "pulse,t_us,x,n_events\n0,0,1,1\n").unwrap();
    let (code, err) = track_status(&[], &input, &out);
    assert!(
        code == Some(1) && err.contains("missing column(s) y"),
        "{err}"
    );
    assert!(!out.join("tracks.parquet").exists() && !out.join("particles.parquet").exists());

    std::fs::write(
        &input,
        "pulse,t_us,x,y,n_events\n0,0,1,1,1\n1,200,nan,1,1\n",
    )
    .unwrap();
    let (code, err) = track_status(&[], &input, &out);
    assert!(code == Some(1) && err.contains("line 3"), "{err}");
    // Failed runs leave nothing behind, not even temporary files.
    let left: Vec<_> = std::fs::read_dir(&out)
        .map(|d| d.map(|e| e.unwrap().file_name()).collect())
        .unwrap_or_default();
    assert!(left.is_empty(), "{left:?}");

    // Impossible, absurdly large or non-finite values are refused up
    // front, naming the parameter. (A batch of 10^12 pulses aborted on its
    // allocation.)
    std::fs::write(&input, "pulse,t_us,x,y,n_events\n0,0,1,1,1\n").unwrap();
    let params = dir.path().join("batch.toml");
    std::fs::write(&params, "[run]\nbatch = 1000000000000\n").unwrap();
    let params = params.to_str().unwrap();
    for (args, name) in [
        (&["--radius=0"][..], "radius"),
        (&["--radius=-1"][..], "radius"),
        (&["--max-disp", "0"][..], "max_disp"),
        (&["--max-disp", "1e9"][..], "max_disp"),
        (&["--min-length", "1000000000"][..], "min_length"),
        (&["--prior", "nan", "0"][..], "run.prior"),
        (&["--prior", "0", "inf"][..], "run.prior"),
        (&["--params", params][..], "batch"),
    ] {
        let (code, err) = track_status(args, &input, &out);
        assert!(code == Some(1) && err.contains(name), "{args:?}: {err}");
    }
}

/// A `--max-disp` below the tracker's smallest search radii (a slow flow,
/// 0.3 px per pulse here) bounds every search instead of stopping the run
/// (it panicked on `clamp(min > max)`): every particle is tracked at its
/// own speed.
#[test]
fn max_disp_below_the_search_floors_runs() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("particles.csv");
    let mut csv = String::from("pulse,t_us,x,y,n_events\n");
    for pulse in 0..20 {
        for k in 0..16 {
            let (x, y) = (10.0 + 12.0 * (k % 4) as f64, 10.0 + 12.0 * (k / 4) as f64);
            let x = x + 0.3 * pulse as f64;
            csv += &format!("{pulse},{},{x},{y},2\n", 200 * pulse);
        }
    }
    std::fs::write(&input, csv).unwrap();
    let out = dir.path().join("out");
    run_ok(
        ebptv()
            .args(["track", "--max-disp", "0.4"])
            .arg(&input)
            .arg("--out")
            .arg(&out),
    );
    let tracks = ebptv::track::read_tracks(&out.join("tracks.parquet")).unwrap();
    assert_eq!(tracks.len(), 16);
    for t in tracks {
        assert_eq!(t.points.len(), 20, "track {}", t.id);
        for p in &t.points {
            // 0.3 px per 200 µs = 1500 px/s.
            assert!((p.u - 1500.0).abs() < 1.0 && p.v.abs() < 1.0, "{p:?}");
        }
    }
}

/// The sliced linker and the sequential one (default) on the same
/// particles.csv, with short slices so that several seams are crossed:
/// both link nearly every particle the same way (the accuracy comparison
/// on truth is tests/ptv_slice.rs), detections are never shared, and a
/// slice of zero pulses is refused.
#[test]
fn sliced_and_sequential_linkers_agree() {
    let dir = tempfile::tempdir().unwrap();
    let (input, _) = synthetic_particles_csv(dir.path(), 80);
    let run = |name: &str, args: &[&str]| {
        let out = dir.path().join(name);
        run_ok(
            ebptv()
                .arg("track")
                .arg(&input)
                .arg("--out")
                .arg(&out)
                .args(args),
        );
        let summary: serde_json::Value =
            serde_json::from_slice(&std::fs::read(out.join("summary.json")).unwrap()).unwrap();
        let tracks = ebptv::track::read_tracks(&out.join("tracks.parquet")).unwrap();
        (tracks, summary)
    };
    let params = |name: &str, text: &str| {
        let p = dir.path().join(name);
        std::fs::write(&p, text).unwrap();
        p.display().to_string()
    };
    let seq_toml = params("seq.toml", "[run]\nlinker = \"sequential\"\n");
    let sli_toml = params(
        "sli.toml",
        "[run]\nlinker = \"sliced\"\nslice_pulses = 16\nslice_overlap = 12\n",
    );
    let (seq, seq_summary) = run("seq", &["--params", &seq_toml]);
    let (sli, sli_summary) = run("sli", &["--params", &sli_toml]);
    let points = |ts: &[ebptv::track::Track]| ts.iter().map(|t| t.points.len()).sum::<usize>();
    let (a, b) = (points(&seq) as f64, points(&sli) as f64);
    assert!(
        a > 10_000.0 && (a - b).abs() < 0.01 * a,
        "{a} vs {b} points"
    );
    let mut seen = std::collections::HashSet::new();
    for t in &sli {
        // min_length 5, or 4 for tracks that agree with the local flow.
        assert!(t.points.len() >= 4);
        assert!(t.points.windows(2).all(|w| w[1].pulse == w[0].pulse + 1));
        for p in &t.points {
            assert!(seen.insert((p.pulse, p.x.to_bits(), t.id)));
        }
    }
    let fa = seq_summary["fraction_on_tracks"].as_f64().unwrap();
    let fb = sli_summary["fraction_on_tracks"].as_f64().unwrap();
    assert!((fa - fb).abs() < 0.01, "{fa} vs {fb}");
    assert_eq!(sli_summary["tracks"].as_u64().unwrap(), sli.len() as u64);

    let zero = params(
        "zero.toml",
        "[run]\nlinker = \"sliced\"\nslice_pulses = 0\n",
    );
    let st = ebptv()
        .args(["track", "--params", &zero])
        .arg(&input)
        .arg("--out")
        .arg(dir.path().join("zero"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&st.stderr);
    assert!(!st.status.success() && err.contains("slice"), "{err}");
}

/// The params.toml a run writes, passed back, gives the same outputs; a
/// command-line option beats the file; an unknown key is refused with its
/// name and the file's.
#[test]
fn params_file_round_trip_override_and_unknown_keys() {
    let dir = tempfile::tempdir().unwrap();
    let (input, _) = synthetic_particles_csv(dir.path(), 40);
    let track = |out: &str, args: &[&str]| {
        let out = dir.path().join(out);
        let st = ebptv()
            .arg("track")
            .arg(&input)
            .arg("--out")
            .arg(&out)
            .args(args)
            .output()
            .unwrap();
        (out, st)
    };
    let read = |p: std::path::PathBuf| std::fs::read_to_string(p).unwrap();
    // Non-default options on the command line end up in params.toml.
    let (a, st) = track("a", &["--max-disp", "8", "--gap", "2", "--min-length", "6"]);
    assert!(
        st.status.success(),
        "{}",
        String::from_utf8_lossy(&st.stderr)
    );
    let written = read(a.join("params.toml"));
    assert!(written.contains("max_disp = 8.0"), "{written}");
    assert!(written.contains("max_gap = 2"), "{written}");
    let params = a.join("params.toml").display().to_string();
    let (b, st) = track("b", &["--params", &params]);
    assert!(
        st.status.success(),
        "{}",
        String::from_utf8_lossy(&st.stderr)
    );
    // The same tables (the files' metadata differ: each records its own
    // command line), the same parameters.
    assert_eq!(read(a.join("params.toml")), read(b.join("params.toml")));
    let tables = |d: &std::path::Path| {
        format!(
            "{:?}{:?}",
            ebptv::track::read_tracks(&d.join("tracks.parquet")).unwrap(),
            ebptv::track::read_particles(&d.join("particles.parquet")).unwrap()
        )
    };
    assert_eq!(tables(&a), tables(&b));
    let prov = |d: &std::path::Path| {
        ebptv::provenance::Provenance::read_from_dir(d)
            .unwrap()
            .unwrap()
    };
    let (pa, pb) = (prov(&a), prov(&b));
    assert_eq!(pa.parameters, pb.parameters);
    assert!(pa.command_line.iter().any(|w| w == "--max-disp"), "{pa:?}");
    assert!(pb.command_line.iter().any(|w| w == "--params"), "{pb:?}");
    assert_eq!(pa.inputs, pb.inputs);
    let meta = ebptv::table::parquet_metadata(&b.join("tracks.parquet")).unwrap();
    let recorded = meta
        .iter()
        .find(|(k, _)| k == ebptv::provenance::PARQUET_KEY)
        .and_then(|(_, v)| v.clone())
        .expect("provenance in the Parquet metadata");
    assert_eq!(
        serde_json::from_str::<serde_json::Value>(&recorded).unwrap(),
        pb.to_json()
    );
    let strip = |p: std::path::PathBuf| -> serde_json::Value {
        let mut v: serde_json::Value = serde_json::from_str(&read(p)).unwrap();
        v.as_object_mut()
            .unwrap()
            .retain(|k, _| !k.contains("time") && k != "provenance");
        v
    };
    assert_eq!(strip(a.join("summary.json")), strip(b.join("summary.json")));
    // The command line beats the file.
    let (c, st) = track("c", &["--params", &params, "--min-length", "9"]);
    assert!(
        st.status.success(),
        "{}",
        String::from_utf8_lossy(&st.stderr)
    );
    let written = read(c.join("params.toml"));
    assert!(written.contains("min_length = 9"), "{written}");
    assert!(written.contains("max_disp = 8.0"), "{written}");
    let tracks = ebptv::track::read_tracks(&c.join("tracks.parquet")).unwrap();
    let before = ebptv::track::read_tracks(&a.join("tracks.parquet")).unwrap();
    assert!(
        !tracks.is_empty() && tracks.len() < before.len(),
        "{} vs {} tracks",
        tracks.len(),
        before.len()
    );
    // An unknown key: the file and the key named, no outputs.
    let bad = dir.path().join("bad.toml");
    std::fs::write(&bad, "[track.gates]\nn_sigma = 3.0\nsearch_sigma = 2.0\n").unwrap();
    let (d, st) = track("d", &["--params", &bad.display().to_string()]);
    let err = String::from_utf8_lossy(&st.stderr);
    assert!(!st.status.success(), "{err}");
    assert!(
        err.contains("bad.toml") && err.contains("search_sigma"),
        "{err}"
    );
    assert!(!d.join("tracks.parquet").exists());
}
