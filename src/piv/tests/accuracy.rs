//! PIV accuracy on synthetic particle images with known displacement.

use crate::piv::synth::{particle_frames, SynthOptions};
use crate::piv::validate::is_valid;
use crate::piv::{piv_frames, PivOptions, VectorField};

/// Bias and rms (about the mean) of the valid vectors against truth, both
/// components pooled; nodes within `border` px of the image edge skipped.
fn errors(
    f: &VectorField,
    truth: &dyn Fn(f64, f64) -> (f64, f64),
    w: f64,
    h: f64,
    border: f64,
) -> (f64, f64, f64, usize) {
    let mut e = Vec::new();
    let mut invalid = 0;
    for k in 0..f.grid.len() {
        let (x, y) = (f.grid.x(k % f.grid.nx), f.grid.y(k / f.grid.nx));
        if x < border || y < border || x > w - border || y > h - border {
            continue;
        }
        if !is_valid(f.flags[k]) {
            invalid += 1;
            continue;
        }
        let (tu, tv) = truth(x, y);
        e.push(f.u[k] - tu);
        e.push(f.v[k] - tv);
    }
    let n = e.len() as f64;
    let mean = e.iter().sum::<f64>() / n;
    let rms_total = (e.iter().map(|x| x * x).sum::<f64>() / n).sqrt();
    let std = (e.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n).sqrt();
    (mean, std, rms_total, invalid)
}

#[ebptv_macros::unit_test]
fn uniform_subpixel_shift_random_error_below_005px_with_nf5() {
    let d = (3.3, -1.7);
    let so = SynthOptions {
        width: 256,
        height: 256,
        ppp: 0.02,
        particle_sigma: 0.8,
        frames: 5,
        seed: 11,
        ..Default::default()
    };
    let frames = particle_frames(&so, &|_, _| d);
    let refs: Vec<_> = frames.iter().collect();
    let o = PivOptions::new(32, 16);
    let f = piv_frames(&refs, &o).unwrap();
    let (bias, std, rms, invalid) = errors(&f, &|_, _| d, 256.0, 256.0, 0.0);
    eprintln!("uniform: bias {bias:.4} std {std:.4} rms {rms:.4} invalid {invalid}");
    assert!(std <= 0.05, "random error {std} px");
    assert!(rms <= 0.05, "total error {rms} px");
    assert_eq!(invalid, 0);
}

#[ebptv_macros::unit_test]
fn two_frames_single_pass_finds_integer_and_large_shifts() {
    let d = (7.0, 4.0);
    let so = SynthOptions {
        frames: 2,
        seed: 5,
        ..Default::default()
    };
    let frames = particle_frames(&so, &|_, _| d);
    let refs: Vec<_> = frames.iter().collect();
    let mut o = PivOptions::new(32, 32);
    o.passes = 1;
    let f = piv_frames(&refs, &o).unwrap();
    let (_, _, rms, invalid) = errors(&f, &|_, _| d, 256.0, 256.0, 0.0);
    assert!(rms < 0.1, "rms {rms}");
    assert!(invalid <= 2, "{invalid} invalid");
}

#[ebptv_macros::unit_test]
fn rectangular_64x8_windows_resolve_a_boundary_layer_profile() {
    // u(y) varies strongly in y: 64x8 windows resolve it where 32x32 smear.
    let (w, h) = (256usize, 128usize);
    let prof = move |_x: f64, y: f64| (4.0 * (y / h as f64).sqrt().min(1.0), 0.0);
    let so = SynthOptions {
        width: w,
        height: h,
        ppp: 0.05,
        frames: 5,
        seed: 2,
        ..Default::default()
    };
    let frames = particle_frames(&so, &prof);
    let refs: Vec<_> = frames.iter().collect();
    let mut o = PivOptions::new(64, 8);
    o.window_h = 8;
    o.spacing_x = 32;
    o.spacing_y = 4;
    let f = piv_frames(&refs, &o).unwrap();
    let (_, _, rms, _) = errors(&f, &prof, w as f64, h as f64, 8.0);
    eprintln!("64x8 profile rms {rms:.4}");
    assert!(rms < 0.15, "rms {rms}");
}

/// Mean error of the inner nodes for a uniform shift `d`.
fn inner_bias(d: (f64, f64), passes: usize, nf: usize, seed: u64) -> (f64, f64) {
    let so = SynthOptions {
        width: 160,
        height: 160,
        ppp: 0.02,
        particle_sigma: 0.8,
        frames: nf,
        seed,
        ..Default::default()
    };
    let frames = particle_frames(&so, &|_, _| d);
    let refs: Vec<_> = frames.iter().collect();
    let mut o = PivOptions::new(32, 16);
    o.passes = passes;
    let f = piv_frames(&refs, &o).unwrap();
    let (mut su, mut sv, mut n) = (0.0, 0.0, 0.0);
    for k in 0..f.grid.len() {
        if is_valid(f.flags[k]) {
            su += f.u[k] - d.0;
            sv += f.v[k] - d.1;
            n += 1.0;
        }
    }
    (su / n, sv / n)
}

/// Peak locking: the bias as a function of the sub-pixel part of the
/// displacement. Printed for BENCHMARKS.md (`-- --nocapture`).
#[ebptv_macros::unit_test]
fn bias_versus_subpixel_displacement_is_small_with_deformation() {
    let mut worst3: f64 = 0.0;
    for k in 0..=10 {
        let frac = k as f64 / 10.0;
        let d = (2.0 + frac, 0.0);
        let b1 = inner_bias(d, 1, 2, 100 + k).0;
        let b3 = inner_bias(d, 3, 2, 100 + k).0;
        eprintln!("peak-locking frac {frac:.1}: bias 1 pass {b1:+.4} px, 3 passes {b3:+.4} px");
        worst3 = worst3.max(b3.abs());
    }
    assert!(worst3 < 0.03, "peak-locking bias {worst3} px with 3 passes");
}
