//! From pixel requests to timestamped events: refractory period, row
//! arbitration with finite throughput, 1 µs timestamps, rate limiter.
//!
//! All stages are stateful streams fed with requests in time order, so the
//! simulator can run block by block with bounded memory and the result does
//! not depend on the block boundaries.
//!
//! **Arbiter** (`arbiter_saturation`): a row-parallel readout (as in
//! Prophesee's Gen4): a pixel with an event raises its row's request and is
//! blocked until read (a second event of a blocked pixel is lost). One
//! server grants rows in the order they requested; a grant takes
//! `row_time_us + n·event_time_us` and reads all n pending events of the row,
//! which all get the grant time as timestamp. At light load each grant reads
//! one event and the latency is the pixel's own. After a pulse, thousands of
//! requests arrive at once: rows queue up, the burst is stretched to about
//! rows·row_time + events·event_time (so it depends on the ROI's row count
//! and the event load, as observed), and when that reaches the pulse period
//! the queue never empties: timestamps lag, many events share one
//! timestamp per row (horizontal stripes) and the folded histogram flattens.
//! Off: each event is stamped with its own request time.

use std::collections::VecDeque;

use super::pixel::Arrival;
use super::scenario::{ArbiterSaturation, Roi};
use ebptv_io::events::EventChunk;

/// Drops requests of a pixel within `period_us` after its previous one.
pub(crate) struct Refractory {
    period_us: f64,
    roi: Roi,
    last: Vec<f64>,
}

impl Refractory {
    /// A refractory filter of `period_us` over `roi`.
    pub(crate) fn new(period_us: f64, roi: Roi) -> Self {
        Refractory {
            period_us,
            roi,
            last: huge_page_vec(roi.width as usize * roi.height as usize, f64::NEG_INFINITY),
        }
    }

    /// Filter time-ordered requests in place.
    #[cfg(feature = "testkit")]
    pub(crate) fn apply(&mut self, reqs: &mut Vec<Arrival>) {
        reqs.retain(|a| self.keep(a));
    }

    #[inline]
    fn index(&self, a: &Arrival) -> usize {
        (a.y as usize - self.roi.y as usize) * self.roi.width as usize
            + (a.x as usize - self.roi.x as usize)
    }

    /// Start loading the state of the pixel at (`dx`, `dy`) from the
    /// ROI's corner into the cache. The state of a full frame is 7 MB,
    /// read in time order, i.e. at pixels all over the frame: without a
    /// prefetch a few requests ahead, the load in [`Self::keep`] waited
    /// for memory on most requests (~70 % of the readout's time).
    #[inline(always)]
    pub(crate) fn prefetch(&self, dx: usize, dy: usize) {
        if let Some(slot) = self.last.get(dy * self.roi.width as usize + dx) {
            prefetch(slot);
        }
    }

    /// [`Self::keep`] for a request at time `t` of the pixel at (`dx`,
    /// `dy`) from the ROI's corner.
    #[inline(always)]
    pub(crate) fn keep_at(&mut self, dx: usize, dy: usize, t: f64) -> bool {
        let last = &mut self.last[dy * self.roi.width as usize + dx];
        if t - *last >= self.period_us {
            *last = t;
            true
        } else {
            false
        }
    }

    /// Whether request `a` would pass now (no state change).
    #[inline]
    pub(crate) fn would_keep(&self, a: &Arrival) -> bool {
        a.t - self.last[self.index(a)] >= self.period_us
    }

    #[cfg(feature = "testkit")]
    /// Whether request `a` passes (requests in time order).
    #[inline]
    pub(crate) fn keep(&mut self, a: &Arrival) -> bool {
        let i = self.index(a);
        if a.t - self.last[i] >= self.period_us {
            self.last[i] = a.t;
            true
        } else {
            false
        }
    }
}

/// Row-arbitrated readout that delays events when many rows request at once.
pub(crate) struct Arbiter {
    params: ArbiterSaturation,
    roi_x: u16,
    roi_y: u16,
    /// 64-bit words per ROI row in `cells`.
    words_per_row: usize,
    /// Per ROI row, per 64 pixels: (pixels with a pending request,
    /// polarity of those requests) as bits. A grant reads the row's
    /// pending requests in x order and stamps them all with its own time,
    /// so the request time need not be kept, and the set bits *are* the x
    /// order: a grant scans them instead of sorting a list, and an
    /// admission touches one 16-byte cell instead of a blocked bit plus a
    /// list that grows.
    cells: Vec<[u64; 2]>,
    /// Per ROI row: which of its words in `cells` hold pending requests.
    occupied: Vec<u64>,
    /// Per ROI row: how many requests are pending.
    counts: Vec<u32>,
    /// Rows with pending requests, by first pending request time (ties:
    /// lower row first). Requests are admitted in (time, row) order, so
    /// a row that becomes non-empty is always last in that order: a FIFO
    /// (a priority queue keyed by the first request time gives the same
    /// order, at log n per grant).
    queue: VecDeque<u16>,
    /// When the server is next free (µs).
    t_free: f64,
    /// Requests lost because their pixel was still blocked.
    pub lost: u64,
    /// (time, row) of the last admitted request (checks the FIFO's premise).
    #[cfg(debug_assertions)]
    last_admitted: (f64, u16),
}

impl Arbiter {
    /// An arbiter with the given timings over `roi`.
    pub(crate) fn new(params: ArbiterSaturation, roi: Roi) -> Self {
        let words_per_row = (roi.width as usize).div_ceil(64);
        assert!(words_per_row <= 64, "ROI wider than 4096 px");
        let rows = roi.height as usize;
        Arbiter {
            params,
            roi_x: roi.x as u16,
            roi_y: roi.y as u16,
            words_per_row,
            cells: vec![[0; 2]; rows * words_per_row],
            occupied: vec![0; rows],
            counts: vec![0; rows],
            queue: VecDeque::new(),
            t_free: f64::NEG_INFINITY,
            lost: 0,
            #[cfg(debug_assertions)]
            last_admitted: (f64::NEG_INFINITY, 0),
        }
    }

    /// Start loading the state of the pixel at (`dx`, `dy`) from the
    /// ROI's corner into the cache, some requests before [`Self::offer`]
    /// needs it.
    #[inline(always)]
    pub(crate) fn prefetch(&self, dx: usize, dy: usize) {
        if let Some(cell) = self.cells.get(dy * self.words_per_row + dx / 64) {
            prefetch(cell);
        }
    }

    /// Admit request `a` (see [`Self::admit_at`]).
    #[cfg(feature = "testkit")]
    fn admit(&mut self, a: &Arrival) {
        self.admit_at(
            a.t,
            (a.x - self.roi_x) as usize,
            (a.y - self.roi_y) as usize,
            a.p,
        );
    }

    /// Admit a request at time `t` of the pixel at (`dx`, `dy`) from the
    /// ROI's corner with polarity `p` (0 or 1): pending, or lost if the
    /// pixel is still blocked.
    #[inline(always)]
    fn admit_at(&mut self, t: f64, dx: usize, dy: usize, p: u8) {
        let (w, bit) = (dx / 64, dx % 64);
        let cell = &mut self.cells[dy * self.words_per_row + w];
        if cell[0] & (1 << bit) != 0 {
            self.lost += 1;
            return;
        }
        debug_assert!(p <= 1, "polarity {p}");
        cell[0] |= 1 << bit;
        cell[1] |= ((p & 1) as u64) << bit;
        self.occupied[dy] |= 1 << w;
        let count = &mut self.counts[dy];
        if *count == 0 {
            self.queue.push_back(dy as u16);
        }
        *count += 1;
        #[cfg(debug_assertions)]
        {
            let y = self.roi_y + dy as u16;
            assert!(self.last_admitted <= (t, y), "requests out of order");
            self.last_admitted = (t, y);
        }
        let _ = t;
    }

    #[cfg(feature = "testkit")]
    /// Serve the requests `reqs`, in (time, row) order (all requests
    /// before `t_end` are known; none later is in `reqs`), emitting events
    /// granted before `t_end`. Requests not yet granted stay pending
    /// inside. The same as [`Self::offer`] for each request, then
    /// [`Self::finish`].
    pub(crate) fn run(&mut self, reqs: &[Arrival], t_end: f64, out: &mut EventChunk) {
        for a in reqs {
            self.offer(a, t_end, out);
        }
        self.finish(t_end, out);
    }

    /// Take the next request `a` (requests in (time, row) order, all
    /// before `t_end` or after it too): first grant the rows the server
    /// reaches before `a` arrives (and before `t_end`), then admit `a`.
    /// The readout feeds its requests one by one as it decodes them.
    // (Always inlined: the readout calls it once per request.)
    #[cfg(feature = "testkit")]
    #[inline(always)]
    pub(crate) fn offer(&mut self, a: &Arrival, t_end: f64, out: &mut EventChunk) {
        self.offer_at(
            a.t,
            (a.x - self.roi_x) as usize,
            (a.y - self.roi_y) as usize,
            a.p,
            t_end,
            out,
        );
    }

    /// [`Self::offer`] for a request at time `t` of the pixel at (`dx`,
    /// `dy`) from the ROI's corner with polarity `p` (0 or 1).
    #[inline(always)]
    pub(crate) fn offer_at(
        &mut self,
        t: f64,
        dx: usize,
        dy: usize,
        p: u8,
        t_end: f64,
        out: &mut EventChunk,
    ) {
        loop {
            if self.queue.is_empty() {
                // Idle: the server waits for this request.
                self.t_free = self.t_free.max(t);
                break;
            }
            if t <= self.t_free || self.t_free >= t_end {
                // Arrives while the server is busy, or the next grant is
                // at or after `t_end`, where later requests (not known
                // yet) could join it.
                break;
            }
            self.grant(out);
        }
        self.admit_at(t, dx, dy, p);
    }

    /// After the last request before `t_end`: emit the grants before
    /// `t_end`.
    pub(crate) fn finish(&mut self, t_end: f64, out: &mut EventChunk) {
        while !self.queue.is_empty() && self.t_free < t_end {
            self.grant(out);
        }
    }

    /// Grant the first queued row at `t_free`.
    ///
    /// The row's events are written straight into the chunk's spare
    /// capacity, one pass over the pending bits for all four columns
    /// (four `resize` fills and then a bounds-checked pass over x and p
    /// were ~half of this function's time).
    fn grant(&mut self, out: &mut EventChunk) {
        let t_grant = self.t_free;
        let r = self.queue.pop_front().expect("non-empty") as usize;
        let n = std::mem::take(&mut self.counts[r]) as usize;
        let (t, y) = (floor_i64(t_grant), self.roi_y + r as u16);
        let base = out.len();
        assert!(out.x.len() == base && out.y.len() == base && out.p.len() == base);
        out.t.reserve(n);
        out.x.reserve(n);
        out.y.reserve(n);
        out.p.reserve(n);
        let ts = out.t.spare_capacity_mut()[..n].as_mut_ptr();
        let xs = out.x.spare_capacity_mut()[..n].as_mut_ptr();
        let ys = out.y.spare_capacity_mut()[..n].as_mut_ptr();
        let ps = out.p.spare_capacity_mut()[..n].as_mut_ptr();
        // The row's pending pixels in x order: its occupied words, each
        // word's set bits (emptied as read).
        let mut words = std::mem::take(&mut self.occupied[r]);
        let cells = &mut self.cells[r * self.words_per_row..(r + 1) * self.words_per_row];
        let mut j = 0;
        while words != 0 {
            let w = words.trailing_zeros() as usize;
            words &= words - 1;
            let [mut pending, polarity] = std::mem::take(&mut cells[w]);
            let x0 = self.roi_x + 64 * w as u16;
            while pending != 0 {
                let b = pending.trailing_zeros();
                pending &= pending - 1;
                // (The count is the row's pending bits: never taken.)
                assert!(j < n, "row count below its pending bits");
                // SAFETY: j < n, each spare slice holds n entries.
                unsafe {
                    (*ts.add(j)).write(t);
                    (*xs.add(j)).write(x0 + b as u16);
                    (*ys.add(j)).write(y);
                    (*ps.add(j)).write((polarity >> b) as u8 & 1);
                }
                j += 1;
            }
        }
        assert_eq!(j, n, "row count above its pending bits");
        // SAFETY: the first n spare entries of each column were written.
        unsafe {
            out.t.set_len(base + n);
            out.x.set_len(base + n);
            out.y.set_len(base + n);
            out.p.set_len(base + n);
        }
        self.t_free = t_grant + self.params.row_time_us + n as f64 * self.params.event_time_us;
    }

    /// The batch loop `run` was before requests could be offered one by
    /// one (the reference `offer_matches_batch_run` compares with).
    #[cfg(feature = "testkit")]
    fn run_batch(&mut self, reqs: &[Arrival], t_end: f64, out: &mut EventChunk) {
        let mut i = 0;
        loop {
            if self.queue.is_empty() {
                if i == reqs.len() {
                    break;
                }
                self.t_free = self.t_free.max(reqs[i].t);
            }
            while i < reqs.len() && reqs[i].t <= self.t_free {
                self.admit(&reqs[i]);
                i += 1;
            }
            if self.queue.is_empty() {
                continue;
            }
            if self.t_free >= t_end {
                while i < reqs.len() {
                    self.admit(&reqs[i]);
                    i += 1;
                }
                break;
            }
            self.grant(out);
        }
    }

    #[cfg(feature = "testkit")]
    /// Requests still waiting.
    pub(crate) fn pending(&self) -> usize {
        self.counts.iter().map(|&n| n as usize).sum()
    }
}

/// Drops events beyond `max_rate_ev_s · window_us` in each window of the
/// event timestamps (a counter reset every window).
pub(crate) struct RateLimiter {
    window_us: f64,
    max_per_window: f64,
    window: i64,
    count: u64,
}

impl RateLimiter {
    /// A limiter allowing `max_rate_ev_s` events/s in windows of `window_us`.
    pub(crate) fn new(max_rate_ev_s: f64, window_us: f64) -> Self {
        RateLimiter {
            window_us,
            max_per_window: max_rate_ev_s * window_us * 1e-6,
            window: i64::MIN,
            count: 0,
        }
    }

    pub(crate) fn apply(&mut self, ev: &mut EventChunk) {
        ev.retain(|t, _, _, _| {
            let w = (t as f64 / self.window_us).floor() as i64;
            if w != self.window {
                self.window = w;
                self.count = 0;
            }
            self.count += 1;
            self.count as f64 <= self.max_per_window
        });
    }
}

/// `v.floor() as i64` (saturating, NaN → 0) without a libm call.
#[inline]
pub(crate) fn floor_i64(v: f64) -> i64 {
    let t = v as i64;
    if (t as f64) > v {
        t.saturating_sub(1)
    } else {
        t
    }
}

/// `vec![value; n]`, on Linux in memory the kernel is asked to back with
/// huge pages (transparent huge pages, `madvise`): a full frame's
/// per-pixel state is megabytes read at random pixels, and with 4 kB
/// pages nearly every access also missed the TLB (the prefetches waited
/// on page walks). A hint: without huge pages the vector is the same.
pub(crate) fn huge_page_vec<T: Copy>(n: usize, value: T) -> Vec<T> {
    let mut v: Vec<T> = Vec::with_capacity(n);
    #[cfg(target_os = "linux")]
    {
        const HUGE: usize = 2 << 20;
        let bytes = n * std::mem::size_of::<T>();
        if bytes >= HUGE {
            let start = v.as_ptr() as usize;
            let lo = start.next_multiple_of(HUGE);
            let hi = (start + bytes) / HUGE * HUGE;
            if hi > lo {
                // SAFETY: [lo, hi) lies inside the vector's allocation;
                // the advice changes no contents (none written yet).
                unsafe {
                    libc::madvise(lo as *mut libc::c_void, hi - lo, libc::MADV_HUGEPAGE);
                }
            }
        }
    }
    v.resize(n, value);
    v
}

/// Hint the CPU to load the cache line of `r` (no effect on results; a
/// no-op off x86-64).
#[inline(always)]
pub(crate) fn prefetch<T>(r: &T) {
    prefetch_ptr(r as *const T);
}

/// [`prefetch`] by address: any address, valid or not (a prefetch never
/// faults and changes no result).
#[inline(always)]
pub(crate) fn prefetch_ptr<T>(p: *const T) {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: a prefetch never faults, whatever the address.
    unsafe {
        use std::arch::x86_64::{_mm_prefetch, _MM_HINT_T0};
        _mm_prefetch::<_MM_HINT_T0>(p as *const i8);
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = p;
}

/// Stamp requests without a readout bottleneck: each at its own time.
pub(crate) fn stamp_ideal(reqs: &[Arrival], out: &mut EventChunk) {
    for a in reqs {
        out.push(floor_i64(a.t), a.x, a.y, a.p);
    }
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;

    fn roi() -> Roi {
        Roi {
            x: 0,
            y: 0,
            width: 64,
            height: 8,
        }
    }

    /// Random requests in (time, row) order: ns-quantised times, many
    /// shared; repeats of pending pixels (lost).
    fn random_requests(
        rng: &mut rand_pcg::Pcg64,
        roi: Roi,
        n: usize,
        span_us: f64,
    ) -> Vec<Arrival> {
        use rand::Rng;
        let mut reqs: Vec<Arrival> = (0..n)
            .map(|_| Arrival {
                t: rng.gen_range(0..(span_us * 1000.0) as u64) as f64 * 1e-3,
                x: roi.x as u16 + rng.gen_range(0..roi.width) as u16,
                y: roi.y as u16 + rng.gen_range(0..roi.height) as u16,
                p: rng.gen_range(0..2),
            })
            .collect();
        reqs.sort_by(|a, b| a.t.total_cmp(&b.t).then(a.y.cmp(&b.y)));
        reqs
    }

    /// Feed `reqs` (spanning `span_us`) to two arbiters in eight time
    /// blocks, the last one open-ended, requiring the same events and the
    /// same pending count after every block; returns the events. Each
    /// `run` closure runs its arbiter on a block and returns its pending
    /// count.
    fn same_in_blocks(
        reqs: &[Arrival],
        span_us: f64,
        label: &str,
        mut run_a: impl FnMut(&[Arrival], f64, &mut EventChunk) -> usize,
        mut run_b: impl FnMut(&[Arrival], f64, &mut EventChunk) -> usize,
    ) -> EventChunk {
        let (mut a, mut b) = (EventChunk::default(), EventChunk::default());
        let mut from = 0;
        for k in 1..=8 {
            let t_end = if k == 8 {
                f64::INFINITY
            } else {
                span_us * k as f64 / 8.0
            };
            let to = reqs.partition_point(|r| r.t < t_end);
            let pending_a = run_a(&reqs[from..to], t_end, &mut a);
            let pending_b = run_b(&reqs[from..to], t_end, &mut b);
            assert_eq!(pending_a, pending_b, "{label}, block {k}");
            assert_eq!(a, b, "{label}, block {k}");
            from = to;
        }
        a
    }

    #[ebptv_macros::unit_test]
    fn bit_cells_match_row_lists() {
        // The bit-cell arbiter against the list arbiter it replaced:
        // light to heavily saturated loads, ROI widths around the 64-bit
        // words (1, 63, 64, 65, 1280, 4096), offset ROIs, fed in blocks
        // (grants reaching past block ends), polarities of both kinds.
        use rand::SeedableRng;
        let mut rng = rand_pcg::Pcg64::seed_from_u64(31);
        let mut lost = 0;
        let mut shared = 0;
        for (width, height, n, span_us, row_time, event_time) in [
            (1280u32, 720u32, 80_000usize, 2000.0, 0.005, 0.024),
            (1280, 720, 60_000, 2000.0, 0.5, 0.05),
            (4096, 20, 30_000, 1000.0, 0.02, 0.05),
            (64, 40, 20_000, 500.0, 0.3, 0.2),
            (65, 3, 5000, 100.0, 0.1, 0.02),
            (63, 9, 5000, 300.0, 0.1, 0.1),
            (1, 50, 3000, 200.0, 0.2, 0.1),
            (300, 50, 2000, 20_000.0, 0.5, 0.1),
        ] {
            let roi = Roi {
                x: 7,
                y: 11,
                width,
                height,
            };
            let reqs = random_requests(&mut rng, roi, n, span_us);
            let p = ArbiterSaturation {
                row_time_us: row_time,
                event_time_us: event_time,
            };
            let mut bits = Arbiter::new(p, roi);
            let mut lists = list_reference::ListArbiter::new(p, roi);
            let a = same_in_blocks(
                &reqs,
                span_us,
                &format!("{width}x{height}"),
                |r, t_end, out| {
                    bits.run(r, t_end, out);
                    bits.pending()
                },
                |r, t_end, out| {
                    lists.run(r, t_end, out);
                    lists.pending()
                },
            );
            assert_eq!(bits.lost, lists.lost);
            assert_eq!(a.len() as u64 + bits.lost, n as u64);
            lost += bits.lost;
            shared += a
                .iter()
                .zip(a.iter().skip(1))
                .filter(|(e, f)| e.t == f.t && e.y == f.y)
                .count();
        }
        assert!(lost > 1000, "{lost}");
        assert!(shared > 10_000, "{shared}");
    }

    /// The arbiter before the bit cells (reference).
    mod list_reference {
        use super::super::*;

        /// The arbiter as it was before the bit cells (one list of pending
        /// requests per row, sorted at the grant): the reference
        /// `bit_cells_match_row_lists` compares [`Arbiter`] with.
        pub(super) struct ListArbiter {
            params: ArbiterSaturation,
            roi_y: u16,
            /// Pending requests per ROI row as `x << 8 | polarity` (the grant
            /// reads them in x order and stamps them all with its own time, so the
            /// request time need not be kept; x is unique in a row's pending list,
            /// so sorting these integers is sorting by x).
            rows: Vec<Vec<u32>>,
            /// Rows with pending requests, by first pending request time (ties:
            /// lower row first). Requests are admitted in (time, row) order, so
            /// a row that becomes non-empty is always last in that order: a FIFO
            /// (a priority queue keyed by the first request time gives the same
            /// order, at log n per grant).
            queue: VecDeque<u16>,
            /// When the server is next free (µs).
            t_free: f64,
            /// Requests lost because their pixel was still blocked.
            pub lost: u64,
            roi_x: u16,
            /// Bits per row of `blocked` (the ROI width).
            row_bits: usize,
            /// Pixels with a pending request (one bit per ROI pixel): the check
            /// for a blocked pixel without scanning its row's pending list.
            blocked: Vec<u64>,
            /// (time, row) of the last admitted request (checks the FIFO's premise).
            #[cfg(debug_assertions)]
            last_admitted: (f64, u16),
        }

        impl ListArbiter {
            pub(crate) fn new(params: ArbiterSaturation, roi: Roi) -> Self {
                ListArbiter {
                    params,
                    roi_y: roi.y as u16,
                    rows: vec![Vec::new(); roi.height as usize],
                    queue: VecDeque::new(),
                    t_free: f64::NEG_INFINITY,
                    lost: 0,
                    roi_x: roi.x as u16,
                    row_bits: roi.width as usize,
                    blocked: vec![0; (roi.width as usize * roi.height as usize).div_ceil(64)],
                    #[cfg(debug_assertions)]
                    last_admitted: (f64::NEG_INFINITY, 0),
                }
            }

            #[inline(always)]
            fn admit(&mut self, a: &Arrival) {
                let r = (a.y - self.roi_y) as usize;
                let bit = r * self.row_bits + (a.x - self.roi_x) as usize;
                let (word, mask) = (bit / 64, 1u64 << (bit % 64));
                if self.blocked[word] & mask != 0 {
                    self.lost += 1;
                    return;
                }
                self.blocked[word] |= mask;
                let row = &mut self.rows[r];
                if row.is_empty() {
                    self.queue.push_back(r as u16);
                }
                #[cfg(debug_assertions)]
                {
                    assert!(self.last_admitted <= (a.t, a.y), "requests out of order");
                    self.last_admitted = (a.t, a.y);
                }
                row.push((a.x as u32) << 8 | a.p as u32);
            }

            /// Serve the requests `reqs`, in (time, row) order (all requests
            /// before `t_end` are known; none later is in `reqs`), emitting events
            /// granted before `t_end`. Requests not yet granted stay pending
            /// inside. The same as [`Self::offer`] for each request, then
            /// [`Self::finish`].
            pub(crate) fn run(&mut self, reqs: &[Arrival], t_end: f64, out: &mut EventChunk) {
                for a in reqs {
                    self.offer(a, t_end, out);
                }
                self.finish(t_end, out);
            }

            /// Take the next request `a` (requests in (time, row) order, all
            /// before `t_end` or after it too): first grant the rows the server
            /// reaches before `a` arrives (and before `t_end`), then admit `a`.
            /// The readout feeds its requests one by one as it decodes them.
            // (Always inlined: the readout calls it once per request.)
            #[inline(always)]
            pub(crate) fn offer(&mut self, a: &Arrival, t_end: f64, out: &mut EventChunk) {
                loop {
                    if self.queue.is_empty() {
                        // Idle: the server waits for this request.
                        self.t_free = self.t_free.max(a.t);
                        break;
                    }
                    if a.t <= self.t_free || self.t_free >= t_end {
                        // Arrives while the server is busy, or the next grant is
                        // at or after `t_end`, where later requests (not known
                        // yet) could join it.
                        break;
                    }
                    self.grant(out);
                }
                self.admit(a);
            }

            /// After the last request before `t_end`: emit the grants before
            /// `t_end`.
            pub(crate) fn finish(&mut self, t_end: f64, out: &mut EventChunk) {
                while !self.queue.is_empty() && self.t_free < t_end {
                    self.grant(out);
                }
            }

            /// Grant the first queued row at `t_free`.
            fn grant(&mut self, out: &mut EventChunk) {
                let t_grant = self.t_free;
                let r = self.queue.pop_front().expect("non-empty");
                let row = &mut self.rows[r as usize];
                if row.len() > 1 {
                    row.sort_unstable();
                }
                let ts = floor_i64(t_grant);
                let y = self.roi_y + r;
                let base = r as usize * self.row_bits;
                let n = row.len();
                // The row's events column by column (one capacity check per
                // column, not four per event).
                out.t.extend(std::iter::repeat_n(ts, n));
                out.y.extend(std::iter::repeat_n(y, n));
                out.x.extend(row.iter().map(|&e| (e >> 8) as u16));
                out.p.extend(row.iter().map(|&e| e as u8));
                for &e in row.iter() {
                    let bit = base + ((e >> 8) as u16 - self.roi_x) as usize;
                    self.blocked[bit / 64] &= !(1u64 << (bit % 64));
                }
                self.t_free =
                    t_grant + self.params.row_time_us + n as f64 * self.params.event_time_us;
                row.clear();
            }

            /// Requests still waiting.
            pub(crate) fn pending(&self) -> usize {
                self.rows.iter().map(|r| r.len()).sum()
            }
        }
    }

    /// A plain reference: simulate the server in 1 ns ticks.
    fn reference(reqs: &[Arrival], p: ArbiterSaturation) -> Vec<(i64, u16, u16)> {
        let mut pending: Vec<Vec<(f64, u16)>> = vec![Vec::new(); 8];
        let mut order: Vec<(f64, usize)> = Vec::new();
        let mut out = Vec::new();
        let mut busy_until = f64::NEG_INFINITY;
        let mut i = 0;
        let mut t = 0.0f64;
        while i < reqs.len() || pending.iter().any(|r| !r.is_empty()) {
            while i < reqs.len() && reqs[i].t <= t + 1e-12 {
                let a = reqs[i];
                let r = a.y as usize;
                if !pending[r].iter().any(|e| e.1 == a.x) {
                    if pending[r].is_empty() {
                        order.push((a.t, r));
                    }
                    pending[r].push((a.t, a.x));
                }
                i += 1;
            }
            if t >= busy_until - 1e-12 && !order.is_empty() {
                order.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
                let (_, r) = order.remove(0);
                let mut row = std::mem::take(&mut pending[r]);
                row.sort_by_key(|e| e.1);
                for e in &row {
                    out.push((t.floor() as i64, e.1, r as u16));
                }
                busy_until = t + p.row_time_us + row.len() as f64 * p.event_time_us;
            }
            t += 0.001;
        }
        out
    }

    #[ebptv_macros::unit_test]
    fn arbiter_matches_tick_reference_and_shares_timestamps() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(5);
        let mut reqs: Vec<Arrival> = (0..400)
            .map(|_| Arrival {
                t: (rng.gen_range(0..20_000) as f64) * 0.01,
                x: rng.gen_range(0..64),
                y: rng.gen_range(0..8),
                p: 1,
            })
            .collect();
        // (time, row) order, as the simulator's request sort delivers.
        reqs.sort_by(|a, b| a.t.total_cmp(&b.t).then(a.y.cmp(&b.y)));
        let p = ArbiterSaturation {
            row_time_us: 0.5,
            event_time_us: 0.25,
        };
        let expect = reference(&reqs, p);
        // Feed in two blocks to check block independence.
        let mut arb = Arbiter::new(p, roi());
        let mut out = EventChunk::default();
        let split = reqs.partition_point(|a| a.t < 100.0);
        arb.run(&reqs[..split], 100.0, &mut out);
        arb.run(&reqs[split..], f64::INFINITY, &mut out);
        let got: Vec<(i64, u16, u16)> = out.iter().map(|e| (e.t, e.x, e.y)).collect();
        assert_eq!(got.len() as u64 + arb.lost, 400);
        assert_eq!(got, expect);
        // Saturated: the load (400 events in 200 µs at ≥0.25 µs each plus row
        // grants) exceeds throughput, so rows carry several events per grant.
        let mut shared = 0;
        for w in got.windows(2) {
            shared += (w[0].0 == w[1].0 && w[0].2 == w[1].2) as usize;
        }
        assert!(shared > 50, "{shared}");
        assert!(got.windows(2).all(|w| w[0].0 <= w[1].0), "time-ordered");
    }

    #[ebptv_macros::unit_test]
    fn offer_matches_batch_run() {
        // Requests offered one by one against the batch loop: light and
        // saturated loads, repeats of blocked pixels (lost), idle gaps,
        // grants reaching past a block end; fed in blocks.
        use rand::SeedableRng;
        let mut rng = rand_pcg::Pcg64::seed_from_u64(9);
        let mut lost = 0;
        for (width, height, n, span_us, row_time, event_time) in [
            (1280u32, 720u32, 60_000usize, 2000.0, 0.02, 0.01),
            (1280, 720, 60_000, 2000.0, 0.5, 0.05),
            (200, 30, 20_000, 500.0, 0.3, 0.2),
            (64, 8, 5000, 1000.0, 0.5, 0.25),
            (65, 3, 5000, 100.0, 0.1, 0.02),
            (300, 50, 2000, 20_000.0, 0.5, 0.1),
        ] {
            let roi = Roi {
                x: 7,
                y: 11,
                width,
                height,
            };
            let reqs = random_requests(&mut rng, roi, n, span_us);
            let p = ArbiterSaturation {
                row_time_us: row_time,
                event_time_us: event_time,
            };
            let (mut one, mut batch) = (Arbiter::new(p, roi), Arbiter::new(p, roi));
            let a = same_in_blocks(
                &reqs,
                span_us,
                &format!("{width}x{height}"),
                |r, t_end, out| {
                    one.run(r, t_end, out);
                    one.pending()
                },
                |r, t_end, out| {
                    batch.run_batch(r, t_end, out);
                    batch.pending()
                },
            );
            assert_eq!(one.lost, batch.lost);
            assert_eq!(a.len() as u64 + one.lost, n as u64);
            lost += one.lost;
        }
        assert!(lost > 1000, "{lost}");
    }

    #[ebptv_macros::unit_test]
    fn refractory_drops_only_close_repeats() {
        let mut r = Refractory::new(10.0, roi());
        let mut v = vec![
            Arrival {
                t: 0.0,
                x: 1,
                y: 1,
                p: 1,
            },
            Arrival {
                t: 5.0,
                x: 1,
                y: 1,
                p: 1,
            },
            Arrival {
                t: 6.0,
                x: 2,
                y: 1,
                p: 1,
            },
            Arrival {
                t: 10.0,
                x: 1,
                y: 1,
                p: 0,
            },
        ];
        r.apply(&mut v);
        assert_eq!(
            v.iter().map(|a| a.t).collect::<Vec<_>>(),
            vec![0.0, 6.0, 10.0]
        );
    }

    #[ebptv_macros::unit_test]
    fn floor_matches_libm() {
        for v in [
            0.0,
            -0.0,
            0.5,
            -0.5,
            1.0,
            -1.0,
            1e15 + 0.5,
            -1e15 - 0.5,
            3e19,
            -3e19,
            f64::NAN,
            f64::INFINITY,
            f64::NEG_INFINITY,
            0.999_999_999_999_999_9,
            -1e-300,
        ] {
            assert_eq!(floor_i64(v), v.floor() as i64, "{v}");
        }
        for i in -100_000i64..100_000 {
            let v = i as f64 * 0.013 + [0.0, 1e-12, -1e-12][(i % 3).unsigned_abs() as usize];
            assert_eq!(floor_i64(v), v.floor() as i64, "{v}");
        }
    }

    #[ebptv_macros::unit_test]
    fn rate_limiter_caps_each_window() {
        let mut ev = EventChunk::default();
        for t in 0..100 {
            ev.push(t, 0, 0, 1);
            ev.push(t, 1, 0, 1);
        }
        let mut rl = RateLimiter::new(1e6, 10.0); // 10 per 10 µs window
        rl.apply(&mut ev);
        assert_eq!(ev.len(), 100);
        assert!(ev.t.iter().filter(|&&t| t < 10).count() == 10);
    }
}
