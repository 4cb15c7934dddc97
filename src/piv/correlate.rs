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
//! The fast path works in the frequency domain and uses the realness of
//! every signal twice:
//!
//! * **Forward**: two real windows are packed into one complex window
//!   `z = a + i·b`, so one complex 2-D FFT yields both spectra
//!   (`A(k) = (Z(k) + Z*(-k))/2`, `B(k) = (Z(k) − Z*(-k))/2i`). Only the
//!   half `kx ≤ w/2` of each ([`Spectrum`], the rest is its conjugate
//!   mirror) is kept. A window's spectrum is a value of its own, so a frame
//!   shared by the pairs `(k−1, k)` and `(k, k+1)` of a multi-frame sum is
//!   transformed once: `⌈N_f/2⌉` complex FFTs per node instead of `N_f − 1`.
//! * **Inverse**: the summed cross-spectrum `Σ A*·B / sqrt(Σa²Σb²)` is
//!   Hermitian; after the inverse transform along y of its half (`w/2 + 1`
//!   columns instead of `w`), every row is the half spectrum of a real
//!   row, and two such rows are packed into one complex inverse FFT along
//!   x (`h/2` transforms instead of `h`).
//!
//! Per 32×32 node and frame pair that is 64 + 33 FFTs of length 32 instead
//! of 128 for two full complex transforms. Plans are built once
//! ([`CorrelationPlan`]) and shared by all threads; each thread owns its
//! scratch buffers ([`Workspace`]), allocated once per pass. Windows of any
//! size work (rustfft handles any length; rectangular windows such as 64×8
//! are just rows of 64 and columns of 8; odd sizes take the unpaired last
//! row alone).
//!
//! [`direct_correlation`] is the plain O(w²h²) definition above; the tests
//! require the FFT path to match it.

use std::sync::Arc;

use ebptv_fft::{plan_f32, Complex32, Direction, Fft};

/// FFT plans for one window size, shareable across threads.
#[derive(Clone)]
pub(crate) struct CorrelationPlan {
    pub w: usize,
    pub h: usize,
    fwd_w: Arc<dyn Fft<f32>>,
    fwd_h: Arc<dyn Fft<f32>>,
    inv_w: Arc<dyn Fft<f32>>,
    inv_h: Arc<dyn Fft<f32>>,
}

impl CorrelationPlan {
    pub(crate) fn new(w: usize, h: usize) -> Self {
        assert!(w > 0 && h > 0, "window size must be positive");
        let (fwd_w, inv_w) = (
            plan_f32(w, Direction::Forward),
            plan_f32(w, Direction::Inverse),
        );
        // A square window's rows and columns share one pair of plans.
        let (fwd_h, inv_h) = if h == w {
            (fwd_w.clone(), inv_w.clone())
        } else {
            (
                plan_f32(h, Direction::Forward),
                plan_f32(h, Direction::Inverse),
            )
        };
        CorrelationPlan {
            w,
            h,
            fwd_w,
            fwd_h,
            inv_w,
            inv_h,
        }
    }

    /// Length of a half spectrum ([`Spectrum`]): `(w/2 + 1) · h`.
    pub(crate) fn half_len(&self) -> usize {
        (self.w / 2 + 1) * self.h
    }

    pub(crate) fn workspace(&self) -> Workspace {
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
        let half = self.half_len();
        Workspace {
            plan: self.clone(),
            z: vec![Complex32::default(); n],
            zt: vec![Complex32::default(); n],
            acc: vec![Complex32::default(); half],
            sa: self.spectrum(),
            sb: self.spectrum(),
            scratch: vec![Complex32::default(); scratch_len],
            pairs: 0,
        }
    }

    /// An empty half spectrum of this window size.
    pub(crate) fn spectrum(&self) -> Spectrum {
        Spectrum {
            data: vec![Complex32::default(); self.half_len()],
            energy: 0.0,
        }
    }
}

/// Half spectrum (`kx ≤ w/2`, layout `[kx][ky]`) of one mean-removed real
/// window, with the window's energy (sum of squares).
#[derive(Clone, Debug)]
pub(crate) struct Spectrum {
    pub data: Vec<Complex32>,
    pub energy: f64,
}

impl Spectrum {
    fn empty() -> Self {
        Spectrum {
            data: Vec::new(),
            energy: 0.0,
        }
    }
}

/// Per-thread buffers for accumulating a sum of correlation.
pub(crate) struct Workspace {
    plan: CorrelationPlan,
    z: Vec<Complex32>,
    /// Transposed spectrum (`w` rows of `h`).
    zt: Vec<Complex32>,
    /// Accumulated half cross-spectrum, layout `[kx][ky]`, `kx ≤ w/2`.
    acc: Vec<Complex32>,
    sa: Spectrum,
    sb: Spectrum,
    scratch: Vec<Complex32>,
    pairs: usize,
}

/// `dst[c * rows + r] = src[r * cols + c]`. 4×4 tiles: four source rows are
/// read in step (exact chunks, no bounds checks), four destination runs
/// written; the ragged edges go one by one.
#[inline(always)]
fn transpose(src: &[Complex32], dst: &mut [Complex32], rows: usize, cols: usize) {
    let (src, dst) = (&src[..rows * cols], &mut dst[..rows * cols]);
    let (rt, ct) = (rows / 4 * 4, cols / 4 * 4);
    for r0 in (0..rt).step_by(4) {
        let s0 = &src[r0 * cols..(r0 + 1) * cols];
        let s1 = &src[(r0 + 1) * cols..(r0 + 2) * cols];
        let s2 = &src[(r0 + 2) * cols..(r0 + 3) * cols];
        let s3 = &src[(r0 + 3) * cols..(r0 + 4) * cols];
        let tiles = s0
            .chunks_exact(4)
            .zip(s1.chunks_exact(4))
            .zip(s2.chunks_exact(4).zip(s3.chunks_exact(4)));
        for (t, ((a, b), (c, d))) in tiles.enumerate() {
            for k in 0..4 {
                let o = (4 * t + k) * rows + r0;
                dst[o..o + 4].copy_from_slice(&[a[k], b[k], c[k], d[k]]);
            }
        }
        for c in ct..cols {
            for r in r0..r0 + 4 {
                dst[c * rows + r] = src[r * cols + c];
            }
        }
    }
    for r in rt..rows {
        for (c, v) in src[r * cols..(r + 1) * cols].iter().enumerate() {
            dst[c * rows + r] = *v;
        }
    }
}

/// Sum of 8 independent lanes of `v` (of `v²` with `SQUARE`): keeps the
/// rounding error of long windows small (each lane sums only n/8 values).
/// On x86-64 the lanes are two SSE registers — the compiler's own
/// vectorisation of the scalar form split the lanes 2+4+1+1 — with the
/// same lane assignment and operation order, hence the same bits.
#[inline(always)]
fn lane_sum<const SQUARE: bool>(v: &[f32]) -> f64 {
    let f = |x: f32| if SQUARE { x * x } else { x };
    let mut acc = [0.0f32; 8];
    let chunks = v.chunks_exact(8);
    let rest = chunks.remainder();
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::*;
        // SAFETY: SSE is part of x86-64; every load reads 4 floats of an
        // 8-float chunk, the stores write the 8-float `acc`.
        unsafe {
            let (mut a0, mut a1) = (_mm_setzero_ps(), _mm_setzero_ps());
            for c in chunks {
                let (mut x0, mut x1) = (_mm_loadu_ps(c.as_ptr()), _mm_loadu_ps(c.as_ptr().add(4)));
                if SQUARE {
                    x0 = _mm_mul_ps(x0, x0);
                    x1 = _mm_mul_ps(x1, x1);
                }
                a0 = _mm_add_ps(a0, x0);
                a1 = _mm_add_ps(a1, x1);
            }
            _mm_storeu_ps(acc.as_mut_ptr(), a0);
            _mm_storeu_ps(acc.as_mut_ptr().add(4), a1);
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
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
#[inline(always)]
pub(crate) fn remove_mean(win: &mut [f32]) -> f64 {
    let n = win.len() as f64;
    let mean = (lane_sum::<false>(win) / n) as f32;
    for v in win.iter_mut() {
        *v -= mean;
    }
    lane_sum::<true>(win)
}

/// Copy the `w × h` window at `(x0, y0)` of a row-major image `stride`
/// pixels wide into `dst` with its mean removed (and, with `clip`, values
/// below the mean set to 0: [`clip_below_mean`]); returns its energy.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
pub(crate) fn cut_window(
    img: &[f32],
    stride: usize,
    x0: usize,
    y0: usize,
    w: usize,
    h: usize,
    clip: bool,
    dst: &mut [f32],
) -> f64 {
    #[cfg(target_arch = "x86_64")]
    if w % 8 == 0 {
        return cut_window_lanes(img, stride, x0, y0, w, h, clip, dst);
    }
    cut_window_plain(img, stride, x0, y0, w, h, clip, dst)
}

/// [`cut_window`] as the composition of its steps: copy, [`remove_mean`],
/// [`clip_below_mean`] (the reference for [`cut_window_lanes`]).
#[allow(clippy::too_many_arguments)]
#[inline(always)]
pub(crate) fn cut_window_plain(
    img: &[f32],
    stride: usize,
    x0: usize,
    y0: usize,
    w: usize,
    h: usize,
    clip: bool,
    dst: &mut [f32],
) -> f64 {
    for (y, d) in dst[..w * h].chunks_exact_mut(w).enumerate() {
        let row = (y0 + y) * stride + x0;
        d.copy_from_slice(&img[row..row + w]);
    }
    let e = remove_mean(&mut dst[..w * h]);
    if clip {
        clip_below_mean(&mut dst[..w * h])
    } else {
        e
    }
}

/// [`cut_window_plain`] in two passes instead of six, for windows whose
/// width is a multiple of 8: copy and sum, then mean removal (clipping)
/// and sum of squares. With `w % 8 == 0` every 8-value chunk lies in one
/// row, so each of [`lane_sum`]'s lanes adds the same values in the same
/// order: the same bits (tested). The row copies were `memcpy` calls of
/// 128 bytes, and the window was read six times.
#[cfg(target_arch = "x86_64")]
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn cut_window_lanes(
    img: &[f32],
    stride: usize,
    x0: usize,
    y0: usize,
    w: usize,
    h: usize,
    clip: bool,
    dst: &mut [f32],
) -> f64 {
    use std::arch::x86_64::*;
    debug_assert!(w % 8 == 0);
    let n = w * h;
    let dst = &mut dst[..n];
    let lanes = |a0: __m128, a1: __m128| -> f64 {
        let mut acc = [0.0f32; 8];
        // SAFETY: two 4-float stores into the 8-float `acc`.
        unsafe {
            _mm_storeu_ps(acc.as_mut_ptr(), a0);
            _mm_storeu_ps(acc.as_mut_ptr().add(4), a1);
        }
        acc.iter().map(|&a| a as f64).sum()
    };
    // SAFETY: SSE is part of x86-64; every load and store covers 4 floats
    // of an 8-float chunk of a bounds-checked row slice (`w % 8 == 0`).
    unsafe {
        let (mut a0, mut a1) = (_mm_setzero_ps(), _mm_setzero_ps());
        for (y, d) in dst.chunks_exact_mut(w).enumerate() {
            let row = (y0 + y) * stride + x0;
            let src = &img[row..row + w];
            for (dc, sc) in d.chunks_exact_mut(8).zip(src.chunks_exact(8)) {
                let (v0, v1) = (_mm_loadu_ps(sc.as_ptr()), _mm_loadu_ps(sc.as_ptr().add(4)));
                _mm_storeu_ps(dc.as_mut_ptr(), v0);
                _mm_storeu_ps(dc.as_mut_ptr().add(4), v1);
                a0 = _mm_add_ps(a0, v0);
                a1 = _mm_add_ps(a1, v1);
            }
        }
        let mean = _mm_set1_ps((lanes(a0, a1) / n as f64) as f32);
        let zero = _mm_setzero_ps();
        let (mut e0, mut e1) = (zero, zero);
        for dc in dst.chunks_exact_mut(8) {
            let mut v0 = _mm_sub_ps(_mm_loadu_ps(dc.as_ptr()), mean);
            let mut v1 = _mm_sub_ps(_mm_loadu_ps(dc.as_ptr().add(4)), mean);
            if clip {
                // max(v, 0) + 0: as `clip_below_mean` (NaN and ±0 → +0).
                v0 = _mm_add_ps(_mm_max_ps(v0, zero), zero);
                v1 = _mm_add_ps(_mm_max_ps(v1, zero), zero);
            }
            _mm_storeu_ps(dc.as_mut_ptr(), v0);
            _mm_storeu_ps(dc.as_mut_ptr().add(4), v1);
            e0 = _mm_add_ps(e0, _mm_mul_ps(v0, v0));
            e1 = _mm_add_ps(e1, _mm_mul_ps(v1, v1));
        }
        lanes(e0, e1)
    }
}

/// Background clipping of a mean-removed window: negative values (pixels
/// darker than the window mean) become 0; returns the energy left.
///
/// Particle images are bright spots on a dark background. After mean
/// removal the background is a negative plateau that correlates with
/// itself and with the particles' holes in it; zeroing it leaves the
/// particles alone. On the peer-comparison images (Gaussian particles,
/// σ 0.8 px, one pass, 32×32) it lowers the rms error against truth by
/// 3–15 %, most at large shifts where the plateau's loss of overlap
/// weighs most (OpenPIV's earlier `normalize_intensity` clipped the same
/// way). Used in single-pass evaluations only (see
/// `PivOptions::clip_background` for why not in multi-pass ones).
#[inline(always)]
pub(crate) fn clip_below_mean(win: &mut [f32]) -> f64 {
    // A select written as `max` (+0.0 turns a −0.0 from `max` into +0.0):
    // the `if` form compiled to masked stores (`vmaskmovps`), microcoded
    // and slow on AMD — a quarter of the single-pass node time.
    for v in win.iter_mut() {
        *v = v.max(0.0) + 0.0;
    }
    lane_sum::<true>(win)
}

impl Workspace {
    /// Start a new sum of correlation.
    #[inline(always)]
    pub(crate) fn reset(&mut self) {
        // The first pair overwrites the accumulator (no zeroing pass).
        self.pairs = 0;
    }

    /// Number of pairs that contributed since [`reset`](Self::reset).
    pub(crate) fn pairs(&self) -> usize {
        self.pairs
    }

    /// Half spectra of two real, mean-removed windows (`w*h` values each,
    /// row-major) with one complex FFT; `b = None` transforms `a` alone.
    /// The energies are the caller's (e.g. from [`cut_window`]).
    #[inline(always)]
    pub(crate) fn transform_two(
        &mut self,
        a: &[f32],
        b: Option<&[f32]>,
        sa: &mut Spectrum,
        sb: Option<&mut Spectrum>,
    ) {
        let (w, h) = (self.plan.w, self.plan.h);
        let n = w * h;
        debug_assert!(a.len() == n);
        match b {
            Some(b) => {
                debug_assert!(b.len() == n);
                for ((z, &x), &y) in self.z.iter_mut().zip(&a[..n]).zip(&b[..n]) {
                    *z = Complex32::new(x, y);
                }
            }
            None => {
                for (z, &x) in self.z.iter_mut().zip(&a[..n]) {
                    *z = Complex32::new(x, 0.0);
                }
            }
        }
        self.plan
            .fwd_w
            .process_with_scratch(&mut self.z, &mut self.scratch);
        transpose(&self.z, &mut self.zt, h, w);
        self.plan
            .fwd_h
            .process_with_scratch(&mut self.zt, &mut self.scratch);
        // zt index: kx * h + ky; the mirror frequency -k of (kx, ky) is
        // ((w - kx) % w, (h - ky) % h). With Z = A + iB:
        // A = (Z(k) + Z*(-k))/2, B = (Z(k) - Z*(-k))/2i.
        let mut dummy = Vec::new();
        let sbd: &mut [Complex32] = match sb {
            Some(s) => &mut s.data,
            None => &mut dummy,
        };
        let with_b = !sbd.is_empty();
        for kx in 0..=w / 2 {
            let mkx = if kx == 0 { 0 } else { w - kx };
            let row = &self.zt[kx * h..(kx + 1) * h];
            let mrow = &self.zt[mkx * h..(mkx + 1) * h];
            let oa = &mut sa.data[kx * h..(kx + 1) * h];
            let (zk, zn) = (row[0], mrow[0]);
            oa[0] = Complex32::new(0.5 * (zk.re + zn.re), 0.5 * (zk.im - zn.im));
            for ((o, zk), zn) in oa[1..]
                .iter_mut()
                .zip(&row[1..])
                .zip(mrow[1..].iter().rev())
            {
                *o = Complex32::new(0.5 * (zk.re + zn.re), 0.5 * (zk.im - zn.im));
            }
            if with_b {
                let ob = &mut sbd[kx * h..(kx + 1) * h];
                ob[0] = Complex32::new(0.5 * (zk.im + zn.im), 0.5 * (zn.re - zk.re));
                for ((o, zk), zn) in ob[1..]
                    .iter_mut()
                    .zip(&row[1..])
                    .zip(mrow[1..].iter().rev())
                {
                    *o = Complex32::new(0.5 * (zk.im + zn.im), 0.5 * (zn.re - zk.re));
                }
            }
        }
    }

    /// Add the normalised correlation of two windows given by their half
    /// spectra: `acc += A*·B / sqrt(ea·eb)`. A window with no signal adds
    /// nothing.
    #[inline(always)]
    pub(crate) fn accumulate(&mut self, a: &Spectrum, b: &Spectrum) {
        if !(a.energy > 0.0 && b.energy > 0.0) {
            return;
        }
        let scale = (1.0 / (a.energy * b.energy).sqrt()) as f32;
        let terms = self.acc.iter_mut().zip(&a.data).zip(&b.data);
        if self.pairs == 0 {
            for ((acc, x), y) in terms {
                acc.re = (x.re * y.re + x.im * y.im) * scale;
                acc.im = (x.re * y.im - x.im * y.re) * scale;
            }
        } else {
            for ((acc, x), y) in terms {
                acc.re += (x.re * y.re + x.im * y.im) * scale;
                acc.im += (x.re * y.im - x.im * y.re) * scale;
            }
        }
        self.pairs += 1;
    }

    /// Add the normalised correlation of one window pair. `a`, `b`: `w*h`
    /// values, row-major, **mean already removed**, with energies `ea`, `eb`
    /// (sums of squares). A pair with no signal in either window adds nothing.
    #[inline(always)]
    pub(crate) fn add_pair(&mut self, a: &[f32], b: &[f32], ea: f64, eb: f64) {
        if !(ea > 0.0 && eb > 0.0) {
            return;
        }
        let mut sa = std::mem::replace(&mut self.sa, Spectrum::empty());
        let mut sb = std::mem::replace(&mut self.sb, Spectrum::empty());
        self.transform_two(a, Some(b), &mut sa, Some(&mut sb));
        sa.energy = ea;
        sb.energy = eb;
        self.accumulate(&sa, &sb);
        self.sa = sa;
        self.sb = sb;
    }

    /// Transform the accumulated cross-spectrum back: `out[dy * w + dx]` is
    /// the summed correlation at circular shift `(dx, dy)`, divided by the
    /// number of pairs (so a perfect match peaks at 1 whatever `N_f`).
    /// The accumulator is transformed in place: [`reset`](Self::reset)
    /// before the next sum ([`pairs`](Self::pairs) stays readable).
    #[inline(always)]
    pub(crate) fn finish(&mut self, out: &mut [f32]) {
        let (w, h) = (self.plan.w, self.plan.h);
        let m = w / 2 + 1;
        if self.pairs == 0 {
            // Nothing accumulated (the buffer holds a previous sum).
            out[..w * h].iter_mut().for_each(|v| *v = 0.0);
            return;
        }
        // Inverse along y of the half spectrum: P(kx, y), kx ≤ w/2.
        self.plan
            .inv_h
            .process_with_scratch(&mut self.acc[..m * h], &mut self.scratch);
        // Row y is the half spectrum of a real row (P(w−kx, y) = P*(kx, y)):
        // rows y1, y2 go into one complex row Q = P1 + i·P2, full length:
        // Q(kx) = P1 + i·P2 and Q(w−kx) = P1* + i·P2* for kx ≤ w/2.
        // Transposed first (zt: [y][kx]) so that both rows are contiguous.
        transpose(&self.acc[..m * h], &mut self.zt, m, h);
        let rows = h.div_ceil(2);
        let zero = [Complex32::default(); 1];
        for (r, zrow) in self.z[..rows * w].chunks_exact_mut(w).enumerate() {
            let (lo, hi) = zrow.split_at_mut(m);
            let p1 = &self.zt[2 * r * m..(2 * r + 1) * m];
            if 2 * r + 1 < h {
                let p2 = &self.zt[(2 * r + 1) * m..(2 * r + 2) * m];
                for (q, (a, b)) in lo.iter_mut().zip(p1.iter().zip(p2)) {
                    *q = Complex32::new(a.re - b.im, a.im + b.re);
                }
                for (q, (a, b)) in hi.iter_mut().rev().zip(p1[1..].iter().zip(&p2[1..])) {
                    *q = Complex32::new(a.re + b.im, b.re - a.im);
                }
            } else {
                lo.copy_from_slice(p1);
                for (q, a) in hi.iter_mut().rev().zip(&p1[1..]) {
                    *q = a.conj();
                }
            }
            // Self-mirrored frequencies (kx = 0, and w/2 for even w) are
            // real: drop the rounding residue of their imaginary parts.
            let p2 = if 2 * r + 1 < h {
                &self.zt[(2 * r + 1) * m..(2 * r + 2) * m]
            } else {
                &zero[..]
            };
            zrow[0] = Complex32::new(p1[0].re, p2[0].re);
            if w % 2 == 0 && 2 * r + 1 < h {
                zrow[w / 2] = Complex32::new(p1[w / 2].re, p2[w / 2].re);
            } else if w % 2 == 0 {
                zrow[w / 2] = Complex32::new(p1[w / 2].re, 0.0);
            }
        }
        self.plan
            .inv_w
            .process_with_scratch(&mut self.z[..rows * w], &mut self.scratch);
        let norm = 1.0 / ((w * h) as f32 * self.pairs.max(1) as f32);
        for (r, zrow) in self.z[..rows * w].chunks_exact(w).enumerate() {
            let y1 = 2 * r;
            for (o, z) in out[y1 * w..(y1 + 1) * w].iter_mut().zip(zrow) {
                *o = z.re * norm;
            }
            if y1 + 1 < h {
                for (o, z) in out[(y1 + 1) * w..(y1 + 2) * w].iter_mut().zip(zrow) {
                    *o = z.im * norm;
                }
            }
        }
    }
}

/// The definition, computed directly (test oracle for the FFT path):
/// normalised circular cross-correlation averaged over the given pairs, with
/// mean removal done here.
#[cfg(feature = "testkit")]
pub(crate) fn direct_correlation(pairs: &[(&[f32], &[f32])], w: usize, h: usize) -> Vec<f32> {
    let prepared: Vec<(Vec<f32>, Vec<f32>)> = pairs
        .iter()
        .map(|(a, b)| {
            let (mut a, mut b) = (a.to_vec(), b.to_vec());
            remove_mean(&mut a);
            remove_mean(&mut b);
            (a, b)
        })
        .collect();
    let refs: Vec<(&[f32], &[f32])> = prepared
        .iter()
        .map(|(a, b)| (a.as_slice(), b.as_slice()))
        .collect();
    direct_correlation_prepared(&refs, w, h)
}

/// [`direct_correlation`] of windows used as given (already mean-removed,
/// or clipped): `Σ a·b(·+d) / sqrt(Σa²·Σb²)`, averaged over the pairs with
/// signal in both windows.
#[cfg(feature = "testkit")]
pub(crate) fn direct_correlation_prepared(
    pairs: &[(&[f32], &[f32])],
    w: usize,
    h: usize,
) -> Vec<f32> {
    let mut out = vec![0.0f64; w * h];
    let mut used = 0usize;
    for (a, b) in pairs {
        let ea = lane_sum::<true>(a);
        let eb = lane_sum::<true>(b);
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
pub(crate) struct Peak {
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
#[inline(always)]
pub(crate) fn subpixel3(lm: f32, c: f32, rp: f32) -> f64 {
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
#[inline(always)]
pub(crate) fn find_peak(plane: &[f32], w: usize, h: usize) -> Peak {
    // Maximum over 8 independent lanes (vectorises: the comparison form is
    // a plain `max` instruction), then the first chunk holding it, then its
    // first index: the same peak as a sequential scan, without its
    // dependency chain. NaN never wins (as with `f32::max`).
    let mut lanes = [f32::NEG_INFINITY; 8];
    let chunks = plane.chunks_exact(8);
    let rest = chunks.remainder();
    for c in chunks {
        for l in 0..8 {
            lanes[l] = if c[l] > lanes[l] { c[l] } else { lanes[l] };
        }
    }
    let bv = rest.iter().fold(
        lanes.iter().fold(f32::NEG_INFINITY, |m, &v| m.max(v)),
        |m, &v| m.max(v),
    );
    let chunk = plane
        .chunks(8)
        .position(|c| c.iter().fold(false, |hit, &v| hit | (v == bv)))
        .unwrap_or(0);
    let best = chunk * 8
        + plane[chunk * 8..]
            .iter()
            .position(|&v| v == bv)
            .unwrap_or(0);
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

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn random_window(rng: &mut rand_pcg::Pcg64, n: usize) -> Vec<f32> {
        (0..n).map(|_| rng.gen::<f32>()).collect()
    }

    /// The fused window cut against copy + mean removal (+ clipping) done
    /// step by step: the same bits and energy, for widths that take the
    /// fused path (multiples of 8) and widths that do not.
    #[ebptv_macros::unit_test]
    fn cut_window_equals_its_steps() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(12);
        let (width, height) = (70usize, 50usize);
        let img: Vec<f32> = (0..width * height)
            .map(|_| rng.gen_range(0.0f32..5000.0))
            .collect();
        for &(w, h) in &[(32usize, 32usize), (64, 8), (8, 3), (12, 7), (33, 20)] {
            for clip in [false, true] {
                for &(x0, y0) in &[(0usize, 0usize), (5, 9), (width - w, height - h)] {
                    let mut fast = vec![0.0f32; w * h];
                    let mut slow = vec![0.0f32; w * h];
                    let ef = cut_window(&img, width, x0, y0, w, h, clip, &mut fast);
                    let es = cut_window_plain(&img, width, x0, y0, w, h, clip, &mut slow);
                    assert_eq!(ef.to_bits(), es.to_bits(), "{w}x{h} clip {clip}");
                    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                    assert_eq!(bits(&fast), bits(&slow), "{w}x{h} clip {clip}");
                }
            }
        }
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

    #[ebptv_macros::unit_test]
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

    #[ebptv_macros::unit_test]
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

    #[ebptv_macros::unit_test]
    fn empty_window_contributes_nothing() {
        let plan = CorrelationPlan::new(8, 8);
        let mut ws = plan.workspace();
        ws.reset();
        let z = vec![0.0f32; 64];
        ws.add_pair(&z, &z, 0.0, 0.0);
        assert_eq!(ws.pairs(), 0);
    }

    /// A workspace reused for a second sum (no zeroing between sums) gives
    /// what a fresh one gives, and a sum of nothing is a zero plane.
    #[ebptv_macros::unit_test]
    fn reused_workspace_equals_fresh_and_empty_sum_is_zero() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(5);
        let (w, h) = (12, 10);
        let wins: Vec<Vec<f32>> = (0..4).map(|_| random_window(&mut rng, w * h)).collect();
        let plan = CorrelationPlan::new(w, h);
        let mut ws = plan.workspace();
        let add = |ws: &mut Workspace, k: usize| {
            let (mut a, mut b) = (wins[k].clone(), wins[k + 1].clone());
            let (ea, eb) = (remove_mean(&mut a), remove_mean(&mut b));
            ws.add_pair(&a, &b, ea, eb);
        };
        ws.reset();
        add(&mut ws, 0);
        add(&mut ws, 1);
        let mut first = vec![0.0; w * h];
        ws.finish(&mut first);
        ws.reset();
        add(&mut ws, 2);
        let mut second = vec![0.0; w * h];
        ws.finish(&mut second);
        let mut fresh_ws = plan.workspace();
        fresh_ws.reset();
        add(&mut fresh_ws, 2);
        let mut fresh = vec![0.0; w * h];
        fresh_ws.finish(&mut fresh);
        assert_eq!(second, fresh);
        assert_ne!(first, second);
        ws.reset();
        let mut empty = vec![1.0; w * h];
        ws.finish(&mut empty);
        assert!(empty.iter().all(|&v| v == 0.0));
    }

    #[ebptv_macros::unit_test]
    fn gaussian_subpixel_is_exact_on_a_gaussian() {
        for &d in &[-0.4, -0.1, 0.0, 0.25, 0.49] {
            let g = |x: f64| (-(x - d) * (x - d) / 2.0).exp() as f32;
            let est = subpixel3(g(-1.0), g(0.0), g(1.0));
            assert!((est - d).abs() < 1e-5, "d={d} est={est}");
        }
    }
}
