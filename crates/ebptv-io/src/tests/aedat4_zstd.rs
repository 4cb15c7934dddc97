//! AEDAT4 with real Zstd compression (entropy-coded blocks, not only stored
//! ones): a tiny fixture in data/, made by our own writer with each packet
//! compressed by the `zstd` tool (see `make_fixture`, run with --ignored).

use std::path::{Path, PathBuf};

use ebptv_io::aedat4::{encode_aedat4, Aedat4Reader, Compression};
use ebptv_io::EventSource;
use ebptv_io::{Chunk, Edge, Event, Geometry, Trigger};

fn fixture() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../..")
        .join("data/aedat4_zstd_small.aedat4")
}

/// The fixture's content, deterministic.
fn content() -> (Vec<Event>, Vec<Trigger>) {
    let events = (0..400i64)
        .map(|i| Event {
            t: 1_000 + i * 25,
            x: ((i * 37) % 346) as u16,
            y: ((i * 11) % 260) as u16,
            p: (i % 5 != 0) as u8,
        })
        .collect();
    let triggers = (0..20i64)
        .map(|i| Trigger {
            t: 1_000 + i * 500,
            channel: 0,
            edge: if i % 2 == 0 {
                Edge::Rising
            } else {
                Edge::Falling
            },
        })
        .collect();
    (events, triggers)
}

fn zstd_cli(data: &[u8]) -> Vec<u8> {
    use std::io::Write;
    use std::process::{Command, Stdio};
    let mut child = Command::new("zstd")
        .args(["-19", "-c", "-q"])
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .spawn()
        .expect("zstd tool");
    child.stdin.take().unwrap().write_all(data).unwrap();
    let out = child.wait_with_output().unwrap();
    assert!(out.status.success());
    out.stdout
}

#[ebptv_macros::unit_test]
#[ignore = "regenerates data/aedat4_zstd_small.aedat4 with the zstd tool"]
fn make_fixture() {
    let (events, triggers) = content();
    let bytes = encode_aedat4(
        &events,
        &triggers,
        Geometry::new(346, 260),
        Compression::Zstd,
        150,
        &zstd_cli,
    );
    std::fs::write(fixture(), bytes).unwrap();
}

#[ebptv_macros::unit_test]
fn zstd_fixture_decodes() {
    let mut r = Aedat4Reader::open(&fixture(), 64).unwrap();
    let mut c = Chunk::default();
    let (mut ev, mut tr) = (Vec::new(), Vec::new());
    while r.next_chunk(&mut c).unwrap() {
        ev.extend(c.events.iter());
        tr.extend_from_slice(&c.triggers);
    }
    let (events, triggers) = content();
    assert_eq!(ev, events);
    assert_eq!(tr, triggers);
    assert_eq!(r.info().geometry, Some(Geometry::new(346, 260)));
    assert!(r
        .info()
        .header
        .iter()
        .any(|(k, v)| k == "compression" && v == "Zstd"));
    // The packets really are entropy-coded: far smaller than 16 bytes/event.
    let bytes = std::fs::read(fixture()).unwrap();
    let header = 18 + u32::from_le_bytes(bytes[14..18].try_into().unwrap()) as usize;
    let packets = bytes.len() - header;
    assert!(packets < 400 * 16 / 2, "{packets}");
}
