//! Writers round-trip through the readers: EVT 3.0 and EVT 2.0 files written
//! by ebptv decode to exactly the events and triggers that went in, in the
//! same order, across clock loops (24-bit for EVT 3.0, 34-bit for EVT 2.0),
//! large gaps and arbitrary chunk boundaries.

use ebptv::events::{Chunk, Edge, Event, EventChunk, Geometry, Trigger};
use ebptv::io::{create, open_with, EventSource, Format, OpenOptions};
use proptest::prelude::*;

/// Time-ordered groups of events sharing t, y and p (x in any order, with
/// repeats), like the simulator and cameras produce.
#[derive(Debug, Clone)]
struct Group {
    dt: u64,
    y: u16,
    p: u8,
    xs: Vec<u16>,
}

fn group() -> impl Strategy<Value = Group> {
    let dt = prop_oneof![
        4 => Just(0u64),
        6 => 0u64..50,
        2 => 0u64..10_000,
        1 => 0u64..(1 << 26),          // crosses 24-bit loops
        1 => (1u64 << 33)..(1 << 35), // crosses the 34-bit loop
    ];
    let xs = prop_oneof![
        // A particle image: a few neighbouring pixels, sorted.
        3 => (0u16..1270, prop::collection::btree_set(0u16..10, 1..8))
            .prop_map(|(b, s)| s.into_iter().map(|o| b + o).collect::<Vec<_>>()),
        // A saturated row: a dense sorted run.
        1 => (0u16..1000, prop::collection::btree_set(0u16..280, 1..60))
            .prop_map(|(b, s)| s.into_iter().map(|o| b + o).collect::<Vec<_>>()),
        // Anything, unsorted with repeats.
        1 => prop::collection::vec(0u16..1280, 1..6),
    ];
    (dt, 0u16..720, 0u8..2, xs).prop_map(|(dt, y, p, xs)| Group { dt, y, p, xs })
}

fn build(groups: &[Group], trig: &[(u64, u8, bool)], t0: u64) -> (Vec<Event>, Vec<Trigger>) {
    let mut t = t0;
    let mut events = Vec::new();
    for g in groups {
        t += g.dt;
        events.extend(g.xs.iter().map(|&x| Event {
            t: t as i64,
            x,
            y: g.y,
            p: g.p,
        }));
    }
    let t_end = t;
    let mut triggers: Vec<Trigger> = trig
        .iter()
        .map(|&(f, ch, rising)| Trigger {
            t: (t0 + f % (t_end - t0 + 1)) as i64,
            channel: ch,
            edge: if rising { Edge::Rising } else { Edge::Falling },
        })
        .collect();
    triggers.sort_by_key(|tr| tr.t);
    (events, triggers)
}

/// Write `events`/`triggers` split into chunks at `cuts`, read back with
/// `chunk_events`, return what came back and the file size.
fn round_trip(
    format: Format,
    events: &[Event],
    triggers: &[Trigger],
    cuts: &[usize],
    chunk_events: usize,
) -> (Vec<Event>, Vec<Trigger>, u64) {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("rt.raw");
    let geometry = Geometry::new(1280, 720);
    let mut w = create(&path, Some(format), geometry).unwrap();
    let mut bounds: Vec<usize> = cuts.iter().map(|&c| c % (events.len() + 1)).collect();
    bounds.push(0);
    bounds.push(events.len());
    bounds.sort();
    let mut ti = 0;
    for b in bounds.windows(2) {
        let mut chunk = Chunk::default();
        for e in &events[b[0]..b[1]] {
            chunk.events.push(e.t, e.x, e.y, e.p);
        }
        // Triggers up to the last event of this chunk travel with it.
        let until = chunk.events.t.last().copied().unwrap_or(i64::MIN);
        while ti < triggers.len() && (triggers[ti].t <= until || b[1] == events.len()) {
            chunk.triggers.push(triggers[ti]);
            ti += 1;
        }
        w.write_chunk(&chunk).unwrap();
    }
    w.finish().unwrap();
    let size = std::fs::metadata(&path).unwrap().len();
    let mut src = open_with(
        &path,
        &OpenOptions {
            chunk_events: Some(chunk_events),
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!(src.info().format, format);
    assert_eq!(src.info().geometry, Some(geometry));
    let mut chunk = Chunk::default();
    let (mut ev, mut tr) = (Vec::new(), Vec::new());
    while src.next_chunk(&mut chunk).unwrap() {
        ev.extend(chunk.events.iter());
        tr.extend_from_slice(&chunk.triggers);
    }
    let a = src.anomalies();
    assert!(!a.any_problem(), "{a:?}");
    assert_eq!(a.words_before_time_base, 0);
    (ev, tr, size)
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 48, ..ProptestConfig::default() })]

    #[test]
    fn evt3_round_trip(groups in prop::collection::vec(group(), 1..300),
                       trig in prop::collection::vec((any::<u64>(), 0u8..16, any::<bool>()), 0..20),
                       t0 in prop_oneof![Just(0u64), 0u64..(1 << 40)],
                       cuts in prop::collection::vec(any::<usize>(), 0..5), chunk in 1usize..500) {
        let (events, triggers) = build(&groups, &trig, t0);
        let (ev, tr, _) = round_trip(Format::Evt3, &events, &triggers, &cuts, chunk);
        prop_assert_eq!(ev, events);
        prop_assert_eq!(tr, triggers);
    }

    #[test]
    fn evt2_round_trip(groups in prop::collection::vec(group(), 1..300),
                       trig in prop::collection::vec((any::<u64>(), 0u8..32, any::<bool>()), 0..20),
                       t0 in prop_oneof![Just(0u64), 0u64..(1 << 40)],
                       cuts in prop::collection::vec(any::<usize>(), 0..5), chunk in 1usize..500) {
        let (events, triggers) = build(&groups, &trig, t0);
        let (ev, tr, _) = round_trip(Format::Evt2, &events, &triggers, &cuts, chunk);
        prop_assert_eq!(ev, events);
        prop_assert_eq!(tr, triggers);
    }
}

#[test]
fn evt3_vectors_save_words() {
    // Dense rows: 64 rows, each with 40 ON pixels in a 48-pixel span, at
    // 10 timestamps.
    let mut events = Vec::new();
    for k in 0..10i64 {
        for y in 0..64u16 {
            for x in (100..148u16).filter(|x| x % 6 != 0) {
                events.push(Event {
                    t: 1000 + 7 * k,
                    x,
                    y,
                    p: 1,
                });
            }
        }
    }
    let (ev, _, size) = round_trip(Format::Evt3, &events, &[], &[], 1 << 16);
    assert_eq!(ev, events);
    // ADDR_X only would need one word per event plus row and time words.
    let addr_x_only = 2 * (events.len() + 64 * 10 + 2 * 10) as u64;
    assert!(
        size < addr_x_only / 2,
        "{size} bytes vs {addr_x_only} without vectors"
    );
}

#[test]
fn evt3_time_may_step_back_within_a_loop() {
    let events = vec![
        Event {
            t: 50_000,
            x: 1,
            y: 1,
            p: 1,
        },
        Event {
            t: 49_000,
            x: 2,
            y: 1,
            p: 1,
        },
        Event {
            t: 30_000,
            x: 3,
            y: 2,
            p: 0,
        },
        Event {
            t: 60_000,
            x: 4,
            y: 2,
            p: 0,
        },
    ];
    let (ev, _, _) = round_trip(Format::Evt3, &events, &[], &[], 10);
    assert_eq!(ev, events);
}

#[test]
fn writers_refuse_what_they_cannot_encode() {
    let dir = tempfile::tempdir().unwrap();
    let g = Geometry::new(1280, 720);
    for format in [Format::Evt3, Format::Evt2] {
        let path = dir.path().join("bad.raw");
        // Time stepping back across a clock loop.
        let mut w = create(&path, Some(format), g).unwrap();
        let mut c = Chunk::default();
        c.events.push(40_000_000_000, 1, 1, 1);
        c.events.push(1, 1, 1, 1);
        let e = w.write_chunk(&c).unwrap_err().to_string();
        assert!(e.contains("time-ordered"), "{e}");
        drop(w);
        assert!(!path.exists(), "a failed write must leave no file");
        // Negative time, coordinates beyond 11 bits.
        let mut w = create(&path, Some(format), g).unwrap();
        let mut c = Chunk {
            events: EventChunk::default(),
            triggers: vec![],
        };
        c.events.push(-5, 1, 1, 1);
        assert!(w.write_chunk(&c).is_err());
        let mut c = Chunk::default();
        c.events.push(5, 4000, 1, 1);
        assert!(w.write_chunk(&c).is_err());
        drop(w);
        assert!(!path.exists());
    }
    let e = create(
        dir.path().join("g.raw"),
        Some(Format::Evt3),
        Geometry::new(0, 10),
    )
    .err()
    .unwrap()
    .to_string();
    assert!(e.contains("geometry"), "{e}");
}

#[test]
fn evt3_writer_output_is_read_by_the_evt3_crate() {
    let events: Vec<Event> = (0..5000)
        .map(|i: i64| Event {
            t: i * 9_000 + (i % 7),
            x: (i * 37 % 1280) as u16,
            y: (i * 11 % 720) as u16,
            p: (i % 3 == 0) as u8,
        })
        .collect();
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("c.raw");
    let mut w = create(&path, None, Geometry::new(1280, 720)).unwrap();
    let mut c = Chunk::default();
    for e in &events {
        c.events.push(e.t, e.x, e.y, e.p);
    }
    w.write_chunk(&c).unwrap();
    w.finish().unwrap();
    let theirs = evt3::Evt3Decoder::new().decode_file(&path).unwrap();
    assert_eq!(theirs.metadata.width, 1280);
    let got: Vec<Event> = theirs
        .cd_events
        .iter()
        .map(|e| Event {
            t: e.timestamp as i64,
            x: e.x,
            y: e.y,
            p: e.polarity,
        })
        .collect();
    assert_eq!(got, events);
}

/// The simulator's output (every effect on, triggers on) written as EVT 3.0
/// and EVT 2.0 and read back: identical events and triggers.
#[test]
fn simulator_output_round_trips() {
    let mut sc = ebptv::sim::presets::preset("demo").unwrap();
    sc.duration_s = 0.01;
    sc.noise.hot_pixels = Some(ebptv::sim::scenario::HotPixels {
        count: 10,
        rate_hz: 500.0,
    });
    sc.noise.background_noise = Some(ebptv::sim::scenario::BackgroundNoise { rate_hz: 5.0 });
    sc.pixel.off_events = Some(ebptv::sim::scenario::OffEvents {
        threshold: 0.3,
        tau_us: 20.0,
    });
    sc.triggers.enabled = true;
    let out = ebptv::sim::simulate(&sc, 7).unwrap();
    assert!(
        out.events.len() > 1000,
        "the demo scene should produce events"
    );
    let events: Vec<Event> = out.events.iter().collect();
    for format in [Format::Evt3, Format::Evt2] {
        let (ev, tr, size) = round_trip(format, &events, &out.triggers, &[events.len() / 3], 4096);
        assert_eq!(ev.len(), events.len(), "{format:?}");
        assert!(
            ev == events,
            "{format:?}: events differ after the round trip"
        );
        assert_eq!(tr, out.triggers, "{format:?}");
        eprintln!(
            "{format:?}: {} events, {} triggers, {:.2} bytes/event",
            ev.len(),
            tr.len(),
            size as f64 / ev.len() as f64
        );
    }
}
