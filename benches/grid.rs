//! Binning speed (samples/s) of the mergeable grid accumulator, and the
//! per-sample noise estimator.

use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use ebptv::grid::noise::{velocity_noise, NoiseOptions};
use ebptv::grid::{
    estimate, EstimateOptions, Fit, GridAccumulator, GridSpec, Lattice, Sample, Weighting,
};
use rand::{Rng, SeedableRng};

fn samples(n: usize) -> Vec<Sample> {
    let mut rng = rand_pcg::Pcg64::seed_from_u64(1);
    (0..n)
        .map(|k| {
            let (x, y) = (rng.gen::<f64>() * 1280.0, rng.gen::<f64>() * 720.0);
            Sample {
                x,
                y,
                u: 500.0 + 0.1 * y + rng.gen::<f64>() * 20.0,
                v: rng.gen::<f64>() * 20.0,
                t_us: k as f64,
                track_id: (k / 10) as u64,
            }
        })
        .collect()
}

fn bench(c: &mut Criterion) {
    let s = samples(1_000_000);
    let mut g = c.benchmark_group("grid_binning");
    g.sample_size(10)
        .measurement_time(std::time::Duration::from_secs(4))
        .warm_up_time(std::time::Duration::from_secs(1));
    g.throughput(Throughput::Elements(s.len() as u64));
    for (name, w, ov) in [
        ("tophat_ov0", Weighting::TopHat, 0.0),
        ("tophat_ov0.5", Weighting::TopHat, 0.5),
        ("gaussian_ov0", Weighting::Gaussian, 0.0),
    ] {
        let spec = GridSpec::covering(
            Lattice::new(16.0, 16.0, ov).unwrap(),
            w,
            0.0,
            1280.0,
            0.0,
            720.0,
        )
        .unwrap();
        g.bench_with_input(BenchmarkId::new("bin_16px", name), &spec, |b, spec| {
            b.iter(|| {
                let mut acc = GridAccumulator::new(*spec);
                acc.add_all(&s);
                acc.total_count()
            })
        });
    }
    let spec = GridSpec::covering(
        Lattice::new(16.0, 16.0, 0.5).unwrap(),
        Weighting::TopHat,
        0.0,
        1280.0,
        0.0,
        720.0,
    )
    .unwrap();
    let mut acc = GridAccumulator::new(spec);
    acc.add_all(&s);
    g.throughput(Throughput::Elements(spec.n_bins() as u64));
    g.bench_function("estimate_quadratic_bins", |b| {
        b.iter(|| {
            estimate(
                &acc,
                &EstimateOptions {
                    fit: Fit::Quadratic,
                    min_count: 10,
                    noise_rms: 0.0,
                },
            )
            .unwrap()
            .bins
            .len()
        })
    });
    g.finish();

    // Noise estimator: demo-like density (2 300 samples per pulse over
    // 640 × 360 px, 0.01 per px²), 435 pulses ≈ 1 M samples.
    let mut rng = rand_pcg::Pcg64::seed_from_u64(2);
    let dense: Vec<Sample> = (0..1_000_500usize)
        .map(|k| {
            let (x, y) = (rng.gen::<f64>() * 640.0, rng.gen::<f64>() * 360.0);
            Sample {
                x,
                y,
                u: 0.1 * y + rng.gen::<f64>() * 20.0,
                v: rng.gen::<f64>() * 20.0,
                t_us: (k / 2300) as f64 * 200.0,
                track_id: (k % 2300) as u64,
            }
        })
        .collect();
    let spec = GridSpec::covering(
        Lattice::new(16.0, 16.0, 0.0).unwrap(),
        Weighting::TopHat,
        0.0,
        640.0,
        0.0,
        360.0,
    )
    .unwrap();
    let mut acc = GridAccumulator::new(spec);
    acc.add_all(&dense);
    let mean = estimate(&acc, &EstimateOptions::default()).unwrap();
    let mut g = c.benchmark_group("grid_noise");
    g.sample_size(10)
        .measurement_time(std::time::Duration::from_secs(4))
        .warm_up_time(std::time::Duration::from_secs(1));
    g.throughput(Throughput::Elements(dense.len() as u64));
    g.bench_function("velocity_noise_pairs", |b| {
        b.iter(|| {
            velocity_noise(&dense, &mean, &NoiseOptions::default())
                .unwrap()
                .pairs
        })
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
