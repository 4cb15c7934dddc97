//! Branch-free `cos`, `sin` and `exp` for the velocity fields.
//!
//! The flows evaluate these millions of times per simulated second
//! (turbulent_bl: 16 `cos` per field evaluation, four evaluations per
//! particle and pulse); libm's versions are calls with branches, so a loop
//! over modes or particles cannot be vectorised and the calls dominated the
//! profile (67 % of the CPU in `__cos_fma`). These are plain `#[inline]`
//! f64 arithmetic: Cody–Waite range reduction and a Taylor polynomial
//! evaluated by Horner's rule, with the selects done on bits. Each kernel
//! is written once over [`Lanes`] and runs on one f64, on two at once
//! ([`crate::simd::F64x2`], an SSE2 register: part of the x86_64
//! baseline, so no feature detection) or on the AVX2 lanes of
//! [`crate::simd`]. The compiler did not vectorise a loop of the scalar
//! versions by itself (the bit operations), hence the explicit pair.
//!
//! Determinism: only IEEE add, sub and mul (never `mul_add`, which Rust
//! does not contract implicitly either), so the results are the same on
//! every machine and at every vector width.
//!
//! Accuracy against libm (tests below): |cos − f64::cos| and
//! |sin − f64::sin| ≤ 4e-16 for |x| ≤ 1e5 (the fields' phases: a few
//! thousand radians per second of simulated time), ≤ 4e-16 + 1.2e-16 |x|
//! beyond (the reduction's 33-bit multiple of π/2 stops being exact at
//! |x| ≈ 1.6e6; an f64 argument that large is itself only known to
//! ~1.1e-16 |x|); |exp − f64::exp| ≤ 4e-16 · exp(x) for x in
//! [−708, 709], and exp(−708) ≈ 3.3e-308 below (an absolute error under
//! 4e-308; the fields use exp only for decays). `sincos_lanes` gives
//! `cos_lanes`'s cos bit for bit and a sin within 4e-16; the small-angle
//! `sincos_small` (|d| ≤ 1/8) and `sincos_tiny` (|d| ≤ 1/64), for the
//! turbulent field's phase rotations, give sin d within 2e-17 and
//! cos d − 1 within 1e-17 on their domains (no range reduction: callers
//! check the bound).

#[cfg(feature = "testkit")]
use crate::simd::F64x2;
use crate::simd::{Lanes, ROUND};

const INV_PI: f64 = std::f64::consts::FRAC_1_PI;
/// π/2 in two parts: the first has 33 significant bits, so j·Q1 is exact
/// for |j| < 2^20; Q1 + Q2 is π/2 to 3.5e-27.
const Q1: f64 = 1.570_796_326_734_125_6;
const Q2: f64 = 6.077_100_506_506_192e-11;

/// sin r ≈ r + r³ P(r²) on |r| ≤ π/2 with P of degree 7: the Chebyshev
/// fit (mpmath `chebyfit`, near-minimax) of (sin √s − √s)/s^{3/2} on
/// s ∈ [0, (π/2)²], rounded to f64: |error| ≤ 3.6e-17 before rounding
/// of the evaluation (the Taylor series needs two terms more for that).
const S3: f64 = -0.166_666_666_666_666_66;
const S5: f64 = 0.008_333_333_333_333_316;
const S7: f64 = -0.000_198_412_698_412_549_74;
const S9: f64 = 2.755_731_921_916_323_4e-6;
const S11: f64 = -2.505_210_761_699_618_2e-8;
const S13: f64 = 1.605_897_731_246_408_7e-10;
const S15: f64 = -7.643_970_296_798_572e-13;
const S17: f64 = 2.731_444_766_986_399_5e-15;

/// sin(r) for |r| ≲ π/2.
#[inline(always)]
fn sin_kernel<T: Lanes>(r: T) -> T {
    let c = T::splat;
    let s = r * r;
    let p = c(S15) + s * c(S17);
    let p = c(S13) + s * p;
    let p = c(S11) + s * p;
    let p = c(S9) + s * p;
    let p = c(S7) + s * p;
    let p = c(S5) + s * p;
    let p = c(S3) + s * p;
    r + (r * s) * p
}

/// x = j·π/2 + r with j = 2m + 1 (`odd`) or 2m, |r| ≤ π/2 (+ rounding);
/// returns r and ROUND + m (m's parity is bit 0 of its bits).
#[inline(always)]
fn reduce<T: Lanes>(x: T, odd: bool) -> (T, T) {
    let c = T::splat;
    // m = round(x/π − ½) for cos, round(x/π) for sin. A rounding of x/π
    // that picks the neighbouring m near a tie only gives |r| slightly
    // above π/2, where the kernel is still exact.
    let y = if odd {
        x * c(INV_PI) - c(0.5)
    } else {
        x * c(INV_PI)
    };
    let big = y + c(ROUND);
    let m = big - c(ROUND);
    let j = if odd { m + m + c(1.0) } else { m + m };
    ((x - j * c(Q1)) - j * c(Q2), big)
}

/// cos(x) per lane (see the module docs for the accuracy).
#[inline(always)]
pub(crate) fn cos_lanes<T: Lanes>(x: T) -> T {
    // cos((m + ½)π + r) = (−1)^(m+1) sin r: negate for even m.
    let (r, big) = reduce(x, true);
    sin_kernel(r).xor(big.low_bit_as_sign().xor(T::splat(-0.0)))
}

/// sin(x) per lane (see the module docs for the accuracy).
#[inline(always)]
pub(crate) fn sin_lanes<T: Lanes>(x: T) -> T {
    // sin(mπ + r) = (−1)^m sin r.
    let (r, big) = reduce(x, false);
    sin_kernel(r).xor(big.low_bit_as_sign())
}

/// cos r ≈ 1 + r² Q(r²) on |r| ≤ π/2 with Q of degree 7: the Chebyshev
/// fit (mpmath `chebyfit`) of (cos √s − 1)/s on s ∈ [0, (1.0001 π/2)²],
/// rounded to f64: |error| ≤ 1.8e-17 before rounding of the evaluation.
const C2: f64 = -0.5;
const C4: f64 = 0.041_666_666_666_666_34;
const C6: f64 = -0.001_388_888_888_886_067_6;
const C8: f64 = 2.480_158_729_243_711_3e-5;
const C10: f64 = -2.755_731_776_616_188e-7;
const C12: f64 = 2.087_663_079_231_025_5e-9;
const C14: f64 = -1.146_468_748_784_590_9e-11;
const C16: f64 = 4.627_646_089_543_635e-14;

/// cos(r) for |r| ≲ π/2.
#[inline(always)]
fn cos_kernel<T: Lanes>(r: T) -> T {
    let c = T::splat;
    let s = r * r;
    let p = c(C14) + s * c(C16);
    let p = c(C12) + s * p;
    let p = c(C10) + s * p;
    let p = c(C8) + s * p;
    let p = c(C6) + s * p;
    let p = c(C4) + s * p;
    let p = c(C2) + s * p;
    c(1.0) + s * p
}

/// (sin x, cos x) per lane from one reduction (the cos one): the cos is
/// [`cos_lanes`]`(x)` bit for bit, the sin within 4e-16 of libm over the
/// same range (test `sincos_matches_libm_and_cos_lanes`).
#[inline(always)]
pub(crate) fn sincos_lanes<T: Lanes>(x: T) -> (T, T) {
    // x = (m + ½)π + r: cos x = (−1)^(m+1) sin r, sin x = (−1)^m cos r.
    let (r, big) = reduce(x, true);
    let sign = big.low_bit_as_sign();
    (
        cos_kernel(r).xor(sign),
        sin_kernel(r).xor(sign.xor(T::splat(-0.0))),
    )
}

/// Domain of [`sincos_small`]: |d| ≤ 1/8.
pub(crate) const SMALL_ANGLE: f64 = 0.125;
/// Domain of [`sincos_tiny`]: |d| ≤ 1/64.
pub(crate) const TINY_ANGLE: f64 = 1.0 / 64.0;

/// sin d ≈ d + d³ P(d²), cos d − 1 ≈ d² Q(d²) on |d| ≤ 1.001/8, P and
/// Q of degree 3: Chebyshev fits (mpmath `chebyfit`) rounded to f64,
/// |error| ≤ 2.3e-20 (sin) and 2e-18 (cos) before rounding of the
/// evaluation.
const SS3: f64 = -0.166_666_666_666_666_66;
const SS5: f64 = 0.008_333_333_333_309_302;
const SS7: f64 = -0.000_198_412_690_738_161_08;
const SS9: f64 = 2.754_947_585_712_562_5e-6;
const SC2: f64 = -0.499_999_999_999_999_9;
const SC4: f64 = 0.041_666_666_666_402_34;
const SC6: f64 = -0.001_388_888_804_471_751_2;
const SC8: f64 = 2.479_295_981_450_327_6e-5;

/// As the S/SC constants on |d| ≤ 1.001/64, P of degree 1 and Q of
/// degree 2: |error| ≤ 5.7e-18 (sin) and 5.6e-21 (cos).
const TS3: f64 = -0.166_666_666_665_182_46;
const TS5: f64 = 0.008_333_284_795_947_792;
const TC2: f64 = -0.5;
const TC4: f64 = 0.041_666_666_665_831_8;
const TC6: f64 = -0.001_388_879_788_129_873;

/// (sin d, cos d − 1) per lane for |d| ≤ [`SMALL_ANGLE`], no range
/// reduction (a rotation by a small angle: `c + (c·(cos d − 1) − s·sin d)`
/// keeps the rounding of the `1 +` out). Outside the domain the error
/// grows fast: callers check the bound (test
/// `small_angle_sincos_within_bounds`).
#[inline(always)]
pub(crate) fn sincos_small<T: Lanes>(d: T) -> (T, T) {
    let c = T::splat;
    let s = d * d;
    let p = c(SS7) + s * c(SS9);
    let p = c(SS5) + s * p;
    let p = c(SS3) + s * p;
    let q = c(SC6) + s * c(SC8);
    let q = c(SC4) + s * q;
    let q = c(SC2) + s * q;
    (d + (d * s) * p, s * q)
}

/// [`sincos_small`] for |d| ≤ [`TINY_ANGLE`] (shorter polynomials).
#[inline(always)]
pub(crate) fn sincos_tiny<T: Lanes>(d: T) -> (T, T) {
    let c = T::splat;
    let s = d * d;
    let p = c(TS3) + s * c(TS5);
    let q = c(TC4) + s * c(TC6);
    let q = c(TC2) + s * q;
    (d + (d * s) * p, s * q)
}

/// cos(x) (see the module docs for the accuracy).
#[cfg(feature = "testkit")]
#[inline(always)]
pub(crate) fn cos(x: f64) -> f64 {
    cos_lanes(x)
}

/// sin(x) (see the module docs for the accuracy).
#[cfg(feature = "testkit")]
#[inline(always)]
pub(crate) fn sin(x: f64) -> f64 {
    sin_lanes(x)
}

const LOG2E: f64 = std::f64::consts::LOG2_E;
/// ln 2 in two parts: the first has 32 significant bits, so n·LN2_HI is
/// exact for the |n| ≤ 1023 used here.
const LN2_HI: f64 = 0.693_147_180_369_123_8;
const LN2_LO: f64 = 1.908_214_929_270_587_7e-10;

/// 1/k! for k = 2 … 13: on |r| ≤ ln2/2 the first omitted term is below
/// 4e-18 (relative).
const E2: f64 = 0.5;
const E3: f64 = 0.166_666_666_666_666_66;
const E4: f64 = 0.041_666_666_666_666_664;
const E5: f64 = 0.008_333_333_333_333_333;
const E6: f64 = 0.001_388_888_888_888_889;
const E7: f64 = 0.000_198_412_698_412_698_4;
const E8: f64 = 2.480_158_730_158_73e-5;
const E9: f64 = 2.755_731_922_398_589_3e-6;
const E10: f64 = 2.755_731_922_398_589e-7;
const E11: f64 = 2.505_210_838_544_172e-8;
const E12: f64 = 2.087_675_698_786_81e-9;
const E13: f64 = 1.605_904_383_682_161_3e-10;

/// exp(x) per lane (see the module docs for the accuracy and the clamp).
#[inline(always)]
pub(crate) fn exp_lanes<T: Lanes>(x: T) -> T {
    let c = T::splat;
    // Clamped so 2^n stays a normal number (selects: a NaN passes).
    let x = x.raise_to(-708.0).lower_to(709.0);
    let big = x * c(LOG2E) + c(ROUND);
    let n = big - c(ROUND);
    let r = (x - n * c(LN2_HI)) - n * c(LN2_LO);
    // Estrin's scheme: the fields call exp once per evaluation, inside
    // RK4 stages that wait on each other, so the polynomial's latency (5
    // dependent steps instead of Horner's 22) is what counts.
    let r2 = r * r;
    let r4 = r2 * r2;
    let r8 = r4 * r4;
    let q0 = c(E2) + r * c(E3);
    let q1 = c(E4) + r * c(E5);
    let q2 = c(E6) + r * c(E7);
    let q3 = c(E8) + r * c(E9);
    let q4 = c(E10) + r * c(E11);
    let q5 = c(E12) + r * c(E13);
    let p = (q0 + r2 * q1) + r4 * (q2 + r2 * q3) + r8 * (q4 + r2 * q5);
    (c(1.0) + (r + r2 * p)) * big.pow2_of_rounded()
}

/// exp(x) (see the module docs for the accuracy and the clamp).
#[cfg(feature = "testkit")]
#[inline(always)]
pub(crate) fn exp(x: f64) -> f64 {
    exp_lanes(x)
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;

    /// A deterministic spread of arguments: uniform in [lo, hi] plus the
    /// multiples of π/2 (the reduction's boundaries) and their neighbours.
    fn args(lo: f64, hi: f64, n: usize) -> Vec<f64> {
        let mut v: Vec<f64> = (0..n)
            .map(|k| lo + (hi - lo) * ((k as f64 * 0.618_033_988_749_895) % 1.0))
            .collect();
        let h = std::f64::consts::FRAC_PI_2;
        let (jl, jh) = ((lo / h).ceil() as i64, (hi / h).floor() as i64);
        let step = ((jh - jl) / 2000).max(1);
        let mut j = jl;
        while j <= jh {
            let x = j as f64 * h;
            // The neighbouring f64 on either side.
            let (up, down) = (x + x.abs() * f64::EPSILON, x - x.abs() * f64::EPSILON / 2.0);
            v.extend([x, up, down, x + 1e-9, x - 1e-9]);
            j += step;
        }
        v.extend([0.0, -0.0, 1e-300, -1e-300, 5e-324]);
        v
    }

    fn max_err(f: impl Fn(f64) -> f64, g: impl Fn(f64) -> f64, xs: &[f64]) -> (f64, f64) {
        let mut worst = (0.0, 0.0);
        for &x in xs {
            let e = (f(x) - g(x)).abs();
            if e > worst.0 {
                worst = (e, x);
            }
        }
        worst
    }

    #[ebptv_macros::unit_test]
    fn cos_and_sin_match_libm() {
        for (lo, hi) in [(-10.0, 10.0), (-1e3, 1e3), (-1e5, 1e5)] {
            let xs = args(lo, hi, 400_000);
            let (e, x) = max_err(cos, f64::cos, &xs);
            assert!(e <= 4e-16, "cos: {e:e} at {x} in [{lo}, {hi}]");
            let (e, x) = max_err(sin, f64::sin, &xs);
            assert!(e <= 4e-16, "sin: {e:e} at {x} in [{lo}, {hi}]");
        }
        // Beyond the exact reduction: error grows like the argument's own
        // rounding.
        for &x in &args(-1e9, 1e9, 100_000) {
            let tol = 4e-16 + 1.2e-16 * x.abs();
            assert!((cos(x) - x.cos()).abs() <= tol, "cos at {x}");
            assert!((sin(x) - x.sin()).abs() <= tol, "sin at {x}");
        }
        // Exact where it must be, and NaN in, NaN out.
        assert_eq!(cos(0.0), 1.0);
        assert_eq!(sin(0.0), 0.0);
        assert!(cos(f64::NAN).is_nan() && cos(f64::INFINITY).is_nan());
        assert!(sin(f64::NAN).is_nan());
    }

    /// The sin of [`sincos_lanes`] is within 4e-16 of libm and its cos
    /// is [`cos_lanes`] bit for bit (the turbulent field's velocity at a
    /// step's start is the plain evaluation's).
    #[ebptv_macros::unit_test]
    fn sincos_matches_libm_and_cos_lanes() {
        for (lo, hi) in [(-10.0, 10.0), (-1e3, 1e3), (-1e5, 1e5)] {
            let xs = args(lo, hi, 400_000);
            for &x in &xs {
                let c = sincos_lanes(x).1;
                assert_eq!(c.to_bits(), cos(x).to_bits(), "cos at {x}");
            }
            let (e, x) = max_err(|x| sincos_lanes(x).0, f64::sin, &xs);
            assert!(e <= 4e-16, "sin: {e:e} at {x} in [{lo}, {hi}]");
        }
        assert!(sincos_lanes(f64::NAN).0.is_nan());
    }

    /// The small-angle (sin d, cos d − 1) against libm over their whole
    /// domains (and 0.1 % beyond, the callers' bound checks' rounding):
    /// sin d within 2e-17 of libm (half an ulp of 1/8: the result's own
    /// rounding), cos d − 1 within 1e-17 of −2 sin²(d/2) (libm). From
    /// 1.9 to 2 times the domain the error is above 1e-15: the callers'
    /// bound is needed.
    #[ebptv_macros::unit_test]
    fn small_angle_sincos_within_bounds() {
        type F = fn(f64) -> (f64, f64);
        for (f, b, name) in [
            (sincos_small as F, SMALL_ANGLE, "small"),
            (sincos_tiny as F, TINY_ANGLE, "tiny"),
        ] {
            let err = |lo: f64, hi: f64| {
                let (mut es, mut ec) = (0.0f64, 0.0f64);
                for &d in &args(lo, hi, 200_000) {
                    let (s, cm1) = f(d);
                    let h = (0.5 * d).sin();
                    es = es.max((s - d.sin()).abs());
                    ec = ec.max((cm1 + 2.0 * h * h).abs());
                }
                (es, ec)
            };
            let (es, ec) = err(-1.001 * b, 1.001 * b);
            eprintln!("{name}: sin {es:e}, cos - 1 {ec:e}");
            assert!(es <= 2e-17 && ec <= 1e-17, "{name}: {es:e} {ec:e}");
            let (es, ec) = err(1.9 * b, 2.0 * b);
            assert!(es.max(ec) > 1e-15, "{name} beyond: {es:e} {ec:e}");
        }
        assert_eq!(sincos_small(0.0), (0.0, 0.0));
    }

    /// The pair type gives the scalar's bits in both lanes.
    #[ebptv_macros::unit_test]
    fn pairs_are_the_scalar_bit_for_bit() {
        let xs = args(-2e4, 2e4, 100_000);
        let es = args(-800.0, 800.0, 100_000);
        for k in 0..xs.len().min(es.len()) - 1 {
            let v = F64x2::new([xs[k], xs[k + 1]]);
            let w = F64x2::new([es[k], es[k + 1]]);
            let (c, s, e) = (
                cos_lanes(v).to_array(),
                sin_lanes(v).to_array(),
                exp_lanes(w).to_array(),
            );
            let sc = sincos_lanes(v);
            let d = v * F64x2::splat(1e-5);
            let (sm, tn) = (sincos_small(d), sincos_tiny(d * F64x2::splat(0.125)));
            for l in 0..2 {
                let x = xs[k + l];
                let pairs = [
                    (sc.0, sincos_lanes(x).0),
                    (sc.1, sincos_lanes(x).1),
                    (sm.0, sincos_small(x * 1e-5).0),
                    (sm.1, sincos_small(x * 1e-5).1),
                    (tn.0, sincos_tiny(x * 1e-5 * 0.125).0),
                    (tn.1, sincos_tiny(x * 1e-5 * 0.125).1),
                ];
                for (i, (got, want)) in pairs.iter().enumerate() {
                    assert_eq!(got.lane(l).to_bits(), want.to_bits(), "kernel {i} at {x}");
                }
            }
            for l in 0..2 {
                assert_eq!(
                    c[l].to_bits(),
                    cos(xs[k + l]).to_bits(),
                    "cos {}",
                    xs[k + l]
                );
                assert_eq!(
                    s[l].to_bits(),
                    sin(xs[k + l]).to_bits(),
                    "sin {}",
                    xs[k + l]
                );
                assert_eq!(
                    e[l].to_bits(),
                    exp(es[k + l]).to_bits(),
                    "exp {}",
                    es[k + l]
                );
            }
        }
        // The remaining pair operations against the scalar ones.
        for k in 0..xs.len() - 1 {
            let (a, b) = (xs[k], xs[k + 1] - 3.0);
            let (v, w) = (F64x2::new([a, b]), F64x2::new([b, a]));
            let pairs = [
                (v / w, [a / b, b / a]),
                (-v, [-a, -b]),
                (v.abs(), [a.abs(), b.abs()]),
                (v.sign_one(), [a.signum(), b.signum()]),
                (
                    v.select_lt(w, v * w, v + w),
                    [a.select_lt(b, a * b, a + b), b.select_lt(a, b * a, b + a)],
                ),
                (F64x2::from_fn(|i| [a, b][i]), [v.lane(0), v.lane(1)]),
            ];
            for (got, want) in pairs {
                let got = got.to_array();
                assert_eq!(got.map(f64::to_bits), want.map(f64::to_bits), "{a} {b}");
            }
        }
        assert_eq!((-0.0f64).sign_one(), -1.0);
        let n = exp_lanes(F64x2::new([f64::NAN, 1.0])).to_array();
        assert!(n[0].is_nan() && n[1] == exp(1.0));
    }

    /// Every lane type gives the scalar's bits for every operation and
    /// kernel: the portable SSE2 pairs and, on a CPU with AVX2 and FMA,
    /// the AVX2 lanes through the dispatcher (without them both runs take
    /// the portable lanes).
    #[ebptv_macros::unit_test]
    fn every_lane_type_is_the_scalar_bit_for_bit() {
        use crate::simd::{Dispatch, LaneKernel};
        let xs = args(-2e4, 2e4, 100_000);
        let mut es = args(-800.0, 800.0, 100_000);
        es.extend([f64::NAN, f64::INFINITY, f64::NEG_INFINITY, 1e-310]);
        struct Check<'a>(&'a [f64], &'a [f64]);
        impl LaneKernel for Check<'_> {
            type Out = usize;
            #[inline(always)]
            fn run<T: Lanes>(self) -> usize {
                check_lanes::<T>(self.0, self.1);
                T::N
            }
        }
        assert_eq!(Dispatch::portable().run(Check(&xs, &es)), 4);
        let wide = Dispatch::detect().run(Check(&xs, &es));
        if !crate::simd::avx2_fma() {
            eprintln!("no AVX2 + FMA on this CPU: the portable lanes only");
        }
        assert_eq!(wide, if crate::simd::avx2_fma() { 8 } else { 4 });
    }

    #[inline(always)]
    fn check_lanes<T: Lanes>(xs: &[f64], es: &[f64]) {
        let n = T::N;
        let same = |got: T, want: &[f64], what: &str| {
            for (l, w) in want.iter().enumerate() {
                assert_eq!(
                    got.lane(l).to_bits(),
                    w.to_bits(),
                    "{what} lane {l}: {want:?}"
                );
            }
        };
        let map = |a: &[f64], f: &dyn Fn(f64) -> f64| a.iter().map(|&v| f(v)).collect::<Vec<_>>();
        let zip = |a: &[f64], b: &[f64], f: &dyn Fn(f64, f64) -> f64| {
            a.iter().zip(b).map(|(&u, &v)| f(u, v)).collect::<Vec<_>>()
        };
        for k in 0..xs.len().min(es.len()) - n {
            let x = &xs[k..k + n];
            let e = &es[k..k + n];
            // A second operand: the neighbours, shifted.
            let b: Vec<f64> = (0..n).map(|i| x[(i + 1) % n] - 3.0 + i as f64).collect();
            let (v, w, ve) = (
                T::from_fn(|i| x[i]),
                T::from_fn(|i| b[i]),
                T::from_fn(|i| e[i]),
            );
            same(cos_lanes(v), &map(x, &cos), "cos");
            same(sin_lanes(v), &map(x, &sin), "sin");
            same(
                sincos_lanes(v).0,
                &map(x, &|a| sincos_lanes(a).0),
                "sincos sin",
            );
            same(
                sincos_lanes(v).1,
                &map(x, &|a| sincos_lanes(a).1),
                "sincos cos",
            );
            let d = v * T::splat(1e-5);
            let xd = map(x, &|a| a * 1e-5);
            same(
                sincos_small(d).0,
                &map(&xd, &|a| sincos_small(a).0),
                "small sin",
            );
            same(
                sincos_small(d).1,
                &map(&xd, &|a| sincos_small(a).1),
                "small cos",
            );
            let d = d * T::splat(0.125);
            let xd = map(&xd, &|a| a * 0.125);
            same(
                sincos_tiny(d).0,
                &map(&xd, &|a| sincos_tiny(a).0),
                "tiny sin",
            );
            same(
                sincos_tiny(d).1,
                &map(&xd, &|a| sincos_tiny(a).1),
                "tiny cos",
            );
            same(exp_lanes(ve), &map(e, &exp), "exp");
            same(v / w, &zip(x, &b, &|a, c| a / c), "div");
            same(v + w - v * w, &zip(x, &b, &|a, c| a + c - a * c), "arith");
            same(-v, &map(x, &|a| -a), "neg");
            same(v.abs(), &map(x, &f64::abs), "abs");
            same(v.sign_one(), &map(x, &|a| a.sign_one()), "sign");
            same(v.raise_to(1.5), &map(x, &|a| a.raise_to(1.5)), "raise");
            same(v.lower_to(1.5), &map(x, &|a| a.lower_to(1.5)), "lower");
            same(v.xor(w), &zip(x, &b, &|a, c| a.xor(c)), "xor");
            same(
                v.select_lt(w, v, w),
                &zip(x, &b, &|a, c| a.select_lt(c, a, c)),
                "select",
            );
        }
    }

    #[ebptv_macros::unit_test]
    fn exp_matches_libm() {
        for &x in &args(-708.0, 709.0, 400_000) {
            let (a, b) = (exp(x), x.exp());
            assert!((a - b).abs() <= 4e-16 * b, "exp({x}) = {a:e}, libm {b:e}");
        }
        for &x in &args(-2.0, 2.0, 100_000) {
            let (a, b) = (exp(x), x.exp());
            assert!((a - b).abs() <= 4e-16 * b, "exp({x}) = {a:e}, libm {b:e}");
        }
        assert_eq!(exp(0.0), 1.0);
        for x in [-708.5, -1e4, f64::NEG_INFINITY] {
            assert!(exp(x) > 0.0 && exp(x) < 4e-308, "exp({x})");
        }
        assert!(exp(f64::NAN).is_nan());
    }
}
