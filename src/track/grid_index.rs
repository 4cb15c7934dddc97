//! A uniform-grid index for the radius queries of the tracker.
//!
//! Every pulse the tracker asks, for each active track, which of the new
//! pulse's particles lie within a small radius (1.5–3 px for running tracks,
//! up to `max_disp` for new ones) of a predicted position. The particles are
//! spread nearly uniformly over the frame, so a grid of square cells a few
//! pixels wide, filled by a counting sort, answers each query by scanning the
//! handful of cells the disc overlaps: O(n) to build, O(1) per query, and the
//! buffers are reused from pulse to pulse (no allocation in steady state).
//! A k-d tree rebuilt every pulse did the same work with an O(n log n) build
//! and a tree walk per query; the brute-force scan in the tests is the oracle
//! both must match.

/// Points of one pulse, bucketed by grid cell.
#[derive(Debug, Clone, Default)]
pub(crate) struct GridIndex {
    /// Requested cell size (px); 0 (the `Default`) means 4 px.
    base_cell: f64,
    /// Cell size of the current build and its inverse.
    cell: f64,
    inv_cell: f64,
    x0: f64,
    y0: f64,
    nx: usize,
    ny: usize,
    /// `start[c]..start[c + 1]` are the slots of cell `c`.
    start: Vec<u32>,
    /// Point index, x and y per slot, in cell order.
    item: Vec<u32>,
    xs: Vec<f64>,
    ys: Vec<f64>,
    cell_of: Vec<u32>,
}

impl GridIndex {
    #[cfg(feature = "testkit")]
    /// An empty index whose cells are about `cell` px wide (enlarged when the
    /// points are few and spread far, so the grid never has many more cells
    /// than points).
    pub(crate) fn new(cell: f64) -> Self {
        GridIndex {
            base_cell: cell,
            ..Default::default()
        }
    }

    #[cfg(feature = "testkit")]
    /// Number of points indexed.
    pub(crate) fn len(&self) -> usize {
        self.item.len()
    }

    /// Index the points `(x, y)` (finite), numbered in iteration order.
    pub(crate) fn rebuild(&mut self, points: impl Iterator<Item = (f64, f64)> + Clone) {
        let (mut x0, mut y0, mut x1, mut y1) = (f64::MAX, f64::MAX, f64::MIN, f64::MIN);
        let mut n = 0usize;
        for (x, y) in points.clone() {
            x0 = x0.min(x);
            y0 = y0.min(y);
            x1 = x1.max(x);
            y1 = y1.max(y);
            n += 1;
        }
        self.item.clear();
        self.xs.clear();
        self.ys.clear();
        self.cell_of.clear();
        if n == 0 {
            self.nx = 0;
            self.ny = 0;
            self.start.clear();
            return;
        }
        // Cells of the requested size unless that makes far more cells than
        // points (sparse or far-flung points): then grow them.
        let mut cell = if self.base_cell.is_finite() && self.base_cell > 0.0 {
            self.base_cell
        } else {
            4.0
        };
        let max_cells = 4 * n + 64;
        loop {
            let nx = ((x1 - x0) / cell).floor() as usize + 1;
            let ny = ((y1 - y0) / cell).floor() as usize + 1;
            if nx.saturating_mul(ny) <= max_cells {
                self.nx = nx;
                self.ny = ny;
                break;
            }
            cell *= 2.0;
        }
        self.x0 = x0;
        self.y0 = y0;
        let inv = 1.0 / cell;
        let cells = self.nx * self.ny;
        self.start.clear();
        self.start.resize(cells + 1, 0);
        for (x, y) in points.clone() {
            let cx = (((x - x0) * inv) as usize).min(self.nx - 1);
            let cy = (((y - y0) * inv) as usize).min(self.ny - 1);
            let c = (cy * self.nx + cx) as u32;
            self.cell_of.push(c);
            self.start[c as usize + 1] += 1;
        }
        for c in 0..cells {
            self.start[c + 1] += self.start[c];
        }
        self.item.resize(n, 0);
        self.xs.resize(n, 0.0);
        self.ys.resize(n, 0.0);
        // Fill each cell in point order (stable), using `start` as cursors
        // and shifting it back afterwards.
        for (i, (x, y)) in points.enumerate() {
            let c = self.cell_of[i] as usize;
            let slot = self.start[c] as usize;
            self.item[slot] = i as u32;
            self.xs[slot] = x;
            self.ys[slot] = y;
            self.start[c] += 1;
        }
        for c in (1..=cells).rev() {
            self.start[c] = self.start[c - 1];
        }
        self.start[0] = 0;
        self.cell = cell;
        self.inv_cell = inv;
    }

    /// Append to `out` every point within `r` of `(x, y)` (inclusive) as
    /// `(index, squared distance)`, sorted by index.
    pub(crate) fn within(&self, x: f64, y: f64, r: f64, out: &mut Vec<(u32, f64)>) {
        if self.item.is_empty() || !(r >= 0.0) {
            return;
        }
        let base = out.len();
        let inv = self.inv_cell;
        let r2 = r * r;
        // The cell range is widened by a hair so that rounding can never
        // leave out a point the exact distance test accepts.
        // Cell indices by truncating non-negative values (= floor there;
        // `f64::floor` is a libm call on baseline x86-64, 4 per query).
        let lo = |v: f64, o: f64| ((v - r - o) * inv - 1e-9).max(0.0) as usize;
        let hi = |v: f64, o: f64| (v + r - o) * inv + 1e-9;
        let (hx, hy) = (hi(x, self.x0), hi(y, self.y0));
        if !(hx >= 0.0 && hy >= 0.0) {
            return; // the disc ends before the first cell
        }
        let (cx0, cx1) = (lo(x, self.x0), (hx as usize).min(self.nx - 1));
        let (cy0, cy1) = (lo(y, self.y0), (hy as usize).min(self.ny - 1));
        if cx0 > cx1 || cy0 > cy1 {
            return;
        }
        for cy in cy0..=cy1 {
            let row = cy * self.nx;
            let (a, b) = (
                self.start[row + cx0] as usize,
                self.start[row + cx1 + 1] as usize,
            );
            for s in a..b {
                let d2 = (self.xs[s] - x).powi(2) + (self.ys[s] - y).powi(2);
                if d2 <= r2 {
                    out.push((self.item[s], d2));
                }
            }
        }
        // A single cell holds its points in index order already.
        if cy0 != cy1 || cx0 != cx1 {
            out[base..].sort_unstable_by_key(|e| e.0);
        }
    }
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    fn brute(pts: &[(f64, f64)], x: f64, y: f64, r: f64) -> Vec<(u32, f64)> {
        pts.iter()
            .enumerate()
            .filter_map(|(i, p)| {
                let d2 = (p.0 - x).powi(2) + (p.1 - y).powi(2);
                (d2 <= r * r).then_some((i as u32, d2))
            })
            .collect()
    }

    #[ebptv_macros::unit_test]
    fn matches_brute_force() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(5);
        let mut g = GridIndex::new(4.0);
        let mut out = Vec::new();
        for round in 0..200 {
            let n = rng.gen_range(0..300);
            let span = if round % 3 == 0 { 5000.0 } else { 200.0 };
            let mut pts: Vec<(f64, f64)> = (0..n)
                .map(|_| (rng.gen_range(-10.0..span), rng.gen_range(0.0..span / 2.0)))
                .collect();
            if n > 3 {
                pts[1] = pts[0]; // duplicates
                pts[2] = (pts[0].0 + 3.0, pts[0].1); // exactly on a radius
            }
            g.rebuild(pts.iter().copied());
            assert_eq!(g.len(), n);
            for _ in 0..50 {
                let (x, y, r) = if n > 0 && rng.gen_bool(0.3) {
                    (pts[0].0, pts[0].1, 3.0)
                } else {
                    (
                        rng.gen_range(-50.0..span + 50.0),
                        rng.gen_range(-50.0..span),
                        rng.gen_range(0.0..20.0),
                    )
                };
                out.clear();
                g.within(x, y, r, &mut out);
                assert_eq!(out, brute(&pts, x, y, r));
            }
        }
    }

    #[ebptv_macros::unit_test]
    fn masked_queries_equal_a_grid_of_the_unmasked_points() {
        // The backward extension searches a frame's grid over all its
        // particles, skipping the used ones, for what a grid over the
        // unused ones gives (their indices mapped back).
        let mut rng = rand_pcg::Pcg64::seed_from_u64(9);
        let (mut all, mut rest) = (GridIndex::default(), GridIndex::default());
        let (mut a, mut b) = (Vec::new(), Vec::new());
        for _ in 0..50 {
            let n = rng.gen_range(1..400);
            let pts: Vec<(f64, f64)> = (0..n)
                .map(|_| (rng.gen_range(0.0..300.0), rng.gen_range(0.0..200.0)))
                .collect();
            let used: Vec<bool> = (0..n).map(|_| rng.gen_bool(0.8)).collect();
            let idx: Vec<usize> = (0..n).filter(|&i| !used[i]).collect();
            all.rebuild(pts.iter().copied());
            rest.rebuild(idx.iter().map(|&i| pts[i]));
            for _ in 0..40 {
                let (x, y, r) = (
                    rng.gen_range(-10.0..310.0),
                    rng.gen_range(-10.0..210.0),
                    rng.gen_range(0.0..40.0),
                );
                a.clear();
                b.clear();
                all.within(x, y, r, &mut a);
                rest.within(x, y, r, &mut b);
                a.retain(|&(j, _)| !used[j as usize]);
                let b: Vec<(u32, f64)> = b
                    .iter()
                    .map(|&(j, d2)| (idx[j as usize] as u32, d2))
                    .collect();
                assert_eq!(a.len(), b.len());
                for (p, q) in a.iter().zip(&b) {
                    assert_eq!((p.0, p.1.to_bits()), (q.0, q.1.to_bits()));
                }
            }
        }
    }
}
