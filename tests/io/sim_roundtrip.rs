//! Simulated recordings (with triggers) through the CSV and .npy writers and
//! back: the CSV reader returns exactly the simulated events and triggers,
//! the .npy holds them byte for byte; `ebptv info` counts them.

use ebptv::io::csv::CsvReader;
use ebptv::io::npy::{parse_npy_header, NpyEventWriter};
use ebptv::io::{csv::CsvWriter, EventSource, EventWriter};
use ebptv::sim::{presets, simulate};
use ebptv::{Chunk, Event, Trigger};

#[test]
fn simulated_events_roundtrip_csv_and_npy() {
    let mut s = presets::preset("demo").unwrap();
    s.duration_s = 0.01;
    let sim = simulate(&s, 11).unwrap();
    assert!(sim.events.len() > 1000, "{}", sim.events.len());
    assert!(!sim.triggers.is_empty());
    let dir = tempfile::tempdir().unwrap();

    // Write in pieces, as a streaming stage would.
    let csv = dir.path().join("sim.csv");
    let npy = dir.path().join("sim.npy");
    let mut wc: Box<dyn EventWriter> = Box::new(CsvWriter::create(&csv).unwrap());
    let mut wn: Box<dyn EventWriter> = Box::new(NpyEventWriter::create(&npy).unwrap());
    let all: Vec<Event> = sim.events.iter().collect();
    let mut ti = 0;
    for part in all.chunks(777) {
        let mut c = Chunk::default();
        for e in part {
            c.events.push(e.t, e.x, e.y, e.p);
        }
        let last = part.last().unwrap().t;
        while ti < sim.triggers.len() && sim.triggers[ti].t <= last {
            c.triggers.push(sim.triggers[ti]);
            ti += 1;
        }
        wc.write_chunk(&c).unwrap();
        wn.write_chunk(&c).unwrap();
    }
    let rest = Chunk {
        triggers: sim.triggers[ti..].to_vec(),
        ..Default::default()
    };
    wc.write_chunk(&rest).unwrap();
    wn.write_chunk(&rest).unwrap();
    wc.finish().unwrap();
    wn.finish().unwrap();

    let mut r = CsvReader::open(&csv, 5000, None).unwrap();
    let mut c = Chunk::default();
    let (mut ev, mut tr): (Vec<Event>, Vec<Trigger>) = (Vec::new(), Vec::new());
    while r.next_chunk(&mut c).unwrap() {
        ev.extend(c.events.iter());
        tr.extend_from_slice(&c.triggers);
    }
    assert!(ev == all, "{} vs {} events", ev.len(), all.len());
    assert_eq!(tr, sim.triggers);

    let b = std::fs::read(&npy).unwrap();
    let h = parse_npy_header(&b).unwrap();
    assert_eq!(h.shape, vec![all.len()]);
    let data = &b[h.data_offset..];
    for (i, e) in all.iter().enumerate().step_by(97) {
        let r = &data[13 * i..13 * i + 13];
        assert_eq!(i64::from_le_bytes(r[0..8].try_into().unwrap()), e.t);
        assert_eq!(u16::from_le_bytes(r[8..10].try_into().unwrap()), e.x);
        assert_eq!(u16::from_le_bytes(r[10..12].try_into().unwrap()), e.y);
        assert_eq!(r[12], e.p);
    }

    let out = std::process::Command::new(env!("CARGO_BIN_EXE_ebptv"))
        .args(["info", "--json"])
        .arg(&csv)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let j: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(j["events"], all.len() as u64);
    let n_tr: u64 = j["triggers"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| c["rising"].as_u64().unwrap() + c["falling"].as_u64().unwrap())
        .sum();
    assert_eq!(n_tr, sim.triggers.len() as u64);
}
