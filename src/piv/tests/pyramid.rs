//! Pyramid correlation (Sciacchitano, Scarano & Wieneke 2012): summing the
//! correlation of pairs `(k, k+s)`, `s = 1 … S`, scaled to the unit
//! separation, lowers the random error of multi-frame PIV at the same
//! number of frames, on binary pseudo-images (the pixel rounding of the
//! event positions is the dominant noise, as in the real data) of a flow
//! with known displacement and acceleration.

use crate::piv::synth::{accelerating_frames, SynthOptions};
use crate::piv::validate::is_valid;
use crate::piv::{piv_frames, PivOptions};
use rand::{Rng, SeedableRng};

/// Random error (std about the mean, u and v pooled), bias (mean error) and
/// invalid count of the inner nodes against the velocity at the stack's
/// centre time, over several independent particle seedings.
fn errors(
    pyramid: usize,
    nf: usize,
    seeds: std::ops::Range<u64>,
    noise: Option<f32>,
) -> (f64, f64, usize) {
    let (d0, a) = ((2.4, -1.3), (0.15, 0.05));
    let tc = (nf as f64 - 1.0) / 2.0;
    let truth = (d0.0 + a.0 * tc, d0.1 + a.1 * tc);
    let mut e = Vec::new();
    let mut invalid = 0;
    for seed in seeds {
        let so = SynthOptions {
            width: 192,
            height: 192,
            ppp: 0.015,
            frames: nf,
            binary_sigma: if noise.is_some() { None } else { Some(1.0) },
            seed,
            ..Default::default()
        };
        let mut frames = accelerating_frames(&so, d0, a);
        if let Some(sd) = noise {
            let mut rng = rand_pcg::Pcg64::seed_from_u64(1000 + seed);
            for f in frames.iter_mut() {
                for v in f.data.iter_mut() {
                    // Uniform noise of standard deviation `sd`.
                    *v += sd * 3f32.sqrt() * (2.0 * rng.gen::<f32>() - 1.0);
                }
            }
        }
        let refs: Vec<_> = frames.iter().collect();
        let mut o = PivOptions::new(32, 16);
        o.pyramid = pyramid;
        let f = piv_frames(&refs, &o).unwrap();
        for k in 0..f.grid.len() {
            let (i, j) = (k % f.grid.nx, k / f.grid.nx);
            if i == 0 || j == 0 || i + 1 == f.grid.nx || j + 1 == f.grid.ny {
                continue;
            }
            if !is_valid(f.flags[k]) {
                invalid += 1;
                continue;
            }
            e.push(f.u[k] - truth.0);
            e.push(f.v[k] - truth.1);
        }
    }
    let n = e.len() as f64;
    let mean = e.iter().sum::<f64>() / n;
    let std = (e.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n).sqrt();
    (std, mean, invalid)
}

#[ebptv_macros::unit_test]
fn pyramid_lowers_random_error_at_equal_frames() {
    let nf = 5;
    // Binary pseudo-images: the event positions rounded to pixels.
    let (s1, b1, i1) = errors(1, nf, 0..4, None);
    let (s2, b2, i2) = errors(2, nf, 0..4, None);
    let (s4, b4, i4) = errors(4, nf, 0..4, None);
    eprintln!(
        "N_f = {nf}, binary pseudo-images: random error plain {s1:.4} px (bias {b1:+.4}, \
         {i1} invalid), pyramid S=2 {s2:.4} px (bias {b2:+.4}, {i2} invalid), \
         S=4 {s4:.4} px (bias {b4:+.4}, {i4} invalid)"
    );
    // Gaussian particle images with strong uniform noise (std 0.3 of the
    // particle peak): each pair's correlation noise is largely independent.
    let (n1, nb1, _) = errors(1, nf, 0..4, Some(0.3));
    let (n2, nb2, _) = errors(2, nf, 0..4, Some(0.3));
    let (n4, nb4, _) = errors(4, nf, 0..4, Some(0.3));
    eprintln!(
        "N_f = {nf}, noisy particle images: random error plain {n1:.4} px (bias {nb1:+.4}), \
         S=2 {n2:.4} px (bias {nb2:+.4}), S=4 {n4:.4} px (bias {nb4:+.4})"
    );
    // With rounding noise the plain sum already telescopes to the end
    // frames (Σ (x_{k+1} − x_k) = x_4 − x_0), so the gain is smaller there.
    assert!(s1 <= 0.05 && s2 <= 0.05 && s4 <= 0.05);
    assert!(s4 < 0.9 * s1, "pyramid S=4 {s4} px vs plain {s1} px");
    assert!(s2 < s1, "pyramid S=2 {s2} px vs plain {s1} px");
    assert!(
        n2 < 0.85 * n1 && n4 < 0.85 * n1,
        "noisy: S=2 {n2}, S=4 {n4} vs plain {n1} px"
    );
    // Symmetric pair sets: the estimate is the velocity at the centre
    // time; the pyramid also halves the peak-locking bias of binary images.
    assert!(b4.abs() < b1.abs(), "bias S=4 {b4} vs plain {b1}");
    for b in [b1, b2, b4, nb1, nb2, nb4] {
        assert!(b.abs() < 0.03, "bias {b} px");
    }
    assert!(
        i4 <= i1 + 1 && i2 <= i1 + 1,
        "invalid: S=2 {i2}, S=4 {i4}, plain {i1}"
    );
}

#[ebptv_macros::unit_test]
fn pyramid_needs_deformation_and_enough_frames() {
    let so = SynthOptions {
        frames: 3,
        ..Default::default()
    };
    let frames = accelerating_frames(&so, (1.0, 0.0), (0.0, 0.0));
    let refs: Vec<_> = frames.iter().collect();
    let mut o = PivOptions::new(32, 16);
    o.pyramid = 3;
    let e = piv_frames(&refs, &o).unwrap_err().to_string();
    assert!(e.contains("pyramid") && e.contains("3 frames"), "{e}");
    o.pyramid = 2;
    o.passes = 1;
    let e = piv_frames(&refs, &o).unwrap_err().to_string();
    assert!(e.contains("pyramid") && e.contains("passes"), "{e}");
    o.pyramid = 0;
    o.passes = 3;
    assert!(piv_frames(&refs, &o).is_err());
}
