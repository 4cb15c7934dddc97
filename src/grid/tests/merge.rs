//! Split-and-merge equals one run; the accumulator's fits equal a direct
//! least-squares reference; bad input gives clear errors.
use super::grid_common;

use crate::grid::accumulate::basis;
use crate::grid::io::{load_state, save_state};
use crate::grid::{
    bin_samples, estimate, EstimateOptions, Fit, GridAccumulator, GridSpec, Lattice, Sample,
    Weighting,
};
use grid_common::*;
use nalgebra::{DMatrix, DVector};

fn close(a: f64, b: f64, rel: f64) -> bool {
    (a.is_nan() && b.is_nan()) || (a - b).abs() <= rel * a.abs().max(b.abs()).max(1e-9)
}

#[ebptv_macros::unit_test]
fn merged_slices_equal_one_run() {
    let f = Shear {
        u0: 5000.0,
        shear: 3.0,
        su: 40.0,
        sv: 25.0,
        rho: -0.4,
    };
    let s = f.tracks(300.0, 200.0, 20_000, 12, 100.0, 0.9, 11);
    for (w, ov) in [(Weighting::TopHat, 0.5), (Weighting::Gaussian, 0.0)] {
        let lat = Lattice::new(16.0, 8.0, ov).unwrap();
        let single = bin_samples(&s, lat, w).unwrap();
        // Row chunks of the track-grouped file (cuts inside tracks), each
        // on its own window, through the state file.
        let dir = tempfile::tempdir().unwrap();
        let cuts = [0, 70_001, 150_007, s.len()];
        let mut merged: Option<GridAccumulator> = None;
        for k in 0..3 {
            let part = bin_samples(&s[cuts[k]..cuts[k + 1]], lat, w).unwrap();
            let path = dir.path().join(format!("part{k}.json"));
            save_state(&path, &part).unwrap();
            let back = load_state(&path).unwrap();
            assert!(back == part, "state round trip must be exact");
            match merged.as_mut() {
                None => merged = Some(back),
                Some(m) => m.merge(&back).unwrap(),
            }
        }
        let merged = merged.unwrap();
        assert_eq!(merged.total_count(), single.total_count());
        for fit in [Fit::None, Fit::Linear, Fit::Quadratic] {
            let opt = EstimateOptions {
                fit,
                min_count: 10,
                noise_rms: 0.0,
            };
            let a = estimate(&single, &opt).unwrap();
            let b = estimate(&merged, &opt).unwrap();
            // Windows may differ: compare by bin centre.
            let mut compared = 0;
            for (iy, &y) in a.ys.iter().enumerate() {
                for (ix, &x) in a.xs.iter().enumerate() {
                    let p = a.at(ix, iy);
                    let (jx, jy) = b.nearest(x, y);
                    assert!((b.xs[jx] - x).abs() < 1e-9 && (b.ys[jy] - y).abs() < 1e-9);
                    let q = b.at(jx, jy);
                    assert_eq!(p.count, q.count);
                    assert_eq!(
                        p.n_tracks, q.n_tracks,
                        "distinct tracks must survive the cut"
                    );
                    for (name, x1, x2) in [
                        ("u", p.u, q.u),
                        ("v", p.v, q.v),
                        ("uu", p.uu, q.uu),
                        ("vv", p.vv, q.vv),
                        ("uv", p.uv, q.uv),
                        ("se_u", p.se_u, q.se_u),
                        ("dudy", p.dudy, q.dudy),
                    ] {
                        assert!(
                            close(x1, x2, 1e-9),
                            "{w:?} {fit:?} {name} at ({x}, {y}): {x1} vs {x2}"
                        );
                    }
                    compared += p.u.is_finite() as usize;
                }
            }
            assert!(compared > 300, "{compared}");
        }
    }
}

#[ebptv_macros::unit_test]
fn incompatible_grids_do_not_merge() {
    let s = vec![Sample {
        x: 10.0,
        y: 10.0,
        u: 1.0,
        v: 2.0,
        t_us: 0.0,
        track_id: 0,
    }];
    let mut a = bin_samples(
        &s,
        Lattice::new(16.0, 16.0, 0.5).unwrap(),
        Weighting::TopHat,
    )
    .unwrap();
    for other in [
        bin_samples(&s, Lattice::new(8.0, 16.0, 0.5).unwrap(), Weighting::TopHat).unwrap(),
        bin_samples(
            &s,
            Lattice::new(16.0, 16.0, 0.0).unwrap(),
            Weighting::TopHat,
        )
        .unwrap(),
        bin_samples(
            &s,
            Lattice::new(16.0, 16.0, 0.5).unwrap(),
            Weighting::Gaussian,
        )
        .unwrap(),
        bin_samples(
            &s,
            Lattice::with_origin(16.0, 16.0, 0.5, 0.0, 0.0).unwrap(),
            Weighting::TopHat,
        )
        .unwrap(),
    ] {
        let e = a.merge(&other).unwrap_err().to_string();
        assert!(e.contains("incompatible grids"), "{e}");
    }
}

#[ebptv_macros::unit_test]
fn bad_input_is_a_clear_error() {
    assert!(bin_samples(
        &[],
        Lattice::new(16.0, 16.0, 0.0).unwrap(),
        Weighting::TopHat
    )
    .is_err());
    let nan = Sample {
        x: f64::NAN,
        y: 1.0,
        u: 1.0,
        v: 1.0,
        t_us: 0.0,
        track_id: 0,
    };
    assert!(bin_samples(
        &[nan],
        Lattice::new(16.0, 16.0, 0.0).unwrap(),
        Weighting::TopHat
    )
    .is_err());
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("junk.json");
    std::fs::write(&p, b"{\"format\":\"something\"}").unwrap();
    let e = load_state(&p).unwrap_err().to_string();
    assert!(e.contains("junk.json"), "{e}");
    let opt = EstimateOptions {
        fit: Fit::None,
        min_count: 0,
        noise_rms: 0.0,
    };
    let acc = GridAccumulator::new(
        GridSpec::covering(
            Lattice::new(8.0, 8.0, 0.0).unwrap(),
            Weighting::TopHat,
            0.0,
            10.0,
            0.0,
            10.0,
        )
        .unwrap(),
    );
    assert!(estimate(&acc, &opt).is_err());
    assert!(estimate(
        &acc,
        &EstimateOptions {
            noise_rms: -1.0,
            ..EstimateOptions::default()
        }
    )
    .is_err());
}

/// Reference: weighted least squares on the raw samples of one bin
/// (nalgebra SVD), residual variance with the same degrees-of-freedom rule.
fn reference_fit(samples: &[(f64, f64, f64, f64, f64)], p: usize) -> (f64, f64, f64) {
    let n = samples.len();
    let mut a = DMatrix::zeros(n, p);
    let mut bu = DVector::zeros(n);
    let mut bv = DVector::zeros(n);
    for (r, &(xi, eta, w, u, v)) in samples.iter().enumerate() {
        let phi = basis(xi, eta);
        let sw = w.sqrt();
        for c in 0..p {
            a[(r, c)] = sw * phi[c];
        }
        bu[r] = sw * u;
        bv[r] = sw * v;
    }
    let svd = a.clone().svd(true, true);
    let cu = svd.solve(&bu, 1e-12).unwrap();
    let cv = svd.solve(&bv, 1e-12).unwrap();
    let ru = &bu - &a * &cu;
    let rv = &bv - &a * &cv;
    let w: f64 = samples.iter().map(|s| s.2).sum();
    let w2: f64 = samples.iter().map(|s| s.2 * s.2).sum();
    let dof = w * (1.0 - p as f64 / (w * w / w2));
    let _ = rv;
    (cu[0], cv[0], ru.dot(&ru) / dof)
}

#[ebptv_macros::unit_test]
fn accumulated_fit_matches_direct_least_squares() {
    use rand::{Rng, SeedableRng};
    let mut rng = rand_pcg::Pcg64::seed_from_u64(12);
    for w in [Weighting::TopHat, Weighting::Gaussian] {
        let lat = Lattice::new(10.0, 6.0, 0.0).unwrap();
        let spec = GridSpec::covering(lat, w, 0.0, 9.0, 0.0, 5.0).unwrap();
        let mut acc = GridAccumulator::new(spec);
        let mut s = vec![];
        for k in 0..400 {
            let (x, y) = (rng.gen::<f64>() * 9.0, rng.gen::<f64>() * 5.0);
            let u =
                300.0 + 20.0 * x - 7.0 * y + 1.5 * x * y - 0.8 * y * y + rng.gen::<f64>() * 30.0;
            let v = -50.0 + 3.0 * x * x + rng.gen::<f64>() * 10.0;
            s.push(Sample {
                x,
                y,
                u,
                v,
                t_us: 0.0,
                track_id: k / 4,
            });
        }
        acc.add_all(&s);
        for fit in [Fit::None, Fit::Linear, Fit::Quadratic] {
            let g = estimate(
                &acc,
                &EstimateOptions {
                    fit,
                    min_count: 1,
                    noise_rms: 0.0,
                },
            )
            .unwrap();
            let mut checked = 0;
            for (iy, &yc) in g.ys.iter().enumerate() {
                for (ix, &xc) in g.xs.iter().enumerate() {
                    let b = g.at(ix, iy);
                    let mine: Vec<_> = s
                        .iter()
                        .filter_map(|p| {
                            let (xi, eta) = ((p.x - xc) / lat.bin_w, (p.y - yc) / lat.bin_h);
                            w.weight(xi, eta).map(|wt| (xi, eta, wt, p.u, p.v))
                        })
                        .collect();
                    assert_eq!(mine.len() as u64, b.count);
                    if mine.len() < 40 {
                        continue;
                    }
                    assert_eq!(b.fit_params as usize, fit.n_params());
                    let (u0, v0, uu) = reference_fit(&mine, fit.n_params());
                    assert!(close(b.u, u0, 1e-9), "{w:?} {fit:?} u {} vs {u0}", b.u);
                    assert!(close(b.v, v0, 1e-9), "{w:?} {fit:?} v {} vs {v0}", b.v);
                    assert!(close(b.uu, uu, 1e-7), "{w:?} {fit:?} uu {} vs {uu}", b.uu);
                    checked += 1;
                }
            }
            assert!(checked >= 1, "{w:?} {fit:?}");
        }
    }
}

#[ebptv_macros::unit_test]
fn fit_falls_back_when_positions_cannot_resolve_it() {
    // All samples on one line y = const: η-terms are unresolvable.
    let s: Vec<Sample> = (0..50)
        .map(|k| Sample {
            x: k as f64 * 0.15,
            y: 3.0,
            u: 10.0 + k as f64,
            v: 0.0,
            t_us: 0.0,
            track_id: k,
        })
        .collect();
    let acc = bin_samples(&s, Lattice::new(8.0, 8.0, 0.0).unwrap(), Weighting::TopHat).unwrap();
    let g = estimate(
        &acc,
        &EstimateOptions {
            fit: Fit::Quadratic,
            min_count: 1,
            noise_rms: 0.0,
        },
    )
    .unwrap();
    let (ix, iy) = g.nearest(3.5, 3.5);
    let b = g.at(ix, iy);
    assert_eq!(b.count, 50);
    assert_eq!(b.fit_params, 1, "must fall back to the mean");
    assert!(b.u.is_finite());
}

#[ebptv_macros::unit_test]
fn parallel_binning_equals_sequential() {
    let f = Shear {
        u0: 800.0,
        shear: 1.0,
        su: 30.0,
        sv: 20.0,
        rho: 0.3,
    };
    let s = f.tracks(256.0, 128.0, 30_000, 8, 100.0, 0.9, 13);
    let lat = Lattice::new(16.0, 16.0, 0.5).unwrap();
    let seq = bin_samples(&s, lat, Weighting::TopHat).unwrap();
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(3)
        .build()
        .unwrap();
    let mut par = GridAccumulator::new(seq.spec);
    pool.install(|| par.add_par(&s));
    let opt = EstimateOptions {
        fit: Fit::Linear,
        min_count: 5,
        noise_rms: 0.0,
    };
    let (a, b) = (estimate(&seq, &opt).unwrap(), estimate(&par, &opt).unwrap());
    for (p, q) in a.bins.iter().zip(&b.bins) {
        assert_eq!(p.count, q.count);
        assert_eq!(p.n_tracks, q.n_tracks);
        assert!(
            close(p.u, q.u, 1e-10) && close(p.uu, q.uu, 1e-8) && close(p.uv, q.uv, 1e-8),
            "{p:?} {q:?}"
        );
    }
}
