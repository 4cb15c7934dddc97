//! Output-fit speed (samples/s): the adaptive-window fit of every sample
//! of a long gap-free track, by the reference ([`fit_adaptive`], sums and
//! solves per sample) and by the tabulated grid path
//! ([`fit_adaptive_grid`]); and the outlier pass's leave-one-out
//! prediction, plain fit against [`LeaveOneOut`]. One thread. The
//! `_prior` variants run with the curvature prior (`accel_rms` 0.1
//! px/pulse², the tracker's default estimates one): the grid path's
//! rank-one update and full candidate search.
//!
//! `cargo bench -p ebptv-benches --bench fit`

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use std::hint::black_box;
use std::time::Duration;

use ebptv::track::fit::{
    fit_adaptive, fit_adaptive_grid, fit_eval, GridTables, LeaveOneOut, WindowRule,
};

fn bench(c: &mut Criterion) {
    // A gently curving track, 0.2 px of deterministic pseudo-noise.
    let n = 2000;
    let noise = |i: usize, k: u64| {
        let h = (i as u64 ^ k).wrapping_mul(0x9E37_79B9_7F4A_7C15) >> 11;
        (h as f64 / (1u64 << 53) as f64 - 0.5) * 0.4
    };
    let tau: Vec<f64> = (0..n).map(|i| i as f64).collect();
    let xs: Vec<f64> = (0..n)
        .map(|i| 300.0 + 6.0 * i as f64 + 40.0 * (0.01 * i as f64).sin() + noise(i, 1))
        .collect();
    let ys: Vec<f64> = (0..n)
        .map(|i| 500.0 - 2.0 * i as f64 + 40.0 * (0.01 * i as f64).cos() + noise(i, 2))
        .collect();
    let rule = WindowRule {
        min_window: 5,
        max_window: 21,
        order: 2,
        sigma: 0.12,
        bias_weight: 4.0,
        accel_rms: 0.0,
    };
    let tables = GridTables::new(&rule);
    let xy: Vec<[f64; 2]> = xs.iter().zip(&ys).map(|(&x, &y)| [x, y]).collect();
    let mut g = c.benchmark_group("output_fit");
    g.sample_size(10).measurement_time(Duration::from_secs(3));
    g.throughput(Throughput::Elements(n as u64));
    g.bench_function("adaptive_reference", |b| {
        b.iter(|| {
            (0..n)
                .map(|j| fit_adaptive(&tau, &xs, &ys, j, tau[j], &rule).unwrap().0.vx)
                .sum::<f64>()
        })
    });
    g.bench_function("adaptive_grid", |b| {
        b.iter(|| {
            (0..n)
                .map(|j| fit_adaptive_grid(&tables, &xy, j, &rule).unwrap().0.vx)
                .sum::<f64>()
        })
    });
    let prior = WindowRule {
        accel_rms: 0.1,
        ..rule
    };
    g.bench_function("adaptive_reference_prior", |b| {
        b.iter(|| {
            (0..n)
                .map(|j| {
                    fit_adaptive(&tau, &xs, &ys, j, tau[j], &prior)
                        .unwrap()
                        .0
                        .vx
                })
                .sum::<f64>()
        })
    });
    g.bench_function("adaptive_grid_prior", |b| {
        b.iter(|| {
            (0..n)
                .map(|j| fit_adaptive_grid(&tables, &xy, j, &prior).unwrap().0.vx)
                .sum::<f64>()
        })
    });
    let w = 11;
    let loo = LeaveOneOut::new(w);
    g.bench_function("outlier_reference", |b| {
        let (mut t, mut ox, mut oy) = (Vec::new(), Vec::new(), Vec::new());
        b.iter(|| {
            let mut sum = 0.0;
            for i in 0..n - w {
                let e = i + w / 2;
                t.clear();
                ox.clear();
                oy.clear();
                for k in (i..=i + w).filter(|&k| k != e) {
                    t.push(k as f64 - e as f64);
                    ox.push(xs[k]);
                    oy.push(ys[k]);
                }
                sum += fit_eval(&t, &ox, &oy, 2, 0.0).unwrap().x;
            }
            black_box(sum)
        })
    });
    g.bench_function("outlier_grid", |b| {
        b.iter(|| {
            let mut sum = 0.0;
            for i in 0..n - w {
                sum += loo.predict(&xy[i..=i + w], w / 2).unwrap().0;
            }
            black_box(sum)
        })
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
