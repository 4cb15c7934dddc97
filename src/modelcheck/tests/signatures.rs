//! Model-check building blocks: distances against brute-force references and
//! known cases; signatures on hand-built event sets with known answers.

use crate::cluster::Particle;
use crate::events::{EventChunk, Geometry};
use crate::modelcheck::distance::{
    chi_square, distances, histogram_wasserstein, rank, standardise, wasserstein_1d,
};
use crate::modelcheck::signatures::{
    burst_window, compute, count_edges, BinScale, Histogram, SignatureAccumulator, SignatureConfig,
    SignatureValue,
};
use crate::pulses::{PulseSource, PulseTiming};
use crate::track::{Track, TrackPoint};
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;

// ---------------------------------------------------------------- distances

/// W1 between two empirical distributions by their quantile functions:
/// ∫₀¹ |Qa(u) − Qb(u)| du, integrating over the merged breakpoints k/na, k/nb.
fn wasserstein_reference(a: &[f64], b: &[f64]) -> f64 {
    let mut a = a.to_vec();
    let mut b = b.to_vec();
    a.sort_by(f64::total_cmp);
    b.sort_by(f64::total_cmp);
    let (na, nb) = (a.len(), b.len());
    let mut cuts: Vec<f64> = (0..=na).map(|k| k as f64 / na as f64).collect();
    cuts.extend((0..=nb).map(|k| k as f64 / nb as f64));
    cuts.sort_by(f64::total_cmp);
    cuts.dedup_by(|x, y| (*x - *y).abs() < 1e-15);
    let q = |s: &[f64], u: f64| s[((u * s.len() as f64).floor() as usize).min(s.len() - 1)];
    cuts.windows(2)
        .map(|w| {
            let mid = 0.5 * (w[0] + w[1]);
            (q(&a, mid) - q(&b, mid)).abs() * (w[1] - w[0])
        })
        .sum()
}

#[ebptv_macros::unit_test]
fn wasserstein_matches_sorted_sample_reference() {
    let mut rng = Pcg64::seed_from_u64(7);
    // Uneven bin positions, as for geometric binnings on a linear axis.
    let positions: Vec<f64> = (0..15).map(|k| (k as f64).powf(1.5) * 3.0).collect();
    for trial in 0..40 {
        let na = rng.gen_range(1..300);
        let nb = if trial % 3 == 0 {
            na
        } else {
            rng.gen_range(1..300)
        };
        let skew = rng.gen_range(0.0..1.0);
        let draw = |rng: &mut Pcg64, n: usize, bias: f64| -> Vec<usize> {
            (0..n)
                .map(|_| {
                    let u: f64 = rng.gen::<f64>().powf(1.0 + bias);
                    ((u * 15.0) as usize).min(14)
                })
                .collect()
        };
        let ia = draw(&mut rng, na, 0.0);
        let ib = draw(&mut rng, nb, skew * 3.0);
        let mut ha = vec![0.0; 15];
        let mut hb = vec![0.0; 15];
        ia.iter().for_each(|&k| ha[k] += 1.0);
        ib.iter().for_each(|&k| hb[k] += 1.0);
        let sa: Vec<f64> = ia.iter().map(|&k| positions[k]).collect();
        let sb: Vec<f64> = ib.iter().map(|&k| positions[k]).collect();
        let fast = wasserstein_1d(&positions, &ha, &hb).unwrap();
        let slow = wasserstein_reference(&sa, &sb);
        assert!(
            (fast - slow).abs() <= 1e-9 * (1.0 + slow),
            "trial {trial}: {fast} vs reference {slow}"
        );
        if na == nb {
            // Equal sizes: mean |sorted difference|.
            let mut sa = sa.clone();
            let mut sb = sb.clone();
            sa.sort_by(f64::total_cmp);
            sb.sort_by(f64::total_cmp);
            let direct = sa.iter().zip(&sb).map(|(x, y)| (x - y).abs()).sum::<f64>() / na as f64;
            assert!((fast - direct).abs() <= 1e-9 * (1.0 + direct));
        }
        let back = wasserstein_1d(&positions, &hb, &ha).unwrap();
        assert!((fast - back).abs() < 1e-12, "symmetric");
    }
}

#[ebptv_macros::unit_test]
fn wasserstein_known_cases_and_errors() {
    let pos = [0.0, 2.0, 4.0, 6.0];
    assert_eq!(
        wasserstein_1d(&pos, &[1.0, 2.0, 0.0, 1.0], &[2.0, 4.0, 0.0, 2.0]).unwrap(),
        0.0
    );
    // All mass moved by one bin of width 2.
    assert!(
        (wasserstein_1d(&pos, &[0.0, 5.0, 0.0, 0.0], &[0.0, 0.0, 3.0, 0.0]).unwrap() - 2.0).abs()
            < 1e-12
    );
    // Half the mass moved by three bins (6 units): 0.5 * 6 = 3.
    assert!(
        (wasserstein_1d(&pos, &[1.0, 0.0, 0.0, 1.0], &[0.0, 0.0, 0.0, 1.0]).unwrap() - 3.0).abs()
            < 1e-12
    );
    assert!(wasserstein_1d(&pos, &[0.0; 4], &[1.0; 4]).is_err(), "empty");
    assert!(
        wasserstein_1d(&pos, &[1.0; 3], &[1.0; 4]).is_err(),
        "length"
    );
    assert!(
        wasserstein_1d(&pos, &[-1.0, 2.0, 0.0, 0.0], &[1.0; 4]).is_err(),
        "negative"
    );
    assert!(
        wasserstein_1d(&[0.0, 0.0, 1.0, 2.0], &[1.0; 4], &[1.0; 4]).is_err(),
        "positions"
    );
    let h1 = Histogram::new(vec![0.0, 1.0, 2.0], BinScale::Linear).unwrap();
    let h2 = Histogram::new(vec![0.0, 1.0, 3.0], BinScale::Linear).unwrap();
    assert!(histogram_wasserstein(&h1, &h2).is_err(), "different bins");
}

#[ebptv_macros::unit_test]
fn chi_square_known_cases() {
    let c = chi_square(&[10.0, 0.0], &[0.0, 10.0]).unwrap();
    assert!((c.statistic - 20.0).abs() < 1e-12 && c.dof == 1);
    let c = chi_square(&[5.0, 15.0], &[15.0, 5.0]).unwrap();
    assert!((c.statistic - 10.0).abs() < 1e-12);
    // Proportional histograms with different totals agree perfectly.
    let c = chi_square(&[10.0, 20.0, 0.0, 5.0], &[20.0, 40.0, 0.0, 10.0]).unwrap();
    assert!(c.statistic.abs() < 1e-12);
    assert_eq!(c.dof, 2, "the empty bin carries no degree of freedom");
    assert!(chi_square(&[1.0], &[1.0, 2.0]).is_err());
    assert!(chi_square(&[0.0, 0.0], &[1.0, 2.0]).is_err());
    assert!(chi_square(&[f64::NAN, 0.0], &[1.0, 2.0]).is_err());
}

#[ebptv_macros::unit_test]
fn chi_square_of_two_draws_of_one_law_is_about_its_dof() {
    let mut rng = Pcg64::seed_from_u64(11);
    let probs = [0.05, 0.1, 0.2, 0.3, 0.2, 0.1, 0.05];
    let draw = |rng: &mut Pcg64, n: usize| {
        let mut h = vec![0.0; probs.len()];
        for _ in 0..n {
            let mut u: f64 = rng.gen();
            let mut k = 0;
            while k + 1 < probs.len() && u >= probs[k] {
                u -= probs[k];
                k += 1;
            }
            h[k] += 1.0;
        }
        h
    };
    let trials = 300;
    let mut mean = 0.0;
    for _ in 0..trials {
        let (a, b) = (draw(&mut rng, 2000), draw(&mut rng, 5000));
        mean += chi_square(&a, &b).unwrap().reduced() / trials as f64;
    }
    assert!((mean - 1.0).abs() < 0.12, "mean reduced chi-square {mean}");
    // A shifted law is far beyond it.
    let a = draw(&mut rng, 2000);
    let mut b = draw(&mut rng, 2000);
    b.rotate_right(1);
    assert!(chi_square(&a, &b).unwrap().reduced() > 20.0);
}

#[ebptv_macros::unit_test]
fn standardise_and_rank() {
    let s = standardise(10.0, &[1.0, 2.0, 3.0]).unwrap();
    assert!((s.replicate_mean - 2.0).abs() < 1e-12 && (s.replicate_sd - 1.0).abs() < 1e-12);
    assert!((s.z - 8.0).abs() < 1e-12);
    assert!((s.p_value - 0.25).abs() < 1e-12);
    let s = standardise(2.0, &[1.0, 2.0, 3.0]).unwrap();
    assert!(s.z.abs() < 1e-12 && (s.p_value - 0.75).abs() < 1e-12);
    assert!(standardise(1.0, &[1.0]).is_err());
    assert!(standardise(f64::NAN, &[1.0, 2.0]).is_err());
    // Zero spread: an exact match is z = 0, anything above is huge.
    assert_eq!(standardise(0.0, &[0.0, 0.0]).unwrap().z, 0.0);
    assert_eq!(standardise(0.1, &[0.0, 0.0]).unwrap().z, 1000.0, "capped");

    let obs = vec![
        ("latency".to_string(), 5.0),
        ("event_rate".to_string(), 1.05),
        ("min_iei".to_string(), 0.9),
    ];
    let reps: Vec<Vec<(String, f64)>> = [
        [1.0, 1.0, 1.0],
        [1.2, 0.9, 1.1],
        [0.8, 1.1, 0.9],
        [1.0, 1.0, 1.0],
    ]
    .iter()
    .map(|r| {
        vec![
            ("latency".to_string(), r[0]),
            ("event_rate".to_string(), r[1]),
            ("min_iei".to_string(), r[2]),
        ]
    })
    .collect();
    let t = rank(&obs, &reps, 3.0).unwrap();
    assert_eq!(t.rows[0].signature, "latency");
    assert!(t.rows[0].disagrees);
    assert!(t.rows[1..].iter().all(|r| !r.disagrees));
    assert!(t.any_disagreement());
    let md = t.to_markdown();
    assert!(md.contains("| latency |") && md.contains("**yes**"));
    assert!(
        rank(&obs, &reps[..1], 3.0).unwrap().rows.is_empty(),
        "one replicate: no judgement"
    );
    assert!(rank(&obs, &reps, -1.0).is_err());
}

// --------------------------------------------------------------- signatures

fn timing(period: f64, first: f64) -> PulseTiming {
    PulseTiming {
        period_us: period,
        first_pulse_us: first,
        window_offset_us: 0.0,
        source: PulseSource::Trigger,
        pulse_width_us: Some(5.0),
    }
}

fn chunk(events: &[(i64, u16, u16, u8)]) -> EventChunk {
    let mut c = EventChunk::default();
    for &(t, x, y, p) in events {
        c.push(t, x, y, p);
    }
    c
}

#[ebptv_macros::unit_test]
fn folded_latency_on_off_and_rate() {
    let mut cfg = SignatureConfig::new(Geometry::new(8, 8), timing(100.0, 1000.0));
    cfg.latency_bin_us = 10.0;
    // Latencies 15, 15, 95 and one event before pulse 0 (t = 985: latency 85).
    let ev = chunk(&[
        (1015, 1, 1, 1),
        (1115, 2, 2, 1),
        (1295, 3, 3, 0),
        (985, 4, 4, 1),
        (2000, 9, 9, 1),
    ]);
    let s = compute(&cfg, &ev, &[], None).unwrap();
    let lat = s.histogram("latency").unwrap();
    assert_eq!(lat.n_bins(), 10);
    assert_eq!(lat.counts[1], 2.0);
    assert_eq!(lat.counts[9], 1.0);
    assert_eq!(lat.counts[8], 1.0);
    assert_eq!(s.n_events, 4);
    assert_eq!(s.n_outside, 1, "(9, 9) is outside an 8x8 sensor");
    assert!((s.scalar("on_fraction").unwrap() - 0.75).abs() < 1e-12);
    // 4 events over 310 µs.
    assert!((s.scalar("event_rate").unwrap() - 4.0 / 310e-6).abs() < 1e-6);
}

#[ebptv_macros::unit_test]
fn shared_timestamps_and_group_sizes_are_counted_across_chunks() {
    let cfg = SignatureConfig::new(Geometry::new(16, 16), timing(100.0, 0.0));
    let mut acc = SignatureAccumulator::new(cfg).unwrap();
    // t=100: rows 5,5,5 and 7 (one group of 3, one of 1); t=101: row 5 (1);
    // t=102: row 3 twice, split over two chunks (one group of 2).
    acc.add_events(&chunk(&[
        (100, 1, 5, 1),
        (100, 2, 5, 1),
        (100, 9, 7, 1),
        (100, 3, 5, 1),
        (101, 1, 5, 1),
        (102, 4, 3, 1),
    ]));
    acc.add_events(&chunk(&[(102, 6, 3, 1)]));
    let s = acc.finish().unwrap();
    assert!((s.scalar("shared_fraction").unwrap() - 5.0 / 7.0).abs() < 1e-12);
    let g = s.histogram("group_size").unwrap();
    assert_eq!(g.edges[0], 1.0);
    assert_eq!(g.counts[0], 2.0, "two groups of one");
    assert_eq!(g.counts[1], 1.0, "one group of two");
    assert_eq!(g.counts[2], 1.0, "one group of three");
    assert_eq!(g.total(), 4.0);
}

#[ebptv_macros::unit_test]
fn streaming_in_chunks_equals_one_shot() {
    let mut rng = Pcg64::seed_from_u64(3);
    let mut all = EventChunk::default();
    let mut t = 0i64;
    for _ in 0..5000 {
        t += rng.gen_range(0..3);
        all.push(
            t,
            rng.gen_range(0..32),
            rng.gen_range(0..24),
            rng.gen_range(0..2),
        );
    }
    let cfg = SignatureConfig::new(Geometry::new(32, 24), timing(50.0, 7.0));
    let one = compute(&cfg, &all, &[], None).unwrap();
    let mut acc = SignatureAccumulator::new(cfg).unwrap();
    let mut i = 0;
    while i < all.len() {
        let n = rng.gen_range(1..400).min(all.len() - i);
        let mut c = EventChunk::default();
        for k in i..i + n {
            c.push(all.t[k], all.x[k], all.y[k], all.p[k]);
        }
        acc.add_events(&c);
        i += n;
    }
    // Debug text: profiles hold NaN in empty bins, and NaN != NaN.
    assert_eq!(format!("{:?}", acc.finish().unwrap()), format!("{one:?}"));
    assert!(one.profile("tick_events_vs_rows").is_some());
}

/// Random "particle" events: each pulse lights `per_pulse` random pixels
/// with one event each, latency ~ 20 ± 5 µs.
fn particle_events(
    rng: &mut Pcg64,
    g: Geometry,
    period: i64,
    pulses: i64,
    per_pulse: usize,
) -> Vec<(i64, u16, u16, u8)> {
    let mut ev = Vec::new();
    for k in 0..pulses {
        for _ in 0..per_pulse {
            let t = k * period + 20 + rng.gen_range(-5..=5);
            ev.push((
                t,
                rng.gen_range(0..g.width),
                rng.gen_range(0..g.height),
                1u8,
            ));
        }
    }
    ev
}

#[ebptv_macros::unit_test]
fn hot_pixels_show_in_split_half_consistency() {
    let g = Geometry::new(64, 48);
    let (period, pulses) = (100i64, 2000i64);
    let mut rng = Pcg64::seed_from_u64(5);
    let base = particle_events(&mut rng, g, period, pulses, 50);
    let mut cfg = SignatureConfig::new(g, timing(period as f64, 0.0));
    cfg.block_pulses = 20;
    let mut sorted = base.clone();
    sorted.sort();
    let clean = compute(&cfg, &chunk(&sorted), &[], None).unwrap();
    let r0 = clean.scalar("split_half_correlation").unwrap();
    assert!(r0.abs() < 0.08, "chance activity is uncorrelated: r = {r0}");

    // Five hot pixels firing at random times, ~0.3 events per pulse each.
    let hot = [(3u16, 4u16), (40, 10), (60, 47), (0, 0), (33, 33)];
    let mut with_hot = base;
    for &(x, y) in &hot {
        for k in 0..pulses {
            if rng.gen_bool(0.3) {
                with_hot.push((k * period + rng.gen_range(0..period), x, y, 1));
            }
        }
    }
    with_hot.sort();
    let hot_s = compute(&cfg, &chunk(&with_hot), &[], None).unwrap();
    let r1 = hot_s.scalar("split_half_correlation").unwrap();
    assert!(
        r1 > 0.5,
        "fixed-pattern activity correlates halves: r = {r1}"
    );

    // The min(even, odd) histogram: background pixels have ~16 events per
    // half; hot pixels ~300. Exactly the five hot pixels sit above 150.
    let tail = |h: &Histogram| -> f64 {
        h.edges
            .windows(2)
            .zip(&h.counts)
            .filter(|(e, _)| e[0] >= 150.0)
            .map(|(_, c)| c)
            .sum()
    };
    assert_eq!(tail(clean.histogram("split_half_min").unwrap()), 0.0);
    assert_eq!(tail(hot_s.histogram("split_half_min").unwrap()), 5.0);
    assert_eq!(
        hot_s.histogram("pixel_count").unwrap().total(),
        g.pixels() as f64
    );
    // And the distance machinery sees it: pixel_count and the correlation move.
    let d = distances(&clean, &hot_s).unwrap();
    let get = |n: &str| d.iter().find(|(k, _)| k == n).unwrap().1;
    assert!(get("split_half_correlation") > 0.4);
    assert!(get("pixel_count") > 0.0);
}

#[ebptv_macros::unit_test]
fn background_noise_shows_as_off_burst_rate() {
    let g = Geometry::new(32, 32);
    let (period, pulses) = (200i64, 1000i64);
    let mut rng = Pcg64::seed_from_u64(9);
    let mut ev = particle_events(&mut rng, g, period, pulses, 20);
    let mut cfg = SignatureConfig::new(g, timing(period as f64, 0.0));
    cfg.latency_bin_us = 2.0;
    // Fix the burst window from the clean data (as the workflow does from
    // the measurement): events sit at 15..=25 µs.
    let mut clean = ev.clone();
    clean.sort();
    let lat = compute(&cfg, &chunk(&clean), &[], None).unwrap();
    let w = burst_window(lat.histogram("latency").unwrap(), 0.99).unwrap();
    assert!(
        w.0 >= 12.0 && w.0 <= 16.0 && w.1 >= 24.0 && w.1 <= 28.0,
        "window {w:?}"
    );
    cfg.burst_window_us = Some(w);
    let clean_s = compute(&cfg, &chunk(&clean), &[], None).unwrap();
    assert_eq!(clean_s.scalar("off_burst_rate").unwrap(), 0.0);

    // 3000 noise events at latencies 100..180 µs (outside the window).
    for _ in 0..3000 {
        let k = rng.gen_range(0..pulses);
        ev.push((
            k * period + rng.gen_range(100..180),
            rng.gen_range(0..32),
            rng.gen_range(0..32),
            1,
        ));
    }
    ev.sort();
    let s = compute(&cfg, &chunk(&ev), &[], None).unwrap();
    let seconds = s.duration_us * 1e-6;
    let expect = 3000.0 / 1024.0 / seconds;
    let got = s.scalar("off_burst_rate").unwrap();
    assert!((got - expect).abs() < 1e-9 * expect, "{got} vs {expect}");
}

#[ebptv_macros::unit_test]
fn burst_window_wraps_around_the_period() {
    let mut h = Histogram::new(
        (0..=10).map(|k| k as f64 * 10.0).collect(),
        BinScale::Linear,
    )
    .unwrap();
    h.counts = vec![30.0, 5.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 5.0, 60.0];
    let (a, b) = burst_window(&h, 0.9).unwrap();
    // Peak bin 9 (90..100) then bin 0 (wrapping): 90 % of 100 reached.
    assert_eq!((a, b), (90.0, 110.0));
    assert!(burst_window(
        &Histogram::new(vec![0.0, 1.0], BinScale::Linear).unwrap(),
        0.9
    )
    .is_err());
}

#[ebptv_macros::unit_test]
fn min_inter_event_interval_per_pixel() {
    let cfg = SignatureConfig::new(Geometry::new(4, 4), timing(1000.0, 0.0));
    // Pixel (1,1): 0, 50, 1000 → min 50. Pixel (2,2): 10, 13 → 3. Pixel (3,3): one event.
    let ev = chunk(&[
        (0, 1, 1, 1),
        (10, 2, 2, 1),
        (13, 2, 2, 1),
        (50, 1, 1, 1),
        (1000, 1, 1, 1),
        (1001, 3, 3, 1),
    ]);
    let s = compute(&cfg, &ev, &[], None).unwrap();
    let h = s.histogram("min_iei").unwrap();
    assert_eq!(
        h.total(),
        2.0,
        "only pixels with two events have an interval"
    );
    assert_eq!(h.counts[h.bin_of(50.0).unwrap()], 1.0);
    assert_eq!(h.counts[h.bin_of(3.0).unwrap()], 1.0);
    assert_ne!(h.bin_of(50.0), h.bin_of(3.0));
}

fn particle(pulse: i64, x: f64, y: f64, n: u32, lat: f32, ex: f32, ey: f32) -> Particle {
    Particle {
        pulse,
        t_us: pulse as f64 * 100.0,
        x,
        y,
        n_events: n,
        n_pixels: n,
        extent_x: ex,
        extent_y: ey,
        first_latency_us: lat,
    }
}

#[ebptv_macros::unit_test]
fn cluster_and_track_signatures() {
    let cfg = SignatureConfig::new(Geometry::new(64, 64), timing(100.0, 0.0));
    let ev = chunk(&[(10, 1, 1, 1), (20, 2, 2, 1)]);
    let parts = vec![
        particle(0, 10.0, 10.0, 1, 30.0, 1.0, 1.0),
        particle(0, 30.0, 30.0, 1, 40.0, 1.0, 1.0),
        particle(1, 12.0, 10.2, 3, 20.0, 3.0, 1.0),
        particle(1, 50.0, 50.0, 8, 10.0, 2.0, 2.0),
    ];
    let pt = |pulse: i64, x: f64, y: f64, u: f64, v: f64| TrackPoint {
        pulse,
        t_us: pulse as f64 * 100.0,
        x,
        y,
        u,
        v,
        ax: 0.0,
        ay: 0.0,
        interpolated: false,
    };
    let tracks = vec![
        Track {
            id: 1,
            points: vec![
                pt(0, 10.0, 10.0, 3000.0, 0.0),
                pt(1, 12.0, 10.0, 3000.0, 0.0),
            ],
        },
        Track {
            id: 2,
            points: vec![pt(0, 30.5, 30.0, 0.0, 500.0)],
        },
    ];
    let s = compute(&cfg, &ev, &parts, Some(&tracks)).unwrap();
    let epc = s.histogram("events_per_cluster").unwrap();
    assert_eq!(epc.counts[0], 2.0);
    assert_eq!(epc.counts[2], 1.0);
    assert_eq!(epc.counts[7], 1.0);
    let lat = s.profile("latency_vs_brightness").unwrap();
    assert_eq!(
        lat.mean[0], 35.0,
        "mean first latency of the 1-event clusters"
    );
    assert_eq!(lat.mean[2], 20.0);
    assert!(lat.mean[1].is_nan() && lat.count[1] == 0.0);
    let el = s.profile("elongation_vs_speed").unwrap();
    // Speed 3000 px/s (bin 2000..4000): particles at pulse 0 (0 px) and pulse 1
    // (3 − 1 = 2 px along x): mean 1. Speed 500 (bin 0..2000): 0 px. The
    // 8-event particle has no track point within 2 px.
    assert_eq!(el.count[1], 2.0);
    assert_eq!(el.mean[1], 1.0);
    assert_eq!(el.count[0], 1.0);
    assert_eq!(el.mean[0], 0.0);
    let tl = s.histogram("track_length").unwrap();
    assert_eq!(tl.counts[0], 1.0);
    assert_eq!(tl.counts[1], 1.0);
    // Without particles or tracks these signatures are absent.
    let plain = compute(&cfg, &ev, &[], None).unwrap();
    assert!(plain.get("events_per_cluster").is_none() && plain.get("track_length").is_none());
    assert!(matches!(
        plain.get("latency").unwrap().value,
        SignatureValue::Histogram(_)
    ));
}

#[ebptv_macros::unit_test]
fn bad_configuration_and_empty_data_are_errors() {
    let g = Geometry::new(8, 8);
    let mut cfg = SignatureConfig::new(g, timing(0.0, 0.0));
    assert!(SignatureAccumulator::new(cfg.clone()).is_err());
    cfg.timing.period_us = 100.0;
    cfg.latency_bin_us = 200.0;
    assert!(SignatureAccumulator::new(cfg.clone()).is_err());
    cfg.latency_bin_us = 1.0;
    cfg.block_pulses = 0;
    assert!(SignatureAccumulator::new(cfg.clone()).is_err());
    cfg.block_pulses = 10;
    cfg.burst_window_us = Some((50.0, 10.0));
    assert!(SignatureAccumulator::new(cfg.clone()).is_err());
    cfg.burst_window_us = None;
    let e = compute(&cfg, &EventChunk::default(), &[], None).unwrap_err();
    assert!(e.to_string().contains("no events"), "{e}");
    assert!(Histogram::new(vec![1.0], BinScale::Index).is_err());
    assert!(Histogram::new(vec![0.0, 0.0], BinScale::Index).is_err());
    assert_eq!(&count_edges(20.0)[14..], &[14.0, 15.0, 16.0, 19.0, 23.0]);
}

#[ebptv_macros::unit_test]
fn off_burst_pixels_separate_hot_pixels_from_background() {
    let g = Geometry::new(32, 32);
    let (period, pulses) = (200i64, 400i64);
    let mut cfg = SignatureConfig::new(g, timing(period as f64, 0.0));
    cfg.latency_bin_us = 2.0;
    cfg.burst_window_us = Some((10.0, 30.0));
    // Burst events (inside the window) never count.
    let mut ev: Vec<(i64, u16, u16, u8)> =
        (0..pulses).map(|k| (k * period + 20, 5, 5, 1)).collect();
    // Three hot pixels with exactly 7, 7 and 40 off-burst events; one
    // background pixel with one.
    for (x, y, n) in [(1u16, 1u16, 7i64), (2, 9, 7), (30, 30, 40)] {
        for k in 0..n {
            ev.push((k * period + 100 + x as i64, x, y, 1));
        }
    }
    ev.push((50 * period + 150, 17, 3, 0));
    // A late visit: three events of one pixel at one pulse, one count.
    ev.extend([120, 123, 126].map(|dt| (60 * period + dt, 12, 12, 1)));
    ev.sort();
    let s = compute(&cfg, &chunk(&ev), &[], None).unwrap();
    assert!((s.scalar("off_burst_pixels").unwrap() - 5.0 / 1024.0).abs() < 1e-15);
    let h = s.histogram("off_burst_pixel_count").unwrap();
    assert_eq!(
        h.edges[0], 1.0,
        "pixels without off-burst events are left out"
    );
    assert_eq!(h.total(), 5.0);
    assert_eq!(h.counts[h.bin_of(1.0).unwrap()], 2.0);
    assert_eq!(h.counts[h.bin_of(7.0).unwrap()], 2.0);
    assert_eq!(h.counts[h.bin_of(40.0).unwrap()], 1.0);
    // `off_burst_rate` counts the events.
    let total_off = 7.0 + 7.0 + 40.0 + 1.0 + 3.0;
    let rate = s.scalar("off_burst_rate").unwrap();
    assert!((rate - total_off / 1024.0 / (s.duration_us * 1e-6)).abs() < 1e-9 * rate);
    // Without a fixed window they are not computed.
    cfg.burst_window_us = None;
    let s = compute(&cfg, &chunk(&ev), &[], None).unwrap();
    assert!(s.get("off_burst_pixels").is_none());
    assert!(s.get("off_burst_pixel_count").is_none());
}

#[ebptv_macros::unit_test]
fn tick_profile_counts_busy_ticks_only() {
    let cfg = SignatureConfig::new(Geometry::new(16, 16), timing(1000.0, 0.0));
    // Ticks 10, 11, 12, 13 are one busy period; tick 20 stands alone.
    // Inner ticks 11 (rows 1, 2: 2 rows, 3 events) and 12 (rows 4, 5, 6:
    // 3 rows, 3 events) count; the edges 10 and 13 and lone 20 do not.
    let ev = chunk(&[
        (10, 0, 1, 1),
        (11, 0, 1, 1),
        (11, 1, 1, 1),
        (11, 0, 2, 1),
        (12, 0, 4, 1),
        (12, 0, 5, 1),
        (12, 0, 6, 1),
        (13, 0, 7, 1),
        (13, 1, 7, 1),
        (20, 0, 9, 1),
        (20, 1, 9, 1),
        (20, 2, 9, 1),
        (20, 3, 9, 1),
    ]);
    let s = compute(&cfg, &ev, &[], None).unwrap();
    let p = s.profile("tick_events_vs_rows").unwrap();
    assert_eq!(p.count.iter().sum::<f64>(), 2.0);
    let k2 = p.edges.iter().position(|&e| e == 2.0).unwrap();
    let k3 = p.edges.iter().position(|&e| e == 3.0).unwrap();
    assert_eq!((p.count[k2], p.mean[k2]), (1.0, 3.0));
    assert_eq!((p.count[k3], p.mean[k3]), (1.0, 3.0));
}

#[ebptv_macros::unit_test]
fn elongation_is_extent_x_minus_extent_y() {
    let cfg = SignatureConfig::new(Geometry::new(64, 64), timing(100.0, 0.0));
    let ev = chunk(&[(10, 1, 1, 1)]);
    let parts = vec![
        particle(0, 10.0, 10.0, 4, 30.0, 3.0, 1.0),
        particle(0, 20.0, 10.0, 1, 30.0, 1.0, 1.0),
        particle(1, 30.0, 10.0, 6, 30.0, 2.0, 4.0),
        particle(1, 40.0, 10.0, 9, 30.0, 10.0, 1.0),
    ];
    let s = compute(&cfg, &ev, &parts, None).unwrap();
    let h = s.histogram("elongation").unwrap();
    // Bins centred on −6 … 6 px, the end bins open.
    assert_eq!(h.n_bins(), 13);
    assert_eq!(h.positions()[0], -6.0);
    assert_eq!(h.scale, BinScale::Linear);
    let expect = |k: usize| match k {
        8 | 6 | 4 | 12 => 1.0, // +2, 0, −2 and +9 (in the last bin)
        _ => 0.0,
    };
    for (k, &c) in h.counts.iter().enumerate() {
        assert_eq!(c, expect(k), "bin {k}");
    }
    // Streaks along x move the histogram right by the added length; a
    // brighter copy (both extents + 1) does not move it.
    let brighter: Vec<Particle> = parts
        .iter()
        .map(|p| Particle {
            extent_x: p.extent_x + 1.0,
            extent_y: p.extent_y + 1.0,
            ..*p
        })
        .collect();
    let streaked: Vec<Particle> = parts
        .iter()
        .map(|p| Particle {
            extent_x: p.extent_x + 1.0,
            ..*p
        })
        .collect();
    let d = |other: &[Particle]| {
        let o = compute(&cfg, &ev, other, None).unwrap();
        histogram_wasserstein(h, o.histogram("elongation").unwrap()).unwrap()
    };
    assert_eq!(d(&brighter), 0.0);
    // Three particles move by 1 px; the one in the open end bin cannot.
    assert!((d(&streaked) - 0.75).abs() < 1e-12, "{}", d(&streaked));
}

/// Events of `visits` (pixel, pulse, events) visits, time-ordered.
fn visit_events(visits: &[(u16, u16, i64, u32)], period: i64) -> EventChunk {
    let mut ev: Vec<(i64, u16, u16, u8)> = Vec::new();
    for &(x, y, pulse, n) in visits {
        for j in 0..n as i64 {
            ev.push((pulse * period + 10 + j, x, y, 1));
        }
    }
    ev.sort();
    chunk(&ev)
}

#[ebptv_macros::unit_test]
fn latency_vs_yield_known_case() {
    // Pulses every 100 µs from t = 0.5: folded latencies end in .5, kept
    // in quarter µs exactly. Visits (pixel, pulse, events, first event's
    // latency): two of one event (29.5, 39.5), one each of two (19.5),
    // three (11.5) and five (4.5) events; the last visit of each pixel is
    // closed at the end of the stream. Mean over all visits 20.9 µs.
    let cfg = SignatureConfig::new(Geometry::new(8, 8), timing(100.0, 0.5));
    let events = |shift: i64| {
        let mut ev = vec![
            (30, 0, 0, 1),
            (20, 1, 0, 1),
            (25, 1, 0, 1),
            (112, 0, 0, 1),
            (115, 0, 0, 0),
            (118, 0, 0, 1),
            (240, 3, 0, 1),
        ];
        ev.extend((0..5).map(|k| (205 + 3 * k, 2, 0, 1)));
        let mut ev: Vec<(i64, u16, u16, u8)> = ev
            .into_iter()
            .map(|(t, x, y, p)| (t + shift, x, y, p))
            .collect();
        ev.sort();
        chunk(&ev)
    };
    let s = compute(&cfg, &events(0), &[], None).unwrap();
    let p = s.profile("latency_vs_yield").unwrap();
    assert_eq!(p.edges, [1.0, 2.0, 3.0, 4.0, 17.0]);
    assert_eq!(p.count, [2.0, 1.0, 1.0, 1.0]);
    for (m, want) in p.mean.iter().zip([13.6, -1.4, -9.4, -16.4]) {
        assert!((m - want).abs() < 1e-12, "{:?}", p.mean);
    }
    // A later burst moves every latency alike: the profile is the same.
    let later = compute(&cfg, &events(7), &[], None).unwrap();
    assert_eq!(later.profile("latency_vs_yield").unwrap(), p);
}

#[ebptv_macros::unit_test]
fn yield_split_correlation_known_case() {
    // Blocks of one pulse: even and odd pulses are the two halves. Pixel
    // yields (even, odd): A (3, 2), B (1, 1), C (2, 3); D is visited in
    // even pulses only and left out. Means 2, 2; covariance 1/3, variances
    // 2/3: r = 1/2.
    let mut cfg = SignatureConfig::new(Geometry::new(8, 8), timing(100.0, 0.0));
    cfg.block_pulses = 1;
    let ev = visit_events(
        &[
            (0, 0, 0, 3),
            (0, 0, 1, 2),
            (1, 0, 0, 1),
            (1, 0, 1, 1),
            (2, 0, 2, 2),
            (2, 0, 3, 3),
            (3, 0, 0, 4),
            (3, 0, 2, 4),
        ],
        100,
    );
    let s = compute(&cfg, &ev, &[], None).unwrap();
    let r = s.scalar("yield_split_correlation").unwrap();
    assert!((r - 0.5).abs() < 1e-12, "{r}");
}

#[ebptv_macros::unit_test]
fn yield_split_correlation_sees_a_fixed_pattern_not_chance() {
    // Each pixel's visits give 1 + Binomial(3, p) events with its own p:
    // a fixed pattern of variance Var(3p) = 9 · 0.8² / 12 = 0.48 (p uniform
    // on (0.1, 0.9)) plus chance, 3p(1 − p) per visit, 0.59 on average,
    // 0.1475 for the mean of a half's 4 visits. Expected r = 0.48 / (0.48 +
    // 0.1475) = 0.765; with one p for all pixels r ≈ 0 (standard error
    // 1/√4096 ≈ 0.016).
    let g = Geometry::new(64, 64);
    let mut cfg = SignatureConfig::new(g, timing(100.0, 0.0));
    cfg.block_pulses = 1;
    let run = |pattern: bool, seed: u64| -> f64 {
        let mut rng = Pcg64::seed_from_u64(seed);
        let mut visits = Vec::new();
        for y in 0..64u16 {
            for x in 0..64u16 {
                let p: f64 = if pattern {
                    rng.gen_range(0.1..0.9)
                } else {
                    0.5
                };
                for pulse in 0..8i64 {
                    let n = 1 + (0..3).filter(|_| rng.gen_bool(p)).count() as u32;
                    visits.push((x, y, pulse, n));
                }
            }
        }
        let s = compute(&cfg, &visit_events(&visits, 100), &[], None).unwrap();
        s.scalar("yield_split_correlation").unwrap()
    };
    for seed in 0..3 {
        let none = run(false, seed);
        assert!(none.abs() < 0.05, "no pattern: r = {none}");
        let with = run(true, seed);
        assert!((with - 0.765).abs() < 0.03, "pattern: r = {with}");
    }
}

// ------------------------------------- fast accumulator vs its reference

/// Signatures of `events` (in `chunks` pieces), particles and tracks by the
/// fast accumulator and by the reference, as exact text (Debug prints
/// every float round-trip exactly, and NaN equal to NaN).
fn fast_and_reference(
    cfg: &SignatureConfig,
    events: &EventChunk,
    chunks: usize,
    particles: &[Particle],
    tracks: Option<&[Track]>,
) -> (String, String) {
    use crate::modelcheck::signatures::reference::ReferenceAccumulator;
    let mut fast = SignatureAccumulator::new(cfg.clone()).unwrap();
    let mut slow = ReferenceAccumulator::new(cfg.clone()).unwrap();
    let n = events.len();
    let step = n.div_ceil(chunks.max(1)).max(1);
    let mut start = 0;
    while start < n {
        let end = (start + step).min(n);
        let mut c = EventChunk::default();
        for i in start..end {
            c.push(events.t[i], events.x[i], events.y[i], events.p[i]);
        }
        fast.add_events(&c);
        slow.add_events(&c);
        start = end;
    }
    fast.add_particles(particles);
    slow.add_particles(particles);
    if let Some(t) = tracks {
        fast.add_tracks(t, particles).unwrap();
        slow.add_tracks(t, particles).unwrap();
    }
    (
        format!("{:?}", fast.finish().unwrap()),
        format!("{:?}", slow.finish().unwrap()),
    )
}

#[ebptv_macros::unit_test]
fn fast_accumulator_equals_reference_on_simulated_recordings() {
    use crate::modelcheck::scene::SceneSimulator;
    use crate::modelcheck::workflow::{EffectSetting, Simulator};
    let mut scene = crate::sim::scenario::Scenario {
        duration_s: 0.01,
        sensor: crate::sim::scenario::Sensor {
            width: 96,
            height: 64,
            roi: None,
        },
        ..Default::default()
    };
    scene.seeding.ppp = 0.01;
    scene.light.energy = crate::sim::presets::WATER_ENERGY;
    let sim = SceneSimulator::new(scene).unwrap();
    let set = |name: &str, ps: &[(&str, f64)]| EffectSetting {
        name: name.into(),
        parameters: ps.iter().map(|&(k, v)| (k.to_string(), v)).collect(),
    };
    // Every effect that moves a per-pixel or per-tick quantity: hot pixels
    // (huge counts, short intervals), background (off-burst pixels),
    // arbiter saturation (shared timestamps), OFF events, refractory,
    // threshold mismatch (yields).
    let all = vec![
        set("hot_pixels", &[("count", 12.0), ("rate_hz", 20_000.0)]),
        set("background_noise", &[("rate_hz", 50.0)]),
        set(
            "arbiter_saturation",
            &[("row_time_us", 0.05), ("event_time_us", 0.1)],
        ),
        set("off_events", &[("threshold", 0.2), ("tau_us", 30.0)]),
        set("refractory", &[("period_us", 20.0)]),
        set("threshold_mismatch", &[("sigma", 0.3)]),
    ];
    let mut compared = 0;
    for (k, effects) in [vec![], all].iter().enumerate() {
        let rec = sim.simulate(effects, 40 + k as u64).unwrap();
        assert!(rec.events.len() > 1000, "{} events", rec.events.len());
        let mut cfg = sim.signature_config();
        for window in [None, Some((3.0, 60.0)), Some((150.0, 230.0))] {
            cfg.burst_window_us = window;
            for chunks in [1, 7] {
                let (fast, slow) =
                    fast_and_reference(&cfg, &rec.events, chunks, &rec.particles, None);
                assert_eq!(fast, slow, "effects {effects:?}, window {window:?}");
                compared += 1;
            }
        }
    }
    assert_eq!(compared, 12);
}

#[ebptv_macros::unit_test]
fn fast_accumulator_equals_reference_on_odd_streams() {
    // Random events: times mostly rising with backward steps, long gaps
    // (intervals beyond the table and beyond u32 µs), negative times,
    // events outside the geometry, both polarities, clumps of equal
    // timestamps; a period that is not a whole number of µs.
    let mut rng = Pcg64::seed_from_u64(11);
    let g = Geometry::new(40, 30);
    let mut cfg = SignatureConfig::new(g, timing(199.7, -13.3));
    cfg.block_pulses = 3;
    let mut ev = EventChunk::default();
    let mut t: i64 = -5000;
    for _ in 0..60_000 {
        let r: f64 = rng.gen();
        t += if r < 0.3 {
            0
        } else if r < 0.95 {
            rng.gen_range(1..40)
        } else if r < 0.98 {
            -rng.gen_range(1..300)
        } else if r < 0.999 {
            rng.gen_range(1_000..100_000)
        } else {
            rng.gen_range(5_000_000_000i64..6_000_000_000)
        };
        let (x, y) = if rng.gen::<f64>() < 0.01 {
            (rng.gen_range(40..60), rng.gen_range(0..40))
        } else if rng.gen::<f64>() < 0.2 {
            (3, 4) // a busy pixel
        } else {
            (rng.gen_range(0..40), rng.gen_range(0..30))
        };
        ev.push(t, x, y, rng.gen_range(0..2));
    }
    let particles: Vec<Particle> = (0..300)
        .map(|k| {
            particle(
                k / 10,
                rng.gen_range(0.0..40.0),
                rng.gen_range(0.0..30.0),
                rng.gen_range(1..30),
                rng.gen_range(0.0..90.0),
                rng.gen_range(1.0..9.0),
                rng.gen_range(1.0..9.0),
            )
        })
        .collect();
    for window in [None, Some((-20.0, 40.0)), Some((120.0, 250.0))] {
        cfg.burst_window_us = window;
        for chunks in [1, 13] {
            let (fast, slow) = fast_and_reference(&cfg, &ev, chunks, &particles, Some(&[]));
            assert_eq!(fast, slow, "window {window:?}, {chunks} chunks");
        }
    }
}

#[ebptv_macros::unit_test]
fn pulses_of_equals_its_reference() {
    use crate::modelcheck::scene::{pulses_of, pulses_of_reference};
    let mut rng = Pcg64::seed_from_u64(5);
    let tm = timing(199.7, 37.3);
    // Time-ordered, with events before the first pulse, empty pulses, and
    // equal times; then a stream that steps back across a pulse (an error).
    let mut ev = EventChunk::default();
    let mut t = -300i64;
    for _ in 0..20_000 {
        t += if rng.gen::<f64>() < 0.01 {
            rng.gen_range(300..900)
        } else {
            rng.gen_range(0..3)
        };
        ev.push(
            t,
            rng.gen_range(0..50),
            rng.gen_range(0..50),
            rng.gen_range(0..2),
        );
    }
    let fast = pulses_of(&ev, &tm).unwrap();
    let slow = pulses_of_reference(&ev, &tm).unwrap();
    assert!(fast.len() > 100);
    assert_eq!(fast.len(), slow.len());
    for (a, b) in fast.iter().zip(&slow) {
        assert_eq!(
            (a.index, a.start_us.to_bits()),
            (b.index, b.start_us.to_bits())
        );
        assert_eq!(a.events, b.events);
    }
    // Before the first pulse, inside a run: skipped by both.
    let mixed = chunk(&[
        (100, 1, 1, 1),
        (-50, 2, 2, 1),
        (101, 3, 3, 1),
        (400, 4, 4, 0),
    ]);
    let (a, b) = (
        pulses_of(&mixed, &tm).unwrap(),
        pulses_of_reference(&mixed, &tm).unwrap(),
    );
    assert_eq!(a.len(), b.len());
    for (a, b) in a.iter().zip(&b) {
        assert_eq!(a.events, b.events);
    }
    let back = chunk(&[(100, 1, 1, 1), (700, 2, 2, 1), (300, 3, 3, 1)]);
    assert!(pulses_of(&back, &tm).is_err());
    assert!(pulses_of_reference(&back, &tm).is_err());
}

/// `burst_repeat_share` counts the pixels whose shortest interval is under
/// half a pulse period (add-one smoothed, log10): "some repeat" and "none
/// repeats" lie decades apart on a large sensor, a few more or fewer
/// repeats do not.
#[ebptv_macros::unit_test]
fn burst_repeat_share_tells_none_from_few() {
    use crate::modelcheck::signatures::burst_repeat_share;
    let period = 200.0;
    // 1000 pixels with an interval: 300 repeat within a burst (5 µs), the
    // rest only a period later.
    let some = (0..1000).map(|i| if i < 300 { 5.0 } else { 200.0 });
    let v = burst_repeat_share(some, period);
    assert!((v - (301.0f64 / 1001.0).log10()).abs() < 1e-12, "{v}");
    // A third as many repeat: half a decade down.
    let fewer = (0..1000).map(|i| if i < 100 { 5.0 } else { 200.0 });
    let w = burst_repeat_share(fewer, period);
    assert!((v - w - 0.477).abs() < 0.01, "{v} {w}");
    // None of 100 000 pixels repeats: five decades down, finite.
    let none = (0..100_000).map(|_| 180.0);
    let n = burst_repeat_share(none, period);
    assert!((n + 5.0).abs() < 1e-4, "{n}");
    // No pixel with an interval at all: log10(1) = 0.
    assert_eq!(burst_repeat_share(std::iter::empty(), period), 0.0);
}
