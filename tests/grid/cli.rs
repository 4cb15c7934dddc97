//! The `ebptv grid` / `ebptv spectra` commands end to end: file contracts,
//! split-and-merge through files, clear errors on bad input.
use crate::grid_common;

use std::path::Path;
use std::process::Command;

use grid_common::*;

/// `ebptv ARGS`; `grid` writes its tables as CSV here (the files these
/// cases read as text).
fn ebptv(args: &[&str]) -> (bool, String) {
    let csv: &[&str] = if args.first() == Some(&"grid") {
        &["--table-format", "csv"]
    } else {
        &[]
    };
    let o = Command::new(env!("CARGO_BIN_EXE_ebptv"))
        .args(csv)
        .args(args)
        .output()
        .unwrap();
    (
        o.status.success(),
        String::from_utf8_lossy(&o.stderr).into_owned(),
    )
}

fn read_csv(path: &Path) -> (String, Vec<Vec<f64>>) {
    let text = std::fs::read_to_string(path).unwrap();
    let mut lines = text.lines();
    let header = lines.next().unwrap().to_string();
    let rows = lines
        .map(|l| l.split(',').map(|v| v.parse::<f64>().unwrap()).collect())
        .collect();
    (header, rows)
}

/// The sheared flow the command-line cases bin.
fn shear_flow() -> Shear {
    Shear {
        u0: 300.0,
        shear: 2.0,
        su: 40.0,
        sv: 25.0,
        rho: -0.4,
    }
}

#[test]
fn grid_command_writes_the_contract_and_merges_to_the_single_run() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let f = shear_flow();
    let s = f.tracks(200.0, 120.0, 6000, 10, 100.0, 0.8, 21);
    write_tracks(&d.join("all.csv"), &s);
    write_tracks(&d.join("a.csv"), &s[..25_003]);
    write_tracks(&d.join("b.csv"), &s[25_003..]);
    let common = [
        "--bin",
        "16",
        "--overlap",
        "0.5",
        "--fit",
        "linear",
        "--min-count",
        "20",
    ];
    for (inp, out) in [("all.csv", "single"), ("a.csv", "a"), ("b.csv", "b")] {
        let mut args = vec![
            "grid".to_string(),
            d.join(inp).to_str().unwrap().to_string(),
        ];
        args.extend(common.iter().map(|s| s.to_string()));
        args.extend([
            "--out".to_string(),
            d.join(out).to_str().unwrap().to_string(),
        ]);
        if out == "single" {
            args.extend(["--fields-every".to_string(), "1".to_string()]);
        }
        let args: Vec<&str> = args.iter().map(|s| s.as_str()).collect();
        let (ok, err) = ebptv(&args);
        assert!(ok, "{err}");
    }
    let (ok, err) = ebptv(&[
        "grid",
        "--merge",
        d.join("a").to_str().unwrap(),
        d.join("b/grid_state.json").to_str().unwrap(),
        "--fit",
        "linear",
        "--min-count",
        "20",
        "--out",
        d.join("merged").to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    let (h1, single) = read_csv(&d.join("single/grid.csv"));
    let (h2, merged) = read_csv(&d.join("merged/grid.csv"));
    assert_eq!(h1, "x,y,count,u,v,uu,vv,uv");
    assert_eq!(h2, h1);
    assert_eq!(single.len(), merged.len());
    let mut valid = 0;
    for (r1, r2) in single.iter().zip(&merged) {
        for (a, b) in r1.iter().zip(r2) {
            assert!(
                (a.is_nan() && b.is_nan()) || (a - b).abs() <= 1e-9 * a.abs().max(1.0),
                "{r1:?} vs {r2:?}"
            );
        }
        valid += r1[3].is_finite() as usize;
    }
    assert!(valid > 100, "{valid}");
    // Means against truth, stresses sensible.
    for r in &single {
        // Bins whose support lies inside the seeded area (at the edges a
        // linear fit extrapolates to a centre outside the samples).
        if r[2] >= 200.0 && r[0] >= 8.0 && r[0] <= 192.0 && r[1] >= 8.0 && r[1] <= 112.0 {
            assert!(
                (r[3] - f.mean_u(r[1])).abs() < 20.0,
                "{r:?} truth {}",
                f.mean_u(r[1])
            );
        }
    }
    let (hx, extra) = read_csv(&d.join("single/grid_extra.csv"));
    assert_eq!(hx, ebptv::grid::io::EXTRA_HEADER);
    assert_eq!(extra.len(), single.len());
    assert!(d.join("single/map_u.png").exists() && d.join("single/grid.json").exists());
    // .npy arrays: (ny, nx) maps and (frames, ny, nx) fields whose counts
    // add up to the grid counts (each pulse in exactly one frame).
    let npy = |name: &str| {
        let b = std::fs::read(d.join("single").join(name)).unwrap();
        let h = ebptv::io::npy::parse_npy_header(&b).unwrap();
        assert_eq!(h.descr, "'<f8'");
        let v: Vec<f64> = b[h.data_offset..]
            .chunks(8)
            .map(|c| f64::from_le_bytes(c.try_into().unwrap()))
            .collect();
        (h.shape, v)
    };
    let (gs, gcount) = npy("grid_count.npy");
    let (_, gu) = npy("grid_u.npy");
    let (fs, fcount) = npy("fields_count.npy");
    assert_eq!(gs.len(), 2);
    assert_eq!(gs[0] * gs[1], single.len());
    assert_eq!(fs.len(), 3);
    assert_eq!(fs[0], 10, "10 pulses → 10 frames");
    assert_eq!(&fs[1..], &gs[..]);
    let nb = gs[0] * gs[1];
    for b in 0..nb {
        let sum: f64 = (0..fs[0]).map(|k| fcount[k * nb + b]).sum();
        assert_eq!(sum, gcount[b]);
        assert_eq!(gcount[b], single[b][2]);
        assert!(
            (gu[b].is_nan() && single[b][3].is_nan())
                || (gu[b] - single[b][3]).abs() < 1e-9 * gu[b].abs().max(1.0)
        );
    }
}

#[test]
fn profile_and_wall_from_the_command_line() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (h, umax) = (200.0, 800.0);
    let s = tracks_in_steady_flow(
        |_x, y| (umax * 4.0 * y * (h - y) / (h * h), 0.0),
        128.0,
        h,
        20_000,
        6,
        100.0,
        5.0,
        22,
    );
    write_tracks(&d.join("t.csv"), &s);
    let (ok, err) = ebptv(&[
        "grid",
        d.join("t.csv").to_str().unwrap(),
        "--bin",
        "64",
        "--bin-h",
        "2",
        "--origin",
        "0,0",
        "--fit",
        "linear",
        "--profile-x",
        "64",
        "--wall",
        "top",
        "--px-per-mm",
        "10",
        "--wall-points",
        "3",
        "--out",
        d.join("o").to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    let j: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.join("o/grid.json")).unwrap()).unwrap();
    let wall_y = j["wall"]["wall_y_px"].as_f64().unwrap();
    let dudy = j["wall"]["dudy_per_s"].as_f64().unwrap();
    assert!(
        wall_y.abs() < 0.5,
        "{wall_y} {}",
        std::fs::read_to_string(d.join("o/profile.csv")).unwrap()
    );
    assert!(
        (dudy - 4.0 * umax / h).abs() < 0.05 * 4.0 * umax / h,
        "{dudy}"
    );
    let (hdr, rows) = read_csv(&d.join("o/profile.csv"));
    assert_eq!(hdr, "y,count,u,v,uu,vv,uv,y_plus,u_plus,uu_plus");
    assert!(rows.len() >= 95);
}

#[test]
fn bad_input_gives_clear_errors_and_no_output() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let s = tracks_in_steady_flow(|_, _| (10.0, 0.0), 64.0, 64.0, 100, 5, 100.0, 1.0, 23);
    write_tracks(&d.join("t.csv"), &s);
    std::fs::write(d.join("empty.csv"), "").unwrap();
    std::fs::write(d.join("header.csv"), "track_id,pulse,t_us,x,y,u,v\n").unwrap();
    std::fs::write(
        d.join("bad.csv"),
        "track_id,pulse,t_us,x,y,u,v\n1,0,0,1,2,3,4\n1,1,100,1,2,x,4\n",
    )
    .unwrap();
    let t = d.join("t.csv");
    let t = t.to_str().unwrap();
    let cases: Vec<(Vec<String>, &str)> = vec![
        (vec![t.into(), "--bin".into(), "0".into()], "bin"),
        (vec![t.into(), "--bin=-3".into()], "bin"),
        // 3200 x 3200 bins: refused before ~17 GB are allocated.
        (vec![t.into(), "--bin".into(), "0.02".into()], "larger bin"),
        (vec![t.into(), "--overlap".into(), "1".into()], "overlap"),
        (
            vec![t.into(), "--min-count".into(), "0".into()],
            "min-count",
        ),
        (
            vec![t.into(), "--profile-x".into(), "nan".into()],
            "profile_x",
        ),
        (
            vec![t.into(), "--fields-every".into(), "0".into()],
            "fields_every",
        ),
        (
            vec![
                t.into(),
                "--profile-x".into(),
                "32".into(),
                "--px-per-mm".into(),
                "0".into(),
            ],
            "px_per_mm",
        ),
        // Wall-unit options without the wall fit they serve (ignored
        // before, NaN included).
        (vec![t.into(), "--nu".into(), "nan".into()], "--wall"),
        (
            vec![t.into(), "--px-per-mm".into(), "10".into()],
            "--profile-x",
        ),
        (vec![d.join("empty.csv").to_str().unwrap().into()], "empty"),
        (
            vec![d.join("header.csv").to_str().unwrap().into()],
            "no track points",
        ),
        (vec![d.join("bad.csv").to_str().unwrap().into()], "line 3"),
        (
            vec![d.join("missing.csv").to_str().unwrap().into()],
            "missing.csv",
        ),
    ];
    for (k, (args, needle)) in cases.iter().enumerate() {
        let out = d.join(format!("o{k}"));
        let mut a = vec!["grid".to_string()];
        a.extend(args.iter().cloned());
        a.extend(["--out".into(), out.to_str().unwrap().into()]);
        let a: Vec<&str> = a.iter().map(|s| s.as_str()).collect();
        let (ok, err) = ebptv(&a);
        assert!(!ok, "{a:?} should fail");
        assert!(err.contains(needle), "{a:?}: {err}");
        assert!(!out.join("grid.csv").exists());
    }
    // Incompatible merge.
    for (bin, out) in [("16", "m1"), ("8", "m2")] {
        let (ok, err) = ebptv(&[
            "grid",
            t,
            "--bin",
            bin,
            "--out",
            d.join(out).to_str().unwrap(),
        ]);
        assert!(ok, "{err}");
    }
    let (ok, err) = ebptv(&[
        "grid",
        "--merge",
        d.join("m1").to_str().unwrap(),
        d.join("m2").to_str().unwrap(),
        "--out",
        d.join("mm").to_str().unwrap(),
    ]);
    assert!(!ok);
    assert!(err.contains("incompatible grids"), "{err}");
    assert!(!d.join("mm/grid.csv").exists());
}

/// `ebptv track REC --grid "..."`: tracking and binning in one go, the grid
/// in OUT/grid with maps, time-resolved fields and the noise / dynamic
/// range keys; bad grid options are refused before tracking starts.
#[test]
fn track_with_grid_in_one_go() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let sim = d.join("sim");
    let (ok, err) = ebptv(&[
        "simulate",
        "--preset",
        "demo",
        "--seconds",
        "0.01",
        "--out",
        sim.to_str().unwrap(),
    ]);
    assert!(ok, "{err}");
    let rec = sim.join("recording.raw");
    let ptv = d.join("ptv");
    let (ok, err) = ebptv(&[
        "track",
        rec.to_str().unwrap(),
        "--out",
        ptv.to_str().unwrap(),
        "--grid",
        "--bin 16 --fit linear --fields-every 2",
    ]);
    assert!(ok, "{err}");
    let g = ptv.join("grid");
    // The grid tables follow the run's table format (Parquet by default).
    assert!(!g.join("grid.csv").exists());
    for f in [
        "grid.parquet",
        "grid_extra.parquet",
        "grid_u.npy",
        "map_u.png",
        "map_uu.png",
        "fields_u.npy",
        "grid_state.json",
    ] {
        assert!(g.join(f).is_file(), "{f} missing");
    }
    let j: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(g.join("grid.json")).unwrap()).unwrap();
    let noise = j["velocity_noise_rms"].as_f64().unwrap();
    let dvr = j["dynamic_range"].as_f64().unwrap();
    let vmax = j["max_mean_speed"].as_f64().unwrap();
    assert!(
        noise > 0.0 && (dvr - vmax / noise).abs() < 1e-6 * dvr,
        "{j}"
    );
    assert_eq!(j["fit"], "linear");

    let bad = d.join("bad");
    let (ok, err) = ebptv(&[
        "track",
        rec.to_str().unwrap(),
        "--out",
        bad.to_str().unwrap(),
        "--grid",
        "--bogus 3",
    ]);
    assert!(!ok);
    assert!(err.contains("--grid") && err.contains("--bogus"), "{err}");
    assert!(
        !bad.join("tracks.parquet").exists(),
        "tracked despite bad --grid"
    );
}

/// `ebptv grid run/tracks.*`: the shell pattern also names the run's
/// figure, which is skipped (same grid as the table alone); two tables are
/// an error that names both and writes nothing.
#[test]
fn grid_takes_the_table_of_a_pattern_and_refuses_two_tables() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let f = shear_flow();
    let s = f.tracks(200.0, 120.0, 2000, 10, 100.0, 0.8, 5);
    let tracks = d.join("tracks.csv");
    write_tracks(&tracks, &s);
    // A real PNG beside it, as `ebptv track` leaves one.
    let png = d.join("tracks.png");
    ebptv::plot::heatmap(
        &png,
        &ebptv::plot::Heatmap {
            title: "t",
            values: &[0.0, 1.0],
            nx: 2,
            ny: 1,
            x_range: (0.0, 2.0),
            y_range: (0.0, 1.0),
            colorbar_label: "v",
            diverging: false,
            axes_mm: None,
        },
    )
    .unwrap();
    let p = |x: &Path| x.display().to_string();
    let (ok, err) = ebptv(&["grid", &p(&tracks), "--out", &p(&d.join("one"))]);
    assert!(ok, "{err}");
    let (ok, err) = ebptv(&["grid", &p(&tracks), &p(&png), "--out", &p(&d.join("both"))]);
    assert!(ok, "{err}");
    assert!(
        err.contains("skipping") && err.contains("tracks.png"),
        "{err}"
    );
    assert_eq!(
        std::fs::read_to_string(d.join("one/grid.csv")).unwrap(),
        std::fs::read_to_string(d.join("both/grid.csv")).unwrap()
    );
    let other = d.join("other.csv");
    write_tracks(&other, &s);
    let out = d.join("two");
    let (ok, err) = ebptv(&["grid", &p(&tracks), &p(&other), "--out", &p(&out)]);
    assert!(!ok);
    assert!(
        err.contains("2 tracks tables") && err.contains("other.csv") && err.contains("--merge"),
        "{err}"
    );
    assert!(!out.exists());
}
