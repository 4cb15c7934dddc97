//! SIMD for the whole workspace: the one CPU-feature detection point,
//! the lane types the vector kernels are written over, and the one
//! dispatch into AVX2 code.
//!
//! It lives in `ebptv-sim` because the simulator's kernels (the flows'
//! `cos`/`sin`/`exp` in `crate::fastmath`, the particle advection in
//! `seeding`) are its main users and the `ebptv` crate depends on this
//! crate anyway; `ebptv-io`, the file-format crate that readers use on
//! its own, carries no numeric kernels. The `ebptv` crate's PIV
//! (`piv::multipass`) asks [`avx2_fma`] before calling its own
//! `#[target_feature(enable = "avx2,fma")]` functions.
//!
//! - **Detection**: [`avx2_fma`], once per process (cached). No other
//!   code calls `is_x86_feature_detected!`.
//! - **Portable lanes**: `Lanes` on one `f64`, on two (`F64x2`: an
//!   SSE2 register, part of the x86_64 baseline, so always available)
//!   and on pairs of either (`Two`). Kernels are written once over
//!   `Lanes`, so every lane type gives the scalar's bits (IEEE add,
//!   sub, mul and div round the same at every width; nothing is fused).
//! - **AVX2 lanes**: the operations on four f64 in one AVX register are
//!   `unsafe fn`s with `#[target_feature(enable = "avx2,fma")]` (module
//!   `avx`). Their lane type is private to this module: the only way
//!   to run a kernel on it is `Dispatch::run`, whose AVX2 branch is
//!   taken only when `Dispatch::detect` found the features, so no
//!   value of it exists on a CPU without them (the safety argument of
//!   its `Lanes` implementation, which the compiler enforces through
//!   privacy rather than a convention at the call sites). A kernel is a
//!   `LaneKernel`: generic over the lane type, run by the dispatcher.
//!
//! Tests: every operation and kernel on the AVX2 lanes against the
//! scalar (`fastmath`'s `every_lane_type_is_the_scalar_bit_for_bit`),
//! the AVX2 advection against the SSE2 one (`seeding`'s
//! `avx_lanes_are_the_sse2_lanes`).

use std::sync::OnceLock;

/// Whether this CPU has AVX2 and FMA (detected once, then cached): the
/// condition for calling any `#[target_feature(enable = "avx2,fma")]`
/// function of the workspace. Always false off x86_64.
pub fn avx2_fma() -> bool {
    static AVX2_FMA: OnceLock<bool> = OnceLock::new();
    *AVX2_FMA.get_or_init(|| {
        #[cfg(target_arch = "x86_64")]
        {
            std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma")
        }
        #[cfg(not(target_arch = "x86_64"))]
        {
            false
        }
    })
}

/// 1.5 · 2^52: adding it rounds an f64 of magnitude < 2^51 to the nearest
/// integer (ties to even), which then sits in the low mantissa bits.
pub(crate) const ROUND: f64 = 6_755_399_441_055_744.0;

/// A computation written once over the lane type, run by
/// [`Dispatch::run`] on the widest lanes the CPU has.
pub(crate) trait LaneKernel {
    /// What the kernel returns.
    type Out;
    /// Runs the kernel with lanes `T` (mark it `#[inline(always)]`: it
    /// must be compiled inside the dispatcher's AVX2 function).
    fn run<T: Lanes>(self) -> Self::Out;
}

/// Which lanes [`Dispatch::run`] uses: four f64 as two SSE2 pairs
/// ([`F64x4`]), or, where the CPU has AVX2 and FMA, eight as two AVX
/// registers. Decided once on the calling thread and copied into
/// parallel workers.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Dispatch {
    /// True only if [`avx2_fma`] said so (private: the soundness of the
    /// AVX2 branch rests on it).
    avx2_fma: bool,
}

impl Dispatch {
    /// The widest lanes this CPU runs.
    pub(crate) fn detect() -> Dispatch {
        Dispatch {
            avx2_fma: avx2_fma(),
        }
    }

    /// The SSE2 pairs, whatever the CPU (the comparison path of tests).
    pub(crate) fn portable() -> Dispatch {
        Dispatch { avx2_fma: false }
    }

    /// Runs `k` on the chosen lanes.
    #[inline(always)]
    pub(crate) fn run<K: LaneKernel>(self, k: K) -> K::Out {
        #[cfg(target_arch = "x86_64")]
        if self.avx2_fma {
            // SAFETY: `avx2_fma` is true only when the CPU has AVX2 and
            // FMA (`Dispatch::detect`).
            return unsafe { avx::run(k) };
        }
        k.run::<F64x4>()
    }
}

/// The operations the kernels need, on one f64 or on a pair ([`F64x2`]):
/// each kernel is written once, generic over this, so the pair gives
/// exactly the scalar's numbers lane by lane (IEEE add/sub/mul are
/// correctly rounded whatever the register width).
pub(crate) trait Lanes:
    Copy
    + std::ops::Add<Output = Self>
    + std::ops::Sub<Output = Self>
    + std::ops::Mul<Output = Self>
    + std::ops::Div<Output = Self>
    + std::ops::Neg<Output = Self>
{
    /// Lanes per value.
    const N: usize;
    fn splat(v: f64) -> Self;
    /// Lane `i` (< N).
    fn lane(self, i: usize) -> f64;
    /// The value with lane i = `f(i)`.
    fn from_fn(f: impl FnMut(usize) -> f64) -> Self;
    /// `if self < b { yes } else { no }` per lane.
    fn select_lt(self, b: Self, yes: Self, no: Self) -> Self;
    /// |self| per lane (the sign bit cleared).
    fn abs(self) -> Self;
    /// ±1 with the sign bit of each lane (`f64::signum` but for NaN).
    fn sign_one(self) -> Self;
    /// `if self < lo { lo } else { self }` per lane (NaN stays NaN).
    fn raise_to(self, lo: f64) -> Self;
    /// `if self > hi { hi } else { self }` per lane (NaN stays NaN).
    fn lower_to(self, hi: f64) -> Self;
    /// The sign bit set where bit 0 of the lane's bits is set, else +0.
    fn low_bit_as_sign(self) -> Self;
    /// Bitwise xor of the lanes' bits.
    fn xor(self, o: Self) -> Self;
    /// 2^n for `self` = ROUND + n, |n| ≤ 1022 (n in the low mantissa bits).
    fn pow2_of_rounded(self) -> Self;
}

impl Lanes for f64 {
    const N: usize = 1;
    #[inline(always)]
    fn splat(v: f64) -> f64 {
        v
    }
    #[inline(always)]
    fn lane(self, _i: usize) -> f64 {
        self
    }
    #[inline(always)]
    fn from_fn(mut f: impl FnMut(usize) -> f64) -> f64 {
        f(0)
    }
    #[inline(always)]
    fn select_lt(self, b: f64, yes: f64, no: f64) -> f64 {
        if self < b {
            yes
        } else {
            no
        }
    }
    #[inline(always)]
    fn abs(self) -> f64 {
        f64::abs(self)
    }
    #[inline(always)]
    fn sign_one(self) -> f64 {
        1f64.copysign(self)
    }
    #[inline(always)]
    fn raise_to(self, lo: f64) -> f64 {
        if self < lo {
            lo
        } else {
            self
        }
    }
    #[inline(always)]
    fn lower_to(self, hi: f64) -> f64 {
        if self > hi {
            hi
        } else {
            self
        }
    }
    #[inline(always)]
    fn low_bit_as_sign(self) -> f64 {
        f64::from_bits((self.to_bits() & 1) << 63)
    }
    #[inline(always)]
    fn xor(self, o: f64) -> f64 {
        f64::from_bits(self.to_bits() ^ o.to_bits())
    }
    #[inline(always)]
    fn pow2_of_rounded(self) -> f64 {
        // Two's complement n in the low bits of the difference.
        let n = (self.to_bits() as i64).wrapping_sub(ROUND.to_bits() as i64);
        f64::from_bits(((n + 1023) as u64) << 52)
    }
}

/// Two f64 lanes: an SSE2 register on x86_64 (part of its baseline, so no
/// feature detection), a pair elsewhere.
#[derive(Clone, Copy, Debug)]
pub(crate) struct F64x2(
    #[cfg(target_arch = "x86_64")] std::arch::x86_64::__m128d,
    #[cfg(not(target_arch = "x86_64"))] [f64; 2],
);

#[cfg(target_arch = "x86_64")]
mod x2 {
    // SAFETY (every `unsafe` below): the intrinsics are SSE2, which every
    // x86_64 CPU has; the loads and stores go through arrays we own.
    use super::{F64x2, ROUND};
    use std::arch::x86_64::*;

    impl F64x2 {
        #[inline(always)]
        pub(crate) fn new(a: [f64; 2]) -> F64x2 {
            // SAFETY: SSE2, part of the x86_64 baseline; the pointer is to an owned array of the lane count.
            F64x2(unsafe { _mm_loadu_pd(a.as_ptr()) })
        }
        #[inline(always)]
        pub(crate) fn to_array(self) -> [f64; 2] {
            let mut a = [0.0; 2];
            // SAFETY: SSE2, part of the x86_64 baseline; the pointer is to an owned array of the lane count.
            unsafe { _mm_storeu_pd(a.as_mut_ptr(), self.0) };
            a
        }
    }
    impl std::ops::Add for F64x2 {
        type Output = F64x2;
        #[inline(always)]
        fn add(self, o: F64x2) -> F64x2 {
            // SAFETY: SSE2, part of the x86_64 baseline.
            F64x2(unsafe { _mm_add_pd(self.0, o.0) })
        }
    }
    impl std::ops::Sub for F64x2 {
        type Output = F64x2;
        #[inline(always)]
        fn sub(self, o: F64x2) -> F64x2 {
            // SAFETY: SSE2, part of the x86_64 baseline.
            F64x2(unsafe { _mm_sub_pd(self.0, o.0) })
        }
    }
    impl std::ops::Mul for F64x2 {
        type Output = F64x2;
        #[inline(always)]
        fn mul(self, o: F64x2) -> F64x2 {
            // SAFETY: SSE2, part of the x86_64 baseline.
            F64x2(unsafe { _mm_mul_pd(self.0, o.0) })
        }
    }
    impl std::ops::Div for F64x2 {
        type Output = F64x2;
        #[inline(always)]
        fn div(self, o: F64x2) -> F64x2 {
            // SAFETY: SSE2, part of the x86_64 baseline.
            F64x2(unsafe { _mm_div_pd(self.0, o.0) })
        }
    }
    impl std::ops::Neg for F64x2 {
        type Output = F64x2;
        #[inline(always)]
        fn neg(self) -> F64x2 {
            // SAFETY: SSE2, part of the x86_64 baseline.
            F64x2(unsafe { _mm_xor_pd(self.0, _mm_set1_pd(-0.0)) })
        }
    }
    impl super::Lanes for F64x2 {
        const N: usize = 2;
        #[inline(always)]
        fn splat(v: f64) -> F64x2 {
            // SAFETY: SSE2, part of the x86_64 baseline.
            F64x2(unsafe { _mm_set1_pd(v) })
        }
        #[inline(always)]
        fn lane(self, i: usize) -> f64 {
            self.to_array()[i]
        }
        #[inline(always)]
        fn from_fn(mut f: impl FnMut(usize) -> f64) -> F64x2 {
            let a = f(0);
            F64x2::new([a, f(1)])
        }
        #[inline(always)]
        fn select_lt(self, b: F64x2, yes: F64x2, no: F64x2) -> F64x2 {
            // SAFETY: SSE2, part of the x86_64 baseline.
            unsafe {
                let m = _mm_cmplt_pd(self.0, b.0);
                F64x2(_mm_or_pd(_mm_and_pd(m, yes.0), _mm_andnot_pd(m, no.0)))
            }
        }
        #[inline(always)]
        fn abs(self) -> F64x2 {
            // SAFETY: SSE2, part of the x86_64 baseline.
            F64x2(unsafe { _mm_andnot_pd(_mm_set1_pd(-0.0), self.0) })
        }
        #[inline(always)]
        fn sign_one(self) -> F64x2 {
            // SAFETY: SSE2, part of the x86_64 baseline.
            unsafe {
                let sign = _mm_and_pd(_mm_set1_pd(-0.0), self.0);
                F64x2(_mm_or_pd(sign, _mm_set1_pd(1.0)))
            }
        }
        #[inline(always)]
        fn raise_to(self, lo: f64) -> F64x2 {
            // SAFETY: SSE2, part of the x86_64 baseline.
            unsafe {
                let lo = _mm_set1_pd(lo);
                let m = _mm_cmplt_pd(self.0, lo);
                F64x2(_mm_or_pd(_mm_and_pd(m, lo), _mm_andnot_pd(m, self.0)))
            }
        }
        #[inline(always)]
        fn lower_to(self, hi: f64) -> F64x2 {
            // SAFETY: SSE2, part of the x86_64 baseline.
            unsafe {
                let hi = _mm_set1_pd(hi);
                let m = _mm_cmpgt_pd(self.0, hi);
                F64x2(_mm_or_pd(_mm_and_pd(m, hi), _mm_andnot_pd(m, self.0)))
            }
        }
        #[inline(always)]
        fn low_bit_as_sign(self) -> F64x2 {
            // SAFETY: SSE2, part of the x86_64 baseline.
            unsafe {
                F64x2(_mm_castsi128_pd(_mm_slli_epi64::<63>(_mm_castpd_si128(
                    self.0,
                ))))
            }
        }
        #[inline(always)]
        fn xor(self, o: F64x2) -> F64x2 {
            // SAFETY: SSE2, part of the x86_64 baseline.
            F64x2(unsafe { _mm_xor_pd(self.0, o.0) })
        }
        #[inline(always)]
        fn pow2_of_rounded(self) -> F64x2 {
            // SAFETY: SSE2, part of the x86_64 baseline.
            unsafe {
                let n = _mm_sub_epi64(
                    _mm_castpd_si128(self.0),
                    _mm_set1_epi64x(ROUND.to_bits() as i64),
                );
                let e = _mm_add_epi64(n, _mm_set1_epi64x(1023));
                F64x2(_mm_castsi128_pd(_mm_slli_epi64::<52>(e)))
            }
        }
    }
}

#[cfg(not(target_arch = "x86_64"))]
mod x2 {
    use super::{F64x2, Lanes};

    impl F64x2 {
        #[inline(always)]
        pub(crate) fn new(a: [f64; 2]) -> F64x2 {
            F64x2(a)
        }
        #[inline(always)]
        pub(crate) fn to_array(self) -> [f64; 2] {
            self.0
        }
        #[inline(always)]
        fn map(self, o: F64x2, f: impl Fn(f64, f64) -> f64) -> F64x2 {
            F64x2([f(self.0[0], o.0[0]), f(self.0[1], o.0[1])])
        }
    }
    impl std::ops::Add for F64x2 {
        type Output = F64x2;
        #[inline(always)]
        fn add(self, o: F64x2) -> F64x2 {
            self.map(o, |a, b| a + b)
        }
    }
    impl std::ops::Sub for F64x2 {
        type Output = F64x2;
        #[inline(always)]
        fn sub(self, o: F64x2) -> F64x2 {
            self.map(o, |a, b| a - b)
        }
    }
    impl std::ops::Mul for F64x2 {
        type Output = F64x2;
        #[inline(always)]
        fn mul(self, o: F64x2) -> F64x2 {
            self.map(o, |a, b| a * b)
        }
    }
    impl std::ops::Div for F64x2 {
        type Output = F64x2;
        #[inline(always)]
        fn div(self, o: F64x2) -> F64x2 {
            self.map(o, |a, b| a / b)
        }
    }
    impl std::ops::Neg for F64x2 {
        type Output = F64x2;
        #[inline(always)]
        fn neg(self) -> F64x2 {
            F64x2(self.0.map(|a| -a))
        }
    }
    impl Lanes for F64x2 {
        const N: usize = 2;
        #[inline(always)]
        fn splat(v: f64) -> F64x2 {
            F64x2([v, v])
        }
        #[inline(always)]
        fn lane(self, i: usize) -> f64 {
            self.0[i]
        }
        #[inline(always)]
        fn from_fn(mut f: impl FnMut(usize) -> f64) -> F64x2 {
            let a = f(0);
            F64x2([a, f(1)])
        }
        #[inline(always)]
        fn select_lt(self, b: F64x2, yes: F64x2, no: F64x2) -> F64x2 {
            F64x2([0, 1].map(|i| self.0[i].select_lt(b.0[i], yes.0[i], no.0[i])))
        }
        #[inline(always)]
        fn abs(self) -> F64x2 {
            F64x2(self.0.map(f64::abs))
        }
        #[inline(always)]
        fn sign_one(self) -> F64x2 {
            F64x2(self.0.map(|a| a.sign_one()))
        }
        #[inline(always)]
        fn raise_to(self, lo: f64) -> F64x2 {
            F64x2(self.0.map(|a| a.raise_to(lo)))
        }
        #[inline(always)]
        fn lower_to(self, hi: f64) -> F64x2 {
            F64x2(self.0.map(|a| a.lower_to(hi)))
        }
        #[inline(always)]
        fn low_bit_as_sign(self) -> F64x2 {
            F64x2(self.0.map(|a| a.low_bit_as_sign()))
        }
        #[inline(always)]
        fn xor(self, o: F64x2) -> F64x2 {
            self.map(o, |a, b| a.xor(b))
        }
        #[inline(always)]
        fn pow2_of_rounded(self) -> F64x2 {
            F64x2(self.0.map(|a| a.pow2_of_rounded()))
        }
    }
}

/// Two values of a lane type side by side (`Two<F64x2>`: four lanes in two
/// SSE2 registers): two independent dependency chains for the
/// out-of-order core to overlap. Lane i < `T::N` is the first's.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Two<T>(pub(crate) T, pub(crate) T);

/// Four lanes as two SSE2 pairs.
pub(crate) type F64x4 = Two<F64x2>;

macro_rules! two_op {
    ($tr:ident, $f:ident, $op:tt) => {
        impl<T: Lanes> std::ops::$tr for Two<T> {
            type Output = Two<T>;
            #[inline(always)]
            fn $f(self, o: Two<T>) -> Two<T> {
                Two(self.0 $op o.0, self.1 $op o.1)
            }
        }
    };
}
two_op!(Add, add, +);
two_op!(Sub, sub, -);
two_op!(Mul, mul, *);
two_op!(Div, div, /);

impl<T: Lanes> std::ops::Neg for Two<T> {
    type Output = Two<T>;
    #[inline(always)]
    fn neg(self) -> Two<T> {
        Two(-self.0, -self.1)
    }
}

impl<T: Lanes> Lanes for Two<T> {
    const N: usize = 2 * T::N;
    #[inline(always)]
    fn splat(v: f64) -> Two<T> {
        Two(T::splat(v), T::splat(v))
    }
    #[inline(always)]
    fn lane(self, i: usize) -> f64 {
        if i < T::N {
            self.0.lane(i)
        } else {
            self.1.lane(i - T::N)
        }
    }
    #[inline(always)]
    fn from_fn(mut f: impl FnMut(usize) -> f64) -> Two<T> {
        let lo = T::from_fn(&mut f);
        Two(lo, T::from_fn(|i| f(i + T::N)))
    }
    #[inline(always)]
    fn select_lt(self, b: Two<T>, yes: Two<T>, no: Two<T>) -> Two<T> {
        Two(
            self.0.select_lt(b.0, yes.0, no.0),
            self.1.select_lt(b.1, yes.1, no.1),
        )
    }
    #[inline(always)]
    fn abs(self) -> Two<T> {
        Two(self.0.abs(), self.1.abs())
    }
    #[inline(always)]
    fn sign_one(self) -> Two<T> {
        Two(self.0.sign_one(), self.1.sign_one())
    }
    #[inline(always)]
    fn raise_to(self, lo: f64) -> Two<T> {
        Two(self.0.raise_to(lo), self.1.raise_to(lo))
    }
    #[inline(always)]
    fn lower_to(self, hi: f64) -> Two<T> {
        Two(self.0.lower_to(hi), self.1.lower_to(hi))
    }
    #[inline(always)]
    fn low_bit_as_sign(self) -> Two<T> {
        Two(self.0.low_bit_as_sign(), self.1.low_bit_as_sign())
    }
    #[inline(always)]
    fn xor(self, o: Two<T>) -> Two<T> {
        Two(self.0.xor(o.0), self.1.xor(o.1))
    }
    #[inline(always)]
    fn pow2_of_rounded(self) -> Two<T> {
        Two(self.0.pow2_of_rounded(), self.1.pow2_of_rounded())
    }
}

/// Four f64 lanes in one AVX register: every operation an `unsafe fn`
/// compiled for AVX2 + FMA. Only IEEE add/sub/mul/div, ordered compares,
/// blends and integer shifts (no fused multiply-add), which round and
/// compare exactly as the SSE2 pair does: the same bits on every machine.
#[cfg(target_arch = "x86_64")]
mod avx {
    use super::{LaneKernel, Lanes, Two, ROUND};
    use std::arch::x86_64::*;

    /// Runs `k` on eight lanes (two AVX registers: two dependency chains
    /// for the out-of-order core, as the two SSE2 pairs of the portable
    /// path; measured 4–7 % less CPU than one register of four).
    ///
    /// # Safety
    /// The CPU must have AVX2 and FMA ([`super::avx2_fma`]).
    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn run<K: LaneKernel>(k: K) -> K::Out {
        k.run::<Two<F64x4Avx>>()
    }

    /// Four f64 in an AVX register. Private to `simd`: values exist only
    /// inside [`run`], which the dispatcher enters after detection; that
    /// is what makes the safe [`Lanes`] methods below sound.
    #[derive(Clone, Copy, Debug)]
    pub(super) struct F64x4Avx(__m256d);

    // The operations. # Safety (each): the CPU must have AVX2 and FMA.
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    unsafe fn add(a: __m256d, b: __m256d) -> __m256d {
        _mm256_add_pd(a, b)
    }
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    unsafe fn sub(a: __m256d, b: __m256d) -> __m256d {
        _mm256_sub_pd(a, b)
    }
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    unsafe fn mul(a: __m256d, b: __m256d) -> __m256d {
        _mm256_mul_pd(a, b)
    }
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    unsafe fn div(a: __m256d, b: __m256d) -> __m256d {
        _mm256_div_pd(a, b)
    }
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    unsafe fn xor(a: __m256d, b: __m256d) -> __m256d {
        _mm256_xor_pd(a, b)
    }
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    unsafe fn splat(v: f64) -> __m256d {
        _mm256_set1_pd(v)
    }
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    unsafe fn load(a: &[f64; 4]) -> __m256d {
        // SAFETY: reads the four f64 of `a` (unaligned load allowed).
        unsafe { _mm256_loadu_pd(a.as_ptr()) }
    }
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    unsafe fn store(v: __m256d) -> [f64; 4] {
        let mut a = [0.0; 4];
        // SAFETY: writes the four f64 of `a` (unaligned store allowed).
        unsafe { _mm256_storeu_pd(a.as_mut_ptr(), v) };
        a
    }
    /// `if a < b { yes } else { no }` per lane (false for NaN).
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    unsafe fn select_lt(a: __m256d, b: __m256d, yes: __m256d, no: __m256d) -> __m256d {
        _mm256_blendv_pd(no, yes, _mm256_cmp_pd::<_CMP_LT_OQ>(a, b))
    }
    /// `if a > b { yes } else { no }` per lane (false for NaN).
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    unsafe fn select_gt(a: __m256d, b: __m256d, yes: __m256d, no: __m256d) -> __m256d {
        _mm256_blendv_pd(no, yes, _mm256_cmp_pd::<_CMP_GT_OQ>(a, b))
    }
    /// |a|: the sign bits cleared.
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    unsafe fn abs(a: __m256d) -> __m256d {
        _mm256_andnot_pd(_mm256_set1_pd(-0.0), a)
    }
    /// ±1 with the sign bits of `a`.
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    unsafe fn sign_one(a: __m256d) -> __m256d {
        _mm256_or_pd(_mm256_and_pd(_mm256_set1_pd(-0.0), a), _mm256_set1_pd(1.0))
    }
    /// Bit 0 of each lane's bits moved to the sign bit, the rest 0.
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    unsafe fn low_bit_as_sign(a: __m256d) -> __m256d {
        _mm256_castsi256_pd(_mm256_slli_epi64::<63>(_mm256_castpd_si256(a)))
    }
    /// 2^n per lane for lanes ROUND + n (see [`Lanes::pow2_of_rounded`]).
    #[target_feature(enable = "avx2,fma")]
    #[inline]
    unsafe fn pow2_of_rounded(a: __m256d) -> __m256d {
        let n = _mm256_sub_epi64(
            _mm256_castpd_si256(a),
            _mm256_set1_epi64x(ROUND.to_bits() as i64),
        );
        let e = _mm256_add_epi64(n, _mm256_set1_epi64x(1023));
        _mm256_castsi256_pd(_mm256_slli_epi64::<52>(e))
    }

    // SAFETY (every `unsafe` block below): a `F64x4Avx` exists only
    // inside `run`, entered after detection (see the type), so the CPU
    // has AVX2 and FMA.
    impl std::ops::Add for F64x4Avx {
        type Output = F64x4Avx;
        #[inline(always)]
        fn add(self, o: F64x4Avx) -> F64x4Avx {
            // SAFETY: see above the impls.
            F64x4Avx(unsafe { add(self.0, o.0) })
        }
    }
    impl std::ops::Sub for F64x4Avx {
        type Output = F64x4Avx;
        #[inline(always)]
        fn sub(self, o: F64x4Avx) -> F64x4Avx {
            // SAFETY: see above the impls.
            F64x4Avx(unsafe { sub(self.0, o.0) })
        }
    }
    impl std::ops::Mul for F64x4Avx {
        type Output = F64x4Avx;
        #[inline(always)]
        fn mul(self, o: F64x4Avx) -> F64x4Avx {
            // SAFETY: see above the impls.
            F64x4Avx(unsafe { mul(self.0, o.0) })
        }
    }
    impl std::ops::Div for F64x4Avx {
        type Output = F64x4Avx;
        #[inline(always)]
        fn div(self, o: F64x4Avx) -> F64x4Avx {
            // SAFETY: see above the impls.
            F64x4Avx(unsafe { div(self.0, o.0) })
        }
    }
    impl std::ops::Neg for F64x4Avx {
        type Output = F64x4Avx;
        #[inline(always)]
        fn neg(self) -> F64x4Avx {
            // SAFETY: see above the impls.
            F64x4Avx(unsafe { xor(self.0, splat(-0.0)) })
        }
    }
    impl Lanes for F64x4Avx {
        const N: usize = 4;
        #[inline(always)]
        fn splat(v: f64) -> F64x4Avx {
            // SAFETY: see above the impls.
            F64x4Avx(unsafe { splat(v) })
        }
        #[inline(always)]
        fn lane(self, i: usize) -> f64 {
            // SAFETY: see above the impls.
            let a = unsafe { store(self.0) };
            a[i]
        }
        #[inline(always)]
        fn from_fn(mut f: impl FnMut(usize) -> f64) -> F64x4Avx {
            let a = [f(0), f(1), f(2), f(3)];
            // SAFETY: see above the impls.
            F64x4Avx(unsafe { load(&a) })
        }
        #[inline(always)]
        fn select_lt(self, b: F64x4Avx, yes: F64x4Avx, no: F64x4Avx) -> F64x4Avx {
            // SAFETY: see above the impls.
            F64x4Avx(unsafe { select_lt(self.0, b.0, yes.0, no.0) })
        }
        #[inline(always)]
        fn abs(self) -> F64x4Avx {
            // SAFETY: see above the impls.
            F64x4Avx(unsafe { abs(self.0) })
        }
        #[inline(always)]
        fn sign_one(self) -> F64x4Avx {
            // SAFETY: see above the impls.
            F64x4Avx(unsafe { sign_one(self.0) })
        }
        #[inline(always)]
        fn raise_to(self, lo: f64) -> F64x4Avx {
            // SAFETY: see above the impls.
            F64x4Avx(unsafe {
                let lo = splat(lo);
                select_lt(self.0, lo, lo, self.0)
            })
        }
        #[inline(always)]
        fn lower_to(self, hi: f64) -> F64x4Avx {
            // SAFETY: see above the impls.
            F64x4Avx(unsafe {
                let hi = splat(hi);
                select_gt(self.0, hi, hi, self.0)
            })
        }
        #[inline(always)]
        fn low_bit_as_sign(self) -> F64x4Avx {
            // SAFETY: see above the impls.
            F64x4Avx(unsafe { low_bit_as_sign(self.0) })
        }
        #[inline(always)]
        fn xor(self, o: F64x4Avx) -> F64x4Avx {
            // SAFETY: see above the impls.
            F64x4Avx(unsafe { xor(self.0, o.0) })
        }
        #[inline(always)]
        fn pow2_of_rounded(self) -> F64x4Avx {
            // SAFETY: see above the impls.
            F64x4Avx(unsafe { pow2_of_rounded(self.0) })
        }
    }
}
