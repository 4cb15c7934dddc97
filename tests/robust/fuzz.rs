//! The whole chain on arbitrary and mutated event streams: pulses →
//! cluster → track → grid. Whatever the input (time jumps, coordinates no
//! sensor has, all noise, one pixel, empty pulses), every stage returns a
//! result or an `Error` — no panic — and its outputs stay within bounds
//! that follow from the input size, not from its time span or coordinates.

use ebptv::cluster::{ClusterParams, Particle};
use ebptv::events::{Chunk, EventChunk, Geometry};
use ebptv::grid::{bin_samples, Lattice, Sample, Weighting};
use ebptv::io::guard::TimeGuard;
use ebptv::io::{EventSource, Format, StreamInfo};
use ebptv::pulses::{split_pulses, Analyzer, PulseOptions, PulseTiming};
use ebptv::track::{PtvSink, PtvStream, Track, TrackParams};
use proptest::prelude::*;

/// A source serving one chunk of events, then the end.
struct Mem(StreamInfo, Option<Chunk>);

impl EventSource for Mem {
    fn info(&self) -> &StreamInfo {
        &self.0
    }
    fn next_chunk(&mut self, chunk: &mut Chunk) -> ebptv::Result<bool> {
        match self.1.take() {
            Some(c) if !c.events.is_empty() || !c.triggers.is_empty() => {
                *chunk = c;
                Ok(true)
            }
            _ => {
                chunk.clear();
                Ok(false)
            }
        }
    }
}

fn source(ev: &EventChunk, geometry: Option<Geometry>) -> Mem {
    let info = StreamInfo {
        path: "fuzz.raw".into(),
        format: Format::Evt3,
        geometry,
        header: vec![],
        payload_offset: 0,
        file_size: None,
    };
    Mem(
        info,
        Some(Chunk {
            events: ev.clone(),
            triggers: vec![],
        }),
    )
}

#[derive(Default)]
struct Collect {
    pulses: u64,
    particles: u64,
    tracks: Vec<Track>,
}

impl PtvSink for Collect {
    fn particles(&mut self, _pulse: i64, _t: f64, ps: &[Particle]) -> ebptv::Result<()> {
        self.pulses += 1;
        self.particles += ps.len() as u64;
        Ok(())
    }
    fn tracks(&mut self, tracks: &[Track]) -> ebptv::Result<()> {
        self.tracks.extend_from_slice(tracks);
        Ok(())
    }
}

/// A pulsed stream (bursts every `period` µs from a few particles moving
/// right), then mutated.
#[derive(Debug, Clone)]
enum Mutation {
    None,
    /// Add `dt` µs to the events from index `at` on (a clock jump that stays).
    Jump {
        at: usize,
        dt: i64,
    },
    /// Add `dt` µs to `len` events from `at` (a glitch that comes back).
    Glitch {
        at: usize,
        len: usize,
        dt: i64,
    },
    /// Coordinates of `len` events from `at` set to (x, y).
    Coords {
        at: usize,
        len: usize,
        x: u16,
        y: u16,
    },
    /// Every event on one pixel.
    OnePixel,
    /// Times replaced by uniform noise over the span.
    AllNoise(u64),
}

fn mutation() -> impl Strategy<Value = Mutation> {
    prop_oneof![
        Just(Mutation::None),
        (
            0usize..4000,
            prop_oneof![
                Just(3_600_000_000i64),
                Just(-3_600_000_000),
                1i64..20_000_000
            ]
        )
            .prop_map(|(at, dt)| Mutation::Jump { at, dt }),
        (
            0usize..4000,
            1usize..300,
            prop_oneof![Just(16_000_000_000i64), 6_000_000i64..1_000_000_000]
        )
            .prop_map(|(at, len, dt)| Mutation::Glitch { at, len, dt }),
        (0usize..4000, 1usize..500, any::<u16>(), any::<u16>())
            .prop_map(|(at, len, x, y)| Mutation::Coords { at, len, x, y }),
        Just(Mutation::OnePixel),
        any::<u64>().prop_map(Mutation::AllNoise),
    ]
}

fn pulsed_stream(period: i64, pulses: i64, seed: u64) -> EventChunk {
    let mut s = seed | 1;
    let mut rnd = |m: u64| {
        s = s
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (s >> 33) % m.max(1)
    };
    let mut ev = EventChunk::default();
    for k in 0..pulses {
        for p in 0..8u64 {
            let x = (20 + p * 25 + 2 * k as u64) % 300;
            let y = 30 + p * 20;
            let t = 1_000 + k * period + 40 + rnd(20) as i64;
            ev.push(t, x as u16, y as u16, 1);
        }
        ev.push(
            1_000 + k * period + rnd(period as u64) as i64,
            rnd(320) as u16,
            rnd(240) as u16,
            0,
        );
    }
    ev
}

fn mutate(mut ev: EventChunk, m: &Mutation) -> EventChunk {
    let n = ev.len();
    match *m {
        Mutation::None => {}
        Mutation::Jump { at, dt } => {
            for t in ev.t.iter_mut().skip(at.min(n)) {
                *t += dt;
            }
        }
        Mutation::Glitch { at, len, dt } => {
            for t in ev.t.iter_mut().skip(at.min(n)).take(len) {
                *t += dt;
            }
        }
        Mutation::Coords { at, len, x, y } => {
            for i in at.min(n)..(at + len).min(n) {
                ev.x[i] = x;
                ev.y[i] = y;
            }
        }
        Mutation::OnePixel => {
            ev.x.iter_mut().for_each(|x| *x = 7);
            ev.y.iter_mut().for_each(|y| *y = 7);
        }
        Mutation::AllNoise(seed) => {
            let (lo, hi) = (ev.t[0], ev.t[n - 1]);
            let mut s = seed | 1;
            let mut ts: Vec<i64> = (0..n)
                .map(|_| {
                    s = s
                        .wrapping_mul(6364136223846793005)
                        .wrapping_add(1442695040888963407);
                    lo + ((s >> 33) % (hi - lo + 1) as u64) as i64
                })
                .collect();
            ts.sort();
            ev.t = ts;
        }
    }
    ev
}

/// The chain on one stream; panics only on a broken bound.
fn chain(ev: &EventChunk, geometry: Option<Geometry>, force: bool) {
    let n = ev.len() as u64;
    let opts = PulseOptions {
        pulse_hz: Some(5000.0),
        require_pulsed: !force,
        ..Default::default()
    };
    let mut src = TimeGuard::new(source(ev, geometry));
    let mut an = Analyzer::new(opts.clone(), src.info().geometry).unwrap();
    let mut c = Chunk::default();
    let report = (|| {
        while src.next_chunk(&mut c)? {
            an.push(&c)?;
        }
        an.finish()
    })();
    let report = match report {
        Ok(r) => r,
        Err(e) => {
            assert!(!e.to_string().is_empty());
            return;
        }
    };
    // Bounded outputs: the map within the largest sensor, pulses within
    // the span of accepted events.
    assert!(report.rate_map.width <= 4096 && report.rate_map.height <= 4096);
    assert!(report.latency.histogram.len() <= 50_000);
    assert!(report.events <= n);
    if !force {
        assert!(report.pulsed.pulsed);
    }
    let timing: PulseTiming = report.timing;
    let mut stream = PtvStream::new(ClusterParams::default(), TrackParams::default(), 8).unwrap();
    let mut sink = Collect::default();
    let mut src = TimeGuard::new(source(ev, geometry));
    let split = split_pulses(&mut src, &timing, &mut |p| stream.push_pulse(p, &mut sink));
    if split.is_err() {
        return;
    }
    let Ok(_stats) = stream.finish(&mut sink) else {
        return;
    };
    assert!(
        sink.pulses <= report.pulses + 8,
        "{} > {}",
        sink.pulses,
        report.pulses
    );
    assert!(sink.particles <= n);
    let samples: Vec<Sample> = sink
        .tracks
        .iter()
        .flat_map(|t| {
            t.points
                .iter()
                .map(move |p| Sample::from_track_point(t.id, p))
        })
        .collect();
    assert!(samples.len() as u64 <= sink.pulses * n.max(1));
    if samples.is_empty() {
        return;
    }
    match bin_samples(
        &samples,
        Lattice::new(16.0, 16.0, 0.0).unwrap(),
        Weighting::TopHat,
    ) {
        Ok(acc) => {
            let _ = acc;
        }
        Err(e) => assert!(!e.to_string().is_empty()),
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 48, failure_persistence: None, ..ProptestConfig::default() })]

    #[test]
    fn chain_survives_mutated_streams(
        m in mutation(),
        pulses in 30i64..400,
        seed in any::<u64>(),
        geom in prop_oneof![Just(None), Just(Some(Geometry::new(320, 240))),
                            Just(Some(Geometry::new(65535, 65535))), Just(Some(Geometry::new(0, 0)))],
        force in any::<bool>(),
    ) {
        let ev = mutate(pulsed_stream(200, pulses, seed), &m);
        chain(&ev, geom, force);
    }

    #[test]
    fn chain_survives_arbitrary_events(
        raw in proptest::collection::vec((any::<i64>(), any::<u16>(), any::<u16>(), 0u8..2), 1..600),
        sorted in any::<bool>(),
    ) {
        let mut raw = raw;
        for r in raw.iter_mut() {
            r.0 >>= 20; // times within ±2^43 µs (the decoders' reach)
        }
        if sorted {
            raw.sort_by_key(|r| r.0);
        }
        let mut ev = EventChunk::default();
        for (t, x, y, p) in raw {
            ev.push(t, x, y, p);
        }
        chain(&ev, None, true);
    }
}

/// The unmutated stream passes the pulsed-light test; all noise does not.
#[test]
fn pulsed_test_tells_bursts_from_noise() {
    let ev = pulsed_stream(200, 400, 5);
    let run = |ev: &EventChunk| {
        let mut an = Analyzer::new(
            PulseOptions {
                pulse_hz: Some(5000.0),
                ..Default::default()
            },
            None,
        )
        .unwrap();
        an.push(&Chunk {
            events: ev.clone(),
            triggers: vec![],
        })
        .unwrap();
        an.finish()
    };
    let r = run(&ev).unwrap();
    assert!(r.pulsed.pulsed, "{:?}", r.pulsed);
    let noise = mutate(ev, &Mutation::AllNoise(3));
    match run(&noise) {
        Ok(r) => assert!(!r.pulsed.pulsed, "{:?}", r.pulsed),
        Err(e) => assert!(e.to_string().contains("no pulses"), "{e}"),
    }
}
