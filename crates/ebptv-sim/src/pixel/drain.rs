//! Eight-lane kernels of the drain of the row ring: writing a group of
//! eight pixels as `Hit`s without a branch per pixel, clearing lanes, and
//! the at-or-above-threshold mask of eight f32 sums. The SSE2 kernels
//! are tested below against plain per-lane loops (and, through the
//! drain, in `tests.rs`: `drained_hits_match_dense_sums`).

use super::*;

/// Write the eight lanes of `v` as [`Hit`]s with keys `rc + j` to
/// consecutive slots from `out`, the j-th to the slot after the hits of
/// lanes below j whose bit is set in `m`: every lane written (a later one
/// overwrites a lane whose bit is clear), no branch on how many fire
/// (the loop over the mask's bits mispredicted ~once per group). Returns
/// the number of set bits.
///
/// # Safety
/// `out` must be valid for writes of eight `Hit`s.
#[inline(always)]
pub(super) unsafe fn write_hits8(
    out: *mut std::mem::MaybeUninit<Hit>,
    v: &[f32; 8],
    rc: u32,
    m: u32,
) -> usize {
    // (`Hit` is `repr(C)` {rc: u32, v: f32}: one u64, key low.)
    let out = out as *mut u64;
    let mut n = 0;
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::*;
        // SAFETY: SSE2 is part of the x86_64 baseline; the loads read
        // the eight f32 of `v`; every store is to one of the eight slots
        // (n ≤ j for lane j).
        unsafe {
            let k0 = _mm_add_epi32(_mm_set1_epi32(rc as i32), _mm_setr_epi32(0, 1, 2, 3));
            let k1 = _mm_add_epi32(k0, _mm_set1_epi32(4));
            let v0 = _mm_castps_si128(_mm_loadu_ps(v.as_ptr()));
            let v1 = _mm_castps_si128(_mm_loadu_ps(v.as_ptr().add(4)));
            // Key and value interleaved: two hits per register.
            let pairs = [
                _mm_unpacklo_epi32(k0, v0),
                _mm_unpackhi_epi32(k0, v0),
                _mm_unpacklo_epi32(k1, v1),
                _mm_unpackhi_epi32(k1, v1),
            ];
            for (i, &p) in pairs.iter().enumerate() {
                _mm_storel_epi64(out.add(n) as *mut __m128i, p);
                n += (m >> (2 * i)) as usize & 1;
                _mm_storeh_pd(out.add(n) as *mut f64, _mm_castsi128_pd(p));
                n += (m >> (2 * i + 1)) as usize & 1;
            }
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    for (j, &x) in v.iter().enumerate() {
        // SAFETY: n ≤ j < 8.
        unsafe {
            out.add(n)
                .write_unaligned((x.to_bits() as u64) << 32 | (rc + j as u32) as u64)
        };
        n += (m >> j) as usize & 1;
    }
    n
}

/// Set lanes `0..n` (n ≤ 8) of `v` to +0.0, keep the others bit for bit.
#[inline(always)]
pub(super) fn clear_lanes8(v: &mut [f32; 8], n: usize) {
    // KEEP[n]: all-ones for lanes n.., zero below.
    const KEEP: [[u32; 8]; 9] = {
        let mut t = [[0u32; 8]; 9];
        let mut n = 0;
        while n < 9 {
            let mut j = n;
            while j < 8 {
                t[n][j] = u32::MAX;
                j += 1;
            }
            n += 1;
        }
        t
    };
    let keep = &KEEP[n];
    for (x, &k) in v.iter_mut().zip(keep) {
        *x = f32::from_bits(x.to_bits() & k);
    }
}

/// Bit j set where `v[j] >= floor` (false for NaN, as `>=`).
#[inline(always)]
pub(super) fn at_least_mask8(v: &[f32; 8], floor: f32) -> u32 {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_mm_cmpge_ps, _mm_loadu_ps, _mm_movemask_ps, _mm_set1_ps};
        // SAFETY: SSE2 is part of the x86_64 baseline; the loads read
        // the eight f32 of `v`.
        unsafe {
            let f = _mm_set1_ps(floor);
            let lo = _mm_cmpge_ps(_mm_loadu_ps(v.as_ptr()), f);
            let hi = _mm_cmpge_ps(_mm_loadu_ps(v.as_ptr().add(4)), f);
            (_mm_movemask_ps(lo) | _mm_movemask_ps(hi) << 4) as u32
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let mut m = 0;
        for (j, &x) in v.iter().enumerate() {
            m |= ((x >= floor) as u32) << j;
        }
        m
    }
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// Eight f32 lanes with the awkward values among random ones: ±0,
    /// the floor itself and its neighbours, infinities, NaN, subnormals.
    fn lanes(rng: &mut Pcg64, floor: f32) -> [f32; 8] {
        let special = [
            0.0,
            -0.0,
            floor,
            f32::from_bits(floor.to_bits() + 1),
            f32::from_bits(floor.to_bits() - 1),
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
            f32::MIN_POSITIVE / 4.0,
        ];
        std::array::from_fn(|_| {
            if rng.gen_bool(0.4) {
                special[rng.gen_range(0..special.len())]
            } else {
                rng.gen_range(-2.0f32..2.0)
            }
        })
    }

    #[ebptv_macros::unit_test]
    fn at_least_mask8_is_the_per_lane_compare() {
        let mut rng = Pcg64::seed_from_u64(41);
        for _ in 0..20_000 {
            let floor = rng.gen_range(1e-4f32..1.0);
            let v = lanes(&mut rng, floor);
            let plain = v
                .iter()
                .enumerate()
                .fold(0u32, |m, (j, &x)| m | ((x >= floor) as u32) << j);
            assert_eq!(at_least_mask8(&v, floor), plain, "{v:?} ≥ {floor}");
        }
    }

    #[ebptv_macros::unit_test]
    fn write_hits8_writes_the_set_lanes_in_order() {
        let mut rng = Pcg64::seed_from_u64(42);
        for _ in 0..20_000 {
            let v = lanes(&mut rng, 0.5);
            let m: u32 = rng.gen_range(0..256);
            let rc: u32 = rng.gen_range(0..(1u32 << 28));
            let mut out = [std::mem::MaybeUninit::<Hit>::uninit(); 8];
            // SAFETY: `out` holds eight `Hit`s.
            let n = unsafe { write_hits8(out.as_mut_ptr(), &v, rc, m) };
            let plain: Vec<(u32, u32)> = (0..8)
                .filter(|j| m >> j & 1 == 1)
                .map(|j| (rc + j as u32, v[j].to_bits()))
                .collect();
            assert_eq!(n, plain.len());
            // SAFETY: the first n slots hold the set lanes (lane j is
            // written to slot ≤ j, a set one is never overwritten).
            let got: Vec<(u32, u32)> = out[..n]
                .iter()
                .map(|h| unsafe { h.assume_init() })
                .map(|h| (h.rc, h.v.to_bits()))
                .collect();
            assert_eq!(got, plain, "mask {m:08b}");
        }
    }

    #[ebptv_macros::unit_test]
    fn clear_lanes8_clears_the_first_n() {
        let mut rng = Pcg64::seed_from_u64(43);
        for n in 0..=8 {
            let v = lanes(&mut rng, 0.5);
            let mut c = v;
            clear_lanes8(&mut c, n);
            for j in 0..8 {
                let want = if j < n {
                    0.0f32.to_bits()
                } else {
                    v[j].to_bits()
                };
                assert_eq!(c[j].to_bits(), want, "n = {n}, lane {j}");
            }
        }
    }
}
