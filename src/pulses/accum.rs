//! The per-event statistics of the streaming pass, and how they are made
//! fast.
//!
//! Every event contributes to: the folded-time histogram of its time block,
//! the block's event count and time sum, the per-pixel count map, the runs
//! of events sharing (row, timestamp), the polarity count and the time
//! range. Done naively (one loop, every statistic per event, float phase,
//! u32 map) this ran at ~45 Mev/s per core, ~7 % of the EVT 3 decode rate.
//! The fast path ([`Accumulator::push`]) computes *exactly* the same
//! numbers (the unit tests compare it with the naive per-event loop,
//! [`tests::reference_push`]) but:
//!
//! - **two stages.** Stage 1 (per event, fold-independent): the pixel
//!   map, the polarity count, and the (row, t) runs, found by a branch-free
//!   compaction into a scratch list; those runs are grouped into *time
//!   runs* (consecutive events sharing a timestamp: (t, events, shared,
//!   large)) by an outer loop per time run around a tight loop per row run.
//!   Stage 2 (per time run): the block roll, the block's counters and one
//!   fold-histogram increment. Readouts deliver events sharing a timestamp
//!   together (EVT 3 vectors, dense bursts), so stage 2 sees ~10× fewer
//!   items than events. A (row, t) run counts in the block holding its
//!   events.
//! - **warm-up without buffering events.** Until the reference period is
//!   known the time runs wait in [`Accumulator::pending`] (32 B per
//!   distinct timestamp instead of 13 B per event) and enter their blocks,
//!   in stream order, when the fold is set: the result is exactly that of
//!   knowing the fold from the start (unit test). The same log gives the
//!   warm-up's event-rate series for the period estimate.
//! - **sub-chunks.** Each statistic's loop runs over 4096 events at a time,
//!   re-reading them from L1/L2 instead of streaming a 1 M-event chunk
//!   (13 MB) from memory once per statistic.
//! - **integer folding.** The fold position `frac((t − t_ref + ½) / P)` is a
//!   64-bit fixed-point product: `(2(t − t_ref) + 1) · round(2⁶⁴ / 2P)`
//!   wraps modulo 2⁶⁴ exactly like taking the fractional part, so the fold
//!   bin is two multiplications and a shift, no float, no branch.
//! - **interleaved size tables.** Run sizes are counted into four tables
//!   in turn, so equal consecutive sizes do not wait on each other's store.
//! - **u8 pixel counts.** A quarter of the memory of u32 (0.9 MB for
//!   1280×720, closer to the core's cache: random pixels make every
//!   increment a cache miss); a count that wraps to 0 appends the pixel to
//!   an overflow list, folded back in when the map is read.

use crate::events::{EventChunk, ON};

/// Largest (row, t) run size counted individually; larger runs share the
/// last bin.
pub(crate) const MAX_GROUP: usize = 64;
/// Events sharing (row, timestamp) in a run at least this long are the
/// arbiter-saturation signature.
pub(crate) const LARGE_GROUP: usize = 4;
/// Largest side of the pixel-count map: the largest sensor side ebptv
/// accepts ([`crate::io::guard::MAX_SENSOR_SIDE`]); 16 MB of u8 at most,
/// whatever geometry a file states or coordinates damaged data holds.
pub(crate) const MAX_MAP_SIDE: usize = crate::io::guard::MAX_SENSOR_SIDE as usize;
/// Interleaved run-size tables (breaks store-to-load chains).
const GROUP_TABLES: usize = 4;

/// Fold reference fixed at the end of the warm-up: fold bin of an event at
/// `t` is `⌊frac((t − t_ref + ½) / p_ref) · nbins⌋`.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Fold {
    pub t_ref: i64,
    pub p_ref: f64,
    pub inv_p: f64,
    pub nbins: usize,
    /// round(2⁶⁴ / (2 p_ref)): fixed-point reciprocal for [`Fold::bin`].
    mul: u64,
}

impl Fold {
    pub(crate) fn new(t_ref: i64, p_ref: f64, nbins: usize) -> Fold {
        assert!(
            p_ref >= 1.0 && (1..1 << 31).contains(&nbins),
            "fold period {p_ref} µs / {nbins} bins"
        );
        Fold {
            t_ref,
            p_ref,
            inv_p: 1.0 / p_ref,
            nbins,
            mul: fixed_reciprocal(p_ref),
        }
    }

    /// Fold bin of time `t` (µs). `(2d + 1)·mul mod 2⁶⁴ = 2⁶⁴·frac((d + ½)/P)`
    /// up to the rounding of `mul` (±½ in 2⁵⁷: < 10⁻⁷ of a bin within 10 h of
    /// sensor time).
    #[inline(always)]
    pub(crate) fn bin(&self, t: i64) -> usize {
        let x = (t.wrapping_sub(self.t_ref) as u64)
            .wrapping_mul(2)
            .wrapping_add(1);
        let frac = x.wrapping_mul(self.mul);
        (((frac >> 32) * self.nbins as u64) >> 32) as usize
    }
}

/// round(2⁶³ / p) computed exactly from the binary value of `p` (an f64
/// quotient would carry a relative error of 2⁻⁵³, i.e. 10⁻⁵ of a bin after
/// a day of recording).
fn fixed_reciprocal(p: f64) -> u64 {
    // p = m · 2^e with an integer mantissa m < 2⁵³.
    let bits = p.to_bits();
    let exp = ((bits >> 52) & 0x7ff) as i32;
    let m = (bits & ((1u64 << 52) - 1)) | (1u64 << 52);
    let e = exp - 1075;
    let shift = 63 - e; // 2⁶³ / p = 2^(63−e) / m
    debug_assert!((0..128).contains(&shift));
    let m = m as u128;
    (((1u128 << shift) + m / 2) / m) as u64
}

/// One time block of the recording: its fold histogram and counters.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Block {
    pub start: i64,
    pub end: i64,
    pub n: u64,
    /// Sum of (t − start): the block's event-weighted centre.
    pub t_rel_sum: i64,
    /// Events in (row, t) runs of ≥ 2 closed in this block.
    pub shared: u64,
    /// Events in (row, t) runs of ≥ [`LARGE_GROUP`] closed in this block.
    pub large: u64,
    pub hist: Vec<u32>,
}

impl Block {
    pub(crate) fn new(start: i64, end: i64, nbins: usize) -> Self {
        Block {
            start,
            end,
            n: 0,
            t_rel_sum: 0,
            shared: 0,
            large: 0,
            hist: vec![0; nbins],
        }
    }

    pub(crate) fn centre(&self) -> f64 {
        self.start as f64 + self.t_rel_sum as f64 / self.n.max(1) as f64
    }

    pub(crate) fn merge(&mut self, o: Block) {
        let c = (self.centre() * self.n as f64 + o.centre() * o.n as f64)
            / (self.n + o.n).max(1) as f64;
        self.n += o.n;
        self.t_rel_sum = ((c - self.start as f64) * self.n as f64).round() as i64;
        self.end = o.end;
        self.shared += o.shared;
        self.large += o.large;
        for (a, b) in self.hist.iter_mut().zip(&o.hist) {
            *a += b;
        }
    }
}

/// A run of consecutive events sharing one timestamp (a group of
/// consecutive closed (row, t) runs with equal `t`): everything the
/// fold-dependent stage needs.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub(crate) struct TimeRun {
    pub t: i64,
    pub n: u64,
    /// Events of this run in (row, t) runs of ≥ 2.
    pub shared: u64,
    /// Events of this run in (row, t) runs of ≥ [`LARGE_GROUP`].
    pub large: u64,
}

/// Events processed per inner step: the per-statistic loops re-read a
/// sub-chunk from L1/L2 instead of streaming a whole 1 M-event chunk
/// (13 MB) from memory once per statistic.
const SUB_CHUNK: usize = 4096;
/// Indices into the sub-chunk scratch are masked with this (a no-op, as
/// they are < SUB_CHUNK) so the compiler drops the bounds checks.
const SUB_MASK: usize = SUB_CHUNK - 1;
const _: () = assert!(SUB_CHUNK.is_power_of_two());

/// Per-event statistics of the stream (see the module doc).
#[derive(Debug, Clone)]
pub(crate) struct Accumulator {
    pub width: usize,
    pub height: usize,
    /// Pixel counts modulo 2⁸, row-major.
    counts: Vec<u8>,
    /// Pixels whose count wrapped, once per wrap.
    overflow: Vec<u32>,
    /// Events with x or y at or beyond [`MAX_MAP_SIDE`]: not in the map.
    pub off_map: u64,
    pub n_events: u64,
    pub n_on: u64,
    pub t_min: i64,
    pub t_max: i64,
    pub block_us: i64,
    pub max_blocks: usize,
    pub blocks: Vec<Block>,
    pub cur: Block,
    /// The fold, once known; until then closed time runs go to `pending`.
    fold: Option<Fold>,
    /// Time runs waiting for the fold (the warm-up), in stream order.
    pub pending: Vec<TimeRun>,
    // The open (row, t) run; `started` once the first event was seen.
    started: bool,
    last_t: i64,
    last_y: u16,
    run: u32,
    /// The open time run (its closed (row, t) runs so far).
    open: TimeRun,
    group_tables: Box<[[u64; MAX_GROUP + 1]; GROUP_TABLES]>,
    /// Scratch: (t, length) of the (row, t) runs closed in a sub-chunk.
    row_t: Vec<i64>,
    row_len: Vec<u32>,
    /// Scratch: the time runs closed in a sub-chunk.
    time_runs: Vec<TimeRun>,
    /// Time runs before this time also go to `head` / `trace` (set with
    /// the fold; see [`Accumulator::watch_start`]).
    watch_until: i64,
    /// (t, events) of the time runs before `head_until` (capped).
    pub head: Vec<(i64, u64)>,
    head_until: i64,
    /// Events per µs from `trace_t0`.
    pub trace: Vec<u32>,
    pub trace_t0: i64,
}

/// Most entries kept in [`Accumulator::head`].
const HEAD_MAX: usize = 200_000;

/// Halve the time resolution of the block list: blocks 2k and 2k+1 merge
/// (keeping memory bounded on long recordings).
fn merge_pairs(blocks: &mut Vec<Block>) {
    let old = std::mem::take(blocks);
    let mut it = old.into_iter();
    while let Some(mut a) = it.next() {
        if let Some(b) = it.next() {
            a.merge(b);
        }
        blocks.push(a);
    }
}

impl Accumulator {
    pub(crate) fn new(width: usize, height: usize, block_us: i64, max_blocks: usize) -> Self {
        let width = width.clamp(1, MAX_MAP_SIDE);
        let height = height.clamp(1, MAX_MAP_SIDE);
        Accumulator {
            width,
            height,
            counts: vec![0; width * height],
            overflow: Vec::new(),
            off_map: 0,
            n_events: 0,
            n_on: 0,
            t_min: i64::MAX,
            t_max: i64::MIN,
            block_us,
            max_blocks,
            blocks: Vec::new(),
            cur: Block::new(i64::MIN, i64::MIN, 0),
            fold: None,
            pending: Vec::new(),
            started: false,
            last_t: i64::MIN,
            last_y: 0,
            run: 0,
            open: TimeRun::default(),
            group_tables: Box::new([[0; MAX_GROUP + 1]; GROUP_TABLES]),
            row_t: vec![0; SUB_CHUNK],
            row_len: vec![0; SUB_CHUNK],
            time_runs: vec![TimeRun::default(); SUB_CHUNK],
            watch_until: i64::MIN,
            head: Vec::new(),
            head_until: i64::MIN,
            trace: Vec::new(),
            trace_t0: 0,
        }
    }

    /// Watch the start of the recording (call before [`Accumulator::set_fold`]):
    /// the events before `head_until` are kept as (t, count) in `head` (to
    /// count those before pulse 0), and those in `[trace_t0, trace_t0 +
    /// trace_len)` are counted per µs in `trace` (the rate figure). Done in
    /// the fold stage, so every event is seen, warm-up or not, at the cost
    /// of one predictable comparison per time run.
    pub(crate) fn watch_start(&mut self, head_until: i64, trace_t0: i64, trace_len: usize) {
        self.head_until = head_until;
        self.trace_t0 = trace_t0;
        self.trace = vec![0; trace_len];
        self.watch_until = head_until.max(trace_t0.saturating_add(trace_len as i64));
    }

    #[cold]
    fn watch(&mut self, r: &TimeRun) {
        if r.t < self.head_until && self.head.len() < HEAD_MAX {
            self.head.push((r.t, r.n));
        }
        let i = r.t.wrapping_sub(self.trace_t0);
        if (0..self.trace.len() as i64).contains(&i) {
            self.trace[i as usize] += r.n as u32;
        }
    }

    /// Events before this time are listed in `head`.
    pub(crate) fn head_until(&self) -> i64 {
        self.head_until
    }

    /// The fold, once set.
    #[cfg(feature = "testkit")]
    pub(crate) fn fold(&self) -> Option<Fold> {
        self.fold
    }

    /// Fix the fold: the pending time runs (warm-up) enter their blocks
    /// now, in stream order, exactly as if the fold had been known all along.
    pub(crate) fn set_fold(&mut self, f: Fold) {
        assert!(self.fold.is_none(), "the fold is set once");
        self.fold = Some(f);
        let pending = std::mem::take(&mut self.pending);
        self.fold_runs(&f, &pending);
    }

    /// Add the events of `ev` (in stream order) with the fold `f` (set on
    /// the first call if not yet set); returns the chunk's time range
    /// (min, max).
    pub(crate) fn push(&mut self, f: &Fold, ev: &EventChunk) -> (i64, i64) {
        if self.fold.is_none() {
            self.set_fold(*f);
        }
        self.push_events(ev)
    }

    /// Add the events of `ev`: before the fold is set their time runs are
    /// kept in [`Accumulator::pending`]. Returns the chunk's time range.
    pub(crate) fn push_events(&mut self, ev: &EventChunk) -> (i64, i64) {
        let n = ev.len();
        if n == 0 {
            return (i64::MAX, i64::MIN);
        }
        if !self.started {
            // The first event opens the first (row, t) run.
            self.started = true;
            self.last_t = ev.t[0];
            self.last_y = ev.y[0];
            self.run = 0;
            self.open = TimeRun {
                t: ev.t[0],
                ..TimeRun::default()
            };
        }
        let (mut lo, mut hi) = (i64::MAX, i64::MIN);
        let mut a = 0;
        while a < n {
            let b = (a + SUB_CHUNK).min(n);
            let (ts, xs, ys) = (&ev.t[a..b], &ev.x[a..b], &ev.y[a..b]);
            self.count_pixels(xs, ys);
            self.n_on += ev.p[a..b].iter().map(|&p| (p == ON) as u64).sum::<u64>();
            let m = self.row_runs(ts, ys);
            let (k, l, h) = self.time_runs_of(m);
            lo = lo.min(l);
            hi = hi.max(h);
            let runs = std::mem::take(&mut self.time_runs);
            match self.fold {
                Some(f) => self.fold_runs(&f, &runs[..k]),
                None => self.pending.extend_from_slice(&runs[..k]),
            }
            self.time_runs = runs;
            a = b;
        }
        // Every event's time is that of a closed (row, t) run, seen by
        // `time_runs_of`, or of the open one. (The first closed run may be
        // the previous chunk's open run: the range may include one earlier
        // time, which no caller minds.)
        lo = lo.min(self.last_t);
        hi = hi.max(self.last_t);
        self.t_min = self.t_min.min(lo);
        self.t_max = self.t_max.max(hi);
        self.n_events += n as u64;
        (lo, hi)
    }

    fn count_pixels(&mut self, xs: &[u16], ys: &[u16]) {
        let mx = xs.iter().copied().max().unwrap_or(0) as usize;
        let my = ys.iter().copied().max().unwrap_or(0) as usize;
        if mx >= self.width || my >= self.height {
            self.grow_map((mx + 1).min(MAX_MAP_SIDE), (my + 1).min(MAX_MAP_SIDE));
            if mx >= MAX_MAP_SIDE || my >= MAX_MAP_SIDE {
                // Coordinates no sensor has (damaged data): not mapped,
                // counted; the map stays within MAX_MAP_SIDE².
                return self.count_pixels_capped(xs, ys);
            }
        }
        let w = self.width;
        let counts = &mut self.counts[..];
        for (&x, &y) in xs.iter().zip(ys) {
            let i = y as usize * w + x as usize;
            let c = counts[i].wrapping_add(1);
            counts[i] = c;
            if c == 0 {
                self.overflow.push(i as u32);
            }
        }
    }

    #[cold]
    fn count_pixels_capped(&mut self, xs: &[u16], ys: &[u16]) {
        let (w, h) = (self.width, self.height);
        for (&x, &y) in xs.iter().zip(ys) {
            let (x, y) = (x as usize, y as usize);
            if x >= w || y >= h {
                self.off_map += 1;
                continue;
            }
            let i = y * w + x;
            let c = self.counts[i].wrapping_add(1);
            self.counts[i] = c;
            if c == 0 {
                self.overflow.push(i as u32);
            }
        }
    }

    fn grow_map(&mut self, w: usize, h: usize) {
        let (nw, nh) = (w.max(self.width), h.max(self.height));
        let mut m = vec![0u8; nw * nh];
        for y in 0..self.height {
            m[y * nw..y * nw + self.width]
                .copy_from_slice(&self.counts[y * self.width..(y + 1) * self.width]);
        }
        for o in &mut self.overflow {
            let (x, y) = (*o as usize % self.width, *o as usize / self.width);
            *o = (y * nw + x) as u32;
        }
        self.counts = m;
        self.width = nw;
        self.height = nh;
    }

    /// Events per pixel, row-major `height × width`.
    pub(crate) fn pixel_counts(&self) -> Vec<u32> {
        let mut out: Vec<u32> = self.counts.iter().map(|&c| c as u32).collect();
        for &i in &self.overflow {
            out[i as usize] += 1 << 8;
        }
        out
    }

    /// Number of (row, t) runs of each size (index = size, last bin = larger).
    pub(crate) fn group_sizes(&self) -> Vec<u64> {
        let mut g = vec![0u64; MAX_GROUP + 1];
        for table in self.group_tables.iter() {
            for (a, b) in g.iter_mut().zip(table) {
                *a += b;
            }
        }
        g
    }

    /// Close the open runs and the current block (end of stream). Without
    /// a fold the last time run stays in `pending`.
    pub(crate) fn close(&mut self) {
        if self.started && self.run > 0 {
            self.row_t[0] = self.last_t;
            self.row_len[0] = self.run;
            let (k, _, _) = self.time_runs_of(1);
            debug_assert!(k <= 1);
            self.run = 0;
            self.started = false;
            let mut runs = self.time_runs[..k].to_vec();
            let open = std::mem::take(&mut self.open);
            if open.n > 0 {
                runs.push(open);
            }
            match self.fold {
                Some(f) => self.fold_runs(&f, &runs),
                None => self.pending.extend_from_slice(&runs),
            }
        }
        // No open block: the next time run opens one.
        let cur = std::mem::replace(&mut self.cur, Block::new(i64::MIN, i64::MIN, 0));
        if cur.n > 0 {
            self.blocks.push(cur);
        }
    }

    /// Stage 1a: the (row, t) runs that end in `ts`/`ys`, as (t, length)
    /// in `row_t`/`row_len` (branch-free compaction: store always, advance
    /// the cursor where (t, y) changes); returns their number. The open run
    /// carries over to the next call.
    fn row_runs(&mut self, ts: &[i64], ys: &[u16]) -> usize {
        let rt = &mut self.row_t[..SUB_CHUNK];
        let rl = &mut self.row_len[..SUB_CHUNK];
        let (mut lt, mut ly, mut run) = (self.last_t, self.last_y, self.run);
        let mut m = 0usize;
        for (&t, &y) in ts.iter().zip(ys) {
            let new = (t != lt) | (y != ly);
            rt[m & SUB_MASK] = lt;
            rl[m & SUB_MASK] = run;
            m += new as usize;
            run = if new { 1 } else { run + 1 };
            lt = t;
            ly = y;
        }
        (self.last_t, self.last_y, self.run) = (lt, ly, run);
        m
    }

    /// Stage 1b: the first `m` closed (row, t) runs → run-size tables and
    /// time runs (consecutive (row, t) runs of equal t) in `time_runs`;
    /// returns how many time runs closed and the range of their times; the
    /// open one carries over. An
    /// outer loop per time run around a tight inner loop per (row, t) run:
    /// both branches are predictable whether a time run holds hundreds of
    /// rows (dense random pixels) or one.
    fn time_runs_of(&mut self, m: usize) -> (usize, i64, i64) {
        let tables = &mut *self.group_tables;
        let out = &mut self.time_runs[..SUB_CHUNK];
        let (rt, rl) = (&self.row_t[..m], &self.row_len[..m]);
        let mut open = self.open;
        let mut k = 0usize;
        let mut i = 0usize;
        let (mut lo, mut hi) = (i64::MAX, i64::MIN);
        while i < m {
            let t = rt[i];
            lo = lo.min(t);
            hi = hi.max(t);
            if t != open.t {
                if open.n > 0 {
                    out[k & SUB_MASK] = open;
                    k += 1;
                }
                open = TimeRun {
                    t,
                    ..TimeRun::default()
                };
            }
            let (mut n, mut shared, mut large) = (open.n, open.shared, open.large);
            while i < m && rt[i] == t {
                let r = rl[i];
                tables[i % GROUP_TABLES][(r as usize).min(MAX_GROUP)] += 1;
                let r = r as u64;
                n += r;
                shared += r * (r >= 2) as u64;
                large += r * (r >= LARGE_GROUP as u64) as u64;
                i += 1;
            }
            (open.n, open.shared, open.large) = (n, shared, large);
        }
        self.open = open;
        (k, lo, hi)
    }

    /// Stage 2: time runs into blocks and their fold histograms.
    fn fold_runs(&mut self, f: &Fold, runs: &[TimeRun]) {
        for r in runs {
            if r.t < self.watch_until {
                self.watch(r);
            }
            if r.t >= self.cur.end {
                self.roll_block(f, r.t);
            }
            let cur = &mut self.cur;
            cur.n += r.n;
            cur.t_rel_sum += r.n as i64 * (r.t - cur.start);
            cur.hist[f.bin(r.t)] += r.n as u32;
            cur.shared += r.shared;
            cur.large += r.large;
        }
    }

    fn roll_block(&mut self, f: &Fold, t: i64) {
        let done = std::mem::replace(&mut self.cur, Block::new(0, 0, 0));
        if done.n > 0 {
            self.blocks.push(done);
        }
        if self.blocks.len() > self.max_blocks {
            merge_pairs(&mut self.blocks);
            self.block_us *= 2;
        }
        let start = f.t_ref + (t - f.t_ref).div_euclid(self.block_us) * self.block_us;
        self.cur = Block::new(start, start + self.block_us, f.nbins);
    }
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;

    /// The naive per-event loop the fast path must reproduce exactly: one
    /// event at a time, every statistic, float phase, u32 pixel map.
    pub(crate) struct Reference {
        pub width: usize,
        pub counts: Vec<u32>,
        pub n_on: u64,
        pub t_min: i64,
        pub t_max: i64,
        pub block_us: i64,
        pub blocks: Vec<Block>,
        pub cur: Block,
        pub last: Option<(i64, u16)>,
        pub run: u32,
        pub groups: Vec<u64>,
    }

    impl Reference {
        pub(crate) fn new(width: usize, height: usize, block_us: i64) -> Self {
            Reference {
                width,
                counts: vec![0; width * height],
                n_on: 0,
                t_min: i64::MAX,
                t_max: i64::MIN,
                block_us,
                blocks: vec![],
                cur: Block::new(i64::MIN, i64::MIN, 0),
                last: None,
                run: 0,
                groups: vec![0; MAX_GROUP + 1],
            }
        }

        fn close_run(&mut self) {
            let r = self.run;
            if r == 0 {
                return;
            }
            self.groups[(r as usize).min(MAX_GROUP)] += 1;
            if r >= 2 {
                self.cur.shared += r as u64;
                if r as usize >= LARGE_GROUP {
                    self.cur.large += r as u64;
                }
            }
            self.run = 0;
        }

        pub(crate) fn push(&mut self, f: &Fold, ev: &EventChunk, max_blocks: usize) {
            for i in 0..ev.len() {
                let (t, x, y) = (ev.t[i], ev.x[i] as usize, ev.y[i]);
                self.counts[y as usize * self.width + x] += 1;
                // A (row, t) run counts in the block holding its events:
                // close it before this event may open a new block.
                if self.last == Some((t, y)) {
                    self.run += 1;
                } else {
                    self.close_run();
                    self.last = Some((t, y));
                    self.run = 1;
                }
                if t >= self.cur.end {
                    let done = std::mem::replace(&mut self.cur, Block::new(0, 0, 0));
                    if done.n > 0 {
                        self.blocks.push(done);
                    }
                    if self.blocks.len() > max_blocks {
                        merge_pairs(&mut self.blocks);
                        self.block_us *= 2;
                    }
                    let start = f.t_ref + (t - f.t_ref).div_euclid(self.block_us) * self.block_us;
                    self.cur = Block::new(start, start + self.block_us, f.nbins);
                }
                let b = f.bin(t);
                self.cur.hist[b] += 1;
                self.cur.n += 1;
                self.cur.t_rel_sum += t - self.cur.start;
                self.n_on += (ev.p[i] == ON) as u64;
                self.t_min = self.t_min.min(t);
                self.t_max = self.t_max.max(t);
            }
        }

        pub(crate) fn close(&mut self) {
            self.close_run();
            let cur = std::mem::replace(&mut self.cur, Block::new(0, 0, 0));
            if cur.n > 0 {
                self.blocks.push(cur);
            }
        }
    }

    /// Deterministic LCG (no dependency on rand in unit tests).
    struct Lcg(u64);
    impl Lcg {
        fn next(&mut self, n: u64) -> u64 {
            self.0 = self
                .0
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (self.0 >> 33) % n
        }
    }

    /// Events with long and short runs of equal t and (row, t), small steps
    /// back in time (EVT 3), one pixel firing > 2¹⁶ times (many u8 wraps), times before
    /// t_ref; split into uneven chunks so runs cross chunk and block edges.
    fn stream() -> Vec<EventChunk> {
        let mut g = Lcg(42);
        let mut all = EventChunk::default();
        let mut t: i64 = -300;
        while all.len() < 400_000 {
            t += g.next(3) as i64;
            let back = if g.next(50) == 0 { g.next(5) as i64 } else { 0 };
            let y = g.next(40) as u16;
            let len = 1 + g.next(12);
            for _ in 0..len {
                all.push(t - back, g.next(64) as u16, y, (g.next(2)) as u8);
            }
            for _ in 0..1 + g.next(3) {
                all.push(t, 63, 39, 1); // the hot pixel, > 65536 events
            }
        }
        let mut chunks = Vec::new();
        let mut i = 0;
        while i < all.len() {
            let j = (i + 1 + g.next(30_000) as usize).min(all.len());
            let mut c = EventChunk::default();
            c.t.extend_from_slice(&all.t[i..j]);
            c.x.extend_from_slice(&all.x[i..j]);
            c.y.extend_from_slice(&all.y[i..j]);
            c.p.extend_from_slice(&all.p[i..j]);
            chunks.push(c);
            i = j;
        }
        chunks
    }

    #[ebptv_macros::unit_test]
    fn fast_path_equals_reference_exactly() {
        for (t_ref, p) in [(0i64, 100.0), (-250, 37.77), (1_000, 199.9993)] {
            let f = Fold::new(t_ref, p, (p.round() as usize).max(8));
            // Small blocks and few of them: merging by doubling happens.
            let mut fast = Accumulator::new(64, 40, 500, 16);
            let mut slow = Reference::new(64, 40, 500);
            for c in stream() {
                fast.push(&f, &c);
                slow.push(&f, &c, 16);
            }
            fast.close();
            slow.close();
            assert!(fast.block_us > 500, "blocks were merged");
            assert_eq!(fast.blocks, slow.blocks, "P = {p}");
            assert_eq!(fast.group_sizes(), slow.groups);
            assert_eq!(fast.pixel_counts(), slow.counts);
            assert!(slow.counts[39 * 64 + 63] > 1 << 16);
            assert_eq!(
                (fast.n_on, fast.t_min, fast.t_max),
                (slow.n_on, slow.t_min, slow.t_max)
            );
        }
    }

    /// The fixed-point fold bin against the definition in exact rational
    /// arithmetic: equal except within 10⁻⁵ of a bin edge (times up to 2³⁶ µs).
    /// The warm-up: events pushed before the fold is known (their time
    /// runs wait in `pending`), the fold set, the rest pushed: the same
    /// blocks as the reference that knew the fold from the start. The
    /// pending runs hold every event's time exactly once.
    #[ebptv_macros::unit_test]
    fn warm_up_then_fold_equals_reference() {
        for warm_chunks in [0usize, 1, 5, 1000] {
            let f = Fold::new(-250, 37.77, 38);
            let mut fast = Accumulator::new(64, 40, 500, 16);
            let mut slow = Reference::new(64, 40, 500);
            let mut per_t: std::collections::BTreeMap<i64, u64> = Default::default();
            let chunks = stream();
            let mut n_warm = 0u64;
            for (i, c) in chunks.iter().enumerate() {
                if i < warm_chunks {
                    fast.push_events(c);
                    for &t in &c.t {
                        *per_t.entry(t).or_default() += 1;
                    }
                    n_warm += c.len() as u64;
                } else {
                    if fast.fold().is_none() {
                        let mut logged: std::collections::BTreeMap<i64, u64> = Default::default();
                        for r in &fast.pending {
                            *logged.entry(r.t).or_default() += r.n;
                        }
                        // The open runs are not logged yet.
                        let open = n_warm - logged.values().sum::<u64>();
                        assert!(open <= 64, "{open} events in open runs");
                        for (t, n) in &logged {
                            assert!(per_t[t] >= *n);
                        }
                        fast.set_fold(f);
                    }
                    fast.push(&f, c);
                }
                slow.push(&f, c, 16);
            }
            if fast.fold().is_none() {
                let mut logged: std::collections::BTreeMap<i64, u64> = Default::default();
                fast.close();
                for r in &fast.pending {
                    *logged.entry(r.t).or_default() += r.n;
                }
                assert_eq!(logged, per_t, "after close every event is logged");
                fast.set_fold(f);
                fast.close();
            } else {
                fast.close();
            }
            slow.close();
            assert_eq!(fast.blocks, slow.blocks, "warm-up {warm_chunks} chunks");
            assert_eq!(fast.group_sizes(), slow.groups);
            assert_eq!(fast.pixel_counts(), slow.counts);
        }
    }

    #[ebptv_macros::unit_test]
    fn fold_bin_matches_exact_phase() {
        let mut g = Lcg(5);
        for (t_ref, p, nb) in [
            (0i64, 100.0, 100),
            (-250, 37.77, 38),
            (7, 199.9993, 200),
            (3, 50.0001, 25),
        ] {
            let f = Fold::new(t_ref, p, nb);
            // P as an exact rational: p_num / 10⁶.
            let p_num = (p * 1e6f64).round() as i128;
            let mut checked = 0;
            for k in 0..200_000i64 {
                let t = if k % 2 == 0 {
                    k - 1000
                } else {
                    g.next(1 << 36) as i64
                };
                // frac((t − t_ref + ½)/P)·nb = ((2d+1)·10⁶ mod 2·p_num)·nb / (2·p_num)
                let num =
                    ((2 * (t - t_ref) as i128 + 1) * 1_000_000).rem_euclid(2 * p_num) * nb as i128;
                let den = 2 * p_num;
                let exact = (num / den) as usize;
                let dist = (num % den).min(den - num % den) as f64 / den as f64;
                if dist > 1e-5 {
                    assert_eq!(f.bin(t), exact, "t = {t}, P = {p}");
                    checked += 1;
                }
            }
            assert!(checked > 190_000);
        }
    }

    #[ebptv_macros::unit_test]
    fn map_stays_bounded_for_absurd_coordinates() {
        let f = Fold::new(0, 50.0, 50);
        let mut a = Accumulator::new(65535, 65535, 1000, 8);
        assert_eq!((a.width, a.height), (MAX_MAP_SIDE, MAX_MAP_SIDE));
        let mut a2 = Accumulator::new(4, 4, 1000, 8);
        let mut c = EventChunk::default();
        c.push(1, 1, 1, 1);
        c.push(2, 65535, 3, 1);
        c.push(3, 2, 60000, 1);
        c.push(4, 2, 2, 1);
        a2.push(&f, &c);
        a.push(&f, &c);
        assert!(a2.width <= MAX_MAP_SIDE && a2.height <= MAX_MAP_SIDE);
        assert_eq!(a2.off_map, 2);
        assert_eq!(a2.pixel_counts().iter().sum::<u32>(), 2);
        assert_eq!(a2.n_events, 4);
    }

    #[ebptv_macros::unit_test]
    fn map_grows_for_events_outside_the_geometry() {
        let f = Fold::new(0, 50.0, 50);
        let mut a = Accumulator::new(4, 4, 1000, 8);
        let mut c = EventChunk::default();
        c.push(1, 1, 1, 1);
        a.push(&f, &c);
        let mut c = EventChunk::default();
        c.push(2, 9, 6, 1);
        c.push(3, 1, 1, 1);
        a.push(&f, &c);
        let m = a.pixel_counts();
        assert_eq!((a.width, a.height), (10, 7));
        assert_eq!(m[10 + 1], 2);
        assert_eq!(m[6 * 10 + 9], 1);
    }
}
