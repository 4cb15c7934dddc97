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
//! - **one statistic per loop.** Polarity count, time range and time sum
//!   are separate loops the compiler vectorises; the pixel map has its own
//!   loop whose body is one increment, so the CPU keeps many cache misses in
//!   flight.
//! - **blocks by segments.** The block boundary test is a scan for the
//!   first event at/after the block end; the events in between are
//!   processed without a per-event block check.
//! - **integer folding.** The fold position `frac((t − t_ref + ½) / P)` is a
//!   64-bit fixed-point product: `(2(t − t_ref) + 1) · round(2⁶⁴ / 2P)`
//!   wraps modulo 2⁶⁴ exactly like taking the fractional part, so the fold
//!   bin is two multiplications and a shift, no float, no branch.
//! - **runs of equal time.** Readouts deliver events sharing a timestamp
//!   consecutively (EVT 3 vectors, dense bursts): the histogram gets one
//!   increment per run of equal `t`, not per event.
//! - **(row, t) runs without branches.** The end of each run is written
//!   to a scratch buffer by a branch-free compaction (store always, advance
//!   the cursor on a boundary); run lengths are then counted from that
//!   (much shorter) list into four interleaved size tables, so equal
//!   consecutive sizes do not wait on each other's store.
//! - **u16 pixel counts.** Half the memory of u32 (1.8 MB for 1280×720,
//!   closer to the core's cache); a count that wraps to 0 appends the pixel
//!   to an overflow list, folded back in when the map is read.

use crate::events::{EventChunk, ON};

/// Largest (row, t) run size counted individually; larger runs share the
/// last bin.
pub const MAX_GROUP: usize = 64;
/// Events sharing (row, timestamp) in a run at least this long are the
/// arbiter-saturation signature.
pub const LARGE_GROUP: usize = 4;
/// Interleaved run-size tables (breaks store-to-load chains).
const GROUP_TABLES: usize = 4;

/// Fold reference fixed at the end of the warm-up: fold bin of an event at
/// `t` is `⌊frac((t − t_ref + ½) / p_ref) · nbins⌋`.
#[derive(Debug, Clone, Copy)]
pub struct Fold {
    pub t_ref: i64,
    pub p_ref: f64,
    pub inv_p: f64,
    pub nbins: usize,
    /// round(2⁶⁴ / (2 p_ref)): fixed-point reciprocal for [`Fold::bin`].
    mul: u64,
}

impl Fold {
    pub fn new(t_ref: i64, p_ref: f64, nbins: usize) -> Fold {
        assert!(
            p_ref >= 1.0 && nbins >= 1 && nbins < 1 << 31,
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
    pub fn bin(&self, t: i64) -> usize {
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
pub struct Block {
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
    pub fn new(start: i64, end: i64, nbins: usize) -> Self {
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

    pub fn centre(&self) -> f64 {
        self.start as f64 + self.t_rel_sum as f64 / self.n.max(1) as f64
    }

    pub fn merge(&mut self, o: Block) {
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

/// Per-event statistics of the stream (see the module doc).
#[derive(Debug, Clone)]
pub struct Accumulator {
    pub width: usize,
    pub height: usize,
    /// Pixel counts modulo 2¹⁶, row-major.
    counts: Vec<u16>,
    /// Pixels whose count wrapped, once per wrap.
    overflow: Vec<u32>,
    pub n_events: u64,
    pub n_on: u64,
    pub t_min: i64,
    pub t_max: i64,
    pub block_us: i64,
    pub max_blocks: usize,
    pub blocks: Vec<Block>,
    pub cur: Block,
    // The open (row, t) run.
    last_t: i64,
    last_y: u16,
    run: u32,
    group_tables: Vec<u64>,
    /// Scratch: lengths of the runs that ended, per segment.
    ends: Vec<u32>,
}

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
    pub fn new(width: usize, height: usize, block_us: i64, max_blocks: usize) -> Self {
        let (width, height) = (width.max(1), height.max(1));
        Accumulator {
            width,
            height,
            counts: vec![0; width * height],
            overflow: Vec::new(),
            n_events: 0,
            n_on: 0,
            t_min: i64::MAX,
            t_max: i64::MIN,
            block_us,
            max_blocks,
            blocks: Vec::new(),
            cur: Block::new(i64::MIN, i64::MIN, 0),
            last_t: i64::MIN,
            last_y: 0,
            run: 0,
            group_tables: vec![0; GROUP_TABLES * (MAX_GROUP + 1)],
            ends: Vec::new(),
        }
    }

    /// Add the events of `ev` (in stream order); returns the chunk's time
    /// range (min, max).
    pub fn push(&mut self, f: &Fold, ev: &EventChunk) -> (i64, i64) {
        let n = ev.len();
        if n == 0 {
            return (i64::MAX, i64::MIN);
        }
        let (ts, xs, ys) = (&ev.t[..n], &ev.x[..n], &ev.y[..n]);
        self.count_pixels(xs, ys);
        self.n_on += ev.p[..n].iter().map(|&p| (p == ON) as u64).sum::<u64>();
        let (lo, hi) = ts
            .iter()
            .fold((i64::MAX, i64::MIN), |(lo, hi), &t| (lo.min(t), hi.max(t)));
        self.t_min = self.t_min.min(lo);
        self.t_max = self.t_max.max(hi);
        let mut i = 0;
        while i < n {
            if ts[i] >= self.cur.end {
                self.roll_block(f, ts[i]);
            }
            let end = self.cur.end;
            let j = i + ts[i..].iter().position(|&t| t >= end).unwrap_or(n - i);
            self.block_segment(f, &ts[i..j], &ys[i..j]);
            i = j;
        }
        self.n_events += n as u64;
        (lo, hi)
    }

    fn count_pixels(&mut self, xs: &[u16], ys: &[u16]) {
        let mx = xs.iter().copied().max().unwrap_or(0) as usize;
        let my = ys.iter().copied().max().unwrap_or(0) as usize;
        if mx >= self.width || my >= self.height {
            self.grow_map(mx + 1, my + 1);
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

    fn grow_map(&mut self, w: usize, h: usize) {
        let (nw, nh) = (w.max(self.width), h.max(self.height));
        let mut m = vec![0u16; nw * nh];
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
    pub fn pixel_counts(&self) -> Vec<u32> {
        let mut out: Vec<u32> = self.counts.iter().map(|&c| c as u32).collect();
        for &i in &self.overflow {
            out[i as usize] += 1 << 16;
        }
        out
    }

    /// Number of (row, t) runs of each size (index = size, last bin = larger).
    pub fn group_sizes(&self) -> Vec<u64> {
        let mut g = vec![0u64; MAX_GROUP + 1];
        for table in self.group_tables.chunks(MAX_GROUP + 1) {
            for (a, b) in g.iter_mut().zip(table) {
                *a += b;
            }
        }
        g[0] = 0; // the tables' bin 0 collects the no-op entries
        g
    }

    /// Close the open run and the current block (end of stream).
    pub fn close(&mut self) {
        let r = self.run;
        if r > 0 {
            self.group_tables[(r as usize).min(MAX_GROUP)] += 1;
            self.account_run_in_block(r);
            self.run = 0;
        }
        let cur = std::mem::replace(&mut self.cur, Block::new(0, 0, 0));
        if cur.n > 0 {
            self.blocks.push(cur);
        }
    }

    fn account_run_in_block(&mut self, r: u32) {
        if r >= 2 {
            self.cur.shared += r as u64;
            if r as usize >= LARGE_GROUP {
                self.cur.large += r as u64;
            }
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

    /// Events `ts`, `ys` all belonging to the current block.
    fn block_segment(&mut self, f: &Fold, ts: &[i64], ys: &[u16]) {
        let n = ts.len();
        let cur = &mut self.cur;
        cur.n += n as u64;
        let start = cur.start;
        cur.t_rel_sum += ts.iter().map(|&t| t - start).sum::<i64>();

        // Fold histogram: one increment per run of equal timestamps.
        let hist = &mut cur.hist[..];
        let mut run_t = ts[0];
        let mut run_n = 0u32;
        for &t in ts {
            if t != run_t {
                hist[f.bin(run_t)] += run_n;
                run_t = t;
                run_n = 0;
            }
            run_n += 1;
        }
        hist[f.bin(run_t)] += run_n;

        // (row, t) runs: branch-free compaction of the lengths of the runs
        // that end in this segment (a run ends where (t, y) changes; the
        // first entry may be the run carried over, or 0 at stream start).
        if self.ends.len() < n + 1 {
            self.ends.resize(n + 1, 0);
        }
        let ends = &mut self.ends[..n + 1];
        let (mut lt, mut ly, mut run) = (self.last_t, self.last_y, self.run);
        let mut m = 0usize;
        for (&t, &y) in ts.iter().zip(ys) {
            let new = (t != lt) | (y != ly);
            ends[m] = run;
            m += new as usize;
            run = if new { 1 } else { run + 1 };
            lt = t;
            ly = y;
        }
        (self.last_t, self.last_y, self.run) = (lt, ly, run);
        let mut shared = 0u64;
        let mut large = 0u64;
        let tables = &mut self.group_tables[..];
        for (k, &r) in ends[..m].iter().enumerate() {
            let r64 = r as u64;
            shared += r64 * (r >= 2) as u64;
            large += r64 * (r as usize >= LARGE_GROUP) as u64;
            let table = (k % GROUP_TABLES) * (MAX_GROUP + 1);
            tables[table + (r as usize).min(MAX_GROUP)] += 1;
        }
        self.cur.shared += shared;
        self.cur.large += large;
    }
}

#[cfg(test)]
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
        pub fn new(width: usize, height: usize, block_us: i64) -> Self {
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

        pub fn push(&mut self, f: &Fold, ev: &EventChunk, max_blocks: usize) {
            for i in 0..ev.len() {
                let (t, x, y) = (ev.t[i], ev.x[i] as usize, ev.y[i]);
                self.counts[y as usize * self.width + x] += 1;
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
                if self.last == Some((t, y)) {
                    self.run += 1;
                } else {
                    self.close_run();
                    self.last = Some((t, y));
                    self.run = 1;
                }
                self.n_on += (ev.p[i] == ON) as u64;
                self.t_min = self.t_min.min(t);
                self.t_max = self.t_max.max(t);
            }
        }

        pub fn close(&mut self) {
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
    /// back in time (EVT 3), one pixel firing > 2¹⁶ times, times before
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

    #[test]
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
    #[test]
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

    #[test]
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
