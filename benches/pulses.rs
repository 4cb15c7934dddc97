//! Throughput of the one-pass pulse analysis and of split_pulses on an
//! in-memory pulsed recording (no decoding): events per second.

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use ebptv::events::{Chunk, Edge, Trigger};
use ebptv::pulses::{Analyzer, PulseOptions, Splitter};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;

/// 10 kHz pulses, ~35 Mev/s-like density: 4 M events over ~0.11 s, in
/// 1 M-event chunks as the readers deliver them.
fn recording() -> Vec<Chunk> {
    let mut rng = Pcg64::seed_from_u64(1);
    let mut ev: Vec<(i64, u16, u16)> = Vec::with_capacity(4_000_000);
    let mut k = 0i64;
    while ev.len() < 4_000_000 {
        let t0 = 20.0 + k as f64 * 100.0;
        for _ in 0..3500 {
            let t = t0 + 10.0 + rng.gen::<f64>() * 15.0;
            ev.push((t as i64, rng.gen_range(0..1280), rng.gen_range(0..720)));
        }
        k += 1;
    }
    ev.sort_by_key(|e| e.0);
    let mut chunks = Vec::new();
    for (i, part) in ev.chunks(1 << 20).enumerate() {
        let mut c = Chunk::default();
        for e in part {
            c.events.push(e.0, e.1, e.2, 1);
        }
        if i == 0 {
            for j in 0..k {
                c.triggers.push(Trigger {
                    t: 20 + j * 100,
                    channel: 1,
                    edge: Edge::Rising,
                });
            }
        }
        chunks.push(c);
    }
    chunks
}

fn bench(c: &mut Criterion) {
    let chunks = recording();
    let n: usize = chunks.iter().map(|c| c.events.len()).sum();
    let mut g = c.benchmark_group("pulses");
    g.sample_size(10)
        .measurement_time(std::time::Duration::from_secs(5));
    g.throughput(Throughput::Elements(n as u64));
    g.bench_function("analyze_triggers", |b| {
        b.iter(|| {
            let mut an = Analyzer::new(
                PulseOptions::default(),
                Some(ebptv::Geometry::new(1280, 720)),
            )
            .unwrap();
            for c in &chunks {
                an.push(c).unwrap();
            }
            an.finish().unwrap()
        })
    });
    g.bench_function("analyze_estimated", |b| {
        b.iter(|| {
            let opts = PulseOptions {
                pulse_hz: Some(10_000.0),
                ignore_triggers: true,
                ..Default::default()
            };
            let mut an = Analyzer::new(opts, Some(ebptv::Geometry::new(1280, 720))).unwrap();
            for c in &chunks {
                an.push(c).unwrap();
            }
            an.finish().unwrap()
        })
    });
    let mut an = Analyzer::new(PulseOptions::default(), None).unwrap();
    for c in &chunks {
        an.push(c).unwrap();
    }
    let timing = an.finish().unwrap().timing;
    g.bench_function("split_pulses", |b| {
        b.iter(|| {
            let mut sp = Splitter::new(timing);
            let mut count = 0usize;
            let mut on = |p: ebptv::pulses::PulseEvents| {
                count += p.events.len();
                Ok(())
            };
            for c in &chunks {
                sp.push(&c.events, &mut on).unwrap();
            }
            sp.finish(&mut on).unwrap();
            count
        })
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
