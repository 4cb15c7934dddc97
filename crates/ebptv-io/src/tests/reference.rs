//! Each reader against a plain, obviously-correct reference decoder (or its
//! writer) on random inputs, across random chunk sizes.

use ebptv_io::aedat4::{encode_aedat4, lz4_frame, Compression};
use ebptv_io::csv::CsvWriter;
use ebptv_io::{self as io, EventSource, EventWriter, Format, OpenOptions};
use ebptv_io::{Chunk, Edge, Event, Geometry, Trigger};
use proptest::prelude::*;

fn read(bytes: &[u8], format: Format, ext: &str, chunk: usize) -> (Vec<Event>, Vec<Trigger>) {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join(format!("f.{ext}"));
    std::fs::write(&p, bytes).unwrap();
    read_path(&p, format, chunk)
}

fn read_path(p: &std::path::Path, format: Format, chunk: usize) -> (Vec<Event>, Vec<Trigger>) {
    let opts = OpenOptions {
        format: Some(format),
        chunk_events: Some(chunk),
        ..Default::default()
    };
    let mut src = io::open_with(p, &opts).unwrap();
    let mut c = Chunk::default();
    let (mut ev, mut tr) = (Vec::new(), Vec::new());
    while src.next_chunk(&mut c).unwrap() {
        ev.extend(c.events.iter());
        tr.extend_from_slice(&c.triggers);
    }
    (ev, tr)
}

/// DAT, the slow way: one record at a time, time unwrapped by comparing
/// with the previous raw value.
fn dat_reference(payload: &[u8]) -> Vec<Event> {
    let mut out = Vec::new();
    let mut offset = 0i64;
    let mut prev: Option<i64> = None;
    for rec in payload.chunks(8).filter(|r| r.len() == 8) {
        let raw = u32::from_le_bytes([rec[0], rec[1], rec[2], rec[3]]) as i64;
        let w = u32::from_le_bytes([rec[4], rec[5], rec[6], rec[7]]);
        if let Some(p) = prev {
            if p - raw > 1 << 31 {
                offset += 1 << 32;
            }
        }
        prev = Some(raw);
        let bits = |lo: u32, n: u32| (w >> lo) & ((1u32 << n) - 1);
        out.push(Event {
            t: offset + raw,
            x: bits(0, 14) as u16,
            y: bits(14, 14) as u16,
            p: (bits(28, 4) > 0) as u8,
        });
    }
    out
}

/// Event Stream DVS, the slow way: an explicit list of pending bytes.
fn es_reference(payload: &[u8]) -> Vec<Event> {
    let mut out = Vec::new();
    let mut t = 0i64;
    let mut pending: Vec<u8> = Vec::new();
    for &b in payload {
        if pending.is_empty() {
            match b {
                0xFF => t += 127,
                0xFE => {}
                _ => pending.push(b),
            }
            continue;
        }
        pending.push(b);
        if pending.len() == 5 {
            t += (pending[0] >> 1) as i64;
            out.push(Event {
                t,
                x: u16::from_le_bytes([pending[1], pending[2]]),
                y: u16::from_le_bytes([pending[3], pending[4]]),
                p: pending[0] & 1,
            });
            pending.clear();
        }
    }
    out
}

fn arb_events(max: usize) -> impl Strategy<Value = Vec<Event>> {
    prop::collection::vec((0i64..5000, any::<u16>(), any::<u16>(), 0u8..2), 0..max).prop_map(|v| {
        let mut t = -1_000i64;
        v.into_iter()
            .map(|(dt, x, y, p)| {
                t += dt;
                Event { t, x, y, p }
            })
            .collect()
    })
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 64, ..ProptestConfig::default() })]

    #[ebptv_macros::unit_test]
    fn dat_matches_reference(payload in prop::collection::vec(any::<u8>(), 0..4000), chunk in 1usize..300) {
        let mut b = b"% Version 2\n".to_vec();
        b.extend_from_slice(&[0x0C, 8]);
        b.extend_from_slice(&payload);
        let (ev, _) = read(&b, Format::Dat, "dat", chunk);
        prop_assert_eq!(ev, dat_reference(&payload));
    }

    #[ebptv_macros::unit_test]
    fn es_matches_reference(payload in prop::collection::vec(any::<u8>(), 0..4000), chunk in 1usize..300) {
        let mut b = b"Event Stream\x02\x00\x00\x01".to_vec();
        b.extend_from_slice(&[0xFF, 0xFF, 0xFF, 0xFF]); // 65535 x 65535: nothing out of range
        b.extend_from_slice(&payload);
        let (ev, _) = read(&b, Format::Es, "es", chunk);
        prop_assert_eq!(ev, es_reference(&payload));
    }

    #[ebptv_macros::unit_test]
    fn csv_writer_reader_roundtrip(events in arb_events(500), trig_every in 1usize..50, chunk in 1usize..200) {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("r.csv");
        let mut w: Box<dyn EventWriter> = Box::new(CsvWriter::create(&p).unwrap());
        let mut c = Chunk::default();
        let mut trig = Vec::new();
        for (i, e) in events.iter().enumerate() {
            c.events.push(e.t, e.x, e.y, e.p);
            if i % trig_every == 0 {
                let tr = Trigger { t: e.t, channel: (i % 7) as u8, edge: if i % 2 == 0 { Edge::Rising } else { Edge::Falling } };
                c.triggers.push(tr);
                trig.push(tr);
            }
            if c.events.len() == 64 {
                w.write_chunk(&c).unwrap();
                c.clear();
            }
        }
        w.write_chunk(&c).unwrap();
        w.finish().unwrap();
        let (ev, tr) = read_path(&p, Format::Csv, chunk);
        prop_assert_eq!(ev, events);
        prop_assert_eq!(tr, trig);
    }

    #[ebptv_macros::unit_test]
    fn aedat4_roundtrip(events in arb_events(400), per_packet in 1usize..100, chunk in 1usize..300) {
        let events: Vec<Event> = events.into_iter().map(|e| Event { x: e.x & 0x7FFF, y: e.y & 0x7FFF, ..e }).collect();
        let b = encode_aedat4(&events, &[], Geometry::new(0x7FFF, 0x7FFF), Compression::Lz4, per_packet, &lz4_frame);
        let (ev, _) = read(&b, Format::Aedat4, "aedat4", chunk);
        prop_assert_eq!(ev, events);
    }
}
