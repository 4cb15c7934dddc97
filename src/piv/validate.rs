//! Outlier detection and replacement: the normalised median test
//! (Westerweel & Scarano, Exp. Fluids 39:1096, 2005).
//!
//! For each vector, the 8 neighbours (3×3 block without the centre) give a
//! median `U_m` and the median of their residuals `r_m = median|U_i − U_m|`;
//! the vector fails when `|U_0 − U_m| / (r_m + ε) > threshold`, tested for
//! u and v separately. `ε` (0.1 px, the typical random error) keeps the test
//! from flagging everything in a perfectly uniform flow, where `r_m ≈ 0`.
//! Failed vectors (and vectors without a usable correlation peak) are
//! replaced by the median of their valid neighbours; a vector with no valid
//! neighbour keeps NaN. Masked nodes are never tested nor used. Border
//! nodes are tested (and replaced) against linear extrapolations from the
//! two inner nodes in each direction instead of the biased one-sided 3×3
//! neighbourhood (see `border_extrapolations`).

/// Validity flags (bit set).
pub(crate) mod flag {
    /// Valid: measured and passed the median test.
    pub(crate) const VALID: u8 = 0;
    /// Failed the normalised median test; value replaced.
    pub(crate) const OUTLIER: u8 = 1;
    /// No usable correlation peak (empty windows, peak at the border).
    pub(crate) const NO_PEAK: u8 = 2;
    /// Node inside the mask: no value.
    pub(crate) const MASKED: u8 = 4;
    /// Value replaced by interpolation from neighbours.
    pub(crate) const REPLACED: u8 = 8;
}

/// Options of the normalised median test.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MedianTest {
    /// A vector fails when its normalised residual exceeds this (default 3).
    pub threshold: f64,
    /// ε added to the neighbours' median residual (px, default 0.1): the
    /// acceptable random error, so a uniform flow is not all flagged.
    pub epsilon: f64,
}

impl Default for MedianTest {
    fn default() -> Self {
        MedianTest {
            threshold: 3.0,
            epsilon: 0.1,
        }
    }
}

fn median(v: &mut [f64]) -> f64 {
    v.sort_by(|a, b| a.partial_cmp(b).unwrap());
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// Up to 8 values on the stack: a node has at most 8 neighbours (or
/// extrapolation directions), and the test runs at every node of every
/// pass — heap vectors there cost more than the medians.
#[derive(Clone, Copy, Default)]
struct Vals {
    v: [f64; 8],
    n: usize,
}

impl Extend<f64> for Vals {
    fn extend<I: IntoIterator<Item = f64>>(&mut self, it: I) {
        for x in it {
            self.v[self.n] = x;
            self.n += 1;
        }
    }
}

impl std::ops::Deref for Vals {
    type Target = [f64];
    fn deref(&self) -> &[f64] {
        &self.v[..self.n]
    }
}

impl std::ops::DerefMut for Vals {
    fn deref_mut(&mut self) -> &mut [f64] {
        &mut self.v[..self.n]
    }
}

/// The eight directions to a node's neighbours.
const DIRECTIONS: [(i64, i64); 8] = [
    (-1, -1),
    (0, -1),
    (1, -1),
    (-1, 0),
    (1, 0),
    (-1, 1),
    (0, 1),
    (1, 1),
];

/// Index of node (i, j) when it lies on the `nx × ny` grid and holds a
/// usable, finite vector.
#[allow(clippy::too_many_arguments)]
#[inline]
fn usable_node(
    u: &[f64],
    v: &[f64],
    flags: &[u8],
    nx: usize,
    ny: usize,
    i: i64,
    j: i64,
    usable: &impl Fn(u8) -> bool,
) -> Option<usize> {
    if i < 0 || j < 0 || i >= nx as i64 || j >= ny as i64 {
        return None;
    }
    let k = j as usize * nx + i as usize;
    (usable(flags[k]) && u[k].is_finite() && v[k].is_finite()).then_some(k)
}

/// Neighbour values (u, v) of node (i, j) whose flags pass `usable`.
#[allow(clippy::too_many_arguments)]
fn neighbours(
    u: &[f64],
    v: &[f64],
    flags: &[u8],
    nx: usize,
    ny: usize,
    i: usize,
    j: usize,
    usable: impl Fn(u8) -> bool,
) -> (Vals, Vals) {
    let (i, j) = (i as i64, j as i64);
    DIRECTIONS
        .iter()
        .filter_map(|&(di, dj)| usable_node(u, v, flags, nx, ny, i + di, j + dj, &usable))
        .map(|k| (u[k], v[k]))
        .unzip()
}

/// Reference values for a node on the grid border: linear extrapolations
/// `2·U(node+o) − U(node+2o)` along every direction `o` in which both nodes
/// exist and are usable. The plain 3×3 median is biased at a border in a
/// velocity gradient (most neighbours lie on the inner side), so it flags
/// correct wall-side vectors of a boundary layer; the extrapolations are
/// exact for a linear field.
#[allow(clippy::too_many_arguments)]
fn border_extrapolations(
    u: &[f64],
    v: &[f64],
    flags: &[u8],
    nx: usize,
    ny: usize,
    i: usize,
    j: usize,
    usable: impl Fn(u8) -> bool,
) -> (Vals, Vals) {
    let (i, j) = (i as i64, j as i64);
    DIRECTIONS
        .iter()
        .filter_map(|&(di, dj)| {
            let k1 = usable_node(u, v, flags, nx, ny, i + di, j + dj, &usable)?;
            let k2 = usable_node(u, v, flags, nx, ny, i + 2 * di, j + 2 * dj, &usable)?;
            Some((2.0 * u[k1] - u[k2], 2.0 * v[k1] - v[k2]))
        })
        .unzip()
}

#[inline]
fn on_border(nx: usize, ny: usize, i: usize, j: usize) -> bool {
    nx >= 3 && ny >= 3 && (i == 0 || j == 0 || i == nx - 1 || j == ny - 1)
}

/// Flag outliers (`flag::OUTLIER`) on a `nx × ny` node grid. Nodes already
/// flagged NO_PEAK or MASKED are skipped and not used as neighbours. Returns
/// the number of new outliers. Nodes with fewer than 3 usable neighbours are
/// left untested.
pub(crate) fn normalized_median_test(
    u: &[f64],
    v: &[f64],
    flags: &mut [u8],
    nx: usize,
    ny: usize,
    test: MedianTest,
) -> usize {
    let bad = flag::NO_PEAK | flag::MASKED;
    let mut outliers = Vec::new();
    for j in 0..ny {
        for i in 0..nx {
            let k = j * nx + i;
            if flags[k] & bad != 0 {
                continue;
            }
            let usable = |f: u8| f & bad == 0;
            let (mut nu, mut nv) = if on_border(nx, ny, i, j) {
                border_extrapolations(u, v, flags, nx, ny, i, j, usable)
            } else {
                neighbours(u, v, flags, nx, ny, i, j, usable)
            };
            if nu.len() < 3 {
                continue;
            }
            let residual = |vals: &mut [f64], x0: f64| -> f64 {
                let m = median(vals);
                let mut r = Vals::default();
                r.extend(vals.iter().map(|x| (x - m).abs()));
                let rm = median(&mut r);
                (x0 - m).abs() / (rm + test.epsilon)
            };
            let ru = residual(&mut nu, u[k]);
            let rv = residual(&mut nv, v[k]);
            if !(ru <= test.threshold && rv <= test.threshold) {
                outliers.push(k);
            }
        }
    }
    for &k in &outliers {
        flags[k] |= flag::OUTLIER;
    }
    outliers.len()
}

/// Replace OUTLIER and NO_PEAK vectors by the median of their valid
/// neighbours, repeating so that holes fill from their rims inwards
/// (bounded number of sweeps). Replaced nodes get `flag::REPLACED`.
pub(crate) fn replace_invalid(
    u: &mut [f64],
    v: &mut [f64],
    flags: &mut [u8],
    nx: usize,
    ny: usize,
) {
    let invalid = flag::OUTLIER | flag::NO_PEAK;
    for _sweep in 0..(nx.max(ny)) {
        let mut changed = Vec::new();
        let mut remaining = 0usize;
        for j in 0..ny {
            for i in 0..nx {
                let k = j * nx + i;
                if flags[k] & invalid == 0 || flags[k] & (flag::REPLACED | flag::MASKED) != 0 {
                    continue;
                }
                // Neighbours replaced in an earlier sweep count as usable.
                let usable =
                    |f: u8| f & flag::MASKED == 0 && (f & invalid == 0 || f & flag::REPLACED != 0);
                let (mut nu, mut nv) = if on_border(nx, ny, i, j) {
                    let e = border_extrapolations(u, v, flags, nx, ny, i, j, usable);
                    if e.0.len() >= 2 {
                        e
                    } else {
                        neighbours(u, v, flags, nx, ny, i, j, usable)
                    }
                } else {
                    neighbours(u, v, flags, nx, ny, i, j, usable)
                };
                if nu.is_empty() {
                    remaining += 1;
                    continue;
                }
                changed.push((k, median(&mut nu), median(&mut nv)));
            }
        }
        if changed.is_empty() {
            break;
        }
        for (k, mu, mv) in changed {
            u[k] = mu;
            v[k] = mv;
            flags[k] |= flag::REPLACED;
        }
        if remaining == 0 {
            break;
        }
    }
    // Invalid vectors nothing could replace carry no value.
    for k in 0..nx * ny {
        if flags[k] & invalid != 0 && flags[k] & flag::REPLACED == 0 {
            u[k] = f64::NAN;
            v[k] = f64::NAN;
        }
    }
}

/// True when the vector is a genuine, validated measurement.
#[inline]
pub(crate) fn is_valid(f: u8) -> bool {
    f == flag::VALID
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;

    #[ebptv_macros::unit_test]
    fn single_outlier_is_found_and_replaced() {
        let (nx, ny) = (5, 5);
        let mut u: Vec<f64> = (0..25).map(|k| 1.0 + 0.01 * (k % 5) as f64).collect();
        let mut v = vec![-0.5; 25];
        u[12] = 4.0;
        let mut f = vec![0u8; 25];
        let n = normalized_median_test(&u, &v, &mut f, nx, ny, MedianTest::default());
        assert_eq!(n, 1);
        assert_eq!(f[12], flag::OUTLIER);
        replace_invalid(&mut u, &mut v, &mut f, nx, ny);
        assert!((u[12] - 1.02).abs() < 0.011, "{}", u[12]);
        assert_eq!(f[12], flag::OUTLIER | flag::REPLACED);
        assert!(f.iter().enumerate().all(|(k, &x)| k == 12 || x == 0));
    }

    #[ebptv_macros::unit_test]
    fn smooth_gradient_passes() {
        let (nx, ny) = (8, 6);
        let u: Vec<f64> = (0..nx * ny).map(|k| 0.1 * (k % nx) as f64).collect();
        let v: Vec<f64> = (0..nx * ny).map(|k| -0.1 * (k / nx) as f64).collect();
        let mut f = vec![0u8; nx * ny];
        assert_eq!(
            normalized_median_test(&u, &v, &mut f, nx, ny, MedianTest::default()),
            0
        );
        // A steep gradient (a wall) passes at the border too.
        let u: Vec<f64> = (0..nx * ny).map(|k| 3.0 * (k / nx) as f64).collect();
        let mut f = vec![0u8; nx * ny];
        assert_eq!(
            normalized_median_test(&u, &v, &mut f, nx, ny, MedianTest::default()),
            0
        );
        // ... while an outlier on the border is still caught.
        let mut u = u;
        u[2] = 10.0;
        assert_eq!(
            normalized_median_test(&u, &v, &mut f, nx, ny, MedianTest::default()),
            1
        );
        assert_eq!(f[2], flag::OUTLIER);
    }

    #[ebptv_macros::unit_test]
    fn hole_fills_from_rim() {
        let (nx, ny) = (6, 6);
        let mut u = vec![2.0; 36];
        let mut v = vec![1.0; 36];
        let mut f = vec![0u8; 36];
        for &k in &[14usize, 15, 20, 21] {
            f[k] = flag::NO_PEAK;
            u[k] = f64::NAN;
            v[k] = f64::NAN;
        }
        replace_invalid(&mut u, &mut v, &mut f, nx, ny);
        for &k in &[14usize, 15, 20, 21] {
            assert_eq!(u[k], 2.0);
            assert_eq!(f[k], flag::NO_PEAK | flag::REPLACED);
        }
    }
}
