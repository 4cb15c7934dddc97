//! The real camera recordings in ../shared/data/real (skipped when absent):
//! counts, geometry and first/last events against independent decodes.

use std::path::{Path, PathBuf};

use ebptv::io::{self, EventSource, Format, OpenOptions};
use ebptv::{Chunk, Edge, Event, Trigger};

fn real(name: &str) -> Option<PathBuf> {
    let p = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../shared/data/real")
        .join(name);
    if p.is_file() {
        Some(p)
    } else {
        eprintln!("skip: {} not found", p.display());
        None
    }
}

fn read_all(path: &Path, format: Format) -> (Vec<Event>, Vec<Trigger>, Box<dyn EventSource>) {
    let opts = OpenOptions {
        format: Some(format),
        chunk_events: Some(4096),
        ..Default::default()
    };
    let mut src = io::open_with(path, &opts).unwrap();
    let mut c = Chunk::default();
    let (mut ev, mut tr) = (Vec::new(), Vec::new());
    while src.next_chunk(&mut c).unwrap() {
        ev.extend(c.events.iter());
        tr.extend_from_slice(&c.triggers);
    }
    (ev, tr, src)
}

#[test]
fn ncars_dat() {
    let Some(p) = real("ncars_sample.dat") else {
        return;
    };
    let bytes = std::fs::read(&p).unwrap();
    let (ev, tr, src) = read_all(&p, Format::Dat);
    assert_eq!(ev.len(), 2009);
    assert!(tr.is_empty());
    assert_eq!(
        src.info().geometry,
        None,
        "the file has no Width/Height lines"
    );
    // Independent decode: the payload starts after the last '\n' of the
    // header and the two type/size bytes; (file size - payload) / 8 records.
    let payload = bytes.len() - 2009 * 8;
    assert_eq!(&bytes[payload - 2..payload], &[0x00, 0x08]);
    let rec = |i: usize| {
        let o = payload + 8 * i;
        let t = u32::from_le_bytes(bytes[o..o + 4].try_into().unwrap());
        let w = u32::from_le_bytes(bytes[o + 4..o + 8].try_into().unwrap());
        Event {
            t: t as i64,
            x: (w & 0x3fff) as u16,
            y: ((w >> 14) & 0x3fff) as u16,
            p: (w >> 28 != 0) as u8,
        }
    };
    assert_eq!(ev[0], rec(0));
    assert_eq!(ev[2008], rec(2008));
    assert_eq!(
        ev[0],
        Event {
            t: 0,
            x: 25,
            y: 8,
            p: 0
        }
    );
    assert_eq!(
        ev[1],
        Event {
            t: 35,
            x: 67,
            y: 35,
            p: 0
        }
    );
    // N-CARS samples are 100 ms, 120x100 px at most.
    assert!(
        ev.iter().all(|e| e.x < 120 && e.y < 100 && e.t < 100_000),
        "{:?}",
        ev.last()
    );
    assert!(ev.windows(2).all(|w| w[0].t <= w[1].t));
    assert!(!src.anomalies().any_problem());
}

#[test]
fn davis346_aedat4() {
    let Some(p) = real("davis346_test.aedat4") else {
        return;
    };
    let (ev, tr, src) = read_all(&p, Format::Aedat4);
    assert_eq!(ev.len(), 78_830);
    assert_eq!(tr.len(), 236);
    assert_eq!(src.info().geometry, Some(ebptv::Geometry::new(346, 260)));
    // The 236 triggers are the DAVIS frame signals of 59 frames: APS frame
    // start/end (types 6/7 → channel 2) and exposure start/end (8/9 → channel 3).
    let mut kinds = std::collections::BTreeMap::new();
    for t in &tr {
        *kinds
            .entry((t.channel, t.edge == Edge::Rising))
            .or_insert(0) += 1;
    }
    let expect: std::collections::BTreeMap<_, _> = [
        ((2, false), 59),
        ((2, true), 59),
        ((3, false), 59),
        ((3, true), 59),
    ]
    .into_iter()
    .collect();
    assert_eq!(kinds, expect);
    // The first event of the first packet, read by hand from the file
    // (decompressed with the lz4 tool): t = 0x0005a555e0e399a4, x 215, y 164, ON.
    assert_eq!(
        ev[0],
        Event {
            t: 0x0005_a555_e0e3_99a4,
            x: 215,
            y: 164,
            p: 1
        }
    );
    assert!(ev.iter().all(|e| e.x < 346 && e.y < 260));
    // Absolute Unix time in µs (tsOffset 1589163005536052 in the header).
    let (t0, t1) = (ev[0].t, ev.last().unwrap().t);
    assert!(
        t0 >= 1_589_163_005_536_052 && t1 > t0 && t1 - t0 < 60_000_000,
        "{t0} {t1}"
    );
    assert!(!src.anomalies().any_problem(), "{:?}", src.anomalies());
    let info = src.info();
    assert!(info
        .header
        .iter()
        .any(|(k, v)| k == "compression" && v == "LZ4"));
}

#[test]
fn atis_dvs_es() {
    let Some(p) = real("atis_dvs.es") else { return };
    let bytes = std::fs::read(&p).unwrap();
    let (ev, tr, src) = read_all(&p, Format::Es);
    assert_eq!(ev.len(), 473_225);
    assert!(tr.is_empty());
    assert_eq!(src.info().geometry, Some(ebptv::Geometry::new(320, 240)));
    assert!(!src.anomalies().any_problem(), "{:?}", src.anomalies());
    // First events, by hand from the bytes after the 20-byte header:
    // 01 00 00 ef 00 -> t 0, ON, (0, 239); 01 01 00 ef 00 -> (1, 239).
    assert_eq!(&bytes[20..30], &[1, 0, 0, 0xef, 0, 1, 1, 0, 0xef, 0]);
    assert_eq!(
        ev[0],
        Event {
            t: 0,
            x: 0,
            y: 239,
            p: 1
        }
    );
    assert_eq!(
        ev[1],
        Event {
            t: 0,
            x: 1,
            y: 239,
            p: 1
        }
    );
    let last = ev.last().unwrap();
    assert!(
        last.t > 900_000 && last.t < 1_100_000,
        "about 1 s: {}",
        last.t
    );
    assert!(ev.windows(2).all(|w| w[0].t <= w[1].t));
    // The recording's clock ticks in whole milliseconds (checked with an
    // independent byte-level decode): 1000 distinct times, 76 785 events at t = 0.
    let distinct: std::collections::BTreeSet<i64> = ev.iter().map(|e| e.t).collect();
    assert_eq!(distinct.len(), 1000);
    assert!(distinct.iter().all(|t| t % 1000 == 0));
    assert_eq!(ev.iter().filter(|e| e.t == 0).count(), 76_785);
}
