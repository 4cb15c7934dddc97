//! Per-pulse clustering of events into particles with a k-d tree (kiddo).
//!
//! # Why clusters
//! One light pulse makes each particle in the sheet fire one to a few events
//! (1.3 in air, ~2 in water) on the pixels its 1.2–1.5 px image covers. The
//! events of one pulse are therefore a sparse point cloud in which a particle
//! is a small group of events on adjacent pixels. Clustering them directly,
//! without building a pseudo-image, gives a sub-pixel position per particle
//! and costs time proportional to the number of events, not to the sensor
//! size.
//!
//! # Algorithm
//! 1. Select events: ON polarity only by default (the biases of the paper's
//!    camera are tuned for ON events), minus a hot-pixel mask.
//! 2. Collapse events to distinct pixels (sort by pixel key), keeping the
//!    event count and the earliest time of each pixel. Repeated events on one
//!    pixel are at distance zero from each other: joining them first makes
//!    the tree small and free of duplicate points.
//! 3. Find the pixel pairs within the join radius and join them with
//!    union-find. Two implementations: a row sweep over the sorted pixels
//!    (default: integer coordinates make the neighbourhood a few rows of
//!    a sorted array) and a kiddo `ImmutableKdTree` with radius queries
//!    (the general path). Two pixels are joined when their squared integer distance is at
//!    most `floor(radius²)`, an exact criterion on integer coordinates that
//!    the brute-force oracle in the tests reproduces bit for bit.
//! 4. Each connected component is a particle: centroid weighted by events
//!    per pixel, event and pixel counts, bounding-box extent and the latency
//!    of its first event after the pulse start. Components outside
//!    `[min_events, max_events]` are dropped (single-event noise can be kept
//!    or not; flares and hot spots exceed `max_events`).
//!
//! Pulses are independent, so [`cluster_pulses`] clusters a batch of pulses
//! in parallel with rayon; the CLI feeds it batches while streaming through
//! the recording.

use std::collections::HashSet;

use kiddo::immutable::float::kdtree::ImmutableKdTree;
use kiddo::SquaredEuclidean;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::error::{Error, Result};
use crate::events::ON;
use crate::pulses::PulseEvents;

/// One particle detected in one pulse.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Particle {
    /// Index of the pulse the particle was seen in.
    pub pulse: i64,
    /// Time of the pulse start the particle belongs to (µs).
    pub t_us: f64,
    /// Sub-pixel centroid (px).
    pub x: f64,
    /// Sub-pixel centroid, y (px).
    pub y: f64,
    /// Events in the particle image.
    pub n_events: u32,
    /// Number of distinct pixels.
    pub n_pixels: u32,
    /// Bounding-box extent (px) along x and y (max - min + 1).
    pub extent_x: f32,
    /// Bounding-box extent along y (px, max - min + 1).
    pub extent_y: f32,
    /// Latency of the first event after the pulse start (µs).
    pub first_latency_us: f32,
}

/// Options of the clustering. In a TOML file (`ebptv track --params`,
/// table `[cluster]`) any key left out takes its default.
#[derive(Debug, Clone, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ClusterParams {
    /// Events on pixels whose centres are at most this far apart (px) join
    /// one cluster.
    pub radius: f64,
    /// Use ON events only (default, as in the paper).
    pub on_only: bool,
    /// Smallest cluster kept (events).
    pub min_events: u32,
    /// Largest cluster kept (events); larger ones are flares or hot spots.
    pub max_events: u32,
    /// Pixels whose events are ignored, as `(x, y)` (written sorted).
    #[serde(serialize_with = "sorted_pixels")]
    pub hot_pixels: HashSet<(u16, u16)>,
    /// Regions that are not flow, whose events are ignored like those of
    /// hot pixels (`ebptv track --mask`, `run.mask`; not part of the
    /// `[cluster]` table).
    #[serde(skip)]
    pub mask: Option<std::sync::Arc<crate::calib::PixelMask>>,
    /// Clusters spanning at least this many pixels along x or y are split
    /// in two along their principal axis (`split_wide_clusters`); 0 = never.
    /// One particle image of 1–1.5 px puts its 1–4 events on at most 2
    /// adjacent pixels per axis, so a span of 3 is nearly always two
    /// particles (or a particle and a noise event) closer than the join
    /// radius.
    pub split_extent: u32,
    /// How neighbouring pixels are found (identical clusters either way).
    pub neighbour_search: NeighbourSearch,
}

/// The neighbour search of step 3 (module docs). Both give exactly the
/// brute-force oracle's clusters (tests/cluster_oracle.rs); they differ in
/// speed only.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum NeighbourSearch {
    /// Row sweep over the (y, x)-sorted pixels (`pixel_labels`): integer
    /// coordinates make the neighbourhood a few rows of a sorted array;
    /// ~3.5× faster than the tree on particle data.
    #[default]
    RowSweep,
    /// kiddo k-d tree with radius queries (`pixel_labels_kdtree`).
    KdTree,
}

fn default_split_extent() -> u32 {
    3
}

/// The hot pixels in (x, y) order, so that a written file does not depend
/// on the set's hashing.
fn sorted_pixels<S: serde::Serializer>(
    set: &HashSet<(u16, u16)>,
    s: S,
) -> std::result::Result<S::Ok, S::Error> {
    let mut v: Vec<&(u16, u16)> = set.iter().collect();
    v.sort_unstable();
    serde::Serialize::serialize(&v, s)
}

impl Default for ClusterParams {
    fn default() -> Self {
        ClusterParams {
            radius: 1.5,
            on_only: true,
            min_events: 1,
            max_events: 64,
            hot_pixels: HashSet::new(),
            mask: None,
            split_extent: default_split_extent(),
            neighbour_search: NeighbourSearch::default(),
        }
    }
}

impl ClusterParams {
    /// The join radius for particle images of the given diameter (px): one
    /// diameter, but never below the 8-neighbourhood (√2).
    pub(crate) fn radius_for_image_diameter(diameter_px: f64) -> f64 {
        diameter_px.max(std::f64::consts::SQRT_2)
    }

    /// Check the parameters; errors name the parameter.
    pub(crate) fn validate(&self) -> Result<()> {
        if !(self.radius.is_finite() && self.radius > 0.0) {
            return Err(Error::param(
                "radius",
                format!("must be a positive number of pixels, got {}", self.radius),
            ));
        }
        if self.radius > 64.0 {
            return Err(Error::param(
                "radius",
                format!(
                    "{} px is far larger than a particle image (1-3 px)",
                    self.radius
                ),
            ));
        }
        if self.min_events == 0 || self.min_events > self.max_events {
            return Err(Error::param(
                "min_events/max_events",
                format!(
                    "need 1 <= min_events <= max_events, got {}..{}",
                    self.min_events, self.max_events
                ),
            ));
        }
        Ok(())
    }

    /// Largest squared integer pixel distance that joins two pixels.
    pub(crate) fn max_d2(&self) -> i64 {
        (self.radius * self.radius).floor() as i64
    }
}

/// A distinct pixel of one pulse with its events folded in.
#[derive(Debug, Clone, Copy, PartialEq)]
#[ebptv_macros::testkit]
pub(crate) struct PixelHits {
    /// Pixel column (px).
    pub x: u16,
    /// Pixel row (px).
    pub y: u16,
    /// Selected events of the pulse at this pixel.
    pub count: u32,
    /// Earliest event time at this pixel (µs, sensor clock).
    pub first_t: i64,
}

/// The selected events of a pulse folded onto distinct pixels, sorted by
/// (y, x).
///
/// The events are grouped by pixel with a two-pass counting sort (by x,
/// then stably by y: O(n + width + height)) instead of a comparison sort,
/// which was ~60 % of this function and a third of the clustering; small
/// or very spread-out pulses, where the histograms would cost more than
/// sorting, take the comparison sort. Both give exactly
/// `pulse_pixels_reference`'s pixels (tested): the earliest time of a
/// pixel is taken as a minimum, not from the order.
#[ebptv_macros::testkit]
pub(crate) fn pulse_pixels(pulse: &PulseEvents, params: &ClusterParams) -> Vec<PixelHits> {
    let (mut keyed, (x_lo, x_hi, y_lo, y_hi)) = selected_events(pulse, params);
    let n = keyed.len();
    if n == 0 {
        return Vec::new();
    }
    let (nx, ny) = ((x_hi - x_lo) as usize + 1, (y_hi - y_lo) as usize + 1);
    if n < COUNTING_SORT_MIN_EVENTS || nx + ny > 2 * n {
        keyed.sort_unstable();
        return fold_pixels(&keyed);
    }
    // Pass 1 by x into `tmp`, pass 2 stably by y back into `keyed`: sorted
    // by (y, x), events of one pixel in input order. `tmp` is every slot
    // overwritten, so it is a per-thread buffer kept between pulses rather
    // than a fresh zeroed one (zeroing it was ~15 % of this function).
    SORT_SCRATCH.with(|scratch| {
        let mut tmp = scratch.borrow_mut();
        if tmp.len() < n {
            tmp.resize(n, (0, 0));
        }
        let tmp = &mut tmp[..n];
        let mut count = vec![0u32; nx.max(ny) + 1];
        counting_pass(&keyed, tmp, &mut count[..nx + 1], |k| {
            ((k & 0xffff) - x_lo) as usize
        });
        count.iter_mut().for_each(|c| *c = 0);
        counting_pass(tmp, &mut keyed, &mut count[..ny + 1], |k| {
            ((k >> 16) - y_lo) as usize
        });
    });
    fold_pixels(&keyed)
}

thread_local! {
    /// [`pulse_pixels`]'s intermediate buffer (the largest pulse's events
    /// seen on this thread).
    static SORT_SCRATCH: std::cell::RefCell<Vec<(u32, i64)>> =
        const { std::cell::RefCell::new(Vec::new()) };
}

/// Pulses with fewer selected events than this sort by comparison.
const COUNTING_SORT_MIN_EVENTS: usize = 64;

/// The selected events as (pixel key `y << 16 | x`, time), in input order,
/// and the (x, y) range they span.
#[allow(clippy::type_complexity)]
fn selected_events(
    pulse: &PulseEvents,
    params: &ClusterParams,
) -> (Vec<(u32, i64)>, (u32, u32, u32, u32)) {
    let ev = &pulse.events;
    let mut keyed: Vec<(u32, i64)> = Vec::with_capacity(ev.len());
    let use_mask = !params.hot_pixels.is_empty();
    let (mut x_lo, mut x_hi, mut y_lo, mut y_hi) = (u32::MAX, 0u32, u32::MAX, 0u32);
    for i in 0..ev.len() {
        if params.on_only && ev.p[i] != ON {
            continue;
        }
        if use_mask && params.hot_pixels.contains(&(ev.x[i], ev.y[i])) {
            continue;
        }
        if let Some(m) = &params.mask {
            if m.is_masked_px(ev.x[i] as u32, ev.y[i] as u32) {
                continue;
            }
        }
        let (x, y) = (ev.x[i] as u32, ev.y[i] as u32);
        x_lo = x_lo.min(x);
        x_hi = x_hi.max(x);
        y_lo = y_lo.min(y);
        y_hi = y_hi.max(y);
        keyed.push(((y << 16) | x, ev.t[i]));
    }
    (keyed, (x_lo, x_hi, y_lo, y_hi))
}

/// One stable counting-sort pass of `src` into `dst` by `bucket(key)`
/// (`count` zeroed, one longer than the number of buckets).
fn counting_pass(
    src: &[(u32, i64)],
    dst: &mut [(u32, i64)],
    count: &mut [u32],
    bucket: impl Fn(u32) -> usize,
) {
    for e in src {
        count[bucket(e.0) + 1] += 1;
    }
    for b in 1..count.len() {
        count[b] += count[b - 1];
    }
    for &e in src {
        let slot = &mut count[bucket(e.0)];
        dst[*slot as usize] = e;
        *slot += 1;
    }
}

/// Distinct pixels of events sorted by pixel key (any order within a
/// pixel): event count and earliest time of each.
fn fold_pixels(keyed: &[(u32, i64)]) -> Vec<PixelHits> {
    let mut pixels: Vec<PixelHits> = Vec::with_capacity(keyed.len());
    let mut last_key = 0; // the key of `pixels.last()` once there is one
    for &(key, t) in keyed {
        match pixels.last_mut() {
            Some(last) if last_key == key => {
                last.count += 1;
                last.first_t = last.first_t.min(t);
            }
            _ => {
                last_key = key;
                pixels.push(PixelHits {
                    x: (key & 0xffff) as u16,
                    y: (key >> 16) as u16,
                    count: 1,
                    first_t: t,
                });
            }
        }
    }
    pixels
}

/// [`pulse_pixels`] by the plain route: a comparison sort of (pixel key,
/// time) pairs, the earliest time of a pixel being its first after the
/// sort. The reference the counting sort is tested against.
#[cfg(feature = "testkit")]
pub(crate) fn pulse_pixels_reference(
    pulse: &PulseEvents,
    params: &ClusterParams,
) -> Vec<PixelHits> {
    let ev = &pulse.events;
    let mut keyed: Vec<(u32, i64)> = Vec::with_capacity(ev.len());
    let use_mask = !params.hot_pixels.is_empty();
    for i in 0..ev.len() {
        if params.on_only && ev.p[i] != ON {
            continue;
        }
        if use_mask && params.hot_pixels.contains(&(ev.x[i], ev.y[i])) {
            continue;
        }
        if let Some(m) = &params.mask {
            if m.is_masked_px(ev.x[i] as u32, ev.y[i] as u32) {
                continue;
            }
        }
        keyed.push((((ev.y[i] as u32) << 16) | ev.x[i] as u32, ev.t[i]));
    }
    keyed.sort_unstable();
    let mut pixels: Vec<PixelHits> = Vec::with_capacity(keyed.len());
    for &(key, t) in &keyed {
        match pixels.last_mut() {
            Some(last) if ((last.y as u32) << 16 | last.x as u32) == key => last.count += 1,
            _ => pixels.push(PixelHits {
                x: (key & 0xffff) as u16,
                y: (key >> 16) as u16,
                count: 1,
                first_t: t, // smallest t of this pixel: keys sort by (key, t)
            }),
        }
    }
    pixels
}

/// Union-find with path halving and union by size.
pub(crate) struct UnionFind {
    parent: Vec<u32>,
    size: Vec<u32>,
}

impl UnionFind {
    pub(crate) fn new(n: usize) -> Self {
        UnionFind {
            parent: (0..n as u32).collect(),
            size: vec![1; n],
        }
    }
    #[inline]
    pub(crate) fn find(&mut self, mut a: u32) -> u32 {
        while self.parent[a as usize] != a {
            let g = self.parent[self.parent[a as usize] as usize];
            self.parent[a as usize] = g;
            a = g;
        }
        a
    }
    #[inline]
    pub(crate) fn union(&mut self, a: u32, b: u32) {
        let (ra, rb) = (self.find(a), self.find(b));
        if ra == rb {
            return;
        }
        let (big, small) = if self.size[ra as usize] >= self.size[rb as usize] {
            (ra, rb)
        } else {
            (rb, ra)
        };
        self.parent[small as usize] = big;
        self.size[big as usize] += self.size[small as usize];
    }
}

/// Component label of every pixel (labels numbered in order of each
/// component's first pixel in (y, x) order). The default path: for join
/// radii of 1 to √3 px (`ClusterParams::max_d2` 1–3, the default 1.5 px
/// among them) the run-length pass `pixel_labels_runs`, else the row
/// sweep `pixel_labels_sweep`. [`pixel_labels_kdtree`] is the general
/// k-d tree path; all match the brute-force oracle exactly.
pub(crate) fn pixel_labels(pixels: &[PixelHits], params: &ClusterParams) -> Vec<u32> {
    if (1..=3).contains(&params.max_d2()) {
        pixel_labels_runs(pixels, params)
    } else {
        pixel_labels_sweep(pixels, params)
    }
}

/// [`pixel_labels`] by runs, for `max_d2` 1–3 (a join radius of 1 to √3
/// px): then two pixels of one row join only when adjacent, and pixels of
/// adjacent rows when `|dx| ≤ slack` (0 for `max_d2` 1, else 1); rows
/// further apart never. The (y, x)-sorted pixels of a pulse come as
/// row-major runs of adjacent pixels (a particle image is one or two
/// short runs): the pass joins the runs of each row with those of the row
/// above in one merge of two sorted interval lists — `[a, b]` above and
/// `[c, d]` below touch iff `c ≤ b + slack` and `a ≤ d + slack` — with
/// union-find over runs instead of pixels, then labels the pixels by run.
/// Components are numbered by their first run, whose first pixel is the
/// component's first pixel: the same labels as the sweep (tested, and
/// `tests/cluster_oracle.rs`). Other radii go to the sweep.
pub(crate) fn pixel_labels_runs(pixels: &[PixelHits], params: &ClusterParams) -> Vec<u32> {
    let max_d2 = params.max_d2();
    if !(1..=3).contains(&max_d2) {
        return pixel_labels_sweep(pixels, params);
    }
    let slack = (max_d2 >= 2) as u32;
    let n = pixels.len();
    // Runs as (y, first x, last x), and the run of every pixel.
    let mut runs: Vec<(u32, u32, u32)> = Vec::with_capacity(n);
    let mut run_of: Vec<u32> = Vec::with_capacity(n);
    let (mut y_last, mut x_last) = (u32::MAX, u32::MAX);
    for p in pixels {
        let (x, y) = (p.x as u32, p.y as u32);
        if y == y_last && x == x_last.wrapping_add(1) {
            if let Some(r) = runs.last_mut() {
                r.2 = x;
            }
        } else {
            runs.push((y, x, x));
        }
        run_of.push(runs.len() as u32 - 1);
        (y_last, x_last) = (y, x);
    }
    let nr = runs.len();
    let mut uf = UnionFind::new(nr);
    // `above..row`: the runs of the row before (if it is y − 1).
    let (mut above, mut row) = (0usize, 0usize);
    while row < nr {
        let y = runs[row].0;
        let mut row_end = row + 1;
        while row_end < nr && runs[row_end].0 == y {
            row_end += 1;
        }
        if above < row && runs[above].0 + 1 == y {
            let (mut i, mut j) = (above, row);
            while i < row && j < row_end {
                let (_, a, b) = runs[i];
                let (_, c, d) = runs[j];
                if c <= b + slack && a <= d + slack {
                    uf.union(i as u32, j as u32);
                }
                // The one ending first meets no later run of the other row.
                if b <= d {
                    i += 1;
                } else {
                    j += 1;
                }
            }
        }
        above = row;
        row = row_end;
    }
    let run_labels = canonical_labels(&mut uf, nr);
    run_of.iter().map(|&r| run_labels[r as usize]).collect()
}

/// The row sweep: over the (y, x)-sorted pixels, exploiting integer
/// coordinates — for each pixel only rows `y..=y+R` (`R = ⌊√max_d2⌋`) can
/// hold partners, and one forward-only cursor per row offset finds them
/// in amortised O(1). Any radius; [`pixel_labels`] for radii above √3 px.
pub(crate) fn pixel_labels_sweep(pixels: &[PixelHits], params: &ClusterParams) -> Vec<u32> {
    let n = pixels.len();
    let mut uf = UnionFind::new(n);
    let max_d2 = params.max_d2();
    if n > 1 && max_d2 >= 1 {
        let r = (max_d2 as f64).sqrt().floor() as u32;
        let keys: Vec<u32> = pixels
            .iter()
            .map(|p| ((p.y as u32) << 16) | p.x as u32)
            .collect();
        // Cursors for the rows below (dy = 1..=r).
        let mut cursor = vec![0usize; r as usize + 1];
        for i in 0..n {
            let (xi, yi) = (pixels[i].x as u32, pixels[i].y as u32);
            // Same row: every pixel at most r to the right is a partner
            // (dx ≤ r ⇒ dx² ≤ max_d2); keys are distinct and sorted.
            let row_end = (yi << 16) | (xi + r).min(u16::MAX as u32);
            let mut j = i + 1;
            while j < n && keys[j] <= row_end {
                uf.union(i as u32, j as u32);
                j += 1;
            }
            for dy in 1..=r {
                let row = yi + dy;
                if row > u16::MAX as u32 {
                    break;
                }
                let lo_key = (row << 16) | xi.saturating_sub(r);
                let hi_key = (row << 16) | (xi + r).min(u16::MAX as u32);
                let c = &mut cursor[dy as usize];
                while *c < n && keys[*c] < lo_key {
                    *c += 1;
                }
                let dy2 = (dy * dy) as i64;
                let mut j = *c;
                while j < n && keys[j] <= hi_key {
                    let dx = pixels[j].x as i64 - xi as i64;
                    if dx * dx + dy2 <= max_d2 {
                        uf.union(i as u32, j as u32);
                    }
                    j += 1;
                }
            }
        }
    }
    canonical_labels(&mut uf, n)
}

/// The row sweep as it was first written (one forward cursor per row
/// offset, the same row included, every pair distance-tested): the
/// reference of [`pixel_labels`], which takes same-row partners without a
/// test.
#[cfg(feature = "testkit")]
pub(crate) fn pixel_labels_reference(pixels: &[PixelHits], params: &ClusterParams) -> Vec<u32> {
    let n = pixels.len();
    let mut uf = UnionFind::new(n);
    let max_d2 = params.max_d2();
    if n > 1 && max_d2 >= 1 {
        let r = (max_d2 as f64).sqrt().floor() as i64;
        let key = |p: &PixelHits| ((p.y as u64) << 16) | p.x as u64;
        let keys: Vec<u64> = pixels.iter().map(key).collect();
        let mut cursor = vec![0usize; r as usize + 1];
        for i in 0..n {
            let (xi, yi) = (pixels[i].x as i64, pixels[i].y as i64);
            for dy in 0..=r {
                let row = yi + dy;
                if row > u16::MAX as i64 {
                    break;
                }
                let x_lo = if dy == 0 { xi + 1 } else { (xi - r).max(0) };
                let lo_key = ((row as u64) << 16) | x_lo.min(u16::MAX as i64 + 1) as u64;
                let hi_key = ((row as u64) << 16) | (xi + r).min(u16::MAX as i64) as u64;
                let c = &mut cursor[dy as usize];
                while *c < n && keys[*c] < lo_key {
                    *c += 1;
                }
                let mut j = *c;
                while j < n && keys[j] <= hi_key {
                    let dx = pixels[j].x as i64 - xi;
                    if dx * dx + dy * dy <= max_d2 {
                        uf.union(i as u32, j as u32);
                    }
                    j += 1;
                }
            }
        }
    }
    canonical_labels(&mut uf, n)
}

/// Component labels by the search `params.neighbour_search` names.
#[ebptv_macros::testkit]
pub(crate) fn pixel_labels_with(pixels: &[PixelHits], params: &ClusterParams) -> Vec<u32> {
    match params.neighbour_search {
        NeighbourSearch::RowSweep => pixel_labels(pixels, params),
        NeighbourSearch::KdTree => pixel_labels_kdtree(pixels, params),
    }
}

/// `pixel_labels` with a kiddo k-d tree and radius queries: the general
/// path (any point set), kept as a second implementation checked against
/// the same oracle and compared in the benchmark.
#[ebptv_macros::testkit]
pub(crate) fn pixel_labels_kdtree(pixels: &[PixelHits], params: &ClusterParams) -> Vec<u32> {
    let n = pixels.len();
    let mut uf = UnionFind::new(n);
    if n > 1 {
        let max_d2 = params.max_d2();
        if max_d2 >= 1 {
            let points: Vec<[f32; 2]> = pixels.iter().map(|p| [p.x as f32, p.y as f32]).collect();
            let tree: ImmutableKdTree<f32, u32, 2, 32> = ImmutableKdTree::new_from_slice(&points);
            for (i, q) in points.iter().enumerate() {
                for nb in tree.within_unsorted::<SquaredEuclidean>(q, max_d2 as f32) {
                    if (nb.item as usize) > i {
                        uf.union(i as u32, nb.item);
                    }
                }
            }
        }
    }
    canonical_labels(&mut uf, n)
}

fn canonical_labels(uf: &mut UnionFind, n: usize) -> Vec<u32> {
    let mut label_of_root = vec![u32::MAX; n];
    let mut labels = Vec::with_capacity(n);
    let mut next = 0u32;
    for i in 0..n as u32 {
        let r = uf.find(i) as usize;
        if label_of_root[r] == u32::MAX {
            label_of_root[r] = next;
            next += 1;
        }
        labels.push(label_of_root[r]);
    }
    labels
}

/// Particles from labelled pixels (labels from [`pixel_labels`]), in label
/// order, filtered by the size limits.
pub(crate) fn particles_from_labels(
    pulse: &PulseEvents,
    pixels: &[PixelHits],
    labels: &[u32],
    params: &ClusterParams,
) -> Vec<Particle> {
    #[derive(Clone, Copy)]
    struct Acc {
        sx: f64,
        sy: f64,
        n: u32,
        npix: u32,
        x0: u16,
        x1: u16,
        y0: u16,
        y1: u16,
        t0: i64,
    }
    let n_labels = labels.iter().map(|&l| l as usize + 1).max().unwrap_or(0);
    let mut acc = vec![
        Acc {
            sx: 0.0,
            sy: 0.0,
            n: 0,
            npix: 0,
            x0: u16::MAX,
            x1: 0,
            y0: u16::MAX,
            y1: 0,
            t0: i64::MAX,
        };
        n_labels
    ];
    for (p, &l) in pixels.iter().zip(labels) {
        let a = &mut acc[l as usize];
        a.sx += p.x as f64 * p.count as f64;
        a.sy += p.y as f64 * p.count as f64;
        a.n += p.count;
        a.npix += 1;
        a.x0 = a.x0.min(p.x);
        a.x1 = a.x1.max(p.x);
        a.y0 = a.y0.min(p.y);
        a.y1 = a.y1.max(p.y);
        a.t0 = a.t0.min(p.first_t);
    }
    let mut out = Vec::with_capacity(acc.len());
    for a in &acc {
        if a.n >= params.min_events && a.n <= params.max_events {
            out.push(Particle {
                pulse: pulse.index,
                t_us: pulse.start_us,
                x: a.sx / a.n as f64,
                y: a.sy / a.n as f64,
                n_events: a.n,
                n_pixels: a.npix,
                extent_x: (a.x1 - a.x0 + 1) as f32,
                extent_y: (a.y1 - a.y0 + 1) as f32,
                first_latency_us: (a.t0 as f64 - pulse.start_us) as f32,
            });
        }
    }
    out
}

/// Cluster the events of one pulse into particles. `params` is assumed
/// valid (see `ClusterParams::validate`).
pub fn cluster_pulse(pulse: &PulseEvents, params: &ClusterParams) -> Vec<Particle> {
    let pixels = pulse_pixels(pulse, params);
    let mut labels = pixel_labels_with(&pixels, params);
    split_wide_clusters(&pixels, &mut labels, params.split_extent);
    particles_from_labels(pulse, &pixels, &labels, params)
}

/// Split every component spanning at least `split_extent` pixels along x
/// or y (0 = none) into two: its pixels, weighted by their events, are
/// projected on the component's principal axis and cut where the two parts'
/// weighted sum of squared deviations is smallest (exact 1-D two-means over
/// every cut of the sorted projections). The second part gets a new label
/// (after all existing ones); labels stay dense.
///
/// Why: two particles closer than the join radius make one image, whose
/// centroid lies between them and belongs to neither track. At ppp 0.01
/// about 7 % of the images are such pairs; most of those that can be
/// separated at all span 3 or more pixels, which one particle image almost
/// never does.
#[ebptv_macros::testkit]
pub(crate) fn split_wide_clusters(pixels: &[PixelHits], labels: &mut [u32], split_extent: u32) {
    if split_extent == 0 || pixels.is_empty() {
        return;
    }
    let n_labels = labels.iter().map(|&l| l as usize + 1).max().unwrap_or(0);
    let mut bbox = vec![(u16::MAX, 0u16, u16::MAX, 0u16); n_labels];
    for (p, &l) in pixels.iter().zip(labels.iter()) {
        let b = &mut bbox[l as usize];
        *b = (b.0.min(p.x), b.1.max(p.x), b.2.min(p.y), b.3.max(p.y));
    }
    // Wide components numbered in label order; `start[s]..start[s + 1]`
    // of `members` will hold the pixel indices of wide component `s` (one
    // flat list for all of them: most particle images of a dense recording
    // are wide, and a list each was a heap block per particle).
    let mut slot = vec![u32::MAX; n_labels];
    let mut start = vec![0usize];
    for (l, b) in bbox.iter().enumerate() {
        if (b.1 - b.0 + 1).max(b.3 - b.2 + 1) as u32 >= split_extent {
            slot[l] = (start.len() - 1) as u32;
            start.push(0);
        }
    }
    let n_wide = start.len() - 1;
    if n_wide == 0 {
        return;
    }
    for &l in labels.iter() {
        let s = slot[l as usize];
        if s != u32::MAX {
            start[s as usize + 1] += 1;
        }
    }
    for s in 0..n_wide {
        start[s + 1] += start[s];
    }
    let mut fill = start[..n_wide].to_vec();
    let mut members = vec![0usize; start[n_wide]];
    for (i, &l) in labels.iter().enumerate() {
        let s = slot[l as usize];
        if s != u32::MAX {
            members[fill[s as usize]] = i;
            fill[s as usize] += 1;
        }
    }
    let mut proj = Vec::new();
    let mut next = n_labels as u32;
    for s in 0..n_wide {
        let m = &members[start[s]..start[s + 1]];
        if m.len() < 2 {
            continue;
        }
        if let Some(k) = two_means_split(pixels, m, &mut proj) {
            for &(_, i) in &proj[k..] {
                labels[i] = next;
            }
            next += 1;
        }
    }
}

/// The principal axis `(cos θ, sin θ)`, θ = ½·atan2(2·cxy, cxx − cyy) ∈
/// (−π/2, π/2], of a covariance, by the half-angle formulas: two square
/// roots instead of an arctangent and a sine and cosine. Each component
/// comes from the formula that does not cancel (cos θ from 1 + cos 2θ
/// where 2θ is within ±π/2, sin θ from 1 − cos 2θ beyond), so both are
/// within a few ulps of the trigonometric route's (tested).
fn principal_axis(cxx: f64, cxy: f64, cyy: f64) -> (f64, f64) {
    let (c2, s2) = (cxx - cyy, 2.0 * cxy);
    let r = (c2 * c2 + s2 * s2).sqrt();
    if r == 0.0 {
        return (1.0, 0.0); // atan2(0, 0) = 0: the x axis
    }
    let (c2, s2) = (c2 / r, s2 / r);
    if c2 >= 0.0 {
        let c = (0.5 * (1.0 + c2)).sqrt();
        (c, s2 / (2.0 * c))
    } else {
        // sin θ has the sign of sin 2θ (cos θ ≥ 0); sin 2θ = +0 is θ = π/2.
        let s = (0.5 * (1.0 - c2)).sqrt().copysign(s2);
        (s2 / (2.0 * s), s)
    }
}

/// The cut of `members`' pixels at the best principal-axis split: `proj`
/// is left holding `(projection, pixel index)` sorted along the axis, and
/// the far side of the cut is `proj[k..]` for the returned `k`; `None`
/// when no cut leaves events on both sides.
fn two_means_split(
    pixels: &[PixelHits],
    members: &[usize],
    proj: &mut Vec<(f64, usize)>,
) -> Option<usize> {
    // Principal axis from exact integer moments (so that the direction,
    // and with it the side that gets the new label, never depends on
    // rounding): covariances scaled by (Σw)².
    let (mut sw, mut sx, mut sy, mut sxx, mut sxy, mut syy) = (0i128, 0i128, 0, 0, 0, 0);
    for &i in members {
        let (w, x, y) = (
            pixels[i].count as i128,
            pixels[i].x as i128,
            pixels[i].y as i128,
        );
        sw += w;
        sx += w * x;
        sy += w * y;
        sxx += w * x * x;
        sxy += w * x * y;
        syy += w * y * y;
    }
    let cxx = sw * sxx - sx * sx;
    let cxy = sw * sxy - sx * sy;
    let cyy = sw * syy - sy * sy;
    let (ax, ay) = principal_axis(cxx as f64, cxy as f64, cyy as f64);
    let (mx, my) = (sx as f64 / sw as f64, sy as f64 / sw as f64);
    proj.clear();
    proj.extend(members.iter().map(|&i| {
        let q = (pixels[i].x as f64 - mx) * ax + (pixels[i].y as f64 - my) * ay;
        (q, i)
    }));
    proj.sort_unstable_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    // Prefix sums of weight, w·q and w·q² give each cut's cost in O(1).
    let (mut w0, mut s0, mut q0) = (0.0, 0.0, 0.0);
    let (wt, st, qt) = proj.iter().fold((0.0, 0.0, 0.0), |a, &(q, i)| {
        let w = pixels[i].count as f64;
        (a.0 + w, a.1 + w * q, a.2 + w * q * q)
    });
    let mut best: Option<(f64, usize)> = None;
    for k in 1..proj.len() {
        let (q, i) = proj[k - 1];
        let w = pixels[i].count as f64;
        w0 += w;
        s0 += w * q;
        q0 += w * q * q;
        if proj[k].0 - q < 1e-9 {
            continue; // equal projections stay together
        }
        let (w1, s1, q1) = (wt - w0, st - s0, qt - q0);
        let cost = (q0 - s0 * s0 / w0) + (q1 - s1 * s1 / w1);
        if best.is_none_or(|(c, _)| cost < c - 1e-9) {
            best = Some((cost, k));
        }
    }
    best.map(|(_, k)| k)
}

/// Cluster a batch of independent pulses in parallel (rayon), one particle
/// list per pulse in input order.
pub fn cluster_pulses(
    pulses: &[PulseEvents],
    params: &ClusterParams,
) -> Result<Vec<Vec<Particle>>> {
    params.validate()?;
    Ok(pulses
        .par_iter()
        .map(|p| cluster_pulse(p, params))
        .collect())
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;
    use crate::events::EventChunk;

    fn pulse_of(events: &[(i64, u16, u16, u8)]) -> PulseEvents {
        let mut ev = EventChunk::default();
        for &(t, x, y, p) in events {
            ev.push(t, x, y, p);
        }
        PulseEvents {
            index: 3,
            start_us: 1000.0,
            events: ev,
        }
    }

    /// The half-angle principal axis against the trigonometric route it
    /// replaces, θ = ½·atan2(2·cxy, cxx − cyy): the same direction and
    /// sign to a few ulps, over integer covariances of every orientation
    /// (pseudo-random, as the clustering's exact moments give them) and the
    /// degenerate ones (isotropic, axis-aligned either way).
    #[ebptv_macros::unit_test]
    fn principal_axis_matches_the_trigonometric_axis() {
        let trig = |cxx: f64, cxy: f64, cyy: f64| {
            let th = 0.5 * (2.0 * cxy).atan2(cxx - cyy);
            (th.cos(), th.sin())
        };
        let mut cases = vec![
            (0.0, 0.0, 0.0),
            (5.0, 0.0, 5.0),
            (7.0, 0.0, 3.0),
            (3.0, 0.0, 7.0),
            (4.0, 2.0, 4.0),
            (4.0, -2.0, 4.0),
            (1.0, -1e-12, 1e12),
            (1e12, 1.0, 1.0),
        ];
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state % 2_000_001) as f64 - 1_000_000.0
        };
        for _ in 0..20_000 {
            let (a, b, c) = (next().abs(), next(), next().abs());
            cases.push((a, b, c));
        }
        for (cxx, cxy, cyy) in cases {
            let (ax, ay) = principal_axis(cxx, cxy, cyy);
            let (tx, ty) = trig(cxx, cxy, cyy);
            assert!(ax >= 0.0, "{cxx} {cxy} {cyy}: cos θ < 0");
            assert!(
                (ax - tx).abs() <= 4e-16 && (ay - ty).abs() <= 4e-16,
                "{cxx} {cxy} {cyy}: ({ax}, {ay}) vs ({tx}, {ty})"
            );
        }
    }

    #[ebptv_macros::unit_test]
    fn two_particles_with_weighted_centroids() {
        let p = pulse_of(&[
            (1100, 10, 10, 1),
            (1090, 10, 10, 1),
            (1120, 11, 10, 1),
            (1200, 30, 5, 1),
            (1150, 31, 6, 0), // OFF: ignored by default
        ]);
        let parts = cluster_pulse(&p, &ClusterParams::default());
        assert_eq!(parts.len(), 2);
        // (30,5) sorts before (10,10) by row.
        assert_eq!((parts[0].x, parts[0].y, parts[0].n_events), (30.0, 5.0, 1));
        let q = parts[1];
        assert!((q.x - 31.0 / 3.0).abs() < 1e-12 && q.y == 10.0);
        assert_eq!(
            (q.n_events, q.n_pixels, q.extent_x, q.extent_y),
            (3, 2, 2.0, 1.0)
        );
        assert_eq!(q.first_latency_us, 90.0);
        assert_eq!((q.pulse, q.t_us), (3, 1000.0));
    }

    #[ebptv_macros::unit_test]
    fn radius_is_inclusive_and_diagonals_join_at_sqrt2() {
        let p = pulse_of(&[(0, 0, 0, 1), (0, 1, 1, 1), (0, 5, 0, 1), (0, 7, 0, 1)]);
        let mut params = ClusterParams {
            radius: 1.5,
            split_extent: 0, // the joins themselves, not the splitting
            ..Default::default()
        };
        assert_eq!(cluster_pulse(&p, &params).len(), 3);
        params.radius = 2.0;
        assert_eq!(cluster_pulse(&p, &params).len(), 2);
        params.radius = 1.0;
        assert_eq!(cluster_pulse(&p, &params).len(), 4);
    }

    #[ebptv_macros::unit_test]
    fn kd_tree_search_gives_the_row_sweeps_particles() {
        // A dense pseudo-random pulse (a 60x40 patch, ~25 % of pixels hit,
        // repeats included) through both neighbour searches, several radii.
        let mut state = 12345u64;
        let mut next = || {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 33) as u32
        };
        let evs: Vec<(i64, u16, u16, u8)> = (0..600)
            .map(|_| {
                (
                    next() as i64 % 200,
                    (next() % 60) as u16,
                    (next() % 40) as u16,
                    1,
                )
            })
            .collect();
        let p = pulse_of(&evs);
        for radius in [1.0, 1.5, 2.0] {
            let sweep = ClusterParams {
                radius,
                ..Default::default()
            };
            let tree = ClusterParams {
                neighbour_search: NeighbourSearch::KdTree,
                ..sweep.clone()
            };
            let (a, b) = (cluster_pulse(&p, &sweep), cluster_pulse(&p, &tree));
            assert!(a.len() > 20, "radius {radius}: {} clusters", a.len());
            assert_eq!(a, b, "radius {radius}");
        }
    }

    /// The counting sort of [`pulse_pixels`] against the comparison sort of
    /// [`pulse_pixels_reference`]: pulses small and large, compact and
    /// spread over the whole u16 range, with repeated pixels, times out of
    /// order, OFF events and a hot-pixel mask.
    #[ebptv_macros::unit_test]
    fn pulse_pixels_equal_the_reference() {
        let mut state = 987654321u64;
        let mut next = |m: u64| {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 33) % m
        };
        let mut counted = 0;
        for round in 0..300 {
            let n = [0, 1, 5, 63, 64, 300, 3000][round % 7];
            let (w, h) = match round % 5 {
                0 => (65535, 65535),
                1 => (8, 8),
                2 => (1280, 720),
                3 => (1, 300),
                _ => (200, 1),
            };
            let evs: Vec<(i64, u16, u16, u8)> = (0..n)
                .map(|_| {
                    (
                        1000 + next(400) as i64,
                        next(w) as u16,
                        next(h) as u16,
                        (next(5) > 0) as u8,
                    )
                })
                .collect();
            let p = pulse_of(&evs);
            let mut params = ClusterParams {
                on_only: round % 4 != 0,
                ..Default::default()
            };
            if round % 3 == 0 && n > 0 {
                params.hot_pixels.insert((evs[0].1, evs[0].2));
            }
            let fast = pulse_pixels(&p, &params);
            assert_eq!(fast, pulse_pixels_reference(&p, &params), "round {round}");
            // Surely the counting sort (selected events ≥ 0.6 n).
            if n >= 2 * COUNTING_SORT_MIN_EVENTS && (w + h) as usize <= n {
                counted += 1;
            }
        }
        assert!(counted > 30, "{counted} rounds took the counting sort");
    }

    /// The row sweep and the run-length pass against the sweep's first
    /// form on dense random patches (so that rows hold runs of
    /// neighbours) and at the u16 edges, radii 1–4 (the run pass for 1 to
    /// √3, the sweep beyond).
    #[ebptv_macros::unit_test]
    fn pixel_labels_equal_the_reference() {
        let mut state = 4242u64;
        let mut next = |m: u64| {
            state = state
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (state >> 33) % m
        };
        for round in 0..200 {
            let (w, h, n) =
                [(30, 20, 250), (200, 3, 300), (5, 5, 40), (1280, 720, 3000)][round % 4];
            let edge = if round % 5 == 0 { 65535 - w } else { 0 };
            let evs: Vec<(i64, u16, u16, u8)> = (0..n)
                .map(|_| {
                    (
                        0,
                        (edge + next(w)) as u16,
                        (edge.min(65535 - h) + next(h)) as u16,
                        1,
                    )
                })
                .collect();
            let p = pulse_of(&evs);
            for radius in [1.0, 1.2, 1.5, 1.7, 2.0, 2.9, 4.0] {
                let params = ClusterParams {
                    radius,
                    ..Default::default()
                };
                let pixels = pulse_pixels(&p, &params);
                let reference = pixel_labels_reference(&pixels, &params);
                assert_eq!(
                    pixel_labels_sweep(&pixels, &params),
                    reference,
                    "round {round}, radius {radius}"
                );
                assert_eq!(
                    pixel_labels_runs(&pixels, &params),
                    reference,
                    "runs: round {round}, radius {radius}"
                );
                assert_eq!(pixel_labels(&pixels, &params), reference);
            }
        }
    }

    #[ebptv_macros::unit_test]
    fn wide_clusters_split_in_two() {
        // Two particles, 2 px apart, joined by a pixel between them: one
        // component spanning 5 px, split into the two images.
        let p = pulse_of(&[
            (0, 10, 10, 1),
            (0, 10, 10, 1),
            (0, 11, 10, 1),
            (0, 12, 11, 1),
            (0, 13, 10, 1),
            (0, 14, 10, 1),
            (0, 14, 10, 1),
        ]);
        let joined = ClusterParams {
            split_extent: 0,
            ..Default::default()
        };
        assert_eq!(cluster_pulse(&p, &joined).len(), 1);
        let mut parts = cluster_pulse(&p, &ClusterParams::default());
        parts.sort_by(|a, b| a.x.total_cmp(&b.x));
        assert_eq!(parts.len(), 2);
        assert_eq!(parts.iter().map(|q| q.n_events).sum::<u32>(), 7);
        assert!(parts[0].x < 11.5 && parts[1].x > 12.5, "{parts:?}");
        // A compact 2×2 image is left alone.
        let q = pulse_of(&[(0, 5, 5, 1), (0, 6, 5, 1), (0, 5, 6, 1), (0, 6, 6, 1)]);
        assert_eq!(cluster_pulse(&q, &ClusterParams::default()).len(), 1);
    }

    #[ebptv_macros::unit_test]
    fn mask_and_size_limits() {
        let p = pulse_of(&[(0, 0, 0, 1), (0, 1, 0, 1), (0, 9, 9, 1), (0, 20, 20, 1)]);
        let mut params = ClusterParams {
            min_events: 2,
            ..Default::default()
        };
        assert_eq!(cluster_pulse(&p, &params).len(), 1);
        params.min_events = 1;
        params.hot_pixels.insert((9, 9));
        assert_eq!(cluster_pulse(&p, &params).len(), 2);
        params.max_events = 1;
        assert_eq!(cluster_pulse(&p, &params).len(), 1);
    }

    #[ebptv_macros::unit_test]
    fn bad_radius_is_an_error() {
        for r in [0.0, -1.0, f64::NAN] {
            let params = ClusterParams {
                radius: r,
                ..Default::default()
            };
            let e = cluster_pulses(&[], &params).unwrap_err().to_string();
            assert!(e.contains("radius"), "{e}");
        }
    }
}
