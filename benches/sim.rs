//! Simulator throughput (events per second of wall time).
//!
//! `cargo bench --bench sim`. Scenes: the full-frame water jet at ~32 Mev/s
//! (the paper's recording regime) and the demo vortex.

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use ebptv::sim::{presets, simulate};

fn bench(c: &mut Criterion) {
    let mut g = c.benchmark_group("simulate");
    g.sample_size(10)
        .measurement_time(std::time::Duration::from_secs(8))
        .warm_up_time(std::time::Duration::from_secs(1));
    for (name, secs) in [("water_jet_5khz", 0.02), ("demo", 0.02), ("rib_wake", 0.02)] {
        let mut s = presets::preset(name).unwrap();
        s.duration_s = secs;
        let n = simulate(&s, 1).unwrap().events.len() as u64;
        g.throughput(Throughput::Elements(n));
        g.bench_function(name, |b| b.iter(|| simulate(&s, 1).unwrap().events.len()));
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
