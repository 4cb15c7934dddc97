//! Binning against analytic truth: steady vortex and channel (means),
//! homogeneous shear with known stresses, the in-bin fit against the
//! top-hat gradient bias, standard errors, noise correction, walls.
use super::grid_common;

use crate::grid::profiles::{profile_at_x, wall_fit, WallOptions, WallSide};
use crate::grid::{
    bin_samples, estimate, EstimateOptions, Fit, GridStats, Lattice, Sample, Weighting,
};
use grid_common::*;

fn stats(samples: &[Sample], bin: (f64, f64), w: Weighting, fit: Fit, min_count: u64) -> GridStats {
    let acc = bin_samples(samples, Lattice::new(bin.0, bin.1, 0.5).unwrap(), w).unwrap();
    estimate(
        &acc,
        &EstimateOptions {
            fit,
            min_count,
            noise_rms: 0.0,
        },
    )
    .unwrap()
}

/// Largest |measured − truth| of the mean velocity over bins whose support
/// lies inside the seeded area, relative to the maximum speed.
fn max_mean_error(
    g: &GridStats,
    truth: impl Fn(f64, f64) -> (f64, f64),
    inside: impl Fn(f64, f64) -> bool,
    vmax: f64,
) -> (f64, usize) {
    let mut worst: f64 = 0.0;
    let mut n = 0;
    for (iy, &y) in g.ys.iter().enumerate() {
        for (ix, &x) in g.xs.iter().enumerate() {
            let b = g.at(ix, iy);
            if !b.u.is_finite() || !inside(x, y) {
                continue;
            }
            let (u, v) = truth(x, y);
            worst = worst.max(((b.u - u).powi(2) + (b.v - v).powi(2)).sqrt() / vmax);
            n += 1;
        }
    }
    (worst, n)
}

fn median_mean_error(
    g: &GridStats,
    truth: impl Fn(f64, f64) -> (f64, f64),
    inside: impl Fn(f64, f64) -> bool,
    vmax: f64,
) -> f64 {
    let mut e = vec![];
    for (iy, &y) in g.ys.iter().enumerate() {
        for (ix, &x) in g.xs.iter().enumerate() {
            let b = g.at(ix, iy);
            if b.u.is_finite() && inside(x, y) {
                let (u, v) = truth(x, y);
                e.push(((b.u - u).powi(2) + (b.v - v).powi(2)).sqrt() / vmax);
            }
        }
    }
    median(e)
}

#[ebptv_macros::unit_test]
fn steady_vortex_mean_within_one_percent_of_max_speed() {
    // In-bin fits evaluate the mean at the bin centre: every bin within 1 %.
    // A top-hat mean belongs to the samples' centroid, which wanders by
    // ~b/√(12·n_tracks) from the centre, so for it the median is tested.
    // Bin 12 in a core of radius 48 keeps the curvature bias of the
    // constant and linear models (~U''b²/24) well below 1 %; the quadratic
    // model also handles bin 16 in a core of 30.
    let cases = [
        (48.0, 12.0, Weighting::TopHat, Fit::Linear, false),
        (48.0, 12.0, Weighting::Gaussian, Fit::Linear, false),
        (48.0, 12.0, Weighting::TopHat, Fit::None, true),
        (30.0, 16.0, Weighting::TopHat, Fit::Quadratic, false),
    ];
    for (rc, bin, w, fit, median_only) in cases {
        let vx = Vortex {
            xc: 160.0,
            yc: 160.0,
            rc,
            vmax: 1000.0,
        };
        let s = tracks_in_steady_flow(
            |x, y| vx.velocity(x, y),
            320.0,
            320.0,
            80_000,
            8,
            500.0,
            10.0,
            1,
        );
        let g = stats(&s, (bin, bin), w, fit, 50);
        let inside =
            |x: f64, y: f64| (bin..320.0 - bin).contains(&x) && (bin..320.0 - bin).contains(&y);
        let (err, n) = max_mean_error(&g, |x, y| vx.velocity(x, y), inside, vx.vmax);
        let med = median_mean_error(&g, |x, y| vx.velocity(x, y), inside, vx.vmax);
        eprintln!("vortex rc {rc} bin {bin} {w:?} {fit:?}: mean error max {err:.4} median {med:.4} of vmax over {n} bins");
        assert!(n > 500, "{n} bins");
        if median_only {
            assert!(med < 0.01, "{w:?} {fit:?}: median {med}");
        } else {
            assert!(err < 0.01, "{w:?} {fit:?}: {err}");
        }
    }
}

#[ebptv_macros::unit_test]
fn channel_mean_within_one_percent_of_max_speed() {
    let (h, umax) = (200.0, 1500.0);
    let flow = |_x: f64, y: f64| (umax * 4.0 * y * (h - y) / (h * h), 0.0);
    let s = tracks_in_steady_flow(flow, 512.0, h, 40_000, 8, 200.0, 15.0, 2);
    for (bin, fit) in [
        ((16.0, 16.0), Fit::None),
        ((32.0, 4.0), Fit::Linear),
        ((16.0, 16.0), Fit::Quadratic),
    ] {
        let g = stats(&s, bin, Weighting::TopHat, fit, 50);
        let inside =
            |x: f64, y: f64| x > 40.0 && x < 300.0 && y > bin.1 / 2.0 && y < h - bin.1 / 2.0;
        let (err, n) = max_mean_error(&g, flow, inside, umax);
        let med = median_mean_error(&g, flow, inside, umax);
        eprintln!("channel {bin:?} {fit:?}: mean error max {err:.4} median {med:.4} over {n} bins");
        assert!(n > 50);
        // Top-hat: centroid wander (see the vortex test) → median.
        if fit == Fit::None {
            assert!(med < 0.01, "{bin:?} {fit:?}: {med}");
        } else {
            assert!(err < 0.01, "{bin:?} {fit:?}: {err}");
        }
    }
}

/// Median relative errors of uu, vv, uv over bins with ≥ 50 samples.
fn stress_errors(g: &GridStats, f: &Shear) -> (f64, f64, f64, usize) {
    let (mut eu, mut ev, mut ec) = (vec![], vec![], vec![]);
    for b in &g.bins {
        if b.count >= 50 && b.uu.is_finite() {
            eu.push((b.uu - f.uu()).abs() / f.uu());
            ev.push((b.vv - f.vv()).abs() / f.vv());
            ec.push((b.uv - f.uv()).abs() / f.uv().abs());
        }
    }
    let n = eu.len();
    (median(eu), median(ev), median(ec), n)
}

#[ebptv_macros::unit_test]
fn shear_flow_stresses_within_ten_percent() {
    let f = Shear {
        u0: 400.0,
        shear: 2.0,
        su: 50.0,
        sv: 30.0,
        rho: -0.45,
    };
    let s = f.tracks(400.0, 300.0, 100_000, 10, 1000.0, 0.5, 3);
    for (w, fit) in [
        (Weighting::TopHat, Fit::Linear),
        (Weighting::TopHat, Fit::Quadratic),
        (Weighting::Gaussian, Fit::Linear),
    ] {
        let g = stats(&s, (16.0, 16.0), w, fit, 50);
        let (eu, ev, ec, n) = stress_errors(&g, &f);
        eprintln!("shear {w:?} {fit:?}: median rel. errors uu {eu:.3} vv {ev:.3} uv {ec:.3} over {n} bins");
        assert!(n >= 100, "{n}");
        assert!(
            eu < 0.10 && ev < 0.10 && ec < 0.10,
            "{w:?} {fit:?}: {eu} {ev} {ec}"
        );
    }
}

#[ebptv_macros::unit_test]
fn in_bin_fit_removes_the_top_hat_gradient_bias_in_a_shear_layer() {
    // Strong shear: the top-hat bias (dU/dy)² b²/12 = 12² · 16² / 12 ≈ 3072
    // (px/s)² exceeds the true uu = 2500.
    let f = Shear {
        u0: 400.0,
        shear: 12.0,
        su: 50.0,
        sv: 30.0,
        rho: -0.45,
    };
    let s = f.tracks(400.0, 300.0, 100_000, 10, 1000.0, 0.5, 4);
    let top = stats(&s, (16.0, 16.0), Weighting::TopHat, Fit::None, 50);
    let lin = stats(&s, (16.0, 16.0), Weighting::TopHat, Fit::Linear, 50);
    let (eu_top, _, _, _) = stress_errors(&top, &f);
    let (eu_lin, ev_lin, ec_lin, _) = stress_errors(&lin, &f);
    let predicted = f.shear * f.shear * 256.0 / 12.0 / f.uu();
    eprintln!(
        "top-hat uu error {eu_top:.3} (predicted bias {predicted:.3}); linear fit {eu_lin:.3}"
    );
    assert!(
        (eu_top - predicted).abs() < 0.2 * predicted,
        "top-hat bias {eu_top} vs predicted {predicted}"
    );
    assert!(
        eu_lin < 0.08 && ev_lin < 0.10 && ec_lin < 0.10,
        "{eu_lin} {ev_lin} {ec_lin}"
    );
    // The fit also returns the gradient.
    let g: Vec<f64> = lin
        .bins
        .iter()
        .filter(|b| b.count >= 50)
        .map(|b| b.dudy)
        .collect();
    let m = median(g);
    assert!((m - f.shear).abs() < 0.05 * f.shear, "dU/dy {m}");
}

#[ebptv_macros::unit_test]
fn in_bin_fit_removes_spurious_stress_in_a_vortex_core() {
    // Steady vortex, small noise: all "stress" is the unresolved gradient.
    let vx = Vortex {
        xc: 160.0,
        yc: 160.0,
        rc: 24.0,
        vmax: 800.0,
    };
    let noise = 5.0;
    let s = tracks_in_steady_flow(
        |x, y| vx.velocity(x, y),
        320.0,
        320.0,
        50_000,
        6,
        300.0,
        noise,
        5,
    );
    let core = |g: &GridStats| {
        let mut v = vec![];
        for (iy, &y) in g.ys.iter().enumerate() {
            for (ix, &x) in g.xs.iter().enumerate() {
                let b = g.at(ix, iy);
                if ((x - vx.xc).powi(2) + (y - vx.yc).powi(2)).sqrt() < 1.5 * vx.rc && b.count >= 50
                {
                    v.push(b.uu + b.vv);
                }
            }
        }
        assert!(v.len() >= 10, "{} core bins", v.len());
        median(v)
    };
    let top = core(&stats(&s, (24.0, 24.0), Weighting::TopHat, Fit::None, 50));
    let lin = core(&stats(&s, (24.0, 24.0), Weighting::TopHat, Fit::Linear, 50));
    let quad = core(&stats(
        &s,
        (24.0, 24.0),
        Weighting::TopHat,
        Fit::Quadratic,
        50,
    ));
    let floor = 2.0 * noise * noise;
    eprintln!("vortex core uu+vv: top-hat {top:.0}, linear {lin:.0}, quadratic {quad:.0}, noise floor {floor:.0}");
    assert!(
        top > 20.0 * floor,
        "top-hat should be dominated by the gradient: {top}"
    );
    assert!(lin < 0.1 * top, "linear {lin} vs top-hat {top}");
    assert!(
        quad < 0.01 * top && quad < 5.0 * floor,
        "quadratic {quad} vs top-hat {top}, noise floor {floor}"
    );
}

#[ebptv_macros::unit_test]
fn standard_error_counts_tracks_not_samples() {
    // Each track carries one frozen fluctuation over 20 samples: the bin
    // mean has the error of ~50 independent values, not of 1000.
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};
    let n01 = Normal::new(0.0, 1.0).unwrap();
    let mut rng = rand_pcg::Pcg64::seed_from_u64(6);
    let sigma = 40.0;
    let (mut means, mut ses) = (vec![], vec![]);
    let mut last = None;
    for rep in 0..300 {
        let mut s = vec![];
        for t in 0..50u64 {
            let up = sigma * n01.sample(&mut rng);
            for k in 0..20 {
                s.push(Sample {
                    x: 1.0 + 0.3 * k as f64,
                    y: 3.0,
                    u: 100.0 + up,
                    v: 0.0,
                    t_us: k as f64,
                    track_id: rep * 100 + t,
                });
            }
        }
        let lat = Lattice::new(8.0, 8.0, 0.0).unwrap();
        let spec =
            crate::grid::GridSpec::covering(lat, Weighting::TopHat, 0.0, 7.0, 0.0, 7.0).unwrap();
        let mut acc = crate::grid::GridAccumulator::new(spec);
        acc.add_all(&s);
        let g = estimate(&acc, &EstimateOptions::default()).unwrap();
        let (ix, iy) = g.nearest(4.0, 4.0);
        let b = *g.at(ix, iy);
        assert_eq!(b.count, 1000);
        assert_eq!(b.n_tracks, 50);
        means.push(b.u);
        ses.push(b.se_u);
        last = Some(b);
    }
    let m = means.iter().sum::<f64>() / means.len() as f64;
    let sd = (means.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (means.len() - 1) as f64).sqrt();
    let se = median(ses);
    let naive = (last.unwrap().uu / 1000.0).sqrt();
    eprintln!(
        "empirical sd of the mean {sd:.2}, reported se {se:.2}, naive per-sample se {naive:.2}"
    );
    assert!(se / sd > 0.85 && se / sd < 1.15, "se {se} vs sd {sd}");
    assert!(naive < 0.3 * sd);
}

#[ebptv_macros::unit_test]
fn noise_bias_correction_recovers_stresses() {
    let f = Shear {
        u0: 300.0,
        shear: 0.0,
        su: 50.0,
        sv: 30.0,
        rho: -0.45,
    };
    let mut s = f.tracks(256.0, 256.0, 10_000, 10, 1000.0, 0.5, 7);
    use rand::SeedableRng;
    use rand_distr::{Distribution, Normal};
    let noise = 25.0;
    let nz = Normal::new(0.0, noise).unwrap();
    let mut rng = rand_pcg::Pcg64::seed_from_u64(8);
    for p in &mut s {
        p.u += nz.sample(&mut rng);
        p.v += nz.sample(&mut rng);
    }
    let acc = bin_samples(
        &s,
        Lattice::new(32.0, 32.0, 0.0).unwrap(),
        Weighting::TopHat,
    )
    .unwrap();
    let raw = estimate(
        &acc,
        &EstimateOptions {
            fit: Fit::None,
            min_count: 50,
            noise_rms: 0.0,
        },
    )
    .unwrap();
    let cor = estimate(
        &acc,
        &EstimateOptions {
            fit: Fit::None,
            min_count: 50,
            noise_rms: noise,
        },
    )
    .unwrap();
    let (ru, rv, _, _) = stress_errors(&raw, &f);
    let (cu, cv, cc, _) = stress_errors(&cor, &f);
    eprintln!("noise: raw errors uu {ru:.3} vv {rv:.3}; corrected {cu:.3} {cv:.3} uv {cc:.3}");
    assert!(rv > 0.5, "noise must show in vv before correction: {rv}");
    assert!(cu < 0.06 && cv < 0.1 && cc < 0.1, "{cu} {cv} {cc}");
}

#[ebptv_macros::unit_test]
fn wall_position_and_shear_from_thin_bins() {
    // Channel between walls at y = 40 and y = 240; dU/dy at the wall = 4 Umax/H.
    let (y0, h, umax) = (40.0, 200.0, 1000.0);
    let flow = |_x: f64, y: f64| {
        let e = y - y0;
        if (0.0..=h).contains(&e) {
            (umax * 4.0 * e * (h - e) / (h * h), 0.0)
        } else {
            (0.0, 0.0)
        }
    };
    let mut s = tracks_in_steady_flow(flow, 256.0, 300.0, 60_000, 6, 100.0, 5.0, 9);
    s.retain(|p| p.y > y0 && p.y < y0 + h);
    let acc = bin_samples(&s, Lattice::new(64.0, 2.0, 0.0).unwrap(), Weighting::TopHat).unwrap();
    let g = estimate(
        &acc,
        &EstimateOptions {
            fit: Fit::Linear,
            min_count: 20,
            noise_rms: 0.0,
        },
    )
    .unwrap();
    let (_, prof) = profile_at_x(&g, 128.0);
    let nu = 1.0e-6;
    let px_per_mm = 20.0;
    let fit = wall_fit(
        &prof,
        &WallOptions {
            side: WallSide::Top,
            wall_y: None,
            n_fit: 4,
            nu_m2_s: nu,
            px_per_mm,
        },
    )
    .unwrap();
    let slope = 4.0 * umax / h;
    eprintln!(
        "wall at {:.2} px (true {y0}), dU/dy {:.2} (true {slope}), u_tau {:.4} m/s",
        fit.wall_y_px, fit.dudy_per_s, fit.u_tau_m_s
    );
    assert!((fit.wall_y_px - y0).abs() < 0.5, "{}", fit.wall_y_px);
    assert!(
        (fit.dudy_per_s - slope).abs() < 0.05 * slope,
        "{}",
        fit.dudy_per_s
    );
    assert!((fit.u_tau_m_s - (nu * slope).sqrt()).abs() < 0.03 * (nu * slope).sqrt());
    let known = wall_fit(
        &prof,
        &WallOptions {
            side: WallSide::Top,
            wall_y: Some(y0),
            n_fit: 4,
            nu_m2_s: nu,
            px_per_mm,
        },
    )
    .unwrap();
    assert!((known.dudy_per_s - slope).abs() < 0.05 * slope);
    // In inner units the near-wall points sit on u+ = y+.
    let p = prof
        .iter()
        .find(|p| p.u.is_finite() && p.y > y0 + 2.0)
        .unwrap();
    let (yp, up, _) = known.inner(p, px_per_mm);
    assert!((up - yp).abs() < 0.05 * yp, "u+ {up} y+ {yp}");
    assert!(wall_fit(
        &prof,
        &WallOptions {
            side: WallSide::Top,
            wall_y: None,
            n_fit: 4,
            nu_m2_s: 0.0,
            px_per_mm
        }
    )
    .is_err());
}
