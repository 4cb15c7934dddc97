//! Vectors per second of multi-frame PIV: 32x32 windows, 16 px spacing,
//! N_f = 5, 1 and 3 passes (and 3 passes with pyramid correlation up to
//! separation 4), on 512x512 synthetic particle images.

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use ebptv::piv::synth::{particle_frames, SynthOptions};
use ebptv::piv::{node_grid, piv_frames, PivOptions};
use std::time::Duration;

fn bench(c: &mut Criterion) {
    let so = SynthOptions {
        width: 512,
        height: 512,
        frames: 5,
        seed: 1,
        ..Default::default()
    };
    let frames = particle_frames(&so, &|_, _| (2.3, -1.4));
    let refs: Vec<_> = frames.iter().collect();
    let mut g = c.benchmark_group("piv_512x512_w32_s16_nf5");
    g.sample_size(10)
        .measurement_time(Duration::from_secs(4))
        .warm_up_time(Duration::from_secs(1));
    for (passes, pyramid) in [(1usize, 1usize), (3, 1), (3, 4)] {
        let mut o = PivOptions::new(32, 16);
        o.passes = passes;
        o.pyramid = pyramid;
        let nodes = node_grid(512, 512, &o).unwrap().len() as u64;
        g.throughput(Throughput::Elements(nodes));
        g.bench_function(format!("passes{passes}_pyramid{pyramid}"), |b| {
            b.iter(|| piv_frames(&refs, &o).unwrap())
        });
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
