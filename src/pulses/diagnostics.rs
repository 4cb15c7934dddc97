//! Diagnostics computed from the compact statistics of the streaming pass:
//! latency-histogram shape, burst onset, readout-saturation measures, the
//! per-pixel rate map and particle-image statistics of pseudo-images.

use serde::{Deserialize, Serialize};

/// Shape of the folded latency histogram (1 µs bins from the pulse start).
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
pub struct LatencyStats {
    /// Events per 1 µs latency bin, bin i = [i, i+1) µs after the pulse start.
    pub histogram: Vec<f64>,
    /// Cumulative fraction of all events up to the end of each bin.
    pub cumulative: Vec<f64>,
    pub peak_us: f64,
    pub fwhm_us: f64,
    /// Shortest latency interval holding 95 % of the burst (above-floor) events.
    pub window95_us: (f64, f64),
    /// Mean event density inside the 95 % window over that outside.
    pub burst_contrast: f64,
    /// Fraction of events above the random floor (events tied to pulses).
    pub burst_fraction: f64,
    /// Fraction of events on the random floor (noise, or untied by saturation).
    pub random_fraction: f64,
    /// min/max of the smoothed histogram: 1 = flat (no pulse structure).
    pub flatness: f64,
    /// Floor level (events per µs bin).
    pub floor: f64,
}

/// Circular box smoothing with half-width `r`.
pub(crate) fn smooth_circular(h: &[f64], r: usize) -> Vec<f64> {
    let n = h.len();
    if n == 0 || r == 0 {
        return h.to_vec();
    }
    let r = r.min(n / 2);
    let w = (2 * r + 1) as f64;
    let mut acc: f64 = (0..=2 * r).map(|i| h[(i + n - r) % n]).sum();
    let mut out = vec![0.0; n];
    for i in 0..n {
        out[i] = acc / w;
        acc += h[(i + r + 1) % n] - h[(i + n - r) % n];
    }
    out
}

/// Floor of the histogram: its 20th percentile (the random-event level; the
/// burst fills far fewer than 80 % of the bins in a usable recording).
pub(crate) fn floor_level(h: &[f64]) -> f64 {
    let mut v = h.to_vec();
    if v.is_empty() {
        return 0.0;
    }
    let k = v.len() / 5;
    let (_, m, _) = v.select_nth_unstable_by(k, |a, b| a.total_cmp(b));
    *m
}

/// Index (fractional) of the maximum of the smoothed histogram.
pub(crate) fn peak_position(h: &[f64]) -> f64 {
    let n = h.len();
    let s = smooth_circular(h, 1);
    let (k, _) = s
        .iter()
        .enumerate()
        .max_by(|a, b| a.1.total_cmp(b.1))
        .unwrap();
    k as f64 + super::timing::parabolic_offset(s[(k + n - 1) % n], s[k], s[(k + 1) % n])
}

/// Leading edge of the burst, in bins of `h` (circular; may be negative →
/// wraps): the time where the event rate first rises above the *local*
/// floor before the burst by `frac` of the burst amplitude (and by 3 √floor
/// counts, so noise alone does not trigger it).
///
/// Why this is the pulse start: an event cannot precede the light that
/// causes it, so the pulse starts at or before the earliest burst events,
/// and the earliest detectable burst events are the brightest, fastest
/// pixels with the shortest latency jitter. Walking from the flank's
/// half-height back to where the excess vanishes (Willert's "preceding
/// minimum", made robust by a threshold) lands on that earliest-event time;
/// the flank extrapolation of [`burst_onset`] instead lands on the *typical*
/// onset, several jitter widths later. The floor is the minimum of the
/// lightly smoothed histogram in the 30 % of the period before the flank,
/// not a global percentile: a broad burst can fill most of the period.
/// What remains is the sensor's minimum latency for the fastest events,
/// which no event-only estimate can see ([`super::PulseOptions::onset_latency_us`]).
pub(crate) fn leading_edge(h: &[f64], frac: f64) -> f64 {
    let n = h.len();
    if n < 4 {
        return 0.0;
    }
    let s = smooth_circular(h, 1);
    let at = |i: isize| s[i.rem_euclid(n as isize) as usize];
    let (kp, &peak) = s
        .iter()
        .enumerate()
        .max_by(|a, b| a.1.total_cmp(b.1))
        .unwrap();
    let kp = kp as isize;
    let look = ((0.3 * n as f64) as isize).max(3);
    // Half height against the lowest point before the peak.
    let low0 = (1..=look.max(n as isize / 2))
        .map(|d| at(kp - d))
        .fold(f64::MAX, f64::min);
    let half = low0 + 0.5 * (peak - low0);
    let mut x50 = kp;
    while x50 > kp - n as isize && at(x50 - 1) >= half {
        x50 -= 1;
    }
    let floor = (1..=look).map(|d| at(x50 - d)).fold(f64::MAX, f64::min);
    let amp = (peak - floor).max(0.0);
    let level = floor + (frac * amp).max(3.0 * floor.max(1.0).sqrt());
    let mut j = x50;
    while j > x50 - look && at(j - 1) >= level {
        j -= 1;
    }
    // at(j−1) < level ≤ at(j): interpolate between bin centres.
    let (a, b) = (at(j - 1), at(j));
    let f = ((level - a) / (b - a).max(1e-12)).clamp(0.0, 1.0);
    (j - 1) as f64 + 0.5 + f
}

/// Latency statistics of a histogram whose bin 0 starts at the pulse start.
pub(crate) fn latency_stats(h: &[f64]) -> LatencyStats {
    let n = h.len();
    let total: f64 = h.iter().sum();
    if n == 0 || total <= 0.0 {
        return LatencyStats::default();
    }
    let s = smooth_circular(h, 1);
    let floor = floor_level(&s);
    let peak = peak_position(h);
    let kp = (peak.round() as usize) % n;
    let half = floor + 0.5 * (s[kp] - floor);
    let walk = |dir: isize| -> f64 {
        let mut i = kp as isize;
        for _ in 0..n {
            let j = (i + dir).rem_euclid(n as isize) as usize;
            let here = i.rem_euclid(n as isize) as usize;
            if s[j] < half {
                let f = (s[here] - half) / (s[here] - s[j]).max(1e-12);
                return i as f64 + dir as f64 * f;
            }
            i += dir;
        }
        i as f64
    };
    let fwhm = (walk(1) - walk(-1)).clamp(0.0, n as f64);
    // 95 % window of the excess over the floor: shortest circular interval.
    let excess: Vec<f64> = h.iter().map(|v| (v - floor).max(0.0)).collect();
    let ex_total: f64 = excess.iter().sum();
    let mut best = (0usize, n);
    if ex_total > 0.0 {
        let target = 0.95 * ex_total;
        let mut j = 0usize;
        let mut acc = 0.0;
        for i in 0..n {
            while acc < target && j < i + n {
                acc += excess[j % n];
                j += 1;
            }
            if acc >= target && j - i < best.1 {
                best = (i, j - i);
            }
            acc -= excess[i];
        }
    }
    let (w0, wl) = best;
    let inside: f64 = (w0..w0 + wl).map(|i| h[i % n]).sum();
    let outside = total - inside;
    let contrast = if wl < n && outside > 0.0 {
        (inside / wl as f64) / (outside / (n - wl) as f64)
    } else {
        f64::INFINITY
    };
    let random = (floor * n as f64 / total).min(1.0);
    let mut cum = Vec::with_capacity(n);
    let mut c = 0.0;
    for v in h {
        c += v;
        cum.push(c / total);
    }
    let sm = smooth_circular(h, (n / 50).max(1));
    let mx = sm.iter().cloned().fold(f64::MIN, f64::max);
    let mn = sm.iter().cloned().fold(f64::MAX, f64::min);
    LatencyStats {
        histogram: h.to_vec(),
        cumulative: cum,
        peak_us: peak + 0.5,
        fwhm_us: fwhm,
        window95_us: (w0 as f64, (w0 + wl) as f64),
        burst_contrast: if contrast.is_finite() { contrast } else { 1e9 },
        burst_fraction: 1.0 - random,
        random_fraction: random,
        flatness: if mx > 0.0 { mn / mx } else { 1.0 },
        floor,
    }
}

/// Position (bins) of the lowest point of the heavily smoothed histogram:
/// where the assignment window boundary goes.
pub(crate) fn lowest_point(h: &[f64]) -> f64 {
    let n = h.len();
    let s = smooth_circular(h, (n / 20).max(2));
    let (k, _) = s
        .iter()
        .enumerate()
        .min_by(|a, b| a.1.total_cmp(b.1))
        .unwrap();
    k as f64
}

/// A pixel firing far above the rest.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, PartialEq)]
pub struct HotPixel {
    pub x: u16,
    pub y: u16,
    pub rate_hz: f64,
}

/// Hot pixels: rate above `factor` × the mean rate of active pixels and
/// above 100 ev/s, sorted by rate, at most `max` listed.
pub(crate) fn hot_pixels(
    counts: &[u32],
    width: usize,
    duration_s: f64,
    factor: f64,
    max: usize,
) -> (Vec<HotPixel>, f64) {
    let active = counts.iter().filter(|c| **c > 0).count().max(1);
    let total: u64 = counts.iter().map(|c| *c as u64).sum();
    let mean = total as f64 / active as f64 / duration_s.max(1e-9);
    let thr = (factor * mean).max(100.0);
    let mut hot: Vec<HotPixel> = counts
        .iter()
        .enumerate()
        .filter_map(|(i, &c)| {
            let r = c as f64 / duration_s.max(1e-9);
            (r > thr).then(|| HotPixel {
                x: (i % width) as u16,
                y: (i / width) as u16,
                rate_hz: r,
            })
        })
        .collect();
    hot.sort_by(|a, b| b.rate_hz.total_cmp(&a.rate_hz));
    hot.truncate(max);
    (hot, thr)
}

/// Clusters of 8-connected pixels of one pseudo-image.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub(crate) struct ClusterCount {
    pub clusters: u64,
    /// Sum of cluster areas (pixels).
    pub area: u64,
    pub events: u64,
}

/// Count the 8-connected clusters of the set pixels of a binary
/// pseudo-image given as event coordinates (duplicates allowed).
///
/// The pixels are sorted by (y, x) and deduplicated; a pixel's neighbours
/// to the right and in the next row (x−1, x, x+1) are found with one
/// forward-only cursor into the next row, and joined by union–find. The
/// hash-map version in the tests is the reference.
pub(crate) fn count_clusters(xs: &[u16], ys: &[u16]) -> ClusterCount {
    let mut keys: Vec<u32> = xs
        .iter()
        .zip(ys)
        .map(|(&x, &y)| (y as u32) << 16 | x as u32)
        .collect();
    keys.sort_unstable();
    keys.dedup();
    let n = keys.len();
    let mut parent: Vec<u32> = (0..n as u32).collect();
    fn find(p: &mut [u32], mut i: usize) -> usize {
        while p[i] as usize != i {
            p[i] = p[p[i] as usize];
            i = p[i] as usize;
        }
        i
    }
    fn union(p: &mut [u32], a: usize, b: usize) {
        let (a, b) = (find(p, a), find(p, b));
        if a != b {
            p[a.max(b)] = a.min(b) as u32;
        }
    }
    let mut cursor = 0usize;
    for i in 0..n {
        let k = keys[i];
        let (x, y) = (k & 0xffff, k >> 16);
        if i + 1 < n && x < 0xffff && keys[i + 1] == k + 1 {
            union(&mut parent, i, i + 1);
        }
        if y == 0xffff {
            continue;
        }
        // Next row, columns x−1 ..= x+1 (clamped to the u16 range).
        let lo = (y + 1) << 16 | x.saturating_sub(1);
        let hi = (y + 1) << 16 | (x + 1).min(0xffff);
        while cursor < n && keys[cursor] < lo {
            cursor += 1;
        }
        let mut j = cursor;
        while j < n && keys[j] <= hi {
            union(&mut parent, i, j);
            j += 1;
        }
    }
    let clusters = (0..n).filter(|&i| parent[i] as usize == i).count();
    ClusterCount {
        clusters: clusters as u64,
        area: n as u64,
        events: xs.len() as u64,
    }
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;

    /// The reference: hash map of pixels, union of the four forward
    /// neighbours of every pixel.
    /// Count the 8-connected clusters of the set pixels of a binary
    /// pseudo-image given as event coordinates (duplicates allowed).
    fn count_clusters_reference(xs: &[u16], ys: &[u16]) -> ClusterCount {
        let mut id: std::collections::HashMap<(u16, u16), usize> =
            std::collections::HashMap::with_capacity(xs.len());
        for (&x, &y) in xs.iter().zip(ys) {
            let n = id.len();
            id.entry((x, y)).or_insert(n);
        }
        let n = id.len();
        let mut parent: Vec<usize> = (0..n).collect();
        fn find(p: &mut [usize], mut i: usize) -> usize {
            while p[i] != i {
                p[i] = p[p[i]];
                i = p[i];
            }
            i
        }
        for (&(x, y), &i) in &id {
            for (dx, dy) in [(1i32, 0i32), (-1, 1), (0, 1), (1, 1)] {
                let (nx, ny) = (x as i32 + dx, y as i32 + dy);
                if nx < 0 || ny < 0 || nx > u16::MAX as i32 || ny > u16::MAX as i32 {
                    continue;
                }
                if let Some(&j) = id.get(&(nx as u16, ny as u16)) {
                    let (a, b) = (find(&mut parent, i), find(&mut parent, j));
                    if a != b {
                        parent[a] = b;
                    }
                }
            }
        }
        let clusters = (0..n).filter(|&i| find(&mut parent, i) == i).count();
        ClusterCount {
            clusters: clusters as u64,
            area: n as u64,
            events: xs.len() as u64,
        }
    }

    #[ebptv_macros::unit_test]
    fn clusters_equal_reference_on_random_images() {
        let mut s: u64 = 9;
        let mut next = |n: u64| {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (s >> 33) % n
        };
        for case in 0..200 {
            let (w, h) = if case % 10 == 0 {
                (65536, 65536)
            } else {
                (40 + next(200), 30 + next(100))
            };
            let m = next(2000) as usize;
            let (mut xs, mut ys) = (Vec::new(), Vec::new());
            for _ in 0..m {
                // Near the u16 limit now and then.
                let x = if w == 65536 {
                    65535 - next(20)
                } else {
                    next(w)
                };
                let y = if h == 65536 {
                    65535 - next(20)
                } else {
                    next(h)
                };
                xs.push(x as u16);
                ys.push(y as u16);
            }
            assert_eq!(
                count_clusters(&xs, &ys),
                count_clusters_reference(&xs, &ys),
                "case {case}"
            );
        }
    }

    #[ebptv_macros::unit_test]
    fn clusters_of_known_image() {
        // Two blobs (one diagonal pair, one 2x2) and one single pixel.
        let pts = [
            (0u16, 0u16),
            (1, 1),
            (10, 10),
            (11, 10),
            (10, 11),
            (11, 11),
            (11, 11),
            (20, 5),
        ];
        let xs: Vec<u16> = pts.iter().map(|p| p.0).collect();
        let ys: Vec<u16> = pts.iter().map(|p| p.1).collect();
        let c = count_clusters(&xs, &ys);
        assert_eq!(c.clusters, 3);
        assert_eq!(c.area, 7);
        assert_eq!(c.events, 8);
    }

    /// A burst starting at bin 12 (no event before) on a noisy floor, at
    /// several positions in the period (wrapping included).
    #[ebptv_macros::unit_test]
    fn leading_edge_finds_the_first_burst_events() {
        let n = 500;
        let mut s: u64 = 3;
        for shift in [0usize, 100, 480, 495] {
            let h: Vec<f64> = (0..n)
                .map(|i| {
                    s = s
                        .wrapping_mul(6364136223846793005)
                        .wrapping_add(1442695040888963407);
                    let noise = 160.0 + ((s >> 40) % 25) as f64 - 12.0;
                    let lat = ((i + n - shift) % n) as f64 + 0.5 - 12.0;
                    // Gamma(3, 2.5) density × 77k events
                    let burst = if lat > 0.0 {
                        77_000.0 * lat * lat * (-lat / 2.5).exp() / (2.0 * 2.5f64.powi(3))
                    } else {
                        0.0
                    };
                    noise + burst
                })
                .collect();
            let e = leading_edge(&h, 0.002);
            let want = (12.0 + shift as f64) % n as f64;
            let d = (e - want + 1.5 * n as f64) % n as f64 - 0.5 * n as f64;
            assert!(d.abs() < 1.5, "shift {shift}: edge {e}, want {want}");
        }
    }

    #[ebptv_macros::unit_test]
    fn latency_stats_of_gaussian_burst() {
        let n = 200;
        let h: Vec<f64> = (0..n)
            .map(|i| 10.0 + 1000.0 * (-0.5 * ((i as f64 + 0.5 - 50.0) / 10.0).powi(2)).exp())
            .collect();
        let s = latency_stats(&h);
        assert!((s.peak_us - 50.0).abs() < 0.6, "{}", s.peak_us);
        assert!((s.fwhm_us - 23.55).abs() < 1.0, "{}", s.fwhm_us);
        assert!(
            s.window95_us.0 > 25.0 && s.window95_us.1 < 75.0,
            "{:?}",
            s.window95_us
        );
        assert!((s.random_fraction - 2000.0 / h.iter().sum::<f64>()).abs() < 0.02);
    }
}
