//! Tests of the pixel model: each fast path (renderers, drain, SIMD
//! lanes, tables, response passes) against its plain reference, and the
//! model's statistics (mismatch pattern, events per log-contrast step).

use super::*;
use crate::flow::erf;
use crate::scenario::*;

/// Snapshots: dense, overlapping, some straddling the ROI edge; jet-
/// like (v = 0), u = 0, at rest and general velocities.
fn scene(n: usize, w: f64, h: f64, seed: u64) -> Vec<Snapshot> {
    let mut rng = Pcg64::seed_from_u64(seed);
    (0..n)
        .map(|i| {
            let (u, v) = match i % 4 {
                0 => (rng.gen_range(-40_000.0..40_000.0), 0.0),
                1 => (0.0, rng.gen_range(-40_000.0..40_000.0)),
                2 => (0.0, 0.0),
                _ => (
                    rng.gen_range(-40_000.0..40_000.0),
                    rng.gen_range(-40_000.0..40_000.0),
                ),
            };
            Snapshot {
                x: rng.gen_range(-5.0..w + 5.0),
                y: rng.gen_range(-5.0..h + 5.0),
                u,
                v,
                brightness: rng.gen_range(0.2..3.0),
                id: i as u64,
            }
        })
        .collect()
}

/// The streak node count with √(u² + v²) and the hypot fallback is
/// hypot's count exactly, also for speeds whose count ⌈q⌉ sits on an
/// integer (every count's boundary, approached to the last bit, in
/// many directions) and for tiny, axis-aligned and huge velocities.
#[ebptv_macros::unit_test]
fn streak_count_is_hypots() {
    for (scale, width) in [(1.0, 10.0), (0.37, 10.0), (3.0, 5.0), (30.0, 7.3)] {
        streak_count_is_hypots_for(scale, width);
    }
}

fn streak_count_is_hypots_for(scale: f64, width: f64) {
    let mut sc = Scenario::default();
    sc.sensor = small_sensor();
    sc.light.pulse_width_us = width;
    sc.light.pulse_streaks = Some(PulseStreaks { scale });
    let model = PixelModel::new(&sc, 4);
    let scale = model.streak_scale.unwrap();
    let per_speed = model.shape.end_us * 1e-6 * scale / 0.2;
    let want = |u: f64, v: f64| {
        let len = u.hypot(v) * model.shape.end_us * 1e-6 * scale;
        &model.streak_nodes[ceil_count(len / 0.2, 32) - 1]
    };
    let mut speeds = vec![0.0, 1e-300, 1e-12, 1.0, 1e200, f64::MAX];
    for k in 1..=33 {
        let s = k as f64 / per_speed;
        let mut lo = s;
        let mut hi = s;
        for _ in 0..4 {
            speeds.extend([lo, hi]);
            lo = f64::from_bits(lo.to_bits() - 1);
            hi = f64::from_bits(hi.to_bits() + 1);
        }
        speeds.extend([s * (1.0 - 1e-13), s * (1.0 + 1e-13), s * 0.999, s * 1.001]);
    }
    let mut checked = 0;
    for &speed in &speeds {
        for a in 0..720 {
            let th = a as f64 * (std::f64::consts::TAU / 720.0) + 1e-3;
            let (u, v) = (speed * th.cos(), speed * th.sin());
            for (u, v) in [(u, v), (speed, 0.0), (0.0, -speed)] {
                let snap = Snapshot {
                    x: 10.0,
                    y: 10.0,
                    u,
                    v,
                    brightness: 1.0,
                    id: 0,
                };
                assert!(
                    std::ptr::eq(model.streak_nodes_of(&snap), want(u, v).as_slice()),
                    "({u:e}, {v:e})"
                );
                checked += 1;
            }
        }
    }
    assert!(checked > 100_000);
}

fn small_sensor() -> Sensor {
    Sensor {
        width: 80,
        height: 60,
        roi: Some(Roi {
            x: 4,
            y: 3,
            width: 70,
            height: 50,
        }),
    }
}

#[ebptv_macros::unit_test]
fn fast_pixel_signals_match_exact_model() {
    // The fast path (tabulated f32 fractions, merged streaks, ring)
    // against the exact model (erf at every edge, f64 sums): every
    // pixel's summed signal within 1e-5 relative, the same pixels.
    for (streaks, diameter) in [
        (None, 1.3),
        (Some(1.0), 1.5),
        (Some(30.0), 2.5),
        (Some(1.0), 12.0),
        (Some(1.0), 0.3),
    ] {
        let mut sc = Scenario::default();
        sc.sensor = small_sensor();
        sc.optics.particle_diameter_px = diameter;
        sc.light.sawtooth_depth = 0.15;
        sc.light.pulse_streaks = streaks.map(|scale| PulseStreaks { scale });
        let model = PixelModel::new(&sc, 4);
        let snaps = scene(600, 80.0, 60.0, 2);
        let fast = model.pixel_signals(&snaps);
        let exact = model.pixel_signals_reference(&snaps);
        // A merged streak's profile may include a gap pixel no position
        // covers (added as 0): not a pixel of the model.
        let fast: Vec<(u32, f32)> = fast.into_iter().filter(|p| p.1 != 0.0).collect();
        assert_eq!(fast.len(), exact.len(), "{streaks:?} {diameter}");
        let mut worst = 0.0f64;
        for (f, e) in fast.iter().zip(&exact) {
            assert_eq!(f.0, e.0);
            worst = worst.max((f.1 as f64 - e.1).abs() / e.1);
        }
        assert!(
            worst < 1e-5,
            "{streaks:?} {diameter}: relative error {worst:e}"
        );
        // Per particle too (no overlap to hide a wrong pixel).
        for s in snaps.iter().take(100) {
            let mut f: Vec<(u32, u32, f64)> = Vec::new();
            model.particle_contributions_fast(s, |x, y, v| f.push((y, x, v)));
            let mut e: Vec<(u32, u32, f64)> = Vec::new();
            model.particle_contributions(s, |x, y, v| e.push((y, x, v)));
            let sum = |v: &mut Vec<(u32, u32, f64)>| {
                v.sort_by_key(|a| (a.0, a.1));
                let mut out: Vec<(u32, u32, f64)> = Vec::new();
                for &(y, x, s) in v.iter() {
                    match out.last_mut() {
                        Some(l) if (l.0, l.1) == (y, x) => l.2 += s,
                        _ => out.push((y, x, s)),
                    }
                }
                out.retain(|p| p.2 != 0.0);
                out
            };
            let (f, e) = (sum(&mut f), sum(&mut e));
            assert_eq!(f.len(), e.len(), "{s:?}");
            for (a, b) in f.iter().zip(&e) {
                assert_eq!((a.0, a.1), (b.0, b.1));
                assert!((a.2 - b.2).abs() <= 1e-5 * b.2, "{s:?}: {a:?} vs {b:?}");
            }
        }
        assert_eq!(
            model.render_order(&snaps, false),
            model.render_order(&snaps, true)
        );
    }
    assert_eq!(ceil_count(f64::NAN, 32), 1);
    assert_eq!(ceil_count(-3.0, 32), 1);
    assert_eq!(ceil_count(f64::INFINITY, 32), 32);
    for i in 0..20_000 {
        let x = i as f64 * 0.0017;
        assert_eq!(ceil_count(x, 32), (x.ceil() as usize).clamp(1, 32), "{x}");
    }
}

/// A plain [`ContributionSink`]: a dense ROI-sized buffer, only the
/// covered pixels of each run or window added to.
struct DenseSink<'a> {
    sig: &'a mut [f32],
    roi: Roi,
    row: usize,
}

impl ContributionSink for DenseSink<'_> {
    fn row(&mut self, iy: u32) {
        self.row = (iy - self.roi.y) as usize;
    }
    fn add_run(&mut self, ix0: u32, fractions: &[f32], scale: f32) {
        for (a, &f) in fractions.iter().enumerate() {
            let x = (ix0 - self.roi.x) as usize + a;
            self.sig[self.row * self.roi.width as usize + x] += scale * f;
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
        for x in x0..x0 + n as i64 {
            let at = self.row * self.roi.width as usize + (x - self.roi.x as i64) as usize;
            self.sig[at] += scale * window[(x - wx) as usize];
        }
    }
}

#[ebptv_macros::unit_test]
fn drained_hits_match_dense_sums() {
    // The drain (boxes, eight-pixel groups, branch-free hit writes,
    // each box clearing only its own columns) against a dense ROI
    // buffer given the same additions in the same order (particles in
    // render order through `particle_rows`, which the lean paths
    // match bit for bit): every pixel at or above the floor exactly
    // once, with the same f32 sum; and the ring all-zero after each
    // pulse (pulses in a row on one thread: a leftover would also
    // show in a later pulse's sums).
    for (streaks, diameter) in [
        (None, 1.3),
        (Some(1.0), 1.5),
        (Some(3.0), 1.0),
        (Some(30.0), 2.5),
        (Some(1.0), 12.0),
        (Some(1.0), 0.3),
    ] {
        let mut sc = Scenario::default();
        sc.sensor = small_sensor();
        sc.optics.particle_diameter_px = diameter;
        sc.light.pulse_streaks = streaks.map(|scale| PulseStreaks { scale });
        let model = PixelModel::new(&sc, 4);
        let roi = model.roi;
        let w = roi.width;
        for seed in 0..4 {
            // Dense scenes (overlapping images, shared groups) and
            // sparse ones.
            let n = if seed % 2 == 0 { 900 } else { 40 };
            let snaps = scene(n, 80.0, 60.0, 11 + seed);
            let mut dense = vec![0.0f32; (w * roi.height) as usize];
            let mut sink = DenseSink {
                sig: &mut dense,
                roi,
                row: 0,
            };
            let mut prof = Profiles::new();
            for &(key, _, _) in &model.render_order(&snaps, false) {
                let s = &snaps[(key & 0xFFFF_FFFF) as usize];
                model.particle_rows(s, &mut prof, &mut sink);
            }
            for floor in [f32::from_bits(1), model.c_floor_f32, 0.05, 0.4] {
                let mut hits = Vec::new();
                model.render_signals(&snaps, floor, &mut hits);
                let mut got: Vec<(u32, u32)> = hits
                    .iter()
                    .map(|h| {
                        let (r, c) = h.row_col();
                        assert!(r < roi.height && c < w, "{r} {c}");
                        (r * w + c, h.v.to_bits())
                    })
                    .collect();
                got.sort_unstable();
                let want: Vec<(u32, u32)> = dense
                    .iter()
                    .enumerate()
                    .filter(|(_, &v)| v >= floor)
                    .map(|(i, v)| (i as u32, v.to_bits()))
                    .collect();
                assert!(
                    got == want,
                    "{streaks:?} {diameter} seed {seed} floor {floor}: {} hits vs {}",
                    got.len(),
                    want.len()
                );
                RENDER_RING.with(|cell| {
                    let ring = cell.borrow();
                    assert!(ring.sig.iter().all(|&v| v.to_bits() == 0));
                    assert!(ring.boxes.iter().all(|b| b.is_empty()));
                });
            }
        }
    }
}

#[ebptv_macros::unit_test]
fn response_passes_match_respond() {
    // `render_pulse`'s two passes (branch-free threshold pass, then
    // the crossings) against `respond::<false>` (the same fast
    // arithmetic in one plain function) for each pixel the renderer
    // hands over: the same events, bit for bit, for every combination
    // of the switches the passes are specialised on.
    let mut sc = Scenario::default();
    sc.sensor = small_sensor();
    sc.light.pulse_streaks = Some(PulseStreaks { scale: 1.0 });
    for (mismatch, off, jitter, latency) in [
        (false, false, false, false),
        (true, false, false, false),
        (false, true, false, true),
        (true, true, true, true),
        (true, false, true, false),
        (false, true, true, false),
    ] {
        sc.pixel.threshold_mismatch = mismatch.then_some(ThresholdMismatch { sigma: 0.3 });
        sc.pixel.off_events = off.then_some(OffEvents {
            threshold: 0.3,
            tau_us: 15.0,
        });
        sc.pixel.latency_jitter = jitter.then_some(LatencyJitter { spread_us: 2.0 });
        sc.pixel.intensity_latency = latency.then_some(IntensityLatency {
            exponent: 0.5,
            reference: 2.0,
        });
        let model = PixelModel::new(&sc, 4);
        let mut total = 0;
        for pulse in 0..3 {
            let snaps = scene(900, 80.0, 60.0, 5 + pulse);
            let seed = stream_seed(9, 6, pulse);
            let mut fast: Vec<Arrival> = Vec::new();
            model.render_pulse(&snaps, 100.0, seed, &mut fast);
            let mut hits = Vec::new();
            model.render_signals(&snaps, model.c_floor_f32, &mut hits);
            let mut plain: Vec<Arrival> = Vec::new();
            for h in &hits {
                let (r, c) = h.row_col();
                let (x, y) = ((model.roi.x + c) as u16, (model.roi.y + r) as u16);
                let idx = r * model.roi.width + c;
                model.respond::<false>(idx, x, y, h.v as f64, 100.0, seed, &mut plain);
            }
            assert!(!plain.is_empty());
            assert!(
                fast == plain,
                "{mismatch} {off} {jitter} {latency} pulse {pulse}: {} vs {}",
                fast.len(),
                plain.len()
            );
            total += plain.len();
        }
        assert!(total > 1000, "{total}");
    }
}

#[ebptv_macros::unit_test]
fn fast_events_match_exact_model() {
    // Same pixels in the same order: every pixel's events agree
    // (count, and times within 1e-5 of the delay) except where a
    // signal sits within f32 rounding of a threshold crossing. The
    // jitter draws are keyed by (pulse, pixel, polarity),
    // so this holds with jitter on as well (with a sequential stream
    // a mismatched pixel shifted every later pixel's draws).
    let mut sc = Scenario::default();
    sc.sensor = Sensor {
        width: 400,
        height: 300,
        roi: Some(Roi {
            x: 3,
            y: 5,
            width: 390,
            height: 290,
        }),
    };
    sc.pixel.threshold_mismatch = Some(ThresholdMismatch { sigma: 0.15 });
    sc.pixel.intensity_latency = Some(IntensityLatency {
        exponent: 0.7,
        reference: 2.0,
    });
    sc.pixel.off_events = Some(OffEvents {
        threshold: 0.3,
        tau_us: 15.0,
    });
    sc.light.pulse_streaks = Some(PulseStreaks { scale: 1.0 });
    let compare = |sc: &Scenario, pulses: u64| {
        let model = PixelModel::new(sc, 4);
        let (mut fast, mut exact) = (Vec::new(), Vec::new());
        for pulse in 0..pulses {
            let snaps = scene(6000, 400.0, 300.0, 1 + 9 * pulse);
            let seed = stream_seed(9, 6, pulse);
            let (f0, e0) = (fast.len(), exact.len());
            model.render_pulse(&snaps, 100.0, seed, &mut fast);
            model.render_pulse_reference(&snaps, 100.0, seed, &mut exact);
            // The fast path hands pixels over in the order their
            // images finish: per pulse into pixel order (stable, so
            // a pixel's events keep theirs).
            let by_pixel = |a: &Arrival| (a.y, a.x, a.p);
            fast[f0..].sort_by_key(by_pixel);
            exact[e0..].sort_by_key(by_pixel);
        }
        assert!(exact.len() > 5000 * pulses as usize, "{}", exact.len());
        let key = |a: &Arrival| (a.y, a.x, a.p);
        let mut mismatched = 0;
        let (mut i, mut j) = (0, 0);
        while i < fast.len() && j < exact.len() {
            // Events of one pixel and polarity are consecutive in both.
            let k = key(&fast[i]).min(key(&exact[j]));
            let fi = fast[i..].iter().take_while(|a| key(a) == k).count();
            let ej = exact[j..].iter().take_while(|a| key(a) == k).count();
            if fi == ej {
                for (a, b) in fast[i..i + fi].iter().zip(&exact[j..j + ej]) {
                    // (f32 signals: ~1e-7, amplified up to ~20× near the
                    // last crossing of a pixel, where ln(1 − 0.95·kC/ΔL)
                    // is steep.)
                    assert!(
                        (a.t - b.t).abs() < 1e-5 * (b.t - 100.0) + 1e-6,
                        "{a:?} vs {b:?}"
                    );
                }
            } else {
                mismatched += 1;
            }
            i += fi;
            j += ej;
        }
        assert!(i == fast.len() && j == exact.len());
        assert!(
            mismatched * 2000 <= exact.len(),
            "{mismatched} of {}",
            exact.len()
        );
        let d = fast.len().abs_diff(exact.len());
        assert!(d * 1000 <= exact.len(), "{} vs {}", fast.len(), exact.len());
        assert!(fast
            .iter()
            .all(|a| (3..393).contains(&a.x) && (5..295).contains(&a.y)));
        fast
    };
    let plain = compare(&sc, 1);
    // All effects: the jitter moves times, not which pixels fire.
    sc.pixel.latency_jitter = Some(LatencyJitter { spread_us: 2.0 });
    let jittered = compare(&sc, 3);
    assert!(jittered.len() > 2 * plain.len());
    let moved = jittered[..plain.len()]
        .iter()
        .zip(&plain)
        .filter(|(a, b)| a.t != b.t)
        .count();
    assert!(moved * 10 > plain.len() * 9, "jitter moved {moved}");
    // One delay per visit: the events of a pixel and polarity at a pulse
    // move together (their spacing stays the photoreceptor's), and the
    // visits' delays have the jitter's spread.
    let key = |a: &Arrival| (a.y, a.x, a.p);
    let (mut shifts, mut multi, mut i) = (Vec::new(), 0, 0);
    while i < plain.len() {
        let n = plain[i..]
            .iter()
            .take_while(|a| key(a) == key(&plain[i]))
            .count();
        let d = jittered[i].t - plain[i].t;
        for k in i..i + n {
            assert_eq!(key(&jittered[k]), key(&plain[k]));
            assert!((jittered[k].t - plain[k].t - d).abs() < 1e-9, "{k}");
        }
        multi += (n > 1) as usize;
        shifts.push(d);
        i += n;
    }
    assert!(multi * 10 > shifts.len(), "{multi} of {}", shifts.len());
    let m = shifts.iter().sum::<f64>() / shifts.len() as f64;
    let sd = (shifts.iter().map(|d| (d - m).powi(2)).sum::<f64>() / shifts.len() as f64).sqrt();
    assert!(m.abs() < 0.1 && (sd - 2.0).abs() < 0.1, "{m} {sd}");
}

#[ebptv_macros::unit_test]
fn lean_images_match_particle_rows() {
    // The lean renderer writes the ring bit for bit as
    // `particle_rows` does through its sink, with the same box, for
    // every particle it takes (and takes most of them).
    for (streaks, diameter) in [
        (Some(1.0), 1.5),
        (None, 1.3),
        (Some(3.0), 1.0),
        (Some(1.0), 0.3),
        (Some(8.0), 1.99),
    ] {
        let mut sc = Scenario::default();
        sc.sensor = small_sensor();
        sc.optics.particle_diameter_px = diameter;
        sc.light.sawtooth_depth = 0.15;
        sc.light.pulse_streaks = streaks.map(|scale| PulseStreaks { scale });
        let model = PixelModel::new(&sc, 4);
        let q = model.quad.as_ref().expect("small images");
        let rw = model.roi.width as usize;
        let stride = rw + 2 * RING_PAD;
        let rows = (model.roi.height as usize).next_power_of_two();
        let mut taken = 0;
        let snaps = scene(3000, 80.0, 60.0, 7);
        for s in &snaps {
            let mut lean = vec![0.0f32; rows * stride];
            let Some(bx) = model.particle_lean(q, s, &mut lean, rows - 1, stride) else {
                continue;
            };
            taken += 1;
            let mut plain = vec![0.0f32; rows * stride];
            let mut sink = RingRows {
                sig: &mut plain,
                mask: rows - 1,
                stride,
                roi_x: model.roi.x,
                roi_y: model.roi.y,
                sig_at: 0,
                row: 0,
                bx: ImageBox::EMPTY,
            };
            model.particle_rows(s, &mut Profiles::new(), &mut sink);
            let want = sink.bx;
            assert_eq!(
                (bx.col0, bx.col1, bx.row0, bx.row1),
                (want.col0, want.col1, want.row0, want.row1),
                "{s:?}"
            );
            for (a, b) in lean.iter().zip(&plain) {
                assert_eq!(a.to_bits(), b.to_bits(), "{s:?}");
            }
        }
        // (Half of the scene's particles move with v ≠ 0 and u ≠ 0,
        // some sit at the ROI's edge or streak over more than
        // LEAN_NODES positions: not lean. Enough to exercise it.)
        assert!(taken * 8 > snaps.len(), "{streaks:?} {diameter}: {taken}");
    }
}

/// The lean diagonal-streak kernel (`particle_lean_diagonal`)
/// against `particle_rows` through its sink: diagonal streaks of
/// every direction, 2 ..= LEAN_NODES positions (and longer ones,
/// which it must decline), centres all over the sub-pixel range and
/// along the ROI's edges, added onto a ring that already holds sums
/// (so the order of the additions counts): the same ring bit for bit
/// and the same box.
#[ebptv_macros::unit_test]
fn diagonal_streaks_match_particle_rows() {
    for (scale, diameter) in [(1.0, 1.5), (1.0, 1.3), (2.5, 1.0), (1.0, 0.3), (4.0, 1.99)] {
        let mut sc = Scenario::default();
        sc.sensor = small_sensor();
        sc.optics.particle_diameter_px = diameter;
        sc.light.sawtooth_depth = 0.15;
        sc.light.pulse_streaks = Some(PulseStreaks { scale });
        let model = PixelModel::new(&sc, 4);
        let q = model.quad.as_ref().expect("small images");
        let rw = model.roi.width as usize;
        let stride = rw + 2 * RING_PAD;
        let rows = (model.roi.height as usize).next_power_of_two();
        // Speed of a streak of `k` positions (node count ⌈q⌉ = k).
        let per_speed = model.shape.end_us * 1e-6 * scale / 0.2;
        let (rx0, ry0) = (model.roi.x as f64, model.roi.y as f64);
        let (rx1, ry1) = (
            rx0 + model.roi.width as f64 - 1.0,
            ry0 + model.roi.height as f64 - 1.0,
        );
        let mut rng = Pcg64::seed_from_u64(diameter.to_bits() ^ scale.to_bits());
        let mut base = vec![0.0f32; rows * stride];
        for (i, v) in base.iter_mut().enumerate() {
            let col = i % stride;
            if (RING_PAD..RING_PAD + rw).contains(&col) {
                *v = rng.gen_range(0.0..2.0);
            }
        }
        let (mut taken, mut interior, mut interior_taken, mut long_taken) = (0, 0, 0, 0);
        for n in 0..6000 {
            let k = 2 + n % (LEAN_NODES + 2);
            let q_count = k as f64 - rng.gen_range(0.0..1.0);
            let speed = q_count / per_speed;
            let th = rng.gen_range(0.0..std::f64::consts::TAU);
            let (u, v) = (speed * th.cos(), speed * th.sin());
            // Interior, or hugging one of the ROI's edges.
            let (x, y) = match n % 5 {
                0 => (rx0 + rng.gen_range(-1.5..2.5), rng.gen_range(ry0..ry1)),
                1 => (rx1 + rng.gen_range(-2.5..1.5), rng.gen_range(ry0..ry1)),
                2 => (rng.gen_range(rx0..rx1), ry0 + rng.gen_range(-1.5..2.5)),
                3 => (rng.gen_range(rx0..rx1), ry1 + rng.gen_range(-2.5..1.5)),
                _ => (
                    rng.gen_range(rx0 + 3.0..rx1 - 3.0),
                    rng.gen_range(ry0 + 3.0..ry1 - 3.0),
                ),
            };
            let s = Snapshot {
                x,
                y,
                u,
                v,
                brightness: rng.gen_range(0.2..3.0),
                id: n as u64,
            };
            if u == 0.0 || v == 0.0 {
                continue;
            }
            let inside = n % 5 == 4 && k <= LEAN_NODES;
            interior += inside as usize;
            let mut lean = base.clone();
            let Some(bx) = model.particle_lean(q, &s, &mut lean, rows - 1, stride) else {
                continue;
            };
            taken += 1;
            interior_taken += inside as usize;
            let m = model.streak_nodes_of(&s).len();
            assert!((2..=LEAN_NODES).contains(&m), "{s:?}: {m} positions");
            long_taken += (m == LEAN_NODES) as usize;
            let mut plain = base.clone();
            let mut sink = RingRows {
                sig: &mut plain,
                mask: rows - 1,
                stride,
                roi_x: model.roi.x,
                roi_y: model.roi.y,
                sig_at: 0,
                row: 0,
                bx: ImageBox::EMPTY,
            };
            model.particle_rows(&s, &mut Profiles::new(), &mut sink);
            let want = sink.bx;
            assert_eq!(
                (bx.col0, bx.col1, bx.row0, bx.row1),
                (want.col0, want.col1, want.row0, want.row1),
                "{s:?}"
            );
            for (i, (a, b)) in lean.iter().zip(&plain).enumerate() {
                assert_eq!(a.to_bits(), b.to_bits(), "{s:?} at {i}");
            }
            assert!(lean != base, "{s:?}: nothing written");
        }
        // Most interior streaks with up to LEAN_NODES positions are
        // taken (not those in an ambiguous interval); some at the
        // edges too.
        assert!(
            interior_taken * 10 > interior * 8,
            "{scale} {diameter}: {interior_taken} of {interior}"
        );
        assert!(
            taken > interior_taken && long_taken > 0,
            "{scale} {diameter}"
        );
    }
}

#[ebptv_macros::unit_test]
fn quad_path_matches_general_fast_path_exactly() {
    // The four-pixel windows give the general table's numbers bit for
    // bit (0 outside the image's pixels) ...
    for diameter in [0.3, 1.0, 1.3, 1.5, 1.99] {
        let sigma = diameter / 4.0;
        let table = FractionTable::new(sigma);
        let q = QuadTable::new(&table).expect("σ < ½");
        let mut rng = Pcg64::seed_from_u64(21);
        for _ in 0..20_000 {
            let c: f64 = rng.gen_range(-3.0..50.0);
            let (lo, hi) = (round_i64(c - 3.0 * sigma), round_i64(c + 3.0 * sigma));
            let n = (hi - lo + 1) as usize;
            let mut want = vec![0.0f32; n];
            table.eval(c, lo, &mut want);
            let (w, v) = q.eval_masked(c, lo, n).expect("the image fits the window");
            for (a, &f) in v.iter().enumerate() {
                let px = w + a as i64;
                if (lo..=hi).contains(&px) {
                    assert_eq!(f.to_bits(), want[(px - lo) as usize].to_bits(), "{c}");
                } else {
                    assert_eq!(f, 0.0);
                }
            }
        }
    }
    assert!(QuadTable::new(&FractionTable::new(0.5)).is_none());
    // ... so whole pulses (single images, merged streaks, general and
    // too-long streaks that fall back, ROI edges) give the same
    // per-pixel signals as the general fast path, bit for bit.
    for (streaks, diameter) in [
        (None, 1.3),
        (Some(1.0), 1.5),
        (Some(30.0), 1.5),
        (Some(1.0), 0.3),
        (Some(3.0), 1.99),
    ] {
        let mut sc = Scenario::default();
        sc.sensor = small_sensor();
        sc.optics.particle_diameter_px = diameter;
        sc.light.pulse_streaks = streaks.map(|scale| PulseStreaks { scale });
        let model = PixelModel::new(&sc, 4);
        assert!(model.quad.is_some());
        let mut general = PixelModel::new(&sc, 4);
        general.quad = None;
        let snaps = scene(600, 80.0, 60.0, 3);
        let (a, b) = (model.pixel_signals(&snaps), general.pixel_signals(&snaps));
        assert_eq!(a.len(), b.len(), "{streaks:?} {diameter}");
        for (x, y) in a.iter().zip(&b) {
            assert_eq!((x.0, x.1.to_bits()), (y.0, y.1.to_bits()));
        }
    }
}

/// `QuadTable::eval_axis` (lanes from the interval table) against
/// `axis_range` + `eval_masked` (the two extra roundings): the same
/// window, fractions (bit for bit), first pixel and count, for centres
/// all over the sub-pixel range, at and next to every table node and
/// rounding boundary of c ± 3σ, and at the ROI's edges.
#[ebptv_macros::unit_test]
fn quad_axis_lanes_match_axis_range() {
    for diameter in [0.6, 1.0, 1.3, 1.5, 1.9] {
        let mut sc = Scenario::default();
        sc.sensor = small_sensor();
        sc.optics.particle_diameter_px = diameter;
        let model = PixelModel::new(&sc, 1);
        let q = model.quad.as_ref().expect("small images");
        let reach = 3.0 * model.sigma_img;
        let amb = q
            .lanes
            .iter()
            .filter(|&&l| l == QuadTable::AMBIGUOUS)
            .count();
        assert!(
            amb * 10 <= q.lanes.len(),
            "{amb} of {} ambiguous",
            q.lanes.len()
        );
        let mut centres = Vec::new();
        let mut rng = Pcg64::seed_from_u64(diameter.to_bits());
        for _ in 0..20_000 {
            centres.push(rng.gen_range(-3.0..70.0));
        }
        for base in [0.0f64, 1.0, 17.0, 30.0, 62.0, 63.0, 1000.0] {
            for i in 0..=q.steps {
                let d = -0.5 + i as f64 / q.steps as f64;
                for e in [-1e-12, 0.0, 1e-12] {
                    centres.push(base + d + e);
                }
            }
            for k in [-2.0f64, -1.0, 0.0, 1.0, 2.0] {
                for sign in [-1.0, 1.0] {
                    let c = base + k + 0.5 + sign * reach;
                    for e in [-1e-9, -1e-13, 0.0, 1e-13, 1e-9] {
                        centres.push(c + e);
                    }
                }
            }
        }
        let (r0, r1) = (0i64, 63i64);
        for &c in &centres {
            let got = q.eval_axis(&model, c, r0, r1, X_CAP);
            let (lo, n) = model.axis_range(c, r0, r1, X_CAP);
            match (got, n) {
                (QuadAxis::Empty, 0) => {}
                (QuadAxis::Window(w, v, glo, gn), _) => {
                    let (ew, ev) = q.eval_masked(c, lo, n).expect("fits");
                    assert_eq!((w, glo, gn), (ew, lo, n), "c = {c}");
                    let bits = |a: [f32; 4]| a.map(f32::to_bits);
                    assert_eq!(bits(v), bits(ev), "c = {c}");
                }
                (QuadAxis::NoFit, _) => assert!(n > 0 && q.eval_masked(c, lo, n).is_none()),
                (QuadAxis::Empty, _) => panic!("c = {c}: empty, expected {n} pixels"),
            }
        }
    }
}

/// The screened bisection of the quantile table gives the plain
/// bisection's numbers, bit for bit, at every node.
#[ebptv_macros::unit_test]
fn normal_quantiles_screening_is_exact() {
    let table = normal_quantiles();
    for i in 0..=4096 {
        let plain = normal_quantile_bisection(i, false);
        assert_eq!(table[i].to_bits(), plain.to_bits(), "node {i}");
    }
}

#[ebptv_macros::unit_test]
fn fraction_table_matches_erf() {
    for sigma in [0.025, 0.1, 0.325, 0.375, 1.0, 5.0] {
        let t = FractionTable::new(sigma);
        let k = std::f64::consts::FRAC_1_SQRT_2 / sigma;
        let mut rng = Pcg64::seed_from_u64(3);
        let mut worst = 0.0f64;
        for _ in 0..5000 {
            let c: f64 = rng.gen_range(-3.0..50.0);
            let reach = 3.0 * sigma;
            let (lo, hi) = (round_i64(c - reach), round_i64(c + reach));
            let n = (hi - lo + 1) as usize;
            let mut out = vec![0.0f32; n];
            t.eval(c, lo, &mut out);
            for (a, &f) in out.iter().enumerate() {
                let i = (lo + a as i64) as f64;
                let e = 0.5 * (erf_exact((i + 0.5 - c) * k) - erf_exact((i - 0.5 - c) * k));
                worst = worst.max((f as f64 - e).abs() / e);
            }
        }
        assert!(worst < 1e-5, "sigma {sigma}: {worst:e}");
    }
}

#[ebptv_macros::unit_test]
fn ln_table_matches_libm() {
    let mut rng = Pcg64::seed_from_u64(5);
    for _ in 0..200_000 {
        let x: f64 = 10f64.powf(rng.gen_range(-3.0..3.0));
        let (f, e) = (ln_fast(x), x.ln());
        assert!((f - e).abs() <= 2e-15 * e.abs().max(1.0), "{x}: {f} vs {e}");
    }
    for x in [1.0, 2.0, 0.5, 1.0 - 1e-9, 1.0 + 1e-9, 0.05, 0.9999] {
        assert!((ln_fast(x) - x.ln()).abs() <= 2e-15, "{x}");
    }
}

#[ebptv_macros::unit_test]
fn erf_table_is_accurate_and_round_matches() {
    let t = erf_table();
    // Known values (Abramowitz & Stegun, table 7.1).
    for (x, e) in [
        (0.5, 0.520_499_877_813_046_5),
        (1.0, 0.842_700_792_949_714_9),
        (2.0, 0.995_322_265_018_952_7),
        (3.0, 0.999_977_909_503_001_4),
    ] {
        assert!((erf_series(x) - e).abs() < 1e-14, "series {x}");
        assert!((t.eval(x) - e).abs() < 1e-9, "table {x}");
        assert!((t.eval(-x) + e).abs() < 1e-9, "table {}", -x);
    }
    let mut worst = 0.0f64;
    let mut worst_as = 0.0f64;
    for i in 0..70_000 {
        let x = i as f64 * 1e-4 + 0.5e-4;
        worst = worst.max((t.eval(x) - erf_series(x)).abs());
        worst_as = worst_as.max((erf(x) - erf_series(x)).abs());
    }
    assert!(worst < 1e-9, "table error {worst:e}");
    // The table is far closer than the rational approximation it replaces.
    assert!(worst < worst_as / 50.0, "{worst:e} vs {worst_as:e}");
    assert_eq!(t.eval(0.0), 0.0);
    assert_eq!(t.eval(9.0), 1.0);
    assert_eq!(t.eval(-9.0), -1.0);
    for i in -40_000i64..40_000 {
        let v = i as f64 * 0.000_25 + [0.0, 1e-12, -1e-12][(i % 3).unsigned_abs() as usize];
        assert_eq!(round_i64(v), v.round() as i64, "{v}");
    }
    // Around ±2^52 (where the fraction test stops mattering), NaN.
    let big = 4_503_599_627_370_496.0f64; // 2^52
    for v in [
        big - 0.5,
        big - 1.5,
        big,
        big + 2.0,
        -big + 0.5,
        -big,
        -big - 2.0,
        1e17,
        -1e17,
    ] {
        assert_eq!(round_i64(v), v.round() as i64, "{v}");
    }
    assert_eq!(round_i64(f64::NAN), 0);
}

#[ebptv_macros::unit_test]
fn f32_floor_test_equals_f64_test() {
    let mut rng = Pcg64::seed_from_u64(17);
    let mut xs: Vec<f64> = (0..2000).map(|_| rng.gen_range(1e-3..5.0)).collect();
    // Values exactly representable in f32, and the presets' floors.
    xs.extend([0.25, 0.125, 1.0, 0.25 * 0.05, 0.25 * (1.0 - 3.668 * 0.1)]);
    for x in xs {
        let f = f32_at_least(x);
        let near = x as f32;
        for v in [
            near.next_down().next_down(),
            near.next_down(),
            near,
            near.next_up(),
            near.next_up().next_up(),
            0.0,
            f32::INFINITY,
        ] {
            assert_eq!(v >= f, v as f64 >= x, "x {x:e} v {v:e}");
        }
    }
}

#[ebptv_macros::unit_test]
fn table_normal_moments_and_quantiles() {
    // Exact moments of the table distribution: bin i is uniform on
    // [q_i, q_{i+1}] with mass 1/4096.
    let q = normal_quantiles();
    let (mut m1, mut m2, mut m4) = (0.0, 0.0, 0.0);
    for i in 0..4096 {
        let (a, b) = (q[i], q[i + 1]);
        let pow = |k: i32| (b.powi(k + 1) - a.powi(k + 1)) / ((k + 1) as f64 * (b - a));
        m1 += pow(1) / 4096.0;
        m2 += pow(2) / 4096.0;
        m4 += pow(4) / 4096.0;
    }
    let kurt = m4 / (m2 * m2);
    eprintln!("table normal: mean {m1:e} variance {m2:.5} kurtosis {kurt:.4}");
    assert!(m1.abs() < 1e-12, "{m1}");
    assert!((m2 - 0.99946).abs() < 1e-5, "{m2}");
    assert!((kurt - 2.9867).abs() < 1e-3, "{kurt}");
    // Distribution function: exact at the inner bin edges, and inside a
    // bin off the normal's by at most the curvature over one bin (the
    // largest in the outer bins, where the density changes fastest).
    let cdf = |g: f64| 0.5 * (1.0 + erf_series(g.abs() / std::f64::consts::SQRT_2).copysign(g));
    let mut worst: f64 = 0.0;
    for i in 1..4095 {
        assert!((cdf(q[i]) - i as f64 / 4096.0).abs() < 1e-12, "node {i}");
        let mid = 0.5 * (q[i] + q[i + 1]);
        worst = worst.max((cdf(mid) - (i as f64 + 0.5) / 4096.0).abs());
    }
    eprintln!("table normal: largest |ΔF| inside a bin {worst:e}");
    assert!(worst < 2e-5, "{worst}");
    // The bound the tails stop at.
    assert!((q[0] + 3.66833).abs() < 1e-5 && (q[4096] - 3.66833).abs() < 1e-5);
    // Keyed draws (visits of consecutive pixels at consecutive pulses,
    // both polarities, as the jitter takes them): sample moments and
    // quantiles. 2^20 draws: standard errors 1e-3 (mean), 1.4e-3
    // (variance), 2e-4 (P(|g| > 2)), 5e-5 (P(|g| > 3)).
    let mut g = Vec::with_capacity(1 << 20);
    for pulse in 0..4u64 {
        let key = stream_seed(11, 6, pulse);
        for idx in 0..(1u64 << 17) {
            for p in [ON, OFF] {
                g.push(table_normal(q, visit_draw_key(key ^ (idx << 8), p)));
            }
        }
    }
    let n = g.len() as f64;
    let mean = g.iter().sum::<f64>() / n;
    let var = g.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n;
    let beyond = |k: f64| g.iter().filter(|v| v.abs() > k).count() as f64 / n;
    eprintln!(
        "keyed draws: mean {mean:.5} var {var:.5} P(|g|>1) {:.5} P(|g|>2) {:.5} P(|g|>3) {:.6}",
        beyond(1.0),
        beyond(2.0),
        beyond(3.0)
    );
    assert!(mean.abs() < 5e-3, "{mean}");
    assert!((var - 0.99946).abs() < 7e-3, "{var}");
    assert!((beyond(1.0) - 0.31731).abs() < 2.5e-3, "{}", beyond(1.0));
    assert!((beyond(2.0) - 0.04550).abs() < 1e-3, "{}", beyond(2.0));
    assert!((beyond(3.0) - 0.00270).abs() < 2.5e-4, "{}", beyond(3.0));
    // Neighbouring crossings are uncorrelated.
    let lag: f64 = g.windows(2).map(|w| w[0] * w[1]).sum::<f64>() / n;
    assert!(lag.abs() < 5e-3, "lag-1 correlation {lag}");
}

#[ebptv_macros::unit_test]
fn mismatch_pattern_is_gaussian_fixed_and_seeded() {
    let (sigma, key) = (0.1, stream_key(7, 2));
    let f: Vec<f64> = (0..200_000u32)
        .map(|i| PixelModel::mismatch_factor(sigma, key, i))
        .collect();
    let n = f.len() as f64;
    let mean = f.iter().sum::<f64>() / n;
    let sd = (f.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n).sqrt();
    // Standard errors: 2.2e-4 (mean), 1.6e-4 (sd).
    assert!((mean - 1.0).abs() < 1e-3, "{mean}");
    assert!((sd - sigma).abs() < 1e-3, "{sd}");
    // Gaussian tails: P(|g| > 2) = 4.55 %, P(|g| > 3) = 0.27 %.
    // (Standard errors 0.05 % and 0.01 %.)
    let beyond = |k: f64| f.iter().filter(|v| (*v - 1.0).abs() > k * sigma).count() as f64 / n;
    assert!((beyond(2.0) - 0.0455).abs() < 0.002, "{}", beyond(2.0));
    assert!((beyond(3.0) - 0.0027).abs() < 0.0005, "{}", beyond(3.0));
    // Fixed per pixel, different for another seed.
    assert_eq!(PixelModel::mismatch_factor(sigma, key, 123), f[123]);
    let other = stream_key(8, 2);
    let same = (0..1000u32)
        .filter(|&i| PixelModel::mismatch_factor(sigma, other, i) == f[i as usize])
        .count();
    assert!(same < 5, "{same}");
}

#[ebptv_macros::unit_test]
fn events_per_pixel_follow_the_log_contrast() {
    // One bright particle centred on a pixel, no effects: the centre
    // pixel fires floor(ln(1 + s)/C) events, capped.
    let mut sc = Scenario::default();
    sc.sensor = Sensor {
        width: 16,
        height: 16,
        roi: None,
    };
    sc.pixel.max_events_per_pulse = 64;
    sc.light.rise_us = 0.0;
    sc.light.fall_us = 0.0;
    let model = PixelModel::new(&sc, 0);
    let snap = Snapshot {
        x: 8.0,
        y: 8.0,
        u: 0.0,
        v: 0.0,
        brightness: 4.0,
        id: 0,
    };
    let mut out = Vec::new();
    model.render_pulse(&[snap], 0.0, 0, &mut out);
    let centre = out.iter().filter(|a| a.x == 8 && a.y == 8).count();
    let k = std::f64::consts::FRAC_1_SQRT_2 / (sc.optics.particle_diameter_px / 4.0);
    let frac = erf(0.5 * k).powi(2);
    let s = sc.light.energy * 4.0 * frac;
    assert_eq!(
        centre,
        (s.ln_1p() / sc.pixel.contrast_threshold).floor() as usize
    );
    // Crossing times increase and start after the fixed latency.
    let mut t: Vec<f64> = out
        .iter()
        .filter(|a| a.x == 8 && a.y == 8)
        .map(|a| a.t)
        .collect();
    t.sort_by(f64::total_cmp);
    assert!(t[0] >= sc.pixel.latency_us);
    assert!(t.windows(2).all(|w| w[0] < w[1]));
}
