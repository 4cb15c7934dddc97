//! Arbitrary bytes into every reader of this module: never a panic, only a
//! clean error or a (possibly empty) stream. Inputs start with valid headers
//! so the fuzz reaches the payload decoders, and valid files get random
//! byte flips so it reaches the flatbuffer / record parsers.

use ebptv_io::aedat4::{encode_aedat4, lz4_frame, zstd_stored_frame, Compression};
use ebptv_io::{self as io, EventSource, Format, OpenOptions};
use ebptv_io::{Chunk, Edge, Event, Geometry, Trigger};
use proptest::prelude::*;

fn drain(bytes: &[u8], format: Format, ext: &str) {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join(format!("f.{ext}"));
    std::fs::write(&p, bytes).unwrap();
    let opts = OpenOptions {
        format: Some(format),
        chunk_events: Some(97),
        ..Default::default()
    };
    let Ok(mut src) = io::open_with(&p, &opts) else {
        return;
    };
    let mut c = Chunk::default();
    let mut n = 0usize;
    while let Ok(true) = src.next_chunk(&mut c) {
        assert!(!c.is_empty());
        assert!(c.events.len() <= 97);
        n += c.events.len();
        // Each event costs at least one input byte in every format here
        // (AEDAT4 after decompression: bounded by the decompression cap).
        assert!(n <= 16 * bytes.len() + 1_000_000);
    }
    let _ = src.anomalies();
}

fn small_aedat4(comp: Compression) -> Vec<u8> {
    let ev: Vec<Event> = (0..30)
        .map(|i| Event {
            t: i * 3,
            x: i as u16,
            y: 2 * i as u16,
            p: (i % 2) as u8,
        })
        .collect();
    let tr = vec![
        Trigger {
            t: 5,
            channel: 0,
            edge: Edge::Rising,
        },
        Trigger {
            t: 50,
            channel: 2,
            edge: Edge::Falling,
        },
    ];
    let f: &dyn Fn(&[u8]) -> Vec<u8> = match comp {
        Compression::Lz4 => &lz4_frame,
        Compression::Zstd => &zstd_stored_frame,
        _ => &|b: &[u8]| b.to_vec(),
    };
    encode_aedat4(&ev, &tr, Geometry::new(64, 64), comp, 8, f)
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 96, ..ProptestConfig::default() })]

    #[ebptv_macros::unit_test]
    fn dat_payload(ty in prop::sample::select(vec![0u8, 0x0C, 0x0E, 0x33]), size in prop::sample::select(vec![8u8, 4]),
                   body in prop::collection::vec(any::<u8>(), 0..600)) {
        let mut b = b"% Version 2\n% Width 64\n% Height 64\n".to_vec();
        b.push(ty);
        b.push(size);
        b.extend_from_slice(&body);
        drain(&b, Format::Dat, "dat");
    }

    #[ebptv_macros::unit_test]
    fn any_bytes_any_reader(body in prop::collection::vec(any::<u8>(), 0..400)) {
        for (f, ext) in [(Format::Dat, "dat"), (Format::Es, "es"), (Format::Aedat4, "aedat4"), (Format::Csv, "csv")] {
            drain(&body, f, ext);
        }
    }

    #[ebptv_macros::unit_test]
    fn es_payload(kind in 0u8..6, w in any::<u16>(), h in any::<u16>(), body in prop::collection::vec(any::<u8>(), 0..600)) {
        let mut b = b"Event Stream\x02\x00\x00".to_vec();
        b.push(kind);
        b.extend_from_slice(&w.to_le_bytes());
        b.extend_from_slice(&h.to_le_bytes());
        b.extend_from_slice(&body);
        drain(&b, Format::Es, "es");
    }

    #[ebptv_macros::unit_test]
    fn aedat4_flipped(comp in prop::sample::select(vec![Compression::None, Compression::Lz4, Compression::Zstd]),
                      flips in prop::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 1..8),
                      cut in any::<prop::sample::Index>()) {
        let mut b = small_aedat4(comp);
        for (i, v) in flips {
            let k = i.index(b.len());
            b[k] = v;
        }
        drain(&b, Format::Aedat4, "aedat4");
        let k = cut.index(b.len());
        drain(&b[..k], Format::Aedat4, "aedat4");
    }

    #[ebptv_macros::unit_test]
    fn aedat4_random_packets(comp in prop::sample::select(vec![Compression::None, Compression::Lz4, Compression::Zstd]),
                             body in prop::collection::vec(any::<u8>(), 0..400)) {
        let valid = small_aedat4(comp);
        let hlen = u32::from_le_bytes(valid[14..18].try_into().unwrap()) as usize;
        let mut b = valid[..18 + hlen].to_vec();
        // A packet header for the event stream with a plausible size, then noise.
        b.extend_from_slice(&0i32.to_le_bytes());
        b.extend_from_slice(&(body.len() as i32).to_le_bytes());
        b.extend_from_slice(&body);
        drain(&b, Format::Aedat4, "aedat4");
    }

    #[ebptv_macros::unit_test]
    fn csv_text(lines in prop::collection::vec("[0-9txyp,.;\\- e]{0,24}", 0..20)) {
        let text = lines.join("\n");
        drain(text.as_bytes(), Format::Csv, "csv");
        let with_header = format!("t,x,y,p\n{text}");
        drain(with_header.as_bytes(), Format::Csv, "csv");
    }
}
