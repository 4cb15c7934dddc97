//! Gating and assignment (stage 2 of the module doc): the candidates inside
//! each track's search radius, the global minimum-cost assignment
//! ([`super::lap`]), and the innovations that estimate the position noise.

use super::*;

impl Tracker {
    /// Extend active tracks with this pulse's detections (global
    /// assignment); returns the used flags of the detections.
    pub(super) fn extend_active(&mut self, dets: &[Det], pulse: i64) -> FrameLinks {
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
        for ti in 0..self.active.len() {
            if let Some(ahead) = self.active.get(ti + PREFETCH_AHEAD) {
                prefetch_window(&ahead.dets, self.params.gates.predict_window);
            }
            let (px, py, r, l) = self.predict(ti, pulse);
            sc.leverage.push(l);
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
        let sol = lap::assign_sparse(dets.len(), &sc.edges, &sc.miss);
        let flow_on = self.params.init.ghost_check_length > 0;
        for (ti, c) in sol.into_iter().enumerate() {
            // The tracks' tails were evicted by the assignment: fetch the
            // last detection (read here) and the slot it is appended to.
            if let Some(ahead) = self.active.get(ti + PREFETCH_AHEAD) {
                prefetch_window(&ahead.dets, 1);
            }
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
                self.active[ti].dets.push(dets[c]);
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
