//! Gap bridging and stitching (stages 3 and 5 of the module doc): the
//! repair of recent links, the backward extension of new tracks into the
//! pulses before their start, and the stitching of new chains to tracks that
//! ended in the last `stitch_gap` pulses (extrapolation across the gap, the
//! joint turning path test).

use super::*;

/// The stitching tolerance across `gap` missed pulses (px):
/// `gates.min_search_radius` growing by `stitch.stitch_growth` per pulse,
/// never beyond what a particle can travel (`max_disp` per pulse, the
/// linking gates' bound too): an absurd growth would make every ended
/// track a candidate for every new chain (10^12 ran for minutes).
pub(super) fn stitch_tolerance(p: &TrackParams, gap: i64) -> f64 {
    (p.gates.min_search_radius * (1.0 + p.stitch.stitch_growth * gap as f64))
        .min(p.max_disp * (gap + 1) as f64)
}

impl Tracker {
    /// Record `t` as the owner of its detections in the kept frames.
    pub(super) fn set_owner(&mut self, t: &ActiveTrack) {
        for f in self.frames.iter_mut().chain(self.back_frames.iter_mut()) {
            if let Ok(i) = t.dets.binary_search_by_key(&f.pulse, |d| d.pulse) {
                if let Some(j) = f.index_of(t.dets[i].serial) {
                    f.owner[j] = t.uid;
                }
            }
        }
    }

    /// Position of an active track at `pulse` from a fit of its
    /// detections on both sides (pulse itself excluded), with the gate
    /// for a particle there: (x, y, radius).
    pub(super) fn smoothed(&self, t: &ActiveTrack, pulse: i64) -> Option<(f64, f64, f64)> {
        const N: usize = 2 * REPAIR_WINDOW as usize;
        let lo = t.dets.partition_point(|d| d.pulse < pulse - REPAIR_WINDOW);
        let hi = t.dets.partition_point(|d| d.pulse <= pulse + REPAIR_WINDOW);
        let (mut tau, mut xs, mut ys) = ([0.0; N], [0.0; N], [0.0; N]);
        let mut n = 0;
        for d in t.dets[lo..hi].iter().filter(|d| d.pulse != pulse).take(N) {
            tau[n] = (d.pulse - pulse) as f64;
            xs[n] = d.x;
            ys[n] = d.y;
            n += 1;
        }
        if n < 3 {
            return None;
        }
        let f = fit::fit_eval(&tau[..n], &xs[..n], &ys[..n], self.predict_order(n), 0.0)?;
        let (r, _) = self.search_radius(f.leverage, 1);
        Some((f.x, f.y, r))
    }

    /// Revisit the links of pulse `k` (see `TrackParams::repair_lag`).
    pub(super) fn repair(&mut self, k: i64) {
        let Some(fi) = self.frames.iter().position(|f| f.pulse == k) else {
            return;
        };
        let frame = &self.frames[fi];
        if frame.dets.is_empty() {
            return;
        }
        let find =
            |active: &[ActiveTrack], uid: u64| active.binary_search_by_key(&uid, |t| t.uid).ok();
        // Seeds: tracks that missed k. (Seeding also the owners of
        // particles in several gates or far from their prediction helps
        // the densest scenes, ppp 0.02 at 12 px/pulse: precision 0.754 →
        // 0.768, but not paper-like ones, and costs 7 % more linking.)
        let mut rows: Vec<usize> = frame
            .hungry
            .iter()
            .filter_map(|&uid| find(&self.active, uid))
            .collect();
        if rows.is_empty() {
            return;
        }
        rows.sort_unstable();
        rows.dedup();
        let mut row_of = vec![usize::MAX; self.active.len()];
        for (row, &ti) in rows.iter().enumerate() {
            row_of[ti] = row;
        }
        // Two-sided positions; owners of the seeds' candidates join in.
        let mut fits: Vec<Option<(f64, f64, f64)>> = Vec::new();
        let mut near = Vec::new();
        let mut i = 0;
        while i < rows.len() {
            let t = &self.active[rows[i]];
            let fit = if t.dets.len() < INIT_FRAMES
                || t.dets.partition_point(|d| d.pulse < k) < t.context
            {
                // Too short to lose a detection, or inside an already
                // handed-out segment: keeps what it has.
                None
            } else {
                self.smoothed(t, k)
            };
            fits.push(fit);
            if let Some((x, y, r)) = fit {
                near.clear();
                frame.grid.within(x, y, r, &mut near);
                for &(j, _) in &near {
                    let o = frame.owner[j as usize];
                    if o != NO_OWNER {
                        if let Some(ti) = find(&self.active, o) {
                            if row_of[ti] == usize::MAX {
                                row_of[ti] = rows.len();
                                rows.push(ti);
                            }
                        }
                    }
                }
            }
            i += 1;
        }
        // Particles in play: unused ones and those of the rows' tracks.
        let mut edges = Vec::new();
        let current: Vec<Option<usize>> = rows
            .iter()
            .map(|&ti| {
                let t = &self.active[ti];
                t.dets
                    .binary_search_by_key(&k, |d| d.pulse)
                    .ok()
                    .and_then(|i| frame.index_of(t.dets[i].serial))
            })
            .collect();
        // Particles of rows without a fit stay where they are.
        let mut locked = vec![false; frame.dets.len()];
        for (fit, cur) in fits.iter().zip(&current) {
            if let (None, Some(c)) = (fit, cur) {
                locked[*c] = true;
            }
        }
        for (row, (fit, &cur)) in fits.iter().zip(&current).enumerate() {
            let Some((x, y, r)) = *fit else {
                if let Some(c) = cur {
                    edges.push((row, c, 0.0));
                }
                continue;
            };
            near.clear();
            frame.grid.within(x, y, r, &mut near);
            for &(j, d2) in &near {
                let o = frame.owner[j as usize];
                if locked[j as usize] {
                    continue;
                }
                let free = o == NO_OWNER && !frame.used[j as usize];
                if free || find(&self.active, o).is_some_and(|ti| row_of[ti] != usize::MAX) {
                    edges.push((row, j as usize, d2 / (r * r)));
                }
            }
        }
        let sol = lap::assign_sparse(frame.dets.len(), &edges, &vec![1.0; rows.len()]);
        if sol == current {
            return;
        }
        let frame = &mut self.frames[fi];
        for (row, &ti) in rows.iter().enumerate() {
            if sol[row] == current[row] {
                continue;
            }
            let t = &mut self.active[ti];
            if let Some(c) = current[row] {
                let i = t
                    .dets
                    .binary_search_by_key(&k, |d| d.pulse)
                    .expect("current particle");
                t.dets.remove(i);
                if frame.owner[c] == t.uid {
                    frame.owner[c] = NO_OWNER;
                    frame.used[c] = false;
                }
            }
            if let Some(c) = sol[row] {
                let i = t.dets.partition_point(|d| d.pulse < k);
                t.dets.insert(i, frame.dets[c]);
                frame.owner[c] = t.uid;
                frame.used[c] = true;
            }
        }
    }

    /// Extend new tracks backwards through the unused particles of the
    /// `back_extend` pulses before their first detection: per older pulse
    /// each track predicts where its particle was (the predictor's fit over
    /// its first detections, extrapolated backwards, with the forward
    /// gate), and the candidates are assigned globally like a forward step.
    /// A track stops when it would bridge more than `max_gap` pulses.
    pub(super) fn extend_backward(&mut self, tracks: &mut [ActiveTrack]) {
        // Older frames, newest first: those of `frames` before the
        // gap-free chains' first frame (with `init_gap`), then `back_frames`.
        let in_frames = self.frames.len().saturating_sub(INIT_FRAMES);
        let older: Vec<(bool, usize)> = (0..in_frames)
            .rev()
            .map(|i| (true, i))
            .chain((0..self.back_frames.len()).rev().map(|i| (false, i)))
            .collect();
        if tracks.is_empty() || older.is_empty() || self.params.init.back_extend == 0 {
            return;
        }
        let p = &self.params;
        let w = p.gates.predict_window;
        let max_gap = p.max_gap as i64;
        let mut sc = std::mem::take(&mut self.scratch);
        let mut idx: Vec<usize> = Vec::new();
        for &(in_f, fi) in &older {
            let frame = if in_f {
                &self.frames[fi]
            } else {
                &self.back_frames[fi]
            };
            let reach = |ti: usize| tracks[ti].dets[0].pulse - frame.pulse - 1 <= max_gap;
            let open: Vec<usize> = (0..tracks.len())
                .filter(|&ti| tracks[ti].dets[0].pulse > frame.pulse && reach(ti))
                .collect();
            if open.is_empty() {
                if (0..tracks.len()).any(reach) {
                    continue; // tracks that start at or before this frame
                }
                break;
            }
            idx.clear();
            unused_indices(&frame.used[..frame.dets.len()], &mut idx);
            if idx.is_empty() {
                continue;
            }
            sc.edges.clear();
            for (row, &ti) in open.iter().enumerate() {
                let dets = &tracks[ti].dets;
                let n = dets.len().min(w).min(BACK_FIT_WINDOW);
                let first = dets[0].pulse;
                let (mut tau, mut xs, mut ys) = (
                    [0.0; BACK_FIT_WINDOW],
                    [0.0; BACK_FIT_WINDOW],
                    [0.0; BACK_FIT_WINDOW],
                );
                for (i, d) in dets[..n].iter().enumerate() {
                    tau[i] = (d.pulse - first) as f64;
                    xs[i] = d.x;
                    ys[i] = d.y;
                }
                let order = self.predict_order(n);
                let at = (frame.pulse - first) as f64;
                let turned = if !self.params.turn_model {
                    None
                } else if order >= 2 {
                    turn::turn_eval(&tau[..n], &xs[..n], &ys[..n], at, true)
                        .map(|t| (t.x, t.y, t.leverage))
                } else {
                    // The line: young tracks' turning choice here cost the
                    // synthetic paper-like scene recall (0.9505 → 0.9493)
                    // and did not help the vortex.
                    young_prediction(
                        &tau[..n],
                        &xs[..n],
                        &ys[..n],
                        at,
                        self.position_sigma(),
                        0.0,
                    )
                };
                let f = match turned {
                    Some((x, y, leverage)) => fit::FitState {
                        x,
                        y,
                        vx: 0.0,
                        vy: 0.0,
                        ax: 0.0,
                        ay: 0.0,
                        rms_residual: 0.0,
                        leverage,
                        velocity_variance: 0.0,
                    },
                    None => {
                        let Some(f) = fit::fit_eval(&tau[..n], &xs[..n], &ys[..n], order, at)
                        else {
                            continue;
                        };
                        f
                    }
                };
                let (r, _) = self.search_radius(f.leverage, first - frame.pulse);
                // The frame's grid over all its particles, the used ones
                // passed over: the candidates (in particle order) and
                // distances a grid over the unused ones gives, without
                // building one per frame and pulse.
                sc.near.clear();
                frame.grid.within(f.x, f.y, r, &mut sc.near);
                for &(j, d2) in &sc.near {
                    if !frame.used[j as usize] {
                        sc.edges.push((row, j as usize, d2 / (r * r)));
                    }
                }
            }
            if sc.edges.is_empty() {
                continue;
            }
            let sol = lap::assign_sparse(frame.dets.len(), &sc.edges, &vec![1.0; open.len()]);
            let frame = if in_f {
                &mut self.frames[fi]
            } else {
                &mut self.back_frames[fi]
            };
            for (row, c) in sol.into_iter().enumerate() {
                if let Some(c) = c {
                    frame.used[c] = true;
                    tracks[open[row]].dets.insert(0, frame.dets[c]);
                }
            }
        }
        self.scratch = sc;
    }

    /// Join new chains to ended tracks in the pool where both extrapolate
    /// onto each other across the gap; returns the chains left unjoined.
    pub(super) fn stitch(&mut self, chains: Vec<ActiveTrack>) -> Vec<ActiveTrack> {
        if self.pool.is_empty() || chains.is_empty() {
            return chains;
        }
        let sigma = self.position_sigma();
        let p = &self.params;
        let mut edges = Vec::new();
        for (ri, old) in self.pool.iter().enumerate() {
            let end = old.last();
            // Chains start at the same pulse unless extended backwards:
            // each ended track is extrapolated once per start pulse.
            let mut fwd_at: Vec<(i64, Option<(f64, f64)>)> = Vec::new();
            for (ci, new) in chains.iter().enumerate() {
                let start = &new.dets[0];
                let gap = start.pulse - end.pulse - 1;
                if gap < 0 || gap > p.stitch.stitch_gap as i64 {
                    continue;
                }
                let r = stitch_tolerance(p, gap);
                // Out of reach whatever the extrapolation (cheap test first).
                let reach = (gap + 1) as f64 * p.max_disp + 2.0 * r;
                if (end.x - start.x).powi(2) + (end.y - start.y).powi(2) > reach * reach {
                    continue;
                }
                // Never across a region that is not flow (a wall, a model).
                if p.mask
                    .as_ref()
                    .is_some_and(|m| m.crosses((end.x, end.y), (start.x, start.y)))
                {
                    continue;
                }
                let fwd = match fwd_at.iter().find(|e| e.0 == start.pulse) {
                    Some(e) => e.1,
                    None => {
                        let f =
                            extrapolate(&old.dets, p.gates.predict_window, start.pulse, p, sigma);
                        fwd_at.push((start.pulse, f));
                        f
                    }
                };
                let Some(fwd) = fwd else {
                    continue;
                };
                let fwd_d2 = (fwd.0 - start.x).powi(2) + (fwd.1 - start.y).powi(2);
                if fwd_d2 > 2.0 * r * r {
                    continue;
                }
                // The old track's extrapolation reaches the chain, and one
                // turning path through both pieces has the residuals of
                // the position noise: the pair joins even where the young
                // chain's own line back across the gap is off (a vortex
                // core).
                if p.turn_model {
                    if let Some(z) = joint_turn_cost(&old.dets, &new.dets, sigma) {
                        if z <= 1.0 {
                            edges.push((ri, ci, z.max(0.5 * fwd_d2 / (r * r))));
                            continue;
                        }
                    }
                }
                let fwd = Some(fwd);
                let bwd = extrapolate(&new.dets, p.gates.predict_window, end.pulse, p, sigma);
                let (Some(fwd), Some(bwd)) = (fwd, bwd) else {
                    continue;
                };
                let e = ((fwd.0 - start.x).powi(2)
                    + (fwd.1 - start.y).powi(2)
                    + (bwd.0 - end.x).powi(2)
                    + (bwd.1 - end.y).powi(2))
                    / 2.0;
                if e <= r * r {
                    edges.push((ri, ci, e / (r * r)));
                }
            }
        }
        let sol = lap::assign_sparse(chains.len(), &edges, &vec![1.0; self.pool.len()]);
        let mut chain_taken = vec![false; chains.len()];
        let mut revived = Vec::new();
        for (ri, c) in sol.iter().enumerate() {
            if let Some(c) = *c {
                chain_taken[c] = true;
                revived.push((ri, c));
            }
        }
        let mut chains: Vec<Option<ActiveTrack>> = chains.into_iter().map(Some).collect();
        let mut pool: Vec<Option<ActiveTrack>> = std::mem::take(&mut self.pool)
            .into_iter()
            .map(Some)
            .collect();
        for (ri, c) in revived {
            let mut old = pool[ri].take().expect("each pool row matched once");
            old.dets
                .extend(chains[c].take().expect("each chain matched once").dets);
            self.set_owner(&old);
            let at = self.active.partition_point(|t| t.uid < old.uid);
            self.active.insert(at, old);
            self.stats.tracks_stitched += 1;
        }
        self.pool = pool.into_iter().flatten().collect();
        chains.into_iter().flatten().collect()
    }
}

/// Detections of each piece the stitch test's joint turning path fits.
pub(super) const JOINT_SIDE: usize = 8;

/// Cost of joining `old` to `new` (which starts after it) by one turning
/// path ([`turn::turn_rss`]) through the last [`JOINT_SIDE`] detections
/// of `old` and the first of `new`: its residual sum of squares over the
/// position noise `sigma`², in units of the χ² bound `dof + 3·√(2 dof)`
/// (dof = 2·points − 7); ≤ 1 is a fit by noise alone. `None`: fewer than
/// 6 detections on the old side or 10 in all.
pub(super) fn joint_turn_cost(old: &[Det], new: &[Det], sigma: f64) -> Option<f64> {
    let a = old.len().min(JOINT_SIDE);
    let b = new.len().min(JOINT_SIDE);
    if a < 6 || a + b < 10 || sigma <= 0.0 {
        return None;
    }
    let t0 = old[old.len() - 1].pulse;
    let (mut tau, mut xs, mut ys) = (
        [0.0; 2 * JOINT_SIDE],
        [0.0; 2 * JOINT_SIDE],
        [0.0; 2 * JOINT_SIDE],
    );
    for (i, d) in old[old.len() - a..].iter().chain(&new[..b]).enumerate() {
        tau[i] = (d.pulse - t0) as f64;
        xs[i] = d.x;
        ys[i] = d.y;
    }
    let m = a + b;
    let rss = turn::turn_rss(&tau[..m], &xs[..m], &ys[..m])?;
    let dof = (2 * m - 7) as f64;
    Some(rss / (sigma * sigma) / (dof + 3.0 * (2.0 * dof).sqrt()))
}

/// Extrapolation of the positions of `dets` (the `window` detections
/// nearest to `pulse`) to pulse `pulse`: the turning path ([`turn`],
/// with `turn_model`, from 6 detections on), else a line through the
/// nearest `INIT_FRAMES` (`sigma`: the position noise).
pub(super) fn extrapolate(
    dets: &[Det],
    window: usize,
    pulse: i64,
    p: &TrackParams,
    sigma: f64,
) -> Option<(f64, f64)> {
    let n = dets.len();
    let forward = pulse >= dets[n - 1].pulse;
    let w = window.min(n).clamp(1, 64);
    if p.turn_model && w >= 2 * INIT_FRAMES - 2 {
        let win = if forward { &dets[n - w..] } else { &dets[..w] };
        let (mut tau, mut xs, mut ys) = ([0.0; 64], [0.0; 64], [0.0; 64]);
        for (i, d) in win.iter().enumerate() {
            tau[i] = (d.pulse - pulse) as f64;
            xs[i] = d.x;
            ys[i] = d.y;
        }
        if let Some(f) = turn::turn_eval(&tau[..w], &xs[..w], &ys[..w], 0.0, true) {
            return Some((f.x, f.y));
        }
    }
    let w = if p.turn_model { w.min(INIT_FRAMES) } else { w };
    let win = if forward { &dets[n - w..] } else { &dets[..w] };
    let tau: Vec<f64> = win.iter().map(|d| d.pulse as f64 - pulse as f64).collect();
    let xs: Vec<f64> = win.iter().map(|d| d.x).collect();
    let ys: Vec<f64> = win.iter().map(|d| d.y).collect();
    if p.turn_model {
        return young_prediction(&tau, &xs, &ys, 0.0, sigma, 0.0).map(|(x, y, _)| (x, y));
    }
    fit::fit_eval(&tau, &xs, &ys, 1, 0.0).map(|f| (f.x, f.y))
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;

    #[ebptv_macros::unit_test]
    fn stitch_tolerance_grows_with_the_gap_up_to_the_travel_bound() {
        let p = TrackParams::default();
        // The defaults lie below the bound: 1.5 px growing by a quarter
        // per missed pulse.
        for gap in 0..=3 {
            let expect = p.gates.min_search_radius * (1.0 + 0.25 * gap as f64);
            assert_eq!(stitch_tolerance(&p, gap), expect);
        }
        let mut huge = p.clone();
        huge.stitch.stitch_growth = 1e12;
        huge.gates.min_search_radius = 1e12;
        for gap in 0..=3 {
            assert_eq!(stitch_tolerance(&huge, gap), p.max_disp * (gap + 1) as f64);
        }
    }
}
