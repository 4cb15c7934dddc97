//! Particle images onto pixels: where each image falls (`footprint`, the
//! streak positions of `pulse_streaks`), the order particles are rendered
//! in, and the fast separable renderers that add pixel-integrated Gaussian
//! images row by row into a per-thread ring of ROI rows (`particle_rows`,
//! the lean single-position and diagonal-streak kernels, the interval-table
//! `particle_rows_quad`), with the ring itself (`RowRing`, `RingRows`) and
//! the scratch records the response pass reads (`Hit`, `Lit`).

use super::*;

impl PixelModel {
    /// Pixel-integrated Gaussian image of a particle at (x, y): calls
    /// `f(ix, iy, fraction)` for each ROI pixel it covers.
    #[cfg(feature = "testkit")]
    #[inline]
    pub(super) fn footprint(&self, x: f64, y: f64, mut f: impl FnMut(u32, u32, f64)) {
        let erf = erf_table();
        let s = self.sigma_img;
        let reach = 3.0 * s;
        let k = std::f64::consts::FRAC_1_SQRT_2 / s;
        let (rx0, ry0) = (self.roi.x as i64, self.roi.y as i64);
        let (rx1, ry1) = (
            rx0 + self.roi.width as i64 - 1,
            ry0 + self.roi.height as i64 - 1,
        );
        let i0 = round_i64(x - reach).max(rx0);
        let i1 = round_i64(x + reach).min(rx1);
        let j0 = round_i64(y - reach).max(ry0);
        let j1 = round_i64(y + reach).min(ry1);
        if i0 > i1 || j0 > j1 {
            return;
        }
        // Pixel-integrated Gaussian: differences of erf at the pixel edges,
        // each edge evaluated once.
        let nx = ((i1 - i0 + 1) as usize).min(31);
        let mut ex = [0.0f64; 32];
        for (a, e) in ex.iter_mut().enumerate().take(nx + 1) {
            *e = erf.eval((i0 as f64 + a as f64 - 0.5 - x) * k);
        }
        let mut ey_lo = erf.eval((j0 as f64 - 0.5 - y) * k);
        for j in j0..=j1 {
            let ey_hi = erf.eval((j as f64 + 0.5 - y) * k);
            let fy = 0.5 * (ey_hi - ey_lo);
            ey_lo = ey_hi;
            for a in 0..nx {
                f(
                    (i0 + a as i64) as u32,
                    j as u32,
                    0.5 * (ex[a + 1] - ex[a]) * fy,
                );
            }
        }
    }

    /// Image positions of a particle during the pulse and their weights.
    #[cfg(feature = "testkit")]
    pub(super) fn positions(&self, s: &Snapshot, out: &mut Vec<(f64, f64, f64)>) {
        out.clear();
        match self.streak_scale {
            None => out.push((s.x, s.y, 1.0)),
            Some(scale) => {
                let len = (s.u.hypot(s.v)) * self.shape.end_us * 1e-6 * scale;
                let m = ((len / 0.2).ceil() as usize).clamp(1, 32);
                let mut total = 0.0;
                for j in 0..m {
                    let t = (j as f64 + 0.5) / m as f64 * self.shape.end_us;
                    let w = envelope(&self.light, t);
                    let dt = t * 1e-6 * scale;
                    out.push((s.x + s.u * dt, s.y + s.v * dt, w));
                    total += w;
                }
                for p in out.iter_mut() {
                    p.2 /= total;
                }
            }
        }
    }

    /// The order particles are rendered in, with the row bounds of their
    /// images: `(key, row_lo, row_hi)` sorted by key, where `key` packs
    /// `row_lo` (the lowest sensor row any of the particle's streak
    /// positions can touch, a lower bound) above the snapshot index, and
    /// `row_hi` is the matching upper bound.
    ///
    /// Rendering by `row_lo` is what lets [`render_pulse`] finish (drain)
    /// every row below the current particle's `row_lo`: no later particle
    /// can reach it. `sorted_by_reference`: a comparison sort (the
    /// reference path) instead of the radix sort.
    pub(super) fn render_order(
        &self,
        snaps: &[Snapshot],
        sorted_by_reference: bool,
    ) -> Vec<(u64, i64, i64)> {
        let reach = 3.0 * self.sigma_img;
        let streak_s = self
            .streak_scale
            .map_or(0.0, |scale| self.shape.end_us * 1e-6 * scale);
        let mut order: Vec<(u64, i64, i64)> = snaps
            .iter()
            .enumerate()
            .map(|(i, s)| {
                // Streak positions lie between y and y + v·t_end·scale.
                let dy = s.v * streak_s;
                let y_lo = s.y.min(s.y + dy).clamp(-1e6, 1e6);
                let y_hi = s.y.max(s.y + dy).clamp(-1e6, 1e6);
                // (1e-6 px of slack for rounding in the streak positions.)
                let lo = round_i64(y_lo - reach - 1e-6);
                let hi = round_i64(y_hi + reach + 1e-6);
                (((lo + (1 << 24)) as u64) << 32 | i as u64, lo, hi)
            })
            .collect();
        if sorted_by_reference {
            order.sort_unstable_by_key(|o| o.0);
            return order;
        }
        // Keys are (row_lo, index) and `order` is in index order: a stable
        // counting sort by row_lo gives the comparison sort's order.
        let lo_min = order.iter().map(|o| o.1).min().unwrap_or(0);
        let lo_max = order.iter().map(|o| o.1).max().unwrap_or(0);
        let range = (lo_max - lo_min) as usize + 1;
        if range > 4 * order.len() + 4096 {
            // Sparse rows (far-out streaks): the radix sort of the keys.
            let mut keys: Vec<u64> = order.iter().map(|o| o.0).collect();
            crate::radix_sort(&mut keys, &mut Vec::new());
            return keys
                .iter()
                .map(|&k| order[(k & 0xFFFF_FFFF) as usize])
                .collect();
        }
        let mut start = vec![0u32; range + 1];
        for o in &order {
            start[(o.1 - lo_min) as usize + 1] += 1;
        }
        for r in 1..=range {
            start[r] += start[r - 1];
        }
        let mut sorted = vec![(0u64, 0i64, 0i64); order.len()];
        for o in &order {
            let slot = &mut start[(o.1 - lo_min) as usize];
            sorted[*slot as usize] = *o;
            *slot += 1;
        }
        sorted
    }

    /// Signal contributions of one particle's image by the test oracle
    /// ([`Exact`]): `f(ix, iy, signal)` (sensor pixel coordinates inside
    /// the ROI).
    #[cfg(feature = "testkit")]
    pub(super) fn particle_contributions(&self, s: &Snapshot, f: impl FnMut(u32, u32, f64)) {
        Exact.draw(self, s, &mut Profiles::new(), &mut EachPixel(f, 0));
    }

    /// Image positions of a particle during the pulse as offsets along its
    /// velocity: `(dt, weight)` per position for a streak of `m`
    /// positions (index m − 1), the same numbers [`positions`] computes
    /// per particle (weights depend on m only).
    pub(super) fn streak_table(
        light: &Light,
        shape: &PulseShape,
        scale: f64,
    ) -> Vec<Vec<(f64, f64)>> {
        (1..=32usize)
            .map(|m| {
                let mut v: Vec<(f64, f64)> = (0..m)
                    .map(|j| {
                        let t = (j as f64 + 0.5) / m as f64 * shape.end_us;
                        (t * 1e-6 * scale, envelope(light, t))
                    })
                    .collect();
                let mut total = 0.0;
                for p in &v {
                    total += p.1;
                }
                for p in v.iter_mut() {
                    p.1 /= total;
                }
                v
            })
            .collect()
    }

    /// The fast path's image of one particle, as per-pixel signals:
    /// `f(ix, iy, signal)` (for tests; the renderer takes them row by row
    /// through [`Self::particle_rows`]).
    #[cfg(feature = "testkit")]
    pub(super) fn particle_contributions_fast(&self, s: &Snapshot, f: impl FnMut(u32, u32, f64)) {
        Rows.draw(self, s, &mut Profiles::new(), &mut EachPixel(f, 0));
    }

    /// Draws `s` into the ring behind `sink` with the first production
    /// renderer that takes it: [`Lean`] (small images straight into the
    /// ring), else [`Rows`]. The one place the renderers are chosen.
    #[inline(always)]
    pub(super) fn draw_particle(
        &self,
        s: &Snapshot,
        prof: &mut Profiles,
        sink: &mut impl ContributionSink,
    ) {
        if !Lean.draw(self, s, prof, sink) {
            Rows.draw(self, s, prof, sink);
        }
    }

    /// Streak positions of `s` as `(dt, weight)` offsets along its
    /// velocity (from [`Self::streak_table`]; one position at rest or
    /// without `pulse_streaks`).
    #[inline(always)]
    pub(super) fn streak_nodes_of(&self, s: &Snapshot) -> &[(f64, f64)] {
        const SINGLE: &[(f64, f64)] = &[(0.0, 1.0)];
        match self.streak_scale {
            None => SINGLE,
            Some(scale) => {
                let count = |speed: f64| speed * self.shape.end_us * 1e-6 * scale / 0.2;
                let q = if s.v == 0.0 {
                    count(s.u.abs())
                } else if s.u == 0.0 {
                    count(s.v.abs())
                } else {
                    // libm's hypot was 2–5 % of the CPU of the unsteady
                    // presets. √(u² + v²) is within 2 ulp of it, and
                    // times the precomputed `streak_per_speed` (one
                    // multiplication for `count`'s three and a division,
                    // each step within ½ ulp) within ~1e-15 relative of
                    // `count(hypot)`: the two node counts ⌈q⌉ can differ
                    // only when q is within ~1e-15·q of an integer. There
                    // (within 1e-12·q, and for tiny, huge or non-finite
                    // q) hypot decides, so the count is hypot's exactly.
                    let q = (s.u * s.u + s.v * s.v).sqrt() * self.streak_per_speed;
                    if q > 1e-3 && q < 1e12 {
                        // SAFETY: 0 < q < 1e12: in i64's range.
                        let t = unsafe { q.to_int_unchecked::<i64>() };
                        let frac = q - t as f64;
                        if frac > 1e-12 * q && frac < 1.0 - 1e-12 * q {
                            // (q is not an integer: ⌈q⌉ = t + 1, ≥ 1.)
                            return &self.streak_nodes[(t as usize).min(31)];
                        }
                    }
                    Self::streak_count_hypot(s, count)
                };
                &self.streak_nodes[ceil_count(q, 32) - 1]
            }
        }
    }

    /// [`Self::streak_nodes_of`]'s rare exact case, out of line.
    #[cold]
    #[inline(never)]
    pub(super) fn streak_count_hypot(s: &Snapshot, count: impl Fn(f64) -> f64) -> f64 {
        count(s.u.hypot(s.v))
    }

    /// The pixels [`Self::footprint`] covers along one axis for a centre
    /// at `c`, clipped to `[r0, r1]` and to at most `cap` pixels: (first
    /// pixel, count).
    #[inline]
    pub(super) fn axis_range(&self, c: f64, r0: i64, r1: i64, cap: usize) -> (i64, usize) {
        let reach = 3.0 * self.sigma_img;
        let i0 = round_i64(c - reach).max(r0);
        let i1 = round_i64(c + reach).min(r1);
        if i0 > i1 {
            (i0, 0)
        } else {
            (i0, ((i1 - i0 + 1) as usize).min(cap))
        }
    }

    /// The fast path's image of one particle, row by row: `sink.row(iy)`,
    /// then `sink.add_run(ix0, fractions, scale)` adds `scale·fractions[a]`
    /// to pixel `ix0 + a` of row iy.
    ///
    /// The same model as [`Self::particle_contributions`] (tested within
    /// 1e-5 relative), computed differently: pixel fractions come from the
    /// [`FractionTable`] in f32 rather than from erf at every pixel edge,
    /// and a streak whose positions share a row coordinate (v = 0, the
    /// jet's case; or share a column, u = 0) is one separable image —
    /// the weighted sum of its positions' x profiles times the common y
    /// profile — added to the ring once instead of once per position.
    #[inline]
    pub(super) fn particle_rows(
        &self,
        s: &Snapshot,
        prof: &mut Profiles,
        sink: &mut impl ContributionSink,
    ) {
        if let Some(q) = &self.quad {
            if self.particle_rows_quad(q, s, prof, sink) {
                return;
            }
        }
        let amp = self.gain * s.brightness;
        let nodes = self.streak_nodes_of(s);
        let (rx0, ry0) = (self.roi.x as i64, self.roi.y as i64);
        let (rx1, ry1) = (
            rx0 + self.roi.width as i64 - 1,
            ry0 + self.roi.height as i64 - 1,
        );
        // (The single position has dt = 0: the centre itself.)
        let at = |c: f64, dir: f64, dt: f64| c + dir * dt;
        let Profiles { fx, fy, one } = prof;
        if nodes.len() == 1 || s.v == 0.0 || s.u == 0.0 {
            // Separable: one profile along the shared axis, the other the
            // weighted sum over positions (union of their ranges).
            let shared_y = nodes.len() == 1 || s.v == 0.0;
            // (With one position the shared coordinate is that position's;
            // with several it is the same for all: v = 0 or u = 0.)
            let dt0 = nodes[0].0;
            let (c_shared, c_moving, v_moving) = if shared_y {
                (at(s.y, s.v, dt0), s.x, s.u)
            } else {
                (at(s.x, s.u, dt0), s.y, s.v)
            };
            let (s0, s1, m0, m1, s_cap, m_cap) = if shared_y {
                (ry0, ry1, rx0, rx1, AXIS_MAX, X_CAP)
            } else {
                (rx0, rx1, ry0, ry1, X_CAP, AXIS_MAX)
            };
            let (slo, sn) = self.axis_range(c_shared, s0, s1, s_cap);
            if sn == 0 {
                return;
            }
            let (mut lo, mut hi) = (i64::MAX, i64::MIN);
            for &(dt, _) in nodes {
                let (r0, rn) = self.axis_range(at(c_moving, v_moving, dt), m0, m1, m_cap);
                if rn > 0 {
                    lo = lo.min(r0);
                    hi = hi.max(r0 + rn as i64 - 1);
                }
            }
            if lo > hi {
                return;
            }
            let mn = (hi - lo + 1) as usize;
            if mn <= MERGE_MAX {
                let (shared, moving) = if shared_y {
                    (&mut *fy, &mut *fx)
                } else {
                    (&mut *fx, &mut *fy)
                };
                self.table.eval(c_shared, slo, &mut shared[..sn]);
                if nodes.len() == 1 {
                    self.table
                        .eval(at(c_moving, v_moving, dt0), lo, &mut moving[..mn]);
                } else {
                    moving[..mn].fill(0.0);
                    for &(dt, pw) in nodes {
                        let c = at(c_moving, v_moving, dt);
                        let (r0, rn) = self.axis_range(c, m0, m1, m_cap);
                        if rn == 0 {
                            continue;
                        }
                        self.table.eval(c, r0, &mut one[..rn]);
                        let dst = &mut moving[(r0 - lo) as usize..][..rn];
                        let w = pw as f32;
                        for (d, &o) in dst.iter_mut().zip(&one[..rn]) {
                            *d += w * o;
                        }
                    }
                }
                let (xlo, nx, ylo, ny) = if shared_y {
                    (lo, mn, slo, sn)
                } else {
                    (slo, sn, lo, mn)
                };
                emit_rows(sink, xlo, &fx[..nx], ylo, &fy[..ny], amp as f32);
                return;
            }
        }
        // General streak (or one too long to merge): position by position.
        for &(dt, pw) in nodes {
            let (px, py) = (at(s.x, s.u, dt), at(s.y, s.v, dt));
            let (xlo, nx) = self.axis_range(px, rx0, rx1, X_CAP);
            let (ylo, ny) = self.axis_range(py, ry0, ry1, AXIS_MAX);
            if nx == 0 || ny == 0 {
                continue;
            }
            self.table.eval(px, xlo, &mut fx[..nx]);
            self.table.eval(py, ylo, &mut fy[..ny]);
            emit_rows(sink, xlo, &fx[..nx], ylo, &fy[..ny], (amp * pw) as f32);
        }
    }

    /// The common case of [`Self::particle_rows`] straight into the ring
    /// (no [`ContributionSink`] calls): a small image ([`QuadTable`])
    /// whose positions share their row coordinate (one position, or
    /// v = 0), at most [`LEAN_NODES`] positions, every window from the
    /// table's fixed lanes and inside the ROI. The same numbers, added
    /// in the same order, as `particle_rows` (`lean_images_match_particle_rows`).
    /// General (diagonal) streaks of at most [`LEAN_NODES`] positions go
    /// to [`Self::particle_lean_diagonal`].
    /// Returns the box written, or None, having written nothing, when
    /// the particle is not such a case.
    #[inline(always)]
    pub(super) fn particle_lean(
        &self,
        q: &QuadTable,
        s: &Snapshot,
        sig: &mut [f32],
        mask: usize,
        stride: usize,
    ) -> Option<ImageBox> {
        let nodes = self.streak_nodes_of(s);
        let m = nodes.len();
        if m > LEAN_NODES {
            return None;
        }
        if !(m == 1 || s.v == 0.0) {
            // (u = 0 is `particle_rows`' separable case: not lean.)
            if s.u == 0.0 {
                return None;
            }
            return self.particle_lean_diagonal(q, s, nodes, sig, mask, stride);
        }
        let (rx0, ry0) = (self.roi.x as i64, self.roi.y as i64);
        let (rx1, ry1) = (
            rx0 + self.roi.width as i64 - 1,
            ry0 + self.roi.height as i64 - 1,
        );
        let dt0 = nodes[0].0;
        let (sw, fy, ya, yb) = q.eval_axis_table(s.y + s.v * dt0, ry0, ry1)?;
        // The moving axis: the weighted sum of the positions' windows in
        // an eight-pixel window starting at `mw` (as `particle_rows_quad`).
        let mut moving = [0.0f32; 8];
        let (mw, lo, hi);
        if m == 1 {
            let (w, v, a, b) = q.eval_axis_table(s.x + s.u * dt0, rx0, rx1)?;
            moving[..4].copy_from_slice(&v);
            (mw, lo, hi) = (w, w + a as i64, w + b as i64 - 1);
        } else {
            let mut win = [(0i64, [0.0f32; 4], 0.0f32); LEAN_NODES];
            let (mut first, mut last) = (i64::MAX, i64::MIN);
            let (mut l, mut h) = (i64::MAX, i64::MIN);
            for (slot, &(dt, pw)) in win.iter_mut().zip(nodes) {
                let (w, v, a, b) = q.eval_axis_table(s.x + s.u * dt, rx0, rx1)?;
                *slot = (w, v, pw as f32);
                first = first.min(w);
                last = last.max(w);
                l = l.min(w + a as i64);
                h = h.max(w + b as i64 - 1);
            }
            if last + 4 - first > 8 {
                return None;
            }
            for (w, v, pw) in &win[..m] {
                let at = (w - first) as usize;
                for (d, &o) in moving[at..at + 4].iter_mut().zip(v) {
                    *d += pw * o;
                }
            }
            (mw, lo, hi) = (first, l, h);
        }
        let amp = (self.gain * s.brightness) as f32;
        let col = (mw - rx0) as usize + RING_PAD;
        let row0 = (sw + ya as i64 - ry0) as u32;
        for j in ya..yb {
            let r = row0 as usize + (j - ya);
            let at = (r & mask) * stride + col;
            let dst: &mut [f32; 8] = (&mut sig[at..at + 8]).try_into().expect("window");
            let scale = amp * fy[j];
            for (d, &f) in dst.iter_mut().zip(&moving) {
                *d += scale * f;
            }
        }
        Some(ImageBox {
            col0: (lo - rx0) as u32,
            col1: (hi - rx0 + 1) as u32,
            row0,
            row1: row0 + (yb - ya) as u32 - 1,
        })
    }

    /// [`Self::particle_lean`] for a general (diagonal) streak: u ≠ 0,
    /// v ≠ 0, 2 ..= [`LEAN_NODES`] positions, each position's windows from
    /// the table's fixed lanes and inside the ROI. `particle_rows` adds
    /// such a streak position by position (`particle_rows_quad`'s general
    /// streak): per position, per covered row, `(scale · fy) · fx` to the
    /// four pixels of its x window, through a sink call per row that also
    /// finds the ring slot and grows the box. This does the same
    /// additions in the same order straight into the ring, the box once
    /// per particle (the union of the positions' covered pixels, as
    /// `RingRows` grows it).
    /// (`lean_images_match_particle_rows`, `diagonal_streaks_match_particle_rows`.)
    #[inline(always)]
    pub(super) fn particle_lean_diagonal(
        &self,
        q: &QuadTable,
        s: &Snapshot,
        nodes: &[(f64, f64)],
        sig: &mut [f32],
        mask: usize,
        stride: usize,
    ) -> Option<ImageBox> {
        debug_assert!(nodes.len() >= 2 && nodes.len() <= LEAN_NODES);
        let (rx0, ry0) = (self.roi.x as i64, self.roi.y as i64);
        let (rx1, ry1) = (
            rx0 + self.roi.width as i64 - 1,
            ry0 + self.roi.height as i64 - 1,
        );
        let amp = self.gain * s.brightness;
        let m = nodes.len();
        // Per position: x window start and fractions, y window start and
        // fractions, covered window rows, scale (as `particle_rows_quad`);
        // all of them before writing, so a declined streak writes nothing.
        let mut win = [(0i64, [0.0f32; 4], 0i64, [0.0f32; 4], 0usize, 0usize, 0.0f32); LEAN_NODES];
        // Covered pixels (inclusive).
        let (mut xlo, mut xhi, mut ylo, mut yhi) = (i64::MAX, i64::MIN, i64::MAX, i64::MIN);
        for (slot, &(dt, pw)) in win.iter_mut().zip(nodes) {
            let (wx, vx, xa, xb) = q.eval_axis_table(s.x + s.u * dt, rx0, rx1)?;
            let (wy, vy, ya, yb) = q.eval_axis_table(s.y + s.v * dt, ry0, ry1)?;
            *slot = (wx, vx, wy, vy, ya, yb, (amp * pw) as f32);
            xlo = xlo.min(wx + xa as i64);
            xhi = xhi.max(wx + xb as i64 - 1);
            ylo = ylo.min(wy + ya as i64);
            yhi = yhi.max(wy + yb as i64 - 1);
        }
        for &(wx, vx, wy, vy, ya, yb, sc) in &win[..m] {
            let col = (wx - rx0) as usize + RING_PAD;
            let row0 = (wy - ry0) as usize;
            for j in ya..yb {
                let at = ((row0 + j) & mask) * stride + col;
                let dst: &mut [f32; 4] = (&mut sig[at..at + 4]).try_into().expect("window");
                let f = sc * vy[j & 3];
                for (d, &x) in dst.iter_mut().zip(&vx) {
                    *d += f * x;
                }
            }
        }
        Some(ImageBox {
            col0: (xlo - rx0) as u32,
            col1: (xhi - rx0 + 1) as u32,
            row0: (ylo - ry0) as u32,
            row1: (yhi - ry0) as u32,
        })
    }

    /// [`Self::particle_rows`] for small images through the [`QuadTable`]:
    /// the same cases, numbers and operations, with each profile in a
    /// fixed four-pixel window (eight for a merged streak) instead of a
    /// slice. Returns false, having emitted nothing, when a profile does
    /// not fit its window (the caller then takes the general path).
    #[inline]
    pub(super) fn particle_rows_quad(
        &self,
        q: &QuadTable,
        s: &Snapshot,
        prof: &mut Profiles,
        sink: &mut impl ContributionSink,
    ) -> bool {
        let amp = self.gain * s.brightness;
        let nodes = self.streak_nodes_of(s);
        let (rx0, ry0) = (self.roi.x as i64, self.roi.y as i64);
        let (rx1, ry1) = (
            rx0 + self.roi.width as i64 - 1,
            ry0 + self.roi.height as i64 - 1,
        );
        let at = |c: f64, dir: f64, dt: f64| c + dir * dt;
        if nodes.len() == 1 || s.v == 0.0 || s.u == 0.0 {
            let shared_y = nodes.len() == 1 || s.v == 0.0;
            let dt0 = nodes[0].0;
            let (c_shared, c_moving, v_moving) = if shared_y {
                (at(s.y, s.v, dt0), s.x, s.u)
            } else {
                (at(s.x, s.u, dt0), s.y, s.v)
            };
            let (s0, s1, m0, m1, s_cap, m_cap) = if shared_y {
                (ry0, ry1, rx0, rx1, AXIS_MAX, X_CAP)
            } else {
                (rx0, rx1, ry0, ry1, X_CAP, AXIS_MAX)
            };
            let (sw, shared, slo, sn) = match q.eval_axis(self, c_shared, s0, s1, s_cap) {
                QuadAxis::Window(w, v, lo, n) => (w, v, lo, n),
                QuadAxis::Empty => return true,
                QuadAxis::NoFit => return false,
            };
            // The moving axis: the weighted sum of the positions' windows
            // in an eight-pixel window starting at `mw`.
            let mut moving = [0.0f32; 8];
            let (mut lo, mut hi) = (i64::MAX, i64::MIN);
            let mw;
            if nodes.len() == 1 {
                let c = at(c_moving, v_moving, dt0);
                let (w, v, r0, rn) = match q.eval_axis(self, c, m0, m1, m_cap) {
                    QuadAxis::Window(w, v, lo, n) => (w, v, lo, n),
                    QuadAxis::Empty => return true,
                    QuadAxis::NoFit => return false,
                };
                moving[..4].copy_from_slice(&v);
                (mw, lo, hi) = (w, r0, r0 + rn as i64 - 1);
            } else {
                let mut win = [(0i64, [0.0f32; 4], 0.0f32); 32];
                let mut n = 0;
                for &(dt, pw) in nodes {
                    let c = at(c_moving, v_moving, dt);
                    let (w, v, r0, rn) = match q.eval_axis(self, c, m0, m1, m_cap) {
                        QuadAxis::Window(w, v, lo, n) => (w, v, lo, n),
                        QuadAxis::Empty => continue,
                        QuadAxis::NoFit => return false,
                    };
                    lo = lo.min(r0);
                    hi = hi.max(r0 + rn as i64 - 1);
                    win[n] = (w, v, pw as f32);
                    n += 1;
                }
                if n == 0 {
                    return true;
                }
                let first = win[..n].iter().map(|w| w.0).min().unwrap_or(0);
                let last = win[..n].iter().map(|w| w.0).max().unwrap_or(0);
                if last + 4 - first > 8 {
                    return false;
                }
                mw = first;
                for (w, v, pw) in &win[..n] {
                    let at = (w - first) as usize;
                    for (d, &o) in moving[at..at + 4].iter_mut().zip(v) {
                        *d += pw * o;
                    }
                }
            }
            let mn = (hi - lo + 1) as usize;
            let amp = amp as f32;
            if shared_y {
                for y in slo..slo + sn as i64 {
                    sink.row(y as u32);
                    sink.add_window(mw, &moving, amp * shared[(y - sw) as usize], lo, mn);
                }
            } else {
                for y in lo..=hi {
                    sink.row(y as u32);
                    sink.add_window(sw, &shared, amp * moving[(y - mw) as usize], slo, sn);
                }
            }
            return true;
        }
        // General streak: position by position.
        for &(dt, pw) in nodes {
            let (px, py) = (at(s.x, s.u, dt), at(s.y, s.v, dt));
            let (xlo, nx) = self.axis_range(px, rx0, rx1, X_CAP);
            let (ylo, ny) = self.axis_range(py, ry0, ry1, AXIS_MAX);
            if nx == 0 || ny == 0 {
                continue;
            }
            let scale = (amp * pw) as f32;
            match (q.eval_masked(px, xlo, nx), q.eval_masked(py, ylo, ny)) {
                (Some((wx, fx)), Some((wy, fy))) => {
                    for y in ylo..ylo + ny as i64 {
                        sink.row(y as u32);
                        sink.add_window(wx, &fx, scale * fy[(y - wy) as usize], xlo, nx);
                    }
                }
                _ => {
                    let Profiles { fx, fy, .. } = prof;
                    self.table.eval(px, xlo, &mut fx[..nx]);
                    self.table.eval(py, ylo, &mut fy[..ny]);
                    emit_rows(sink, xlo, &fx[..nx], ylo, &fy[..ny], scale);
                }
            }
        }
        true
    }

    /// Signal contributions of a pulse's particle images, particles taken
    /// in [`render_order`]: `f(roi_pixel_index, signal)`.
    #[cfg(feature = "testkit")]
    pub(super) fn contributions(&self, snaps: &[Snapshot], mut f: impl FnMut(u32, f64)) {
        let w = self.roi.width;
        for &(key, _, _) in &self.render_order(snaps, true) {
            let s = &snaps[(key & 0xFFFF_FFFF) as usize];
            self.particle_contributions(s, |ix, iy, sig| {
                f((iy - self.roi.y) * w + (ix - self.roi.x), sig)
            });
        }
    }
}

/// One way of drawing a particle's image: its signal per sensor pixel,
/// handed to a [`ContributionSink`] row by row (the ring of rows in
/// production, lists or dense images in tests). The production renderers
/// are chosen in one place, [`PixelModel::draw_particle`]; the plain one,
/// [`Exact`] (erf at every pixel edge, f64), is the test oracle the fast
/// ones are tested against (`fast_pixel_signals_match_exact_model`;
/// [`Lean`] against [`Rows`] bit for bit:
/// `lean_images_match_particle_rows`,
/// `diagonal_streaks_match_particle_rows`).
pub(super) trait Renderer {
    /// Adds the image of `s` to `sink`; false, having added nothing,
    /// when this renderer does not draw such a particle (the next one
    /// in [`PixelModel::draw_particle`] then does).
    fn draw(
        &self,
        m: &PixelModel,
        s: &Snapshot,
        prof: &mut Profiles,
        sink: &mut impl ContributionSink,
    ) -> bool;
}

/// Small images (the [`QuadTable`]'s windows, at most [`LEAN_NODES`]
/// streak positions) written straight into the ring behind the sink
/// ([`PixelModel::particle_lean`]); declines other particles and sinks
/// without a ring.
pub(super) struct Lean;

impl Renderer for Lean {
    #[inline(always)]
    fn draw(
        &self,
        m: &PixelModel,
        s: &Snapshot,
        _prof: &mut Profiles,
        sink: &mut impl ContributionSink,
    ) -> bool {
        let Some(q) = &m.quad else { return false };
        let Some((sig, mask, stride)) = sink.ring() else {
            return false;
        };
        match m.particle_lean(q, s, sig, mask, stride) {
            Some(bx) => {
                sink.wrote(bx);
                true
            }
            None => false,
        }
    }
}

/// Any image, row by row through the sink ([`PixelModel::particle_rows`]:
/// fixed [`QuadTable`] windows where the profiles fit them, else
/// [`FractionTable`] slices). Takes every particle.
pub(super) struct Rows;

impl Renderer for Rows {
    #[inline(always)]
    fn draw(
        &self,
        m: &PixelModel,
        s: &Snapshot,
        prof: &mut Profiles,
        sink: &mut impl ContributionSink,
    ) -> bool {
        m.particle_rows(s, prof, sink);
        true
    }
}

/// The exact model, plainly: every position's pixel-integrated Gaussian
/// from erf at the pixel edges ([`PixelModel::footprint`]), one pixel at
/// a time in f64 ([`ContributionSink::add`]). The test oracle.
#[cfg(feature = "testkit")]
pub(super) struct Exact;

#[cfg(feature = "testkit")]
impl Renderer for Exact {
    fn draw(
        &self,
        m: &PixelModel,
        s: &Snapshot,
        _prof: &mut Profiles,
        sink: &mut impl ContributionSink,
    ) -> bool {
        let mut pos = Vec::with_capacity(32);
        m.positions(s, &mut pos);
        let amp = m.gain * s.brightness;
        for &(px, py, pw) in &pos {
            let a = amp * pw;
            m.footprint(px, py, |ix, iy, frac| {
                sink.row(iy);
                sink.add(ix, a * frac);
            });
        }
        true
    }
}

/// A sink calling `f(ix, iy, signal)` per pixel contribution (f64 for
/// [`Exact`]'s, the f32 products of the fast renderers' runs).
#[cfg(feature = "testkit")]
pub(super) struct EachPixel<F>(pub(super) F, pub(super) u32);

#[cfg(feature = "testkit")]
impl<F: FnMut(u32, u32, f64)> ContributionSink for EachPixel<F> {
    fn row(&mut self, iy: u32) {
        self.1 = iy;
    }
    fn add_run(&mut self, ix0: u32, fractions: &[f32], scale: f32) {
        for (a, &fx) in fractions.iter().enumerate() {
            (self.0)(ix0 + a as u32, self.1, (scale * fx) as f64)
        }
    }
    fn add_window<const W: usize>(
        &mut self,
        wx: i64,
        window: &[f32; W],
        scale: f32,
        x0: i64,
        n: usize,
    ) {
        let a = (x0 - wx) as usize;
        self.add_run(x0 as u32, &window[a..a + n], scale);
    }
    fn add(&mut self, ix: u32, signal: f64) {
        (self.0)(ix, self.1, signal)
    }
}

/// Receives a particle's contributions row by row.
pub(super) trait ContributionSink {
    /// The following contributions are in sensor row `iy`.
    fn row(&mut self, iy: u32);
    /// Add `scale·fractions[a]` to sensor column `ix0 + a` of the current
    /// row.
    fn add_run(&mut self, ix0: u32, fractions: &[f32], scale: f32);
    /// Add `scale·window[a]` to sensor column `wx + a` of the current row
    /// for the pixels `x0 .. x0 + n` (inside the window and the ROI); the
    /// other lanes are 0 and may be added as such (the ring keeps
    /// [`RING_PAD`] columns either side for them) or skipped.
    fn add_window<const W: usize>(
        &mut self,
        wx: i64,
        window: &[f32; W],
        scale: f32,
        x0: i64,
        n: usize,
    );
    /// Add `signal` to sensor column `ix` of the current row (the plain
    /// renderer's pixel at a time; a sink that sums in f32 rounds it).
    #[cfg(feature = "testkit")]
    fn add(&mut self, ix: u32, signal: f64) {
        self.add_run(ix, &[1.0], signal as f32)
    }
    /// The ring of rows behind the sink, for a renderer that writes
    /// straight into it: (signals, row-slot mask, row stride). None
    /// unless the sink is the ring.
    #[inline(always)]
    fn ring(&mut self) -> Option<(&mut [f32], usize, usize)> {
        None
    }
    /// The box a renderer wrote through [`Self::ring`].
    #[inline(always)]
    fn wrote(&mut self, _bx: ImageBox) {}
}

/// Columns of padding either side of a ring row, for the zero lanes of a
/// window that reach past the ROI's edge.
pub(super) const RING_PAD: usize = 8;

/// Longest axis profile of one image position: up to 31 pixels along x
/// (`footprint`'s cap) and along y (a valid scenario's images, ≤ 20 px
/// across, span at most 32 rows).
pub(super) const AXIS_MAX: usize = 64;
/// `footprint`'s cap on the pixels along x.
pub(super) const X_CAP: usize = 31;
/// Longest merged profile of a streak (positions' union); longer streaks
/// are rendered position by position.
pub(super) const MERGE_MAX: usize = 128;

/// Most streak positions [`PixelModel::particle_lean`] takes.
pub(super) const LEAN_NODES: usize = 4;

/// Add the separable image `scale·fx ⊗ fy` (pixels `xlo..`, rows `ylo..`).
#[inline]
pub(super) fn emit_rows(
    sink: &mut impl ContributionSink,
    xlo: i64,
    fx: &[f32],
    ylo: i64,
    fy: &[f32],
    scale: f32,
) {
    for (j, &f) in fy.iter().enumerate() {
        sink.row((ylo + j as i64) as u32);
        sink.add_run(xlo as u32, fx, scale * f);
    }
}

/// A pixel at or above its threshold, between the two passes of
/// [`PixelModel::render_pulse`]'s response: ROI index, sensor
/// coordinates, ON crossing count, signal, threshold, ΔL.
#[derive(Debug, Clone, Copy)]
pub(super) struct Lit {
    pub(super) idx: u32,
    pub(super) x: u16,
    pub(super) y: u16,
    pub(super) n_on: u32,
    pub(super) sig: f64,
    pub(super) c: f64,
    pub(super) dl: f64,
}

/// A pixel handed out by [`PixelModel::render_signals`]: its ROI row and
/// column packed as `row << 16 | column` (ROIs are at most 4096 px
/// wide), and its summed signal. Eight bytes, `repr(C)`: the drain
/// writes one as a single u64 (`column key | signal bits << 32`).
#[derive(Debug, Clone, Copy)]
#[repr(C)]
pub(super) struct Hit {
    pub(super) rc: u32,
    pub(super) v: f32,
}

impl Hit {
    /// ROI-relative (row, column).
    #[inline(always)]
    pub(super) fn row_col(self) -> (u32, u32) {
        (self.rc >> 16, self.rc & 0xFFFF)
    }
}

/// The ring pixels one image wrote: ROI-relative columns `col0..col1`
/// of rows `row0..=row1` (empty when `col0 >= col1`).
#[derive(Debug, Clone, Copy)]
pub(super) struct ImageBox {
    pub(super) col0: u32,
    pub(super) col1: u32,
    pub(super) row0: u32,
    pub(super) row1: u32,
}

impl ImageBox {
    pub(super) const EMPTY: ImageBox = ImageBox {
        col0: u32::MAX,
        col1: 0,
        row0: u32::MAX,
        row1: 0,
    };
}

/// The row ring as a [`ContributionSink`]: the slot's offset is found
/// once per row; the box of the pixels written grows with each run.
pub(super) struct RingRows<'a> {
    pub(super) sig: &'a mut [f32],
    pub(super) mask: usize,
    /// Ring row length: ROI width plus [`RING_PAD`] either side.
    pub(super) stride: usize,
    pub(super) roi_x: u32,
    pub(super) roi_y: u32,
    pub(super) sig_at: usize,
    /// Current row (ROI-relative).
    pub(super) row: u32,
    pub(super) bx: ImageBox,
}

impl ContributionSink for RingRows<'_> {
    #[inline]
    fn row(&mut self, iy: u32) {
        self.row = iy - self.roi_y;
        self.sig_at = (self.row as usize & self.mask) * self.stride;
    }

    #[inline]
    fn add_run(&mut self, ix0: u32, fractions: &[f32], scale: f32) {
        let x0 = (ix0 - self.roi_x) as usize;
        let n = fractions.len();
        for (d, &f) in self.sig[self.sig_at + RING_PAD + x0..][..n]
            .iter_mut()
            .zip(fractions)
        {
            *d += scale * f;
        }
        self.extend(x0 as u32, n as u32);
    }

    #[inline]
    fn add_window<const W: usize>(
        &mut self,
        wx: i64,
        window: &[f32; W],
        scale: f32,
        x0: i64,
        n: usize,
    ) {
        // (wx ≥ ROI x − RING_PAD: the window holds an ROI pixel.)
        let at = (self.sig_at as i64 + RING_PAD as i64 + wx - self.roi_x as i64) as usize;
        let dst: &mut [f32; W] = (&mut self.sig[at..at + W]).try_into().expect("window");
        for (d, &f) in dst.iter_mut().zip(window) {
            *d += scale * f;
        }
        self.extend((x0 - self.roi_x as i64) as u32, n as u32);
    }

    #[inline(always)]
    fn ring(&mut self) -> Option<(&mut [f32], usize, usize)> {
        Some((&mut *self.sig, self.mask, self.stride))
    }

    #[inline(always)]
    fn wrote(&mut self, bx: ImageBox) {
        self.bx = bx;
    }
}
impl RingRows<'_> {
    /// Grow the box by ROI columns x0 .. x0 + n of the current row.
    #[inline]
    pub(super) fn extend(&mut self, x0: u32, n: u32) {
        let b = &mut self.bx;
        b.col0 = b.col0.min(x0);
        b.col1 = b.col1.max(x0 + n);
        b.row0 = b.row0.min(self.row);
        b.row1 = b.row1.max(self.row);
    }
}

thread_local! {
    /// [`PixelModel::render_signals`]' ring (module level, so that tests
    /// can check that a pulse leaves it all-zero).
    pub(super) static RENDER_RING: std::cell::RefCell<RowRing> =
        const { std::cell::RefCell::new(RowRing::new()) };
}

/// Per-thread accumulation buffer of [`PixelModel::render_pulse`]: `rows`
/// (a power of two) ROI rows, row r in slot r mod rows, and per slot the
/// boxes of the images whose last row it is (drained when the row is
/// complete).
pub(super) struct RowRing {
    pub(super) rows: usize,
    pub(super) width: usize,
    pub(super) sig: Vec<f32>,
    pub(super) boxes: Vec<Vec<ImageBox>>,
    pub(super) profiles: Profiles,
}

/// Scratch axis profiles of [`PixelModel::particle_rows`] (kept per
/// thread: zeroing them per particle was a memset call each).
pub(super) struct Profiles {
    pub(super) fx: [f32; MERGE_MAX],
    pub(super) fy: [f32; MERGE_MAX],
    pub(super) one: [f32; AXIS_MAX],
}

impl Profiles {
    pub(super) const fn new() -> Profiles {
        Profiles {
            fx: [0.0; MERGE_MAX],
            fy: [0.0; MERGE_MAX],
            one: [0.0; AXIS_MAX],
        }
    }
}

impl RowRing {
    pub(super) const fn new() -> RowRing {
        RowRing {
            rows: 1,
            width: 0,
            sig: Vec::new(),
            boxes: Vec::new(),
            profiles: Profiles::new(),
        }
    }

    /// Shape for `rows` × `width` (all-zero, no boxes; a finished pulse
    /// leaves it so).
    pub(super) fn reset(&mut self, rows: usize, width: usize) {
        debug_assert!(rows.is_power_of_two());
        self.rows = rows;
        self.width = width;
        let stride = width + 2 * RING_PAD;
        if self.sig.len() < rows * stride {
            self.sig.resize(rows * stride, 0.0);
        }
        if self.boxes.len() < rows {
            self.boxes.resize_with(rows, Vec::new);
        }
        debug_assert!(self.boxes.iter().all(|b| b.is_empty()));
        debug_assert!(self.sig.iter().all(|&v| v == 0.0));
    }
}
