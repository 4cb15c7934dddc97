//! The `ebptv info` and `ebptv convert` commands, run as a user would.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use ebptv::io::dat::{encode_dat_cd, encode_dat_triggers};
use ebptv::io::{self, EventSource, OpenOptions};
use ebptv::{Chunk, Edge, Event, Geometry, Trigger};

fn ebptv(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_ebptv"))
        .args(args)
        .output()
        .expect("run ebptv")
}

fn s(p: &Path) -> &str {
    p.to_str().unwrap()
}

fn sample_events() -> Vec<Event> {
    (0..3000i64)
        .map(|i| Event {
            t: 10_000 + i * 7,
            x: ((i * 13) % 640) as u16,
            y: ((i * 7) % 480) as u16,
            p: (i % 3 != 0) as u8,
        })
        .collect()
}

fn read_csv(path: &Path) -> (Vec<Event>, Vec<Trigger>) {
    let opts = OpenOptions {
        format: Some(io::Format::Csv),
        ..Default::default()
    };
    let mut src = io::open_with(path, &opts).unwrap();
    let mut c = Chunk::default();
    let (mut ev, mut tr) = (Vec::new(), Vec::new());
    while src.next_chunk(&mut c).unwrap() {
        ev.extend(c.events.iter());
        tr.extend_from_slice(&c.triggers);
    }
    (ev, tr)
}

fn dir_entries(dir: &Path) -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    v.sort();
    v
}

#[test]
fn info_text_and_json() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("a.dat");
    let ev = sample_events();
    std::fs::write(&p, encode_dat_cd(&ev, Some(Geometry::new(640, 480)))).unwrap();
    let out = ebptv(&["info", s(&p)]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains("DAT") && text.contains("640x480") && text.contains("3000"),
        "{text}"
    );

    let out = ebptv(&["info", "--json", s(&p)]);
    assert!(out.status.success());
    let j: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(j["events"], 3000);
    assert_eq!(
        j["on_events"],
        ev.iter().filter(|e| e.p == 1).count() as u64
    );
    assert_eq!(j["min_t_us"], 10_000);
    assert_eq!(j["max_t_us"], 10_000 + 2999 * 7);
    assert_eq!(j["geometry"]["width"], 640);
    // 1 ms bins of events every 7 µs: 143 events in the fullest bin.
    let per_bin = (0..3000i64).map(|i| (10_000 + i * 7) / 1000).fold(
        std::collections::HashMap::new(),
        |mut m, b| {
            *m.entry(b).or_insert(0u64) += 1;
            m
        },
    );
    let peak = *per_bin.values().max().unwrap() as f64 * 1000.0;
    assert_eq!(j["peak_rate_ev_per_s"].as_f64().unwrap(), peak);
}

#[test]
fn info_counts_triggers_per_channel_and_edge() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("trig.dat");
    let tr: Vec<Trigger> = (0..30)
        .map(|i| Trigger {
            t: i * 100,
            channel: (i % 2) as u8,
            edge: if i % 3 == 0 {
                Edge::Rising
            } else {
                Edge::Falling
            },
        })
        .collect();
    std::fs::write(&p, encode_dat_triggers(&tr)).unwrap();
    let out = ebptv(&["info", "--json", s(&p)]);
    assert!(out.status.success());
    let j: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    let chans = j["triggers"].as_array().unwrap();
    assert_eq!(chans.len(), 2);
    for c in chans {
        let ch = c["channel"].as_u64().unwrap() as u8;
        let rising = tr
            .iter()
            .filter(|t| t.channel == ch && t.edge == Edge::Rising)
            .count() as u64;
        let falling = tr
            .iter()
            .filter(|t| t.channel == ch && t.edge == Edge::Falling)
            .count() as u64;
        assert_eq!(
            (
                c["rising"].as_u64().unwrap(),
                c["falling"].as_u64().unwrap()
            ),
            (rising, falling)
        );
    }
}

#[test]
fn info_errors_name_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("missing.dat");
    let empty = dir.path().join("empty.aedat4");
    std::fs::write(&empty, b"").unwrap();
    let wrong = dir.path().join("notes.aedat4");
    std::fs::write(&wrong, b"these are my notes, not events\n").unwrap();
    let text_as_dat = dir.path().join("notes.dat");
    std::fs::write(&text_as_dat, b"these are my notes, not events\n").unwrap();
    for p in [&missing, &empty, &wrong, &text_as_dat] {
        let out = ebptv(&["info", s(p)]);
        assert!(!out.status.success(), "{}", p.display());
        let err = String::from_utf8_lossy(&out.stderr);
        let name = p.file_name().unwrap().to_str().unwrap();
        assert!(err.contains(name), "{err}");
        assert!(!err.contains("panicked"), "{err}");
    }
    let out = ebptv(&["info", "--format", "nope", s(&missing)]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("format"));
}

#[test]
fn convert_dat_to_csv_with_selection() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("in.dat");
    let ev = sample_events();
    std::fs::write(&input, encode_dat_cd(&ev, Some(Geometry::new(640, 480)))).unwrap();
    // Everything.
    let all = dir.path().join("all.csv");
    let out = ebptv(&["convert", s(&input), s(&all)]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(std::fs::read_to_string(&all)
        .unwrap()
        .starts_with("t,x,y,p\n"));
    assert_eq!(read_csv(&all).0, ev);
    // A selection, compared with the same selection done by hand.
    let sel = dir.path().join("sel.csv");
    let out = ebptv(&[
        "convert",
        s(&input),
        s(&sel),
        "--from-us",
        "12000",
        "--to-us",
        "25000",
        "--roi",
        "100,50,300,200",
        "--polarity",
        "on",
    ]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let expect: Vec<Event> = ev
        .iter()
        .copied()
        .filter(|e| {
            e.t >= 12_000
                && e.t < 25_000
                && e.x >= 100
                && e.x < 400
                && e.y >= 50
                && e.y < 250
                && e.p == 1
        })
        .collect();
    assert!(!expect.is_empty());
    assert_eq!(read_csv(&sel).0, expect);
    // To .npy: header and size.
    let npy = dir.path().join("ev.npy");
    let out = ebptv(&["convert", s(&input), s(&npy)]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let b = std::fs::read(&npy).unwrap();
    let h = ebptv::io::npy::parse_npy_header(&b).unwrap();
    assert_eq!(h.shape, vec![3000]);
    assert_eq!(b.len() - h.data_offset, 3000 * 13);
}

#[test]
fn convert_failures_leave_no_output() {
    let dir = tempfile::tempdir().unwrap();
    // An AEDAT4 file whose second packet is garbage: the error comes after
    // the writer has started.
    let good = ebptv::io::aedat4::encode_aedat4(
        &sample_events(),
        &[],
        Geometry::new(640, 480),
        ebptv::io::aedat4::Compression::Lz4,
        1000,
        &ebptv::io::aedat4::lz4_frame,
    );
    let mut bad = good.clone();
    let hlen = u32::from_le_bytes(good[14..18].try_into().unwrap()) as usize;
    let first = 18 + hlen;
    let size1 = i32::from_le_bytes(good[first + 4..first + 8].try_into().unwrap()) as usize;
    let second = first + 8 + size1;
    for b in &mut bad[second + 8..second + 24] {
        *b = 0x5A;
    }
    let input = dir.path().join("bad.aedat4");
    std::fs::write(&input, &bad).unwrap();
    let output = dir.path().join("out.csv");
    let out = ebptv(&["convert", s(&input), s(&output)]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("bad.aedat4") && err.contains("decompress"),
        "{err}"
    );
    assert_eq!(
        dir_entries(dir.path()),
        vec![input.clone()],
        "no output, no temporary left"
    );

    // Missing input, unknown output extension, bad ROI, input == output.
    for args in [
        vec![
            "convert".to_string(),
            dir.path().join("nope.dat").display().to_string(),
            s(&output).to_string(),
        ],
        vec![
            "convert".into(),
            s(&input).into(),
            dir.path().join("out.xyz").display().to_string(),
        ],
        vec![
            "convert".into(),
            s(&input).into(),
            s(&output).into(),
            "--roi".into(),
            "1,2,3".into(),
        ],
        vec![
            "convert".into(),
            s(&input).into(),
            s(&input).into(),
            "--format".into(),
            "csv".into(),
        ],
    ] {
        let out = Command::new(env!("CARGO_BIN_EXE_ebptv"))
            .args(&args)
            .output()
            .unwrap();
        assert!(!out.status.success(), "{args:?}");
        assert!(!String::from_utf8_lossy(&out.stderr).contains("panicked"));
    }
    assert_eq!(dir_entries(dir.path()), vec![input.clone()]);
    assert_eq!(
        std::fs::read(&input).unwrap(),
        bad,
        "the input is untouched"
    );
}

#[test]
fn convert_csv_with_triggers_roundtrip() {
    let dir = tempfile::tempdir().unwrap();
    let input = dir.path().join("rec.csv");
    std::fs::write(
        &input,
        "timestamp_s,x,y,polarity\n0.000010,1,2,1\n0.000020,3,4,0\n0.000030,5,6,1\n",
    )
    .unwrap();
    std::fs::write(
        dir.path().join("rec_triggers.csv"),
        "p,id,t\n1,0,15\n0,0,25\n",
    )
    .unwrap();
    let output = dir.path().join("copy.csv");
    let out = ebptv(&["convert", s(&input), s(&output)]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let (ev, tr) = read_csv(&output);
    assert_eq!(ev.iter().map(|e| e.t).collect::<Vec<_>>(), vec![10, 20, 30]);
    assert_eq!(
        tr,
        vec![
            Trigger {
                t: 15,
                channel: 0,
                edge: Edge::Rising
            },
            Trigger {
                t: 25,
                channel: 0,
                edge: Edge::Falling
            }
        ]
    );
    assert_eq!(
        std::fs::read_to_string(dir.path().join("copy_triggers.csv")).unwrap(),
        "t,id,p\n15,0,1\n25,0,0\n"
    );
}

#[test]
fn wrong_extension_is_read_by_content() {
    let dir = tempfile::tempdir().unwrap();
    let ev = sample_events();
    let dat_as_csv = dir.path().join("really_dat.csv");
    std::fs::write(
        &dat_as_csv,
        encode_dat_cd(&ev, Some(Geometry::new(640, 480))),
    )
    .unwrap();
    let aedat_as_dat = dir.path().join("really_aedat.dat");
    let a = ebptv::io::aedat4::encode_aedat4(
        &ev,
        &[],
        Geometry::new(640, 480),
        ebptv::io::aedat4::Compression::Lz4,
        500,
        &ebptv::io::aedat4::lz4_frame,
    );
    std::fs::write(&aedat_as_dat, a).unwrap();
    for (p, fmt) in [(&dat_as_csv, "dat"), (&aedat_as_dat, "aedat4")] {
        let out = ebptv(&["info", "--json", s(p)]);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let j: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        assert_eq!(j["format"], fmt);
        assert_eq!(j["events"], 3000);
    }
}

#[test]
fn info_on_real_files() {
    let real = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/real");
    for (name, events) in [
        ("ncars_sample.dat", 2009u64),
        ("davis346_test.aedat4", 78_830),
        ("atis_dvs.es", 473_225),
    ] {
        let p = real.join(name);
        if !p.is_file() {
            eprintln!("skip: {} not found", p.display());
            continue;
        }
        let out = ebptv(&["info", "--json", s(&p)]);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let j: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
        assert_eq!(j["events"], events, "{name}");
    }
}
