//! Physical units and masks through the command line: a simulated channel
//! recorded, tracked with a calibration and a mask of its walls, binned in
//! m/s; and the automatic mask of `ebptv pulses --write-mask`.

use std::path::Path;
use std::process::Command;

use ebptv::calib::PixelMask;
use ebptv::sim::scenario::{FlowSpec, HotPixels, Scenario};

/// `ebptv ARGS`; `grid` writes its tables as CSV here (the files these
/// cases read as text).
fn ebptv(args: &[&str]) -> String {
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
    let err = String::from_utf8_lossy(&o.stderr).to_string();
    assert!(o.status.success(), "ebptv {args:?}: {err}");
    err
}

/// The demo scene on a 320 × 160 sensor, 150 pulses at 5 kHz.
fn scene(flow: FlowSpec) -> Scenario {
    let mut sc = ebptv::sim::presets::preset("demo").unwrap();
    sc.duration_s = 0.03;
    sc.sensor.width = 320;
    sc.sensor.height = 160;
    sc.flow = flow;
    sc
}

fn simulate(sc: &Scenario, dir: &Path) -> String {
    let toml = dir.join("scenario.toml");
    std::fs::write(&toml, toml::to_string(sc).unwrap()).unwrap();
    let out = dir.join("sim");
    ebptv(&[
        "simulate",
        "--config",
        toml.to_str().unwrap(),
        "--seed",
        "4",
        "--out",
        out.to_str().unwrap(),
    ]);
    out.join("recording.raw").display().to_string()
}

/// A CSV as its header and rows of numbers (`nan` → NaN).
fn table(path: &Path) -> (Vec<String>, Vec<Vec<f64>>) {
    let text = std::fs::read_to_string(path).unwrap();
    let mut lines = text.lines();
    let head = lines.next().unwrap().split(',').map(String::from).collect();
    let rows = lines
        .map(|l| l.split(',').map(|v| v.parse().unwrap()).collect())
        .collect();
    (head, rows)
}

fn col(head: &[String], name: &str) -> usize {
    head.iter()
        .position(|h| h == name)
        .unwrap_or_else(|| panic!("no column {name} in {head:?}"))
}

/// A Poiseuille profile across the whole sensor (u_max 20 000 px/s =
/// 4 px/pulse), whose bands y < 16 and y ≥ 145 are masked as walls: at
/// 10 px/mm, 20 000 px/s is 2 m/s. With the mask no track point and no
/// grid vector lies in the walls (the wall bins, 15 or 16 of their 16 rows
/// masked, are NaN and counted in grid.json), while without it they are
/// full; the interior bins keep the unmasked run's means within 0.3 % of
/// u_max and the truth within 1 %; the physical columns are the pixel ones
/// scaled (origin at y = 80 px, y up).
#[test]
fn masked_channel_walls_keep_the_interior_profile_and_give_no_vectors() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (u_max, y0, width) = (20_000.0, -48.0, 256.0);
    let rec = simulate(&scene(FlowSpec::Poiseuille { u_max, y0, width }), d);
    let truth = |y: f64| {
        let s = (y - y0) / width;
        4.0 * u_max * s * (1.0 - s)
    };
    let mut wall = PixelMask::new(320, 160);
    for y in (0..16).chain(145..160) {
        for x in 0..320 {
            wall.set(x, y);
        }
    }
    let mask = d.join("walls.png");
    wall.write_png(&mask).unwrap();
    let calib = d.join("calib.toml");
    std::fs::write(
        &calib,
        "px_per_mm = 10.0\norigin_px = [0.0, 80.0]\ny_axis = \"up\"\n",
    )
    .unwrap();
    let p = |x: &Path| x.display().to_string();
    let (plain, masked) = (d.join("plain"), d.join("masked"));
    ebptv(&["--table-format", "csv", "track", &rec, "--out", &p(&plain)]);
    ebptv(&[
        "--table-format",
        "csv",
        "track",
        &rec,
        "--calibration",
        &p(&calib),
        "--mask",
        &p(&mask),
        "--out",
        &p(&masked),
    ]);
    let grid = |tracks: &Path, out: &Path, calibrated: bool| {
        let mut a = vec!["grid".to_string(), p(tracks)];
        a.extend(["--bin", "16", "--fit", "quadratic", "--min-count", "30"].map(String::from));
        if calibrated {
            a.extend(["--calibration".into(), p(&calib)]);
        }
        a.extend(["--out".into(), p(out)]);
        ebptv(&a.iter().map(String::as_str).collect::<Vec<_>>());
    };
    grid(&plain.join("tracks.csv"), &d.join("g_plain"), false);
    // The run's mask.png beside its tracks is picked up by grid.
    grid(&masked.join("tracks.csv"), &d.join("g_masked"), true);

    // Tracks: none in the walls; physical columns = scaled pixel ones.
    let (th, tr) = table(&masked.join("tracks.csv"));
    assert_eq!(
        th.join(","),
        "track_id,pulse,t_us,x,y,u,v,X_mm,Y_mm,U_m_s,V_m_s"
    );
    assert!(tr.len() > 10_000, "{} track points", tr.len());
    let in_wall = |y: f64| !(15.5..144.5).contains(&y);
    let wall_points = tr.iter().filter(|r| in_wall(r[4])).count();
    let (_, pr) = table(&plain.join("tracks.csv"));
    let plain_wall_points = pr.iter().filter(|r| in_wall(r[4])).count();
    eprintln!("track points in the walls: {wall_points} masked, {plain_wall_points} unmasked");
    assert!(plain_wall_points > 1000);
    assert!(
        wall_points <= plain_wall_points / 200,
        "{wall_points} track points in the walls"
    );
    // Within the rounding of both (pixel columns to 1e-4 px and 1e-3 px/s,
    // physical ones to 7 significant digits).
    let tol = [1.1e-5, 1.1e-5, 7e-7, 7e-7];
    for r in &tr {
        let want = [r[3] / 10.0, -(r[4] - 80.0) / 10.0, r[5] / 1e4, -r[6] / 1e4];
        for (k, w) in want.iter().enumerate() {
            assert!(
                (r[7 + k] - w).abs() <= tol[k],
                "{r:?}: column {} = {}, want {w}",
                th[7 + k],
                r[7 + k]
            );
        }
    }

    // Grids: the masked run's, and the unmasked run's binned with --mask.
    let binmask = d.join("g_binmask");
    ebptv(&[
        "grid",
        &p(&plain.join("tracks.csv")),
        "--bin",
        "16",
        "--fit",
        "quadratic",
        "--min-count",
        "30",
        "--mask",
        &p(&mask),
        "--out",
        &p(&binmask),
    ]);
    let (gh, gm) = table(&d.join("g_masked/grid.csv"));
    let (ph, gp) = table(&d.join("g_plain/grid.csv"));
    let (_, gb) = table(&binmask.join("grid.csv"));
    assert_eq!(ph.join(","), "x,y,count,u,v,uu,vv,uv");
    assert_eq!(
        gh.join(","),
        "x,y,count,u,v,uu,vv,uv,X_mm,Y_mm,U_m_s,V_m_s,uu_m2_s2,vv_m2_s2,uv_m2_s2"
    );
    let plain_at: std::collections::HashMap<(u64, u64), &Vec<f64>> = gp
        .iter()
        .map(|r| ((r[0].to_bits(), r[1].to_bits()), r))
        .collect();
    let is_wall = |y: f64| !(16.0..=144.0).contains(&y);
    let (ux, uy, uu, um) = (
        col(&gh, "x"),
        col(&gh, "y"),
        col(&gh, "u"),
        col(&gh, "U_m_s"),
    );
    let (mut interior, mut worst, mut worst_truth) = (0, 0.0f64, 0.0f64);
    for m in &gm {
        let (x, y) = (m[ux], m[uy]);
        if is_wall(y) {
            assert!(m[uu].is_nan() && m[um].is_nan(), "wall bin {m:?}");
        } else if x > 16.0 && x < 304.0 && m[uu].is_finite() {
            let q = plain_at[&(x.to_bits(), y.to_bits())];
            interior += 1;
            worst = worst.max((m[uu] - q[3]).abs() / u_max);
            worst_truth = worst_truth.max((m[uu] - truth(y)).abs() / u_max);
            assert!((m[um] - m[uu] / 1e4).abs() < 1e-9, "{m:?}");
        }
    }
    // Bins of the unmasked tracks binned with the mask: the wall bins
    // empty, the others untouched.
    let (mut walls, mut plain_walls) = (0, 0);
    for (b, q) in gb.iter().zip(&gp) {
        assert_eq!((b[0], b[1]), (q[0], q[1]));
        let on_sensor = b[0] > 0.0 && b[0] < 320.0 && b[1] > 0.0 && b[1] < 160.0;
        if is_wall(b[1]) && on_sensor {
            walls += 1;
            plain_walls += q[3].is_finite() as usize;
            assert!(b[3..8].iter().all(|v| v.is_nan()), "wall bin {b:?}");
        } else if is_wall(b[1]) {
            assert!(b[3].is_nan(), "bin beyond the sensor {b:?}");
        } else {
            assert_eq!(format!("{b:?}"), format!("{q:?}"));
        }
    }
    eprintln!(
        "channel with masked walls: {interior} interior bins, largest change {:.3} % of u_max, largest error {:.3} %; {walls} wall bins empty ({plain_walls} with a vector unmasked)",
        100.0 * worst,
        100.0 * worst_truth
    );
    assert!(interior >= 100, "{interior} interior bins");
    assert!(
        walls >= 38 && plain_walls >= walls / 2,
        "{walls} {plain_walls}"
    );
    assert!(worst < 0.003, "{worst}");
    assert!(worst_truth < 0.01, "{worst_truth}");
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(binmask.join("grid.json")).unwrap()).unwrap();
    assert_eq!(json["masked_bins"], walls as u64);
}

/// A uniform flow of 3 px/pulse (15 000 px/s at 5 kHz) at 12.5 px/mm is
/// 1.2 m/s: the calibrated grid says so within 0.5 %, and a calibration by
/// two reference points 250 px apart over 20 mm gives the same columns.
#[test]
fn uniform_flow_in_metres_per_second() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let rec = simulate(
        &scene(FlowSpec::Uniform {
            u: 15_000.0,
            v: 0.0,
        }),
        d,
    );
    let p = |x: &Path| x.display().to_string();
    std::fs::write(d.join("scale.toml"), "px_per_mm = 12.5\n").unwrap();
    std::fs::write(
        d.join("points.toml"),
        "[reference]\na_px = [10.0, 20.0]\nb_px = [160.0, 220.0]\ndistance_mm = 20.0\n",
    )
    .unwrap();
    let run = d.join("run");
    ebptv(&["--table-format", "csv", "track", &rec, "--out", &p(&run)]);
    for c in ["scale", "points"] {
        ebptv(&[
            "grid",
            &p(&run.join("tracks.csv")),
            "--bin",
            "32",
            "--calibration",
            &p(&d.join(format!("{c}.toml"))),
            "--out",
            &p(&d.join(c)),
        ]);
    }
    let (h, rows) = table(&d.join("scale/grid.csv"));
    let (um, vm) = (col(&h, "U_m_s"), col(&h, "V_m_s"));
    let mut n = 0;
    for r in rows.iter().filter(|r| r[2] >= 50.0) {
        n += 1;
        assert!((r[um] - 1.2).abs() < 0.006, "{r:?}");
        assert!(r[vm].abs() < 0.006, "{r:?}");
    }
    assert!(n >= 30, "{n} bins");
    let a = std::fs::read_to_string(d.join("scale/grid.csv")).unwrap();
    let b = std::fs::read_to_string(d.join("points/grid.csv")).unwrap();
    assert_eq!(a, b);
}

/// Hot pixels fire between the pulses: `ebptv pulses --write-mask` masks
/// every one of them and next to nothing else (particles cross a pixel in
/// few pulses).
#[test]
fn the_automatic_mask_finds_the_hot_pixels() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let mut sc = scene(FlowSpec::Uniform {
        u: 15_000.0,
        v: 0.0,
    });
    sc.noise.hot_pixels = Some(HotPixels {
        count: 12,
        rate_hz: 3000.0,
    });
    let rec = simulate(&sc, d);
    let hot: Vec<(u16, u16)> = ebptv::sim::Simulator::new(&sc, 4)
        .unwrap()
        .hot_pixels()
        .iter()
        .map(|h| (h.0, h.1))
        .collect();
    assert_eq!(hot.len(), 12);
    let mask = d.join("auto.png");
    ebptv(&[
        "pulses",
        &rec,
        "--write-mask",
        &mask.display().to_string(),
        "--out",
        &d.join("pulses").display().to_string(),
    ]);
    let m = PixelMask::from_png(&mask).unwrap();
    assert_eq!(m.size(), (320, 160));
    for &(x, y) in &hot {
        assert!(m.is_masked_px(x as u32, y as u32), "hot pixel ({x}, {y})");
    }
    assert!(m.count() <= hot.len() + 5, "{} pixels masked", m.count());
}

/// A bad calibration or mask stops a command before it writes anything,
/// with an error naming the file and the key.
#[test]
fn bad_calibration_files_are_named_with_their_key() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let tracks = d.join("tracks.csv");
    std::fs::write(
        &tracks,
        "track_id,pulse,t_us,x,y,u,v\n0,0,0,1,1,10,0\n0,1,200,3,1,10,0\n",
    )
    .unwrap();
    let png = d.join("not_a.png");
    std::fs::write(&png, "just text").unwrap();
    for (name, text, want) in [
        ("neg.toml", "px_per_mm = -3\n", "px_per_mm"),
        ("typo.toml", "px_per_mm = 3\norigin = [1, 2]\n", "origin"),
        ("none.toml", "y_axis = \"up\"\n", "px_per_mm"),
        (
            "same.toml",
            "[reference]\na_px = [5, 5]\nb_px = [5, 5]\ndistance_mm = 2\n",
            "reference.a_px",
        ),
        (
            "img.toml",
            "px_per_mm = 3\n[mask]\nimage = \"not_a.png\"\n",
            "mask.image",
        ),
    ] {
        let c = d.join(name);
        std::fs::write(&c, text).unwrap();
        let out = d.join(format!("out_{name}"));
        let o = Command::new(env!("CARGO_BIN_EXE_ebptv"))
            .args(["grid", tracks.to_str().unwrap(), "--calibration"])
            .arg(&c)
            .arg("--out")
            .arg(&out)
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success(), "{name}");
        assert!(err.contains(name) && err.contains(want), "{name}: {err}");
        assert!(!out.join("grid.parquet").exists(), "{name}");
    }
    let o = Command::new(env!("CARGO_BIN_EXE_ebptv"))
        .args(["grid", tracks.to_str().unwrap(), "--mask"])
        .arg(&png)
        .arg("--out")
        .arg(d.join("out_png"))
        .output()
        .unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("not_a.png") && err.contains("PNG"),
        "{err}"
    );
    assert!(!d.join("out_png/grid.parquet").exists());
}
