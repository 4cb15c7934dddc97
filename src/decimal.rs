//! Fast, exact decimal text for the big CSV writers (truth particles,
//! particles, tracks).
//!
//! `core::fmt`'s exact float formatting was 30–40 % of the CPU time of
//! `ebptv simulate` and `ebptv track` at full frame. These functions write
//! the same bytes as `format!("{v:.d$}")` / `v.to_string()`: integer
//! arithmetic on `v·10^d` where its rounding is unambiguous, the exact
//! formatter for the rare values near a rounding tie (and for huge or
//! non-finite ones). Tests compare them with `format!` on ~10^6 values.

/// Append `v` in decimal.
pub(crate) fn push_int(out: &mut Vec<u8>, v: i64) {
    if v < 0 {
        out.push(b'-');
    }
    push_u64(out, v.unsigned_abs());
}

/// Append `v` with `decimals` (≤ 6) digits after the point, byte for byte
/// `format!("{v:.decimals$}")`. Scaling by 10^decimals and rounding to an
/// integer gives the same digits unless the scaled value sits within a
/// few ulps of a rounding tie (or is huge, or not finite): those rare
/// values go through `core::fmt`, which rounds the exact binary value.
pub(crate) fn push_fixed(out: &mut Vec<u8>, v: f64, decimals: u32) {
    let mut b = RevDigits::<24>::new();
    if b.fixed(v, decimals) {
        out.extend_from_slice(b.as_slice());
    } else {
        use std::io::Write as _;
        let d = decimals.min(6) as usize;
        let _ = write!(out, "{v:.d$}");
    }
}

/// Append `n` in decimal.
pub(crate) fn push_u64(out: &mut Vec<u8>, n: u64) {
    let mut b = RevDigits::<24>::new();
    b.u64(n);
    out.extend_from_slice(b.as_slice());
}

/// "00", "01", …, "99": two digits per division.
const DIGIT_PAIRS: &[u8; 200] = b"0001020304050607080910111213141516171819\
2021222324252627282930313233343536373839\
4041424344454647484950515253545556575859\
6061626364656667686970717273747576777879\
8081828384858687888990919293949596979899";

/// Text built right to left in a fixed buffer of `N` bytes: a whole CSV
/// row (or one number) is written field by field from its end, eight
/// digits at a time ([`ascii8`]: a number below 10^8 — every coordinate
/// and most velocities at 3–4 decimals — is one 8-byte store, the decimal
/// point placed by a shift), and appended with a single copy. The caller
/// keeps the total within `N` with 8 bytes to spare in front (a number
/// takes at most 20 digits plus sign and point; the 8-byte stores may
/// write up to 7 bytes ahead of the text).
pub(crate) struct RevDigits<const N: usize> {
    buf: [u8; N],
    start: usize,
}

impl<const N: usize> Default for RevDigits<N> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const N: usize> RevDigits<N> {
    pub(crate) fn new() -> Self {
        RevDigits {
            buf: [b'0'; N],
            start: N,
        }
    }

    /// The text so far.
    pub(crate) fn as_slice(&self) -> &[u8] {
        &self.buf[self.start..]
    }

    /// Prepend one byte.
    #[inline(always)]
    pub(crate) fn byte(&mut self, b: u8) {
        self.start -= 1;
        self.buf[self.start] = b;
    }

    /// Prepend `text` (the caller keeps the total within `N`).
    #[inline(always)]
    pub(crate) fn bytes(&mut self, text: &[u8]) {
        self.start -= text.len();
        self.buf[self.start..self.start + text.len()].copy_from_slice(text);
    }

    /// Bytes still free in front of the text.
    #[inline(always)]
    pub(crate) fn room(&self) -> usize {
        self.start
    }

    #[inline(always)]
    fn pair(&mut self, two: u64) {
        let p = two as usize * 2;
        self.start -= 2;
        self.buf[self.start..self.start + 2].copy_from_slice(&DIGIT_PAIRS[p..p + 2]);
    }

    /// Prepend `n` in decimal: eight digits per step ([`ascii8`]); the
    /// buffer needs 8 bytes of room in front of the text at each step.
    #[inline(always)]
    pub(crate) fn u64(&mut self, mut n: u64) {
        while n >= 100_000_000 {
            let (text, _) = ascii8((n % 100_000_000) as u32);
            self.last8(text, 8);
            n /= 100_000_000;
        }
        let (text, digits) = ascii8(n as u32);
        self.last8(text, digits);
    }

    /// Prepend the last `k` (≤ 8) bytes of the 8 bytes of `text` (in
    /// memory order: the little-endian bytes of the u64). All 8 are
    /// stored; those in front of the text are overwritten by whatever is
    /// prepended next or lie outside [`RevDigits::as_slice`].
    #[inline(always)]
    fn last8(&mut self, text: u64, k: usize) {
        self.buf[self.start - 8..self.start].copy_from_slice(&text.to_le_bytes());
        self.start -= k;
    }

    /// [`RevDigits::u64`] one pair of digits per division: the reference
    /// the eight-digit path is tested against (and the path of the
    /// fallback in [`RevDigits::fixed`]).
    #[inline(always)]
    fn u64_pairs(&mut self, mut n: u64) {
        while n >= 100 {
            self.pair(n % 100);
            n /= 100;
        }
        if n >= 10 {
            self.pair(n);
        } else {
            self.byte(b'0' + n as u8);
        }
    }

    /// Prepend `n` in decimal, or its negation.
    #[inline(always)]
    pub(crate) fn i64(&mut self, n: i64) {
        self.u64(n.unsigned_abs());
        if n < 0 {
            self.byte(b'-');
        }
    }

    /// Prepend `v` with `decimals` (≤ 6) digits after the point, as
    /// `format!("{v:.decimals$}")` writes it, when integer arithmetic on
    /// `v·10^decimals` gives those digits; returns false (and prepends
    /// nothing) for the rare values near a rounding tie, huge or not
    /// finite, which need `core::fmt`'s exact rounding.
    #[inline(always)]
    pub(crate) fn fixed(&mut self, v: f64, decimals: u32) -> bool {
        const SCALE: [f64; 7] = [1.0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6];
        let d = decimals.min(6) as usize;
        let a = v.abs() * SCALE[d];
        if !(a < 1e15) {
            return false; // huge or not finite
        }
        // `as i64` truncates (no libm call): floor for 0 ≤ a < 2^63, and
        // one instruction each way, where u64 conversions take several.
        let whole = a as i64;
        let frac = a - whole as f64;
        // The product is within half an ulp of the exact one; stay well away.
        if (frac - 0.5).abs() <= a * 4.0 * f64::EPSILON {
            return false;
        }
        let n = (whole + (frac > 0.5) as i64) as u64;
        if n < 100_000_000 {
            // All digits at once: the fraction is the last `d` of them,
            // the integer part (at least "0") the ones before.
            let (text, digits) = ascii8(n as u32);
            if d == 0 {
                self.last8(text, digits);
            } else {
                self.last8(text, d);
                self.byte(b'.');
                self.last8(text << (8 * d), digits.saturating_sub(d).max(1));
            }
        } else {
            self.fixed_pairs(n, d);
        }
        if v.is_sign_negative() {
            self.byte(b'-');
        }
        true
    }

    /// The digits of [`RevDigits::fixed`] for `n` = the scaled, rounded
    /// value, a pair per division (values of 10^8 and more after scaling).
    fn fixed_pairs(&mut self, mut n: u64, d: usize) {
        let mut k = d;
        while k >= 2 {
            self.pair(n % 100);
            n /= 100;
            k -= 2;
        }
        if k == 1 {
            self.byte(b'0' + (n % 10) as u8);
            n /= 10;
        }
        if d > 0 {
            self.byte(b'.');
        }
        self.u64_pairs(n);
    }
}

/// The eight decimal digits of `n` < 10^8 (leading zeros included) as
/// ASCII bytes, the most significant first in memory order (the u64's
/// little-endian bytes), and the number of digits without the leading
/// zeros (at least 1). SWAR: the 4-digit halves, then the 2-digit
/// quarters, then the digits are split in all lanes at once with
/// multiply-and-shift divisions (exact for the lane ranges: /100 as
/// ·10486 >> 20 below 10^4, /10 as ·103 >> 10 below 100), instead of
/// four dependent divisions by 100.
#[inline(always)]
fn ascii8(n: u32) -> (u64, usize) {
    debug_assert!(n < 100_000_000);
    let merged = (n / 10_000) as u64 | (((n % 10_000) as u64) << 32);
    let hundreds_digit = ((merged * 10_486) >> 20) & 0x0000_007F_0000_007F;
    let pairs = ((merged - 100 * hundreds_digit) << 16) | hundreds_digit;
    let tens = ((pairs * 103) >> 10) & 0x000F_000F_000F_000F;
    let digits = ((pairs - 10 * tens) << 8) | tens;
    // Leading zero digits are the zero bytes at the low end.
    let leading_zeros = (digits.trailing_zeros() / 8) as usize;
    (digits + 0x3030_3030_3030_3030, (8 - leading_zeros).max(1))
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    #[ebptv_macros::unit_test]
    fn fast_fixed_point_matches_core_fmt() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(3);
        let mut specials = vec![
            0.0,
            -0.0,
            0.5,
            -0.5,
            0.00005,
            -0.00005,
            0.00015,
            1.0005,
            2.5e-4,
            1e-9,
            -1e-9,
            123.45650,
            0.125,
            0.0625,
            1e14,
            1e16,
            -3.0e20,
            f64::NAN,
            f64::INFINITY,
            f64::NEG_INFINITY,
            f64::MIN_POSITIVE,
            1279.99995,
        ];
        // Exact binary ties at 3 and 4 decimals (k/2^n with few bits).
        for k in 0..2000 {
            specials.push(k as f64 / 2048.0);
            specials.push(-(k as f64) / 16.0 + 0.0005);
        }
        for i in 0..200_000 {
            let v = match i % 4 {
                0 => rng.gen_range(-2000.0..2000.0),
                1 => rng.gen_range(-1e6..1e6),
                2 => (rng.gen_range(-1e7..1e7) as i64) as f64 * 1e-4 + 5e-5,
                _ => rng.gen_range(-1.0..1.0) * 10f64.powi(rng.gen_range(-8..12)),
            };
            specials.push(v);
        }
        let mut a = Vec::new();
        for &v in &specials {
            for d in [0, 1, 3, 4, 6] {
                a.clear();
                push_fixed(&mut a, v, d);
                let want = format!("{v:.prec$}", prec = d as usize);
                assert_eq!(std::str::from_utf8(&a).unwrap(), want, "{v:e} at {d}");
            }
        }
    }

    /// The eight-digit path against the pair-per-division reference on
    /// every value below 10^5, every power of ten and its neighbours, and
    /// a million random values over the whole u64 range.
    #[ebptv_macros::unit_test]
    fn eight_digit_path_equals_the_pairs() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(8);
        let mut values: Vec<u64> = (0..100_000).collect();
        for k in 0..20 {
            let p = 10u64.pow(k);
            values.extend([p - 1, p, p + 1, 99_999_999, 100_000_000]);
        }
        values.extend([u64::MAX, u64::MAX - 1, 1 << 63]);
        values.extend((0..1_000_000).map(|i| match i % 3 {
            0 => rng.gen_range(0..100_000_000),
            1 => rng.gen::<u64>() >> rng.gen_range(0..64),
            _ => rng.gen(),
        }));
        for n in values {
            let mut a = RevDigits::<48>::new();
            a.byte(b'|');
            a.u64(n);
            let mut b = RevDigits::<48>::new();
            b.byte(b'|');
            b.u64_pairs(n);
            assert_eq!(a.as_slice(), b.as_slice(), "{n}");
            assert_eq!(a.as_slice(), format!("{n}|").as_bytes());
        }
    }

    #[ebptv_macros::unit_test]
    fn fast_number_formatting_matches_the_formatter() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(3);
        let mut specials = vec![
            0.0, -0.0, 0.5, -0.5, 1.00005, 2.5e-5, -1e-9, 1e15, 9e15, 123.45675, 1e300,
        ];
        specials.extend((0..200_000).map(|i| {
            let mag = 10f64.powi(rng.gen_range(-6..9));
            let v = rng.gen_range(-1.0..1.0) * mag;
            if i % 7 == 0 {
                (v * 1e4).round() / 1e4 + 0.00005 // near a tie
            } else {
                v
            }
        }));
        let mut buf = Vec::new();
        for v in specials {
            for d in [0u32, 3, 4] {
                buf.clear();
                push_fixed(&mut buf, v, d);
                assert_eq!(
                    String::from_utf8(buf.clone()).unwrap(),
                    format!("{v:.*}", d as usize),
                    "{v:e} with {d} decimals"
                );
            }
        }
        for v in [0i64, 7, -7, 1234567890123, i64::MIN, i64::MAX] {
            buf.clear();
            push_int(&mut buf, v);
            assert_eq!(String::from_utf8(buf.clone()).unwrap(), v.to_string());
        }
    }
}
