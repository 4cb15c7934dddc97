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
use crate::events::EventChunk;

/// Drops requests of a pixel within `period_us` after its previous one.
pub struct Refractory {
    period_us: f64,
    roi: Roi,
    last: Vec<f64>,
}

impl Refractory {
    pub fn new(period_us: f64, roi: Roi) -> Self {
        Refractory {
            period_us,
            roi,
            last: vec![f64::NEG_INFINITY; roi.width as usize * roi.height as usize],
        }
    }

    /// Filter time-ordered requests in place.
    pub fn apply(&mut self, reqs: &mut Vec<Arrival>) {
        reqs.retain(|a| self.keep(a));
    }

    #[inline]
    fn index(&self, a: &Arrival) -> usize {
        (a.y as usize - self.roi.y as usize) * self.roi.width as usize
            + (a.x as usize - self.roi.x as usize)
    }

    /// Whether request `a` would pass now (no state change).
    #[inline]
    pub fn would_keep(&self, a: &Arrival) -> bool {
        a.t - self.last[self.index(a)] >= self.period_us
    }

    /// Whether request `a` passes (requests in time order).
    #[inline]
    pub fn keep(&mut self, a: &Arrival) -> bool {
        let i = self.index(a);
        if a.t - self.last[i] >= self.period_us {
            self.last[i] = a.t;
            true
        } else {
            false
        }
    }
}

pub struct Arbiter {
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

impl Arbiter {
    pub fn new(params: ArbiterSaturation, roi: Roi) -> Self {
        Arbiter {
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
    pub fn run(&mut self, reqs: &[Arrival], t_end: f64, out: &mut EventChunk) {
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
    pub fn offer(&mut self, a: &Arrival, t_end: f64, out: &mut EventChunk) {
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
    pub fn finish(&mut self, t_end: f64, out: &mut EventChunk) {
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
        self.t_free = t_grant + self.params.row_time_us + n as f64 * self.params.event_time_us;
        row.clear();
    }

    /// The batch loop `run` was before requests could be offered one by
    /// one (the reference `offer_matches_batch_run` compares with).
    #[cfg(test)]
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

    /// Requests still waiting.
    pub fn pending(&self) -> usize {
        self.rows.iter().map(|r| r.len()).sum()
    }
}

/// Drops events beyond `max_rate_ev_s · window_us` in each window of the
/// event timestamps (a counter reset every window).
pub struct RateLimiter {
    window_us: f64,
    max_per_window: f64,
    window: i64,
    count: u64,
}

impl RateLimiter {
    pub fn new(max_rate_ev_s: f64, window_us: f64) -> Self {
        RateLimiter {
            window_us,
            max_per_window: max_rate_ev_s * window_us * 1e-6,
            window: i64::MIN,
            count: 0,
        }
    }

    pub fn apply(&mut self, ev: &mut EventChunk) {
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

/// Stamp requests without a readout bottleneck: each at its own time.
pub fn stamp_ideal(reqs: &[Arrival], out: &mut EventChunk) {
    for a in reqs {
        out.push(floor_i64(a.t), a.x, a.y, a.p);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn roi() -> Roi {
        Roi {
            x: 0,
            y: 0,
            width: 64,
            height: 8,
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

    #[test]
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

    #[test]
    fn offer_matches_batch_run() {
        // Requests offered one by one against the batch loop: light and
        // saturated loads, repeats of blocked pixels (lost), idle gaps,
        // grants reaching past a block end; fed in blocks.
        use rand::{Rng, SeedableRng};
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
            let mut reqs: Vec<Arrival> = (0..n)
                .map(|_| Arrival {
                    // ns-quantised times, many shared.
                    t: rng.gen_range(0..(span_us * 1000.0) as u64) as f64 * 1e-3,
                    x: 7 + rng.gen_range(0..width) as u16,
                    y: 11 + rng.gen_range(0..height) as u16,
                    p: rng.gen_range(0..2),
                })
                .collect();
            reqs.sort_by(|a, b| a.t.total_cmp(&b.t).then(a.y.cmp(&b.y)));
            let p = ArbiterSaturation {
                row_time_us: row_time,
                event_time_us: event_time,
            };
            let (mut one, mut batch) = (Arbiter::new(p, roi), Arbiter::new(p, roi));
            let (mut a, mut b) = (EventChunk::default(), EventChunk::default());
            let mut from = 0;
            for k in 1..=8 {
                let t_end = if k == 8 {
                    f64::INFINITY
                } else {
                    span_us * k as f64 / 8.0
                };
                let to = reqs.partition_point(|r| r.t < t_end);
                one.run(&reqs[from..to], t_end, &mut a);
                batch.run_batch(&reqs[from..to], t_end, &mut b);
                assert_eq!(one.pending(), batch.pending());
                assert_eq!(a, b, "{width}x{height}, block {k}");
                from = to;
            }
            assert_eq!(one.lost, batch.lost);
            assert_eq!(a.len() as u64 + one.lost, n as u64);
            lost += one.lost;
        }
        assert!(lost > 1000, "{lost}");
    }

    #[test]
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

    #[test]
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

    #[test]
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
