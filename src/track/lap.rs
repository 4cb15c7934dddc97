//! Sparse linear assignment: each row (a track, a track end) takes at most
//! one column (a particle, a track start), minimising the total cost of the
//! chosen pairs plus a per-row cost for rows left unmatched.
//!
//! Candidate sets are sparse (a track sees a handful of particles inside its
//! search radius), so the bipartite candidate graph falls apart into small
//! connected components; each is solved exactly with the shortest-augmenting-
//! path Hungarian algorithm (Kuhn–Munkres with potentials, O(r²c)) on a
//! dense matrix padded with one "miss" column per row. Conflicts are thus
//! resolved by global cost, never by the order tracks were visited in.

use crate::cluster::UnionFind;

/// Cost used for pairs that are not candidates.
const FORBIDDEN: f64 = 1e15;

/// Solve the sparse assignment. `edges` are `(row, col, cost)` candidate
/// pairs (costs finite, non-negative); `miss_cost[row]` is paid when `row`
/// stays unmatched. Returns the column of each row, if any.
///
/// Most rows of a tracking step are alone in their component: none of
/// their candidate columns is anyone else's candidate. Such a row takes
/// its cheapest candidate when that beats its miss — exactly what
/// `assign_sparse_general` does for a one-row component (same
/// tie-break: the first of equal gains in edge order) — so they are solved
/// in one pass over the edges, and only the edges of rows that share a
/// column go through the component search and the Hungarian algorithm.
/// The result is identical to `assign_sparse_general` (tested).
pub(crate) fn assign_sparse(
    n_cols: usize,
    edges: &[(usize, usize, f64)],
    miss_cost: &[f64],
) -> Vec<Option<usize>> {
    let n_rows = miss_cost.len();
    let mut result = vec![None; n_rows];
    if edges.is_empty() {
        return result;
    }
    COLUMNS.with(|cell| {
        let mut col_rows = cell.borrow_mut();
        assign_sparse_in(&mut col_rows, n_cols, edges, miss_cost, &mut result);
    });
    result
}

thread_local! {
    /// Per-column scratch of [`assign_sparse`], all zero between calls:
    /// a call touches (and resets) only its edges' columns, so it costs
    /// O(edges + rows), not O(columns) — the backward extension solves a
    /// handful of rows against a frame of thousands of particles.
    static COLUMNS: std::cell::RefCell<Vec<u32>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// [`assign_sparse`] with its per-column scratch `col` (all zero on entry
/// and on return; grown to `n_cols`).
fn assign_sparse_in(
    col: &mut Vec<u32>,
    n_cols: usize,
    edges: &[(usize, usize, f64)],
    miss_cost: &[f64],
    result: &mut [Option<usize>],
) {
    let n_rows = miss_cost.len();
    if col.len() < n_cols {
        col.resize(n_cols, 0);
    }
    // Candidate rows per column (saturating: only "more than one" matters).
    for &(_, c, _) in edges {
        col[c] = col[c].saturating_add(1);
    }
    // A row touching a shared column (or one column twice) is not alone;
    // the others take their best positive gain (miss - cost), the first
    // one on ties. (A row found shared after a pick gets the general
    // solver's answer below.)
    let mut shared = vec![false; n_rows];
    let mut any_shared = false;
    let mut best_gain = vec![0.0f64; n_rows];
    for &(r, c, w) in edges {
        if col[c] > 1 {
            shared[r] = true;
            any_shared = true;
        } else {
            let gain = miss_cost[r] - w;
            if gain > best_gain[r] {
                best_gain[r] = gain;
                result[r] = Some(c);
            }
        }
    }
    for &(_, c, _) in edges {
        col[c] = 0;
    }
    if !any_shared {
        return;
    }
    // The shared rows' edges, their columns renumbered 0.. in order of
    // first appearance (`col` holds number + 1): the general solver then
    // sizes its tables by the columns in play. Components, their order of
    // rows and columns and so the assignment do not depend on the numbers.
    let mut cols: Vec<usize> = Vec::new();
    let rest: Vec<(usize, usize, f64)> = edges
        .iter()
        .filter(|e| shared[e.0])
        .map(|&(r, c, w)| {
            if col[c] == 0 {
                cols.push(c);
                col[c] = cols.len() as u32;
            }
            (r, col[c] as usize - 1, w)
        })
        .collect();
    for &c in &cols {
        col[c] = 0;
    }
    let solved = assign_sparse_general(cols.len(), &rest, miss_cost);
    for (r, c) in solved.into_iter().enumerate() {
        if shared[r] {
            result[r] = c.map(|j| cols[j]);
        }
    }
}

/// [`assign_sparse`] for any candidate graph: every connected component
/// solved on its own (one-row and one-column components by their best
/// pair, the others by [`hungarian_in`]). The fast path's solver for rows
/// that share columns, and the definition its tests compare it with.
pub(crate) fn assign_sparse_general(
    n_cols: usize,
    edges: &[(usize, usize, f64)],
    miss_cost: &[f64],
) -> Vec<Option<usize>> {
    let n_rows = miss_cost.len();
    let mut result = vec![None; n_rows];
    if edges.is_empty() {
        return result;
    }
    // Components over rows (0..n_rows) and columns (n_rows..).
    let mut uf = UnionFind::new(n_rows + n_cols);
    for &(r, c, _) in edges {
        uf.union(r as u32, (n_rows + c) as u32);
    }
    // Edge indices grouped by component (sorting by root keeps the edges of
    // a component in input order).
    let mut keyed: Vec<(u32, u32)> = edges
        .iter()
        .enumerate()
        .map(|(k, &(r, _, _))| (uf.find(r as u32), k as u32))
        .collect();
    keyed.sort_unstable();
    let mut row_local = vec![usize::MAX; n_rows];
    let mut col_local = vec![usize::MAX; n_cols];
    let mut comp: Vec<usize> = Vec::new();
    let (mut cost, mut sol, mut work) = (Vec::new(), Vec::new(), Hungarian::default());
    let mut rows = Vec::new();
    let mut cols = Vec::new();
    let mut s = 0;
    while s < keyed.len() {
        let mut e = s;
        while e < keyed.len() && keyed[e].0 == keyed[s].0 {
            e += 1;
        }
        comp.clear();
        comp.extend(keyed[s..e].iter().map(|&(_, k)| k as usize));
        s = e;
        rows.clear();
        cols.clear();
        for &k in &comp {
            let (r, c, _) = edges[k];
            if row_local[r] == usize::MAX {
                row_local[r] = rows.len();
                rows.push(r);
            }
            if col_local[c] == usize::MAX {
                col_local[c] = cols.len();
                cols.push(c);
            }
        }
        for &r in &rows {
            row_local[r] = usize::MAX;
        }
        for &c in &cols {
            col_local[c] = usize::MAX;
        }
        // One row or one column (most components): the optimum is the
        // cheapest pair when it beats that row's miss, with every other row
        // missing. Saving (miss - cost) is what a pair is worth.
        if rows.len() == 1 || cols.len() == 1 {
            let mut best: Option<(f64, usize)> = None;
            for &k in &comp {
                let (r, _, w) = edges[k];
                let gain = miss_cost[r] - w;
                if gain > 0.0 && best.is_none_or(|(g, _)| gain > g) {
                    best = Some((gain, k));
                }
            }
            if let Some((_, k)) = best {
                result[edges[k].0] = Some(edges[k].1);
            }
            continue;
        }
        for (i, &r) in rows.iter().enumerate() {
            row_local[r] = i;
        }
        for (j, &c) in cols.iter().enumerate() {
            col_local[c] = j;
        }
        let (nr, nc) = (rows.len(), cols.len());
        let width = nc + nr;
        cost.clear();
        cost.resize(nr * width, FORBIDDEN);
        for (i, &r) in rows.iter().enumerate() {
            for j in nc..width {
                cost[i * width + j] = miss_cost[r];
            }
        }
        for &k in &comp {
            let (r, c, w) = edges[k];
            let cell = &mut cost[row_local[r] * width + col_local[c]];
            *cell = cell.min(w);
        }
        hungarian_in(&mut work, &cost, nr, width, &mut sol);
        for (i, &j) in sol.iter().enumerate() {
            if j < nc && cost[i * width + j] < FORBIDDEN {
                result[rows[i]] = Some(cols[j]);
            }
        }
        for &r in &rows {
            row_local[r] = usize::MAX;
        }
        for &c in &cols {
            col_local[c] = usize::MAX;
        }
    }
    result
}

/// The work arrays of [`hungarian_in`], reused from one component to the
/// next.
#[derive(Default)]
struct Hungarian {
    u: Vec<f64>,
    v: Vec<f64>,
    p: Vec<usize>,
    way: Vec<usize>,
    minv: Vec<f64>,
    used: Vec<bool>,
}

/// Dense rectangular Hungarian algorithm (rows <= cols): the column of each
/// row in a minimum-cost perfect assignment of the rows, into
/// `row_to_col`; the work arrays in `h`.
fn hungarian_in(h: &mut Hungarian, cost: &[f64], n: usize, m: usize, row_to_col: &mut Vec<usize>) {
    assert!(n <= m && cost.len() == n * m);
    // 1-based potentials u (rows), v (cols); p[j] = row matched to col j.
    let reset = |a: &mut Vec<f64>, len: usize| {
        a.clear();
        a.resize(len, 0.0);
    };
    reset(&mut h.u, n + 1);
    reset(&mut h.v, m + 1);
    reset(&mut h.minv, m + 1);
    h.p.clear();
    h.p.resize(m + 1, 0);
    h.way.clear();
    h.way.resize(m + 1, 0);
    h.used.clear();
    h.used.resize(m + 1, false);
    let Hungarian {
        u,
        v,
        p,
        way,
        minv,
        used,
    } = h;
    for i in 1..=n {
        p[0] = i;
        let mut j0 = 0usize;
        minv.iter_mut().for_each(|x| *x = f64::INFINITY);
        used.iter_mut().for_each(|x| *x = false);
        loop {
            used[j0] = true;
            let i0 = p[j0];
            let mut delta = f64::INFINITY;
            let mut j1 = 0usize;
            for j in 1..=m {
                if !used[j] {
                    let cur = cost[(i0 - 1) * m + (j - 1)] - u[i0] - v[j];
                    if cur < minv[j] {
                        minv[j] = cur;
                        way[j] = j0;
                    }
                    if minv[j] < delta {
                        delta = minv[j];
                        j1 = j;
                    }
                }
            }
            for j in 0..=m {
                if used[j] {
                    u[p[j]] += delta;
                    v[j] -= delta;
                } else {
                    minv[j] -= delta;
                }
            }
            j0 = j1;
            if p[j0] == 0 {
                break;
            }
        }
        loop {
            let j1 = way[j0];
            p[j0] = p[j1];
            j0 = j1;
            if j0 == 0 {
                break;
            }
        }
    }
    row_to_col.clear();
    row_to_col.resize(n, 0);
    for j in 1..=m {
        if p[j] != 0 {
            row_to_col[p[j] - 1] = j - 1;
        }
    }
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    /// Exhaustive reference: the minimum total cost over every assignment.
    fn brute(n_cols: usize, edges: &[(usize, usize, f64)], miss: &[f64]) -> f64 {
        fn rec(r: usize, used: &mut Vec<bool>, edges: &[(usize, usize, f64)], miss: &[f64]) -> f64 {
            if r == miss.len() {
                return 0.0;
            }
            let mut best = miss[r] + rec(r + 1, used, edges, miss);
            for &(er, c, w) in edges {
                if er == r && !used[c] {
                    used[c] = true;
                    best = best.min(w + rec(r + 1, used, edges, miss));
                    used[c] = false;
                }
            }
            best
        }
        rec(0, &mut vec![false; n_cols], edges, miss)
    }

    fn total(sol: &[Option<usize>], edges: &[(usize, usize, f64)], miss: &[f64]) -> f64 {
        let mut used = std::collections::HashSet::new();
        sol.iter()
            .enumerate()
            .map(|(r, c)| match c {
                None => miss[r],
                Some(c) => {
                    assert!(used.insert(*c), "column used twice");
                    edges
                        .iter()
                        .filter(|e| e.0 == r && e.1 == *c)
                        .map(|e| e.2)
                        .fold(f64::INFINITY, f64::min)
                }
            })
            .sum()
    }

    #[ebptv_macros::unit_test]
    fn sparse_assignment_is_optimal() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(11);
        for _ in 0..2000 {
            let n_rows = rng.gen_range(0..7);
            let n_cols = rng.gen_range(1..7);
            let mut edges = Vec::new();
            for r in 0..n_rows {
                for c in 0..n_cols {
                    if rng.gen_bool(0.4) {
                        edges.push((r, c, rng.gen_range(0.0..1.0)));
                    }
                }
            }
            let miss: Vec<f64> = (0..n_rows).map(|_| rng.gen_range(0.2..1.2)).collect();
            let sol = assign_sparse(n_cols, &edges, &miss);
            let got = total(&sol, &edges, &miss);
            let want = brute(n_cols, &edges, &miss);
            assert!((got - want).abs() < 1e-9, "got {got}, optimum {want}");
        }
    }

    /// The lone-row fast path must give exactly the reference's
    /// assignment, ties included: costs from a small set of values (many
    /// equal gains), duplicate edges, rows without candidates, sparse
    /// scenes (mostly lone rows) and dense ones (mostly shared columns).
    #[ebptv_macros::unit_test]
    fn fast_path_equals_reference() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(23);
        let mut lone_rows = 0;
        for round in 0..3000 {
            let n_rows = rng.gen_range(0..40);
            let n_cols = rng.gen_range(1..60);
            let density = [0.01, 0.05, 0.2][round % 3];
            let mut edges = Vec::new();
            for r in 0..n_rows {
                for c in 0..n_cols {
                    if rng.gen_bool(density) {
                        edges.push((r, c, rng.gen_range(0..8) as f64 * 0.25));
                        if rng.gen_bool(0.05) {
                            edges.push((r, c, rng.gen_range(0..8) as f64 * 0.25));
                        }
                    }
                }
            }
            // Rows visited in any order (as the repair's are).
            if round % 2 == 1 {
                for i in (1..edges.len()).rev() {
                    edges.swap(i, rng.gen_range(0..=i));
                }
            }
            let miss: Vec<f64> = (0..n_rows)
                .map(|_| rng.gen_range(1..6) as f64 * 0.25)
                .collect();
            let fast = assign_sparse(n_cols, &edges, &miss);
            assert_eq!(fast, assign_sparse_general(n_cols, &edges, &miss));
            let mut deg = vec![0; n_cols];
            edges.iter().for_each(|e| deg[e.1] += 1);
            lone_rows += (0..n_rows)
                .filter(|&r| {
                    edges.iter().any(|e| e.0 == r)
                        && edges.iter().all(|e| e.0 != r || deg[e.1] == 1)
                })
                .count();
        }
        assert!(
            lone_rows > 2_000,
            "{lone_rows} lone rows: the fast path was hardly used"
        );
    }

    #[ebptv_macros::unit_test]
    fn greedy_would_fail_here() {
        // Row 0 grabs column 0 first-come; the optimum gives it column 1.
        let edges = [(0, 0, 0.1), (0, 1, 0.2), (1, 0, 0.15)];
        let sol = assign_sparse(2, &edges, &[1.0, 1.0]);
        assert_eq!(sol, vec![Some(1), Some(0)]);
    }
}
