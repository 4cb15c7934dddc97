//! Gating and assignment (stage 2 of the module doc): the candidates inside
//! each track's search radius, the global minimum-cost assignment
//! ([`super::lap`]), the neighbour offsets the step test uses, and the
//! splitting of merged images between two tracks' predictions.

use super::*;

impl Tracker {
    /// Extend active tracks with this pulse's detections (global
    /// assignment); returns the used flags of the detections.
    pub(super) fn extend_active(
        &mut self,
        dets: &mut Vec<Det>,
        pixels: Option<&ParticlePixels>,
        pulse: i64,
    ) -> FrameLinks {
        let mut links = FrameLinks {
            used: vec![false; dets.len()],
            owner: vec![NO_OWNER; dets.len()],
            hungry: Vec::new(),
            grid_stale: true,
        };
        if self.active.is_empty() || dets.is_empty() {
            links.hungry.extend(self.active.iter().map(|t| t.uid));
            return links;
        }
        links.grid_stale = false;
        let mut sc = std::mem::take(&mut self.scratch);
        sc.grid.rebuild(dets.iter().map(|d| (d.x, d.y)));
        sc.edges.clear();
        sc.edge_d2.clear();
        sc.row_start.clear();
        sc.leverage.clear();
        sc.pred.clear();
        for ti in 0..self.active.len() {
            if let Some(ahead) = self.active.get(ti + PREFETCH_AHEAD) {
                prefetch_window(&ahead.dets, self.params.predict_window);
            }
            let (px, py, r, l) = self.predict(ti, pulse);
            sc.leverage.push(l);
            sc.pred.push((px, py, r));
            sc.row_start.push(sc.edges.len());
            sc.near.clear();
            sc.grid.within(px, py, r, &mut sc.near);
            for &(j, d2) in &sc.near {
                sc.edges.push((ti, j as usize, d2 / (r * r)));
                sc.edge_d2.push(d2);
            }
        }
        sc.row_start.push(sc.edges.len());
        let sigma = self.position_sigma();
        sc.miss.clear();
        sc.miss.resize(self.active.len(), 1.0);
        let mut sol = lap::assign_sparse(dets.len(), &sc.edges, &sc.miss);
        if let (true, Some(px)) = (self.params.split_merged, pixels) {
            let parents = self.split_merged_images(dets, px, &mut sc, &mut sol);
            if !parents.is_empty() {
                links.used.resize(dets.len(), false);
                links.owner.resize(dets.len(), NO_OWNER);
                // The split images are replaced by their parts: nobody's,
                // and not free for new tracks either.
                for j in parents {
                    links.used[j] = true;
                }
                links.grid_stale = true;
            }
        }
        let flow_on = self.params.ghost_check_length > 0;
        for (ti, c) in sol.into_iter().enumerate() {
            let Some(c) = c else {
                links.hungry.push(self.active[ti].uid);
                continue;
            };
            {
                if flow_on && self.active[ti].dets.len() >= FLOW_MIN_DETECTIONS {
                    let (a, b) = (self.active[ti].last(), &dets[c]);
                    let gap = (b.pulse - a.pulse) as f64;
                    let sample = local_flow::FlowSample {
                        pulse: b.pulse,
                        x: 0.5 * (a.x + b.x),
                        y: 0.5 * (a.y + b.y),
                        u: (b.x - a.x) / gap,
                        v: (b.y - a.y) / gap,
                    };
                    self.flow.add_sample(sample);
                    self.flow_log.push(sample);
                }
                let mut det = dets[c];
                if self.params.step_split_hinted > 0.0 && !links.grid_stale {
                    det.nb = nearest_neighbour(&sc.grid, dets, c, &mut sc.near);
                }
                self.active[ti].dets.push(det);
                links.used[c] = true;
                links.owner[c] = self.active[ti].uid;
                let row = sc.row_start[ti]..sc.row_start[ti + 1];
                if let Some(k) = row.clone().find(|&k| sc.edges[k].1 == c) {
                    // Squared innovation per axis, normalised by the
                    // predictor's variance factor. Only innovations within
                    // CLIP_K σ count (wrong links, whose innovations are
                    // large, would otherwise inflate σ, widen the gates and
                    // let in more wrong links: a runaway in dense, noisy
                    // scenes); dividing by the truncated Gaussian's second
                    // moment keeps the estimate unbiased.
                    let z2 = sc.edge_d2[k] / (1.0 + sc.leverage[ti]);
                    if z2 <= (CLIP_K * sigma).powi(2) {
                        self.innov_sum += z2 / (2.0 * clipped_second_moment(CLIP_K));
                        self.innov_n += 1.0;
                    }
                }
            }
        }
        self.scratch = sc;
        links
    }

    /// Split multi-pixel images that two tracks predict into (see
    /// `TrackParams::split_merged`), after the assignment `sol` of the
    /// whole images: for each such image and pair of its candidate tracks
    /// (the image taken by one of them or by none), the pixels go to the
    /// nearer prediction; when both parts lie in their track's gate and
    /// their costs plus `split_penalty` are below what the two tracks pay
    /// now (their assigned candidates, or a miss), the best pair gets the
    /// parts (appended to `dets`, `sol` updated). A track takes part in at
    /// most one split per pulse. Returns the indices of the split images.
    /// Only images in two gates are looked at: the per-pulse cost is a
    /// pass over the candidate pairs.
    pub(super) fn split_merged_images(
        &mut self,
        dets: &mut Vec<Det>,
        px: &ParticlePixels,
        sc: &mut Scratch,
        sol: &mut [Option<usize>],
    ) -> Vec<usize> {
        let mut parents = Vec::new();
        sc.multi.clear();
        for &(ti, j, c) in &sc.edges {
            if px.start[j + 1] - px.start[j] >= 2 {
                sc.multi.push((j, ti, c));
            }
        }
        if sc.multi.len() < 2 {
            return parents;
        }
        sc.multi.sort_unstable_by_key(|a| (a.0, a.1));
        // What a track pays now: its assigned candidate's cost, or a miss.
        let cost_now = |sc: &Scratch, sol: &[Option<usize>], ti: usize| match sol[ti] {
            None => sc.miss[ti],
            Some(c) => sc.edges[sc.row_start[ti]..sc.row_start[ti + 1]]
                .iter()
                .find(|e| e.1 == c)
                .map_or(sc.miss[ti], |e| e.2),
        };
        let mut locked: Vec<usize> = Vec::new();
        let mut side = Vec::new();
        let penalty = self.params.split_penalty;
        let sep_weight = 1.0 / (self.params.n_sigma * self.position_sigma()).powi(2);
        let mut g = 0;
        while g < sc.multi.len() {
            let j = sc.multi[g].0;
            let mut e = g + 1;
            while e < sc.multi.len() && sc.multi[e].0 == j {
                e += 1;
            }
            let group = g..e;
            g = e;
            if group.len() < 2 {
                continue;
            }
            let taker = group
                .clone()
                .map(|k| sc.multi[k].1)
                .find(|&t| sol[t] == Some(j));
            let image = px.of(j);
            // (gain, a, b, parts)
            let mut best: Option<(f64, usize, usize, SplitParts)> = None;
            for ia in group.clone() {
                for ib in ia + 1..group.end {
                    let (a, b) = (sc.multi[ia].1, sc.multi[ib].1);
                    if locked.contains(&a)
                        || locked.contains(&b)
                        || taker.is_some_and(|t| t != a && t != b)
                    {
                        continue;
                    }
                    let (pa, pb) = (sc.pred[a], sc.pred[b]);
                    let Some((cost, parts)) = split_by_predictions(image, pa, pb, &mut side) else {
                        continue;
                    };
                    // Each part inside its track's gate.
                    let inside = |q: (f64, f64, u32), p: Prediction| {
                        (q.0 - p.0).powi(2) + (q.1 - p.1).powi(2) <= p.2 * p.2
                    };
                    if !(inside(parts[0], pa) && inside(parts[1], pb)) {
                        continue;
                    }
                    // Two images in one: the parts' separation, which one
                    // particle's image seldom shows, in the assignment's
                    // units (squared distance over n_σ² σ²).
                    let (na, nb) = (parts[0].2 as f64, parts[1].2 as f64);
                    let sep2 =
                        (parts[0].0 - parts[1].0).powi(2) + (parts[0].1 - parts[1].1).powi(2);
                    let bonus = sep_weight * na * nb / (na + nb) * sep2;
                    let gain =
                        cost_now(sc, sol, a) + cost_now(sc, sol, b) - (cost + penalty - bonus);
                    if gain > 0.0 && best.as_ref().is_none_or(|x| gain > x.0) {
                        best = Some((gain, a, b, parts));
                    }
                }
            }
            let Some((_, a, b, parts)) = best else {
                continue;
            };
            locked.extend([a, b]);
            parents.push(j);
            self.stats.images_split += 1;
            if self.record_splits {
                // `side` belongs to the last pair tried: partition again.
                split_by_predictions(image, sc.pred[a], sc.pred[b], &mut side);
            }
            let parent = dets[j];
            for (k, (ti, part)) in [(a, parts[0]), (b, parts[1])].into_iter().enumerate() {
                let serial = SPLIT_SERIAL_BIT | self.next_split;
                self.next_split += 1;
                dets.push(Det {
                    serial,
                    x: part.0,
                    y: part.1,
                    nb: NO_NEIGHBOUR,
                    ..parent
                });
                sol[ti] = Some(dets.len() - 1);
                if self.record_splits {
                    self.splits.push(SplitDetection {
                        serial,
                        parent: parent.serial,
                        pulse: parent.pulse,
                        x: part.0,
                        y: part.1,
                        pixels: image
                            .iter()
                            .zip(&side)
                            .filter(|(_, &s)| s == (k == 1))
                            .map(|(p, _)| *p)
                            .collect(),
                    });
                }
            }
        }
        parents
    }
}

/// Offset (px, as f32) from detection `c` to the nearest other detection
/// of `dets` (indexed by `grid`) within [`NEIGHBOUR_RADIUS`];
/// [`NO_NEIGHBOUR`] when there is none.
pub(super) fn nearest_neighbour(
    grid: &GridIndex,
    dets: &[Det],
    c: usize,
    near: &mut Vec<(u32, f64)>,
) -> [f32; 2] {
    let d = &dets[c];
    near.clear();
    grid.within(d.x, d.y, NEIGHBOUR_RADIUS, near);
    near.iter()
        .filter(|&&(j, _)| j as usize != c)
        .min_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)))
        .map_or(NO_NEIGHBOUR, |&(j, _)| {
            let o = &dets[j as usize];
            [(o.x - d.x) as f32, (o.y - d.y) as f32]
        })
}

/// The two parts of a split image: event-weighted centroid (px) and
/// events of the part given to the first and to the second prediction.
pub type SplitParts = [(f64, f64, u32); 2];

/// A track's predicted position and search radius (px) at a pulse.
pub type Prediction = (f64, f64, f64);

/// Most pixels of an image that [`split_by_predictions`] tries to split
/// (it tries every partition; one or two particle images of 1–4 events
/// cover 2–5 pixels, and clustering already splits images ≥ 3 px wide).
pub const MAX_SPLIT_PIXELS: usize = 12;

/// Integer event sums (Σw, Σw·x, Σw·y) of a set of pixels: exact, so that
/// every way of adding them up gives the same cost bit for bit.
pub(super) type Sums = (i64, i64, i64);

/// Cost of giving the pixels with sums `b` to prediction `pb` and the
/// rest (`total − b`) to `pa`: each part's centroid's squared distance
/// from its prediction over the squared search radius (the assignment's
/// cost); `None` when a part has no events.
pub(super) fn split_cost(total: Sums, b: Sums, pa: Prediction, pb: Prediction) -> Option<f64> {
    let a = (total.0 - b.0, total.1 - b.1, total.2 - b.2);
    if a.0 == 0 || b.0 == 0 {
        return None;
    }
    let c = |s: Sums, p: Prediction| {
        let (x, y) = (s.1 as f64 / s.0 as f64, s.2 as f64 / s.0 as f64);
        ((x - p.0).powi(2) + (y - p.1).powi(2)) / (p.2 * p.2)
    };
    Some(c(a, pa) + c(b, pb))
}

pub(super) fn sums_of(p: &ImagePixel) -> Sums {
    let w = p.count as i64;
    (w, w * p.x as i64, w * p.y as i64)
}

/// Split the pixels of one image between two predictions `a` and `b`
/// (x, y, search radius): of all partitions into two non-empty parts, the
/// one of least summed assignment cost (each part's centroid against its
/// own prediction, see [`split_cost`]; on equal costs the partition whose
/// mask — pixel i in part b = bit i — is smallest). `side` receives per
/// pixel `false` (a) or `true` (b). Returns the cost and the parts, or
/// `None` for fewer than 2 or more than [`MAX_SPLIT_PIXELS`] pixels.
///
/// Every partition is tried, in Gray-code order so that each step moves
/// one pixel and updates the parts' sums in O(1) (up to 4096 partitions;
/// images of 2–4 pixels have 2–14). Which pixels are whose cannot be read
/// from the image alone (both particles' images overlap): the predictions
/// decide. [`split_by_predictions_reference`] evaluates every partition
/// from scratch.
pub fn split_by_predictions(
    pixels: &[ImagePixel],
    a: Prediction,
    b: Prediction,
    side: &mut Vec<bool>,
) -> Option<(f64, SplitParts)> {
    let n = pixels.len();
    if !(2..=MAX_SPLIT_PIXELS).contains(&n) {
        return None;
    }
    let total = pixels
        .iter()
        .map(sums_of)
        .fold((0, 0, 0), |s, q| (s.0 + q.0, s.1 + q.1, s.2 + q.2));
    let (mut mask, mut inb) = (0u32, (0i64, 0i64, 0i64));
    let mut best: Option<(f64, u32)> = None;
    for i in 1u32..1 << n {
        // Gray code: step i flips bit trailing_zeros(i).
        let bit = i.trailing_zeros() as usize;
        let q = sums_of(&pixels[bit]);
        let sign = if mask >> bit & 1 == 1 { -1 } else { 1 };
        mask ^= 1 << bit;
        inb = (inb.0 + sign * q.0, inb.1 + sign * q.1, inb.2 + sign * q.2);
        if let Some(c) = split_cost(total, inb, a, b) {
            if best.is_none_or(|(bc, bm)| c < bc || (c == bc && mask < bm)) {
                best = Some((c, mask));
            }
        }
    }
    let (cost, mask) = best?;
    side.clear();
    side.extend((0..n).map(|i| mask >> i & 1 == 1));
    Some((cost, parts_of(pixels, side)))
}

/// Centroids and events of the two sides of a partition (both non-empty).
pub(super) fn parts_of(pixels: &[ImagePixel], side: &[bool]) -> SplitParts {
    let mut acc = [(0i64, 0i64, 0i64); 2];
    for (p, &s) in pixels.iter().zip(side) {
        let q = sums_of(p);
        let a = &mut acc[s as usize];
        *a = (a.0 + q.0, a.1 + q.1, a.2 + q.2);
    }
    acc.map(|(w, sx, sy)| (sx as f64 / w as f64, sy as f64 / w as f64, w as u32))
}

/// [`split_by_predictions`] by plain enumeration: every mask from 1 to
/// 2ⁿ − 2 in increasing order, each part's sums added up afresh.
pub fn split_by_predictions_reference(
    pixels: &[ImagePixel],
    a: Prediction,
    b: Prediction,
) -> Option<(f64, Vec<bool>, SplitParts)> {
    let n = pixels.len();
    if !(2..=MAX_SPLIT_PIXELS).contains(&n) {
        return None;
    }
    let mut best: Option<(f64, u32)> = None;
    let total = pixels.iter().fold((0, 0, 0), |s, p| {
        let q = sums_of(p);
        (s.0 + q.0, s.1 + q.1, s.2 + q.2)
    });
    for mask in 1u32..(1 << n) - 1 {
        let mut inb = (0, 0, 0);
        for (i, p) in pixels.iter().enumerate() {
            if mask >> i & 1 == 1 {
                let q = sums_of(p);
                inb = (inb.0 + q.0, inb.1 + q.1, inb.2 + q.2);
            }
        }
        let c = split_cost(total, inb, a, b).expect("both parts hold pixels");
        if best.is_none_or(|(bc, _)| c < bc) {
            best = Some((c, mask));
        }
    }
    let (cost, mask) = best?;
    let side: Vec<bool> = (0..n).map(|i| mask >> i & 1 == 1).collect();
    let parts = parts_of(pixels, &side);
    Some((cost, side, parts))
}

/// Tracks ahead of the current one whose recent detections are prefetched.
pub(super) const PREFETCH_AHEAD: usize = 6;

/// Append the indices of the `false` entries of `used` to `idx` (a plain
/// loop: the filtered `extend` it replaces cost ~20 instructions per
/// particle, 4 % of the linking).
pub(super) fn unused_indices(used: &[bool], idx: &mut Vec<usize>) {
    for (i, &u) in used.iter().enumerate() {
        if !u {
            idx.push(i);
        }
    }
}

/// Ask the CPU to fetch the last `window` detections of a track into the
/// cache. Every pulse the tracker touches the recent history of each of
/// its ~3000 active tracks, each in its own heap block: without this the
/// walk is one cache miss after another (~40 % of the tracking thread's
/// cycles at full frame). A hint only: it changes no result.
#[inline]
pub(super) fn prefetch_window(dets: &[Det], window: usize) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        let tail = &dets[dets.len().saturating_sub(window)..];
        let bytes = std::mem::size_of_val(tail);
        let base = tail.as_ptr() as *const i8;
        for off in (0..bytes).step_by(64) {
            // SAFETY: a prefetch never faults, and the address is inside `tail`.
            unsafe { _mm_prefetch::<_MM_HINT_T0>(base.wrapping_add(off)) };
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = (dets, window);
}
