//! FFT cross-correlation of interrogation windows, summed over frame pairs.
//!
//! The correlation of a window pair `(a, b)` (both `w × h`, mean removed) is
//! the circular cross-correlation
//!
//! ```text
//! R(dx, dy) = Σ_x Σ_y a(x, y) · b((x + dx) mod w, (y + dy) mod h) / sqrt(Σa² · Σb²)
//! ```
//!
//! so that a pattern displaced by `+d` from `a` to `b` peaks at `R(d)`; the
//! normalisation makes every pair contribute on the same scale (a perfectly
//! matching pair peaks at 1), which is what a *sum of correlation* over `N_f`
//! frames needs: one bright pulse must not dominate the sum.
//!
//! The fast path works in the frequency domain. Two real windows are packed
//! into one complex window `z = a + i·b`, so one complex 2-D FFT yields both
//! spectra (`A(k) = (Z(k) + Z*(-k))/2`, `B(k) = (Z(k) − Z*(-k))/2i`). The
//! products `A*(k)·B(k)` of all pairs are summed in the frequency domain and
//! transformed back once: `N_f − 1` forward FFTs and one inverse per window.
//! The summed cross-spectrum of real windows is Hermitian, so only half of
//! it (`kx ≤ w/2`) is accumulated and the rest filled by symmetry before the
//! inverse transform.
//! Plans are built once ([`CorrelationPlan`]) and shared by all threads; each
//! thread owns its scratch buffers ([`Workspace`]). Windows of any size work
//! (rustfft handles any length; rectangular windows such as 64×8 are just
//! rows of 64 and columns of 8).
//!
//! [`direct_correlation`] is the plain O(w²h²) definition above; the tests
//! require the FFT path to match it.

use std::sync::Arc;

use rustfft::num_complex::Complex32;
use rustfft::{Fft, FftPlanner};

/// FFT plans for one window size, shareable across threads.
#[derive(Clone)]
pub struct CorrelationPlan {
    pub w: usize,
    pub h: usize,
    fwd_w: Arc<dyn Fft<f32>>,
    fwd_h: Arc<dyn Fft<f32>>,
    inv_w: Arc<dyn Fft<f32>>,
    inv_h: Arc<dyn Fft<f32>>,
}

impl CorrelationPlan {
    pub fn new(w: usize, h: usize) -> Self {
        assert!(w > 0 && h > 0, "window size must be positive");
        let mut planner = FftPlanner::<f32>::new();
        CorrelationPlan {
            w,
            h,
            fwd_w: planner.plan_fft_forward(w),
            fwd_h: planner.plan_fft_forward(h),
            inv_w: planner.plan_fft_inverse(w),
            inv_h: planner.plan_fft_inverse(h),
        }
    }

    pub fn workspace(&self) -> Workspace {
        let n = self.w * self.h;
        let scratch_len = [
            self.fwd_w.get_inplace_scratch_len(),
            self.fwd_h.get_inplace_scratch_len(),
            self.inv_w.get_inplace_scratch_len(),
            self.inv_h.get_inplace_scratch_len(),
        ]
        .into_iter()
        .max()
        .unwrap_or(0);
        Workspace {
            plan: self.clone(),
            z: vec![Complex32::default(); n],
            zt: vec![Complex32::default(); n],
            acc: vec![Complex32::default(); n],
            scratch: vec![Complex32::default(); scratch_len],
            pairs: 0,
        }
    }
}

/// Per-thread buffers for accumulating a sum of correlation.
pub struct Workspace {
    plan: CorrelationPlan,
    z: Vec<Complex32>,
    /// Transposed spectrum (`w` rows of `h`).
    zt: Vec<Complex32>,
    /// Accumulated cross-spectrum, transposed layout like `zt`.
    acc: Vec<Complex32>,
    scratch: Vec<Complex32>,
    pairs: usize,
}

fn transpose(src: &[Complex32], dst: &mut [Complex32], rows: usize, cols: usize) {
    for r in 0..rows {
        for c in 0..cols {
            dst[c * rows + r] = src[r * cols + c];
        }
    }
}

/// Sum of 8 independent lanes: vectorises, and keeps the rounding error of
/// long windows small (each lane sums only n/8 values).
#[inline]
fn lane_sum(v: &[f32], f: impl Fn(f32) -> f32) -> f64 {
    let mut acc = [0.0f32; 8];
    let chunks = v.chunks_exact(8);
    let rest = chunks.remainder();
    for c in chunks {
        for l in 0..8 {
            acc[l] += f(c[l]);
        }
    }
    let mut s: f64 = acc.iter().map(|&a| a as f64).sum();
    for &x in rest {
        s += f(x) as f64;
    }
    s
}

/// Mean removal in place; returns the energy (sum of squares) left.
pub fn remove_mean(win: &mut [f32]) -> f64 {
    let n = win.len() as f64;
    let mean = (lane_sum(win, |x| x) / n) as f32;
    for v in win.iter_mut() {
        *v -= mean;
    }
    lane_sum(win, |x| x * x)
}

impl Workspace {
    pub fn size(&self) -> (usize, usize) {
        (self.plan.w, self.plan.h)
    }

    /// Start a new sum of correlation.
    pub fn reset(&mut self) {
        // Only rows kx <= w/2 are accumulated and read (see `add_pair`).
        let used = (self.plan.w / 2 + 1) * self.plan.h;
        self.acc[..used]
            .iter_mut()
            .for_each(|c| *c = Complex32::default());
        self.pairs = 0;
    }

    /// Number of pairs that contributed since [`reset`](Self::reset).
    pub fn pairs(&self) -> usize {
        self.pairs
    }

    /// Add the normalised correlation of one window pair. `a`, `b`: `w*h`
    /// values, row-major, **mean already removed**, with energies `ea`, `eb`
    /// (sums of squares). A pair with no signal in either window adds nothing.
    pub fn add_pair(&mut self, a: &[f32], b: &[f32], ea: f64, eb: f64) {
        let (w, h) = (self.plan.w, self.plan.h);
        let n = w * h;
        debug_assert!(a.len() == n && b.len() == n);
        if !(ea > 0.0 && eb > 0.0) {
            return;
        }
        for i in 0..n {
            self.z[i] = Complex32::new(a[i], b[i]);
        }
        self.plan
            .fwd_w
            .process_with_scratch(&mut self.z, &mut self.scratch);
        transpose(&self.z, &mut self.zt, h, w);
        self.plan
            .fwd_h
            .process_with_scratch(&mut self.zt, &mut self.scratch);
        let scale = (1.0 / (ea * eb).sqrt()) as f32;
        // zt index: kx * h + ky; the mirror frequency -k of (kx, ky) is
        // ((w - kx) % w, (h - ky) % h). The cross-spectrum of real windows
        // is Hermitian, so only kx <= w/2 is accumulated; `finish` fills
        // the other half by symmetry.
        for kx in 0..=w / 2 {
            let mkx = if kx == 0 { 0 } else { w - kx };
            let row = &self.zt[kx * h..(kx + 1) * h];
            let mrow = &self.zt[mkx * h..(mkx + 1) * h];
            let acc = &mut self.acc[kx * h..(kx + 1) * h];
            for ky in 0..h {
                let mky = if ky == 0 { 0 } else { h - ky };
                let zk = row[ky];
                let zn = mrow[mky];
                // With A = (Z(k) + Z*(-k))/2 and B = (Z(k) - Z*(-k))/2i,
                // conj(A)·B = Im(Z(-k)·Z(k))/2 - i(|Z(k)|² - |Z(-k)|²)/4.
                let im = zn.re * zk.im + zn.im * zk.re;
                let dn = zk.norm_sqr() - zn.norm_sqr();
                acc[ky] += Complex32::new(0.5 * im * scale, -0.25 * dn * scale);
            }
        }
        self.pairs += 1;
    }

    /// Transform the accumulated cross-spectrum back: `out[dy * w + dx]` is
    /// the summed correlation at circular shift `(dx, dy)`, divided by the
    /// number of pairs (so a perfect match peaks at 1 whatever `N_f`).
    pub fn finish(&mut self, out: &mut [f32]) {
        let (w, h) = (self.plan.w, self.plan.h);
        let n = w * h;
        self.zt.copy_from_slice(&self.acc);
        for kx in w / 2 + 1..w {
            let mkx = w - kx;
            for ky in 0..h {
                let mky = if ky == 0 { 0 } else { h - ky };
                self.zt[kx * h + ky] = self.zt[mkx * h + mky].conj();
            }
        }
        self.plan
            .inv_h
            .process_with_scratch(&mut self.zt, &mut self.scratch);
        transpose(&self.zt, &mut self.z, w, h);
        self.plan
            .inv_w
            .process_with_scratch(&mut self.z, &mut self.scratch);
        let norm = 1.0 / (n as f32 * self.pairs.max(1) as f32);
        for i in 0..n {
            out[i] = self.z[i].re * norm;
        }
    }
}

/// The definition, computed directly (test oracle for the FFT path):
/// normalised circular cross-correlation averaged over the given pairs, with
/// mean removal done here.
pub fn direct_correlation(pairs: &[(&[f32], &[f32])], w: usize, h: usize) -> Vec<f32> {
    let mut out = vec![0.0f64; w * h];
    let mut used = 0usize;
    for (a, b) in pairs {
        let mut a = a.to_vec();
        let mut b = b.to_vec();
        let ea = remove_mean(&mut a);
        let eb = remove_mean(&mut b);
        if !(ea > 0.0 && eb > 0.0) {
            continue;
        }
        used += 1;
        let s = 1.0 / (ea * eb).sqrt();
        for dy in 0..h {
            for dx in 0..w {
                let mut acc = 0.0f64;
                for y in 0..h {
                    for x in 0..w {
                        acc += a[y * w + x] as f64 * b[((y + dy) % h) * w + (x + dx) % w] as f64;
                    }
                }
                out[dy * w + dx] += acc * s;
            }
        }
    }
    let k = used.max(1) as f64;
    out.into_iter().map(|v| (v / k) as f32).collect()
}

/// A correlation peak: integer position (signed shift), sub-pixel shift,
/// peak height, and whether the sub-pixel fit was possible.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Peak {
    pub dx: f64,
    pub dy: f64,
    pub height: f32,
    /// Peak on the border of the unambiguous shift range (|d| = size/2):
    /// the true shift may be beyond it.
    pub at_border: bool,
}

/// Signed circular shift of index `i` in a correlation plane of size `n`.
#[inline]
pub(crate) fn signed(i: usize, n: usize) -> i64 {
    if i <= (n - 1) / 2 {
        i as i64
    } else {
        i as i64 - n as i64
    }
}

/// Sub-pixel offset of a 3-point peak: Gaussian fit when all three values
/// are positive, parabolic fit otherwise (normalised correlations can be
/// negative beside weak peaks).
#[inline]
pub fn subpixel3(lm: f32, c: f32, rp: f32) -> f64 {
    let (lm, c, rp) = (lm as f64, c as f64, rp as f64);
    if lm > 0.0 && c > 0.0 && rp > 0.0 {
        let (l0, l1, l2) = (lm.ln(), c.ln(), rp.ln());
        let den = 2.0 * (l0 - 2.0 * l1 + l2);
        if den < 0.0 {
            let d = (l0 - l2) / den;
            if d.abs() < 1.0 {
                return d;
            }
        }
    }
    let den = 2.0 * (lm - 2.0 * c + rp);
    if den < 0.0 {
        let d = (lm - rp) / den;
        if d.abs() < 1.0 {
            return d;
        }
    }
    0.0
}

/// Highest peak of a circular correlation plane with a 3-point Gaussian
/// sub-pixel estimate in x and y separately.
pub fn find_peak(plane: &[f32], w: usize, h: usize) -> Peak {
    // Maximum over 8 independent lanes (vectorises), then its first index:
    // the same peak as a sequential scan, without its dependency chain.
    let mut lanes = [f32::NEG_INFINITY; 8];
    let chunks = plane.chunks_exact(8);
    let rest = chunks.remainder();
    for c in chunks {
        for l in 0..8 {
            lanes[l] = lanes[l].max(c[l]);
        }
    }
    let bv = rest.iter().fold(
        lanes.iter().fold(f32::NEG_INFINITY, |m, &v| m.max(v)),
        |m, &v| m.max(v),
    );
    let best = plane.iter().position(|&v| v == bv).unwrap_or(0);
    let (ix, iy) = (best % w, best / w);
    let sx = signed(ix, w);
    let sy = signed(iy, h);
    let at = |x: usize, y: usize| plane[y * w + x];
    let fx = if w >= 3 {
        subpixel3(at((ix + w - 1) % w, iy), bv, at((ix + 1) % w, iy))
    } else {
        0.0
    };
    let fy = if h >= 3 {
        subpixel3(at(ix, (iy + h - 1) % h), bv, at(ix, (iy + 1) % h))
    } else {
        0.0
    };
    let at_border = (w >= 2 && sx.unsigned_abs() as usize >= w / 2)
        || (h >= 2 && sy.unsigned_abs() as usize >= h / 2);
    Peak {
        dx: sx as f64 + fx,
        dy: sy as f64 + fy,
        height: bv,
        at_border,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn random_window(rng: &mut rand_pcg::Pcg64, n: usize) -> Vec<f32> {
        (0..n).map(|_| rng.gen::<f32>()).collect()
    }

    fn fft_sum(pairs: &[(&[f32], &[f32])], w: usize, h: usize) -> Vec<f32> {
        let plan = CorrelationPlan::new(w, h);
        let mut ws = plan.workspace();
        ws.reset();
        for (a, b) in pairs {
            let mut a = a.to_vec();
            let mut b = b.to_vec();
            let ea = remove_mean(&mut a);
            let eb = remove_mean(&mut b);
            ws.add_pair(&a, &b, ea, eb);
        }
        let mut out = vec![0.0; w * h];
        ws.finish(&mut out);
        out
    }

    #[test]
    fn fft_matches_direct_square_rect_and_odd() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
        for &(w, h, np) in &[(16, 16, 1), (12, 5, 3), (64, 8, 2), (9, 7, 4), (1, 6, 1)] {
            let wins: Vec<Vec<f32>> = (0..2 * np)
                .map(|_| random_window(&mut rng, w * h))
                .collect();
            let pairs: Vec<(&[f32], &[f32])> = (0..np)
                .map(|k| (wins[2 * k].as_slice(), wins[2 * k + 1].as_slice()))
                .collect();
            let f = fft_sum(&pairs, w, h);
            let d = direct_correlation(&pairs, w, h);
            let maxerr = f
                .iter()
                .zip(&d)
                .map(|(a, b)| (a - b).abs())
                .fold(0.0, f32::max);
            assert!(
                maxerr < 1e-4,
                "{w}x{h} np={np}: max |fft-direct| = {maxerr}"
            );
        }
    }

    #[test]
    fn integer_shift_peaks_at_shift_and_self_match_is_one() {
        let (w, h) = (32, 16);
        let mut rng = rand_pcg::Pcg64::seed_from_u64(3);
        let a = random_window(&mut rng, w * h);
        // b is a shifted by (+5, -3) circularly: b(x) = a(x - s).
        let (sx, sy) = (5i64, -3i64);
        let mut b = vec![0.0; w * h];
        for y in 0..h {
            for x in 0..w {
                let xs = (x as i64 - sx).rem_euclid(w as i64) as usize;
                let ys = (y as i64 - sy).rem_euclid(h as i64) as usize;
                b[y * w + x] = a[ys * w + xs];
            }
        }
        let plane = fft_sum(&[(&a, &b)], w, h);
        let p = find_peak(&plane, w, h);
        assert!(
            (p.dx - 5.0).abs() < 0.2 && (p.dy + 3.0).abs() < 0.2,
            "{p:?}"
        );
        assert!((p.height - 1.0).abs() < 1e-4, "{p:?}");
    }

    #[test]
    fn empty_window_contributes_nothing() {
        let plan = CorrelationPlan::new(8, 8);
        let mut ws = plan.workspace();
        ws.reset();
        let z = vec![0.0f32; 64];
        ws.add_pair(&z, &z, 0.0, 0.0);
        assert_eq!(ws.pairs(), 0);
    }

    #[test]
    fn gaussian_subpixel_is_exact_on_a_gaussian() {
        for &d in &[-0.4, -0.1, 0.0, 0.25, 0.49] {
            let g = |x: f64| (-(x - d) * (x - d) / 2.0).exp() as f32;
            let est = subpixel3(g(-1.0), g(0.0), g(1.0));
            assert!((est - d).abs() < 1e-5, "d={d} est={est}");
        }
    }
}
