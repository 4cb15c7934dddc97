//! The k-d tree clustering must reproduce an obviously-correct O(n²)
//! reference exactly: same partition of events, same particles.

use std::collections::{BTreeMap, BTreeSet, HashMap};

use crate::cluster::{
    cluster_pulse, pixel_labels, pixel_labels_kdtree, pulse_pixels, ClusterParams, NeighbourSearch,
};
use crate::events::EventChunk;
use crate::pulses::PulseEvents;
use proptest::prelude::*;

/// Reference: every pair of selected events closer than the radius (squared
/// integer distance <= floor(r²)) is joined, by repeated relabelling.
fn brute_partition(pulse: &PulseEvents, params: &ClusterParams) -> BTreeSet<BTreeSet<usize>> {
    let ev = &pulse.events;
    let sel: Vec<usize> = (0..ev.len())
        .filter(|&i| {
            (!params.on_only || ev.p[i] == 1) && !params.hot_pixels.contains(&(ev.x[i], ev.y[i]))
        })
        .collect();
    let mut label: Vec<usize> = (0..sel.len()).collect();
    let max_d2 = (params.radius * params.radius).floor() as i64;
    loop {
        let mut changed = false;
        for a in 0..sel.len() {
            for b in 0..sel.len() {
                let (i, j) = (sel[a], sel[b]);
                let dx = ev.x[i] as i64 - ev.x[j] as i64;
                let dy = ev.y[i] as i64 - ev.y[j] as i64;
                if dx * dx + dy * dy <= max_d2 && label[b] > label[a] {
                    label[b] = label[a];
                    changed = true;
                }
            }
        }
        if !changed {
            break;
        }
    }
    let mut groups: BTreeMap<usize, BTreeSet<usize>> = BTreeMap::new();
    for (a, &l) in label.iter().enumerate() {
        groups.entry(l).or_default().insert(sel[a]);
    }
    groups.into_values().collect()
}

fn fast_partition(
    pulse: &PulseEvents,
    params: &ClusterParams,
    kdtree: bool,
) -> BTreeSet<BTreeSet<usize>> {
    let pixels = pulse_pixels(pulse, params);
    let labels = if kdtree {
        pixel_labels_kdtree(&pixels, params)
    } else {
        pixel_labels(&pixels, params)
    };
    let label_of: HashMap<(u16, u16), u32> = pixels
        .iter()
        .zip(&labels)
        .map(|(p, &l)| ((p.x, p.y), l))
        .collect();
    let ev = &pulse.events;
    let mut groups: BTreeMap<u32, BTreeSet<usize>> = BTreeMap::new();
    for i in 0..ev.len() {
        if let Some(&l) = label_of.get(&(ev.x[i], ev.y[i])) {
            if !params.on_only || ev.p[i] == 1 {
                groups.entry(l).or_default().insert(i);
            }
        }
    }
    groups.into_values().collect()
}

/// Reference particle features from a partition, sorted by position.
fn brute_particles(
    pulse: &PulseEvents,
    part: &BTreeSet<BTreeSet<usize>>,
    params: &ClusterParams,
) -> Vec<(i64, i64, u32, u32, f32, f32, f32)> {
    let ev = &pulse.events;
    let mut out = Vec::new();
    for g in part {
        let n = g.len() as u32;
        if n < params.min_events || n > params.max_events {
            continue;
        }
        let sx: f64 = g.iter().map(|&i| ev.x[i] as f64).sum();
        let sy: f64 = g.iter().map(|&i| ev.y[i] as f64).sum();
        let pix: BTreeSet<(u16, u16)> = g.iter().map(|&i| (ev.x[i], ev.y[i])).collect();
        let ex = g.iter().map(|&i| ev.x[i]).max().unwrap()
            - g.iter().map(|&i| ev.x[i]).min().unwrap()
            + 1;
        let ey = g.iter().map(|&i| ev.y[i]).max().unwrap()
            - g.iter().map(|&i| ev.y[i]).min().unwrap()
            + 1;
        let t0 = g.iter().map(|&i| ev.t[i]).min().unwrap();
        // Centroid rounded to 1e-9 px so the summation order does not matter.
        out.push((
            (sx / n as f64 * 1e9).round() as i64,
            (sy / n as f64 * 1e9).round() as i64,
            n,
            pix.len() as u32,
            ex as f32,
            ey as f32,
            (t0 as f64 - pulse.start_us) as f32,
        ));
    }
    out.sort_by(|a, b| a.partial_cmp(b).unwrap());
    out
}

fn random_pulse() -> impl Strategy<Value = PulseEvents> {
    // Small frames make dense clouds with many chained neighbours.
    (
        4u16..40,
        prop::collection::vec((0i64..300, 0u16..1000, 0u16..1000, 0u8..2), 0..250),
    )
        .prop_map(|(side, evs)| {
            let mut ev = EventChunk::default();
            for (t, x, y, p) in evs {
                ev.push(1000 + t, x % side, y % side, p);
            }
            PulseEvents {
                index: 7,
                start_us: 1000.0,
                events: ev,
            }
        })
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(300))]
    #[ebptv_macros::unit_test]
    fn kdtree_matches_brute_force(pulse in random_pulse(), r10 in 5u32..40, on_only in any::<bool>(), min_events in 1u32..3, hot in prop::collection::vec((0u16..40, 0u16..40), 0..5), kd_tree in any::<bool>()) {
        let params = ClusterParams {
            radius: r10 as f64 / 10.0,
            on_only,
            min_events,
            max_events: 12,
            hot_pixels: hot.into_iter().collect(),
            mask: None,
            split_extent: 0, // the partition oracle; splitting has its own below
            // cluster_pulse below runs either neighbour search
            neighbour_search: if kd_tree { NeighbourSearch::KdTree } else { NeighbourSearch::RowSweep },
        };
        let brute = brute_partition(&pulse, &params);
        prop_assert_eq!(&fast_partition(&pulse, &params, false), &brute);
        prop_assert_eq!(&fast_partition(&pulse, &params, true), &brute);
        let mut fast: Vec<_> = cluster_pulse(&pulse, &params).iter().map(|p| (
            (p.x * 1e9).round() as i64, (p.y * 1e9).round() as i64, p.n_events, p.n_pixels, p.extent_x, p.extent_y, p.first_latency_us,
        )).collect();
        fast.sort_by(|a, b| a.partial_cmp(b).unwrap());
        prop_assert_eq!(fast, brute_particles(&pulse, &brute, &params));
    }
}

/// Reference of `split_wide_clusters` for one component: try every
/// threshold between distinct projections on the principal axis and cost
/// each two-part division directly (weighted squared deviations about each
/// part's own mean), O(n²).
fn brute_split(pix: &[(f64, f64, f64)]) -> Option<BTreeSet<usize>> {
    // Covariances scaled by (Σw)², in exact integers.
    let m = |f: &dyn Fn(&(f64, f64, f64)) -> f64| pix.iter().map(f).sum::<f64>() as i128;
    let (sw, sx, sy) = (m(&|p| p.2), m(&|p| p.2 * p.0), m(&|p| p.2 * p.1));
    let (sxx, sxy, syy) = (
        m(&|p| p.2 * p.0 * p.0),
        m(&|p| p.2 * p.0 * p.1),
        m(&|p| p.2 * p.1 * p.1),
    );
    let (cxx, cxy, cyy) = (sw * sxx - sx * sx, sw * sxy - sx * sy, sw * syy - sy * sy);
    let th = 0.5 * (2.0 * cxy as f64).atan2((cxx - cyy) as f64);
    let (mx, my) = (sx as f64 / sw as f64, sy as f64 / sw as f64);
    let q: Vec<f64> = pix
        .iter()
        .map(|p| (p.0 - mx) * th.cos() + (p.1 - my) * th.sin())
        .collect();
    let mut cuts: Vec<f64> = q.clone();
    cuts.sort_by(|a, b| a.total_cmp(b));
    let mut best: Option<(f64, BTreeSet<usize>)> = None;
    for w in cuts.windows(2) {
        if w[1] - w[0] < 1e-9 {
            continue;
        }
        let far: BTreeSet<usize> = (0..pix.len()).filter(|&i| q[i] >= w[1]).collect();
        let part_cost = |inside: &dyn Fn(usize) -> bool| {
            let idx: Vec<usize> = (0..pix.len()).filter(|&i| inside(i)).collect();
            let w: f64 = idx.iter().map(|&i| pix[i].2).sum();
            let m = idx.iter().map(|&i| pix[i].2 * q[i]).sum::<f64>() / w;
            idx.iter()
                .map(|&i| pix[i].2 * (q[i] - m).powi(2))
                .sum::<f64>()
        };
        let cost = part_cost(&|i| far.contains(&i)) + part_cost(&|i| !far.contains(&i));
        if best.as_ref().is_none_or(|(c, _)| cost < c - 1e-9) {
            best = Some((cost, far));
        }
    }
    best.map(|b| b.1)
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(300))]
    #[ebptv_macros::unit_test]
    fn split_matches_brute_force(pulse in random_pulse(), extent in 2u32..5) {
        let params = ClusterParams { split_extent: extent, on_only: false, ..Default::default() };
        let pixels = pulse_pixels(&pulse, &params);
        let base = pixel_labels(&pixels, &params);
        let mut split = base.clone();
        crate::cluster::split_wide_clusters(&pixels, &mut split, extent);
        let n_base = base.iter().map(|&l| l + 1).max().unwrap_or(0);
        let mut by_label: BTreeMap<u32, Vec<usize>> = BTreeMap::new();
        for (i, &l) in base.iter().enumerate() {
            by_label.entry(l).or_default().push(i);
        }
        for (_, m) in by_label {
            let xs: Vec<u16> = m.iter().map(|&i| pixels[i].x).collect();
            let ys: Vec<u16> = m.iter().map(|&i| pixels[i].y).collect();
            let span = |v: &[u16]| (v.iter().max().unwrap() - v.iter().min().unwrap() + 1) as u32;
            let wide = span(&xs).max(span(&ys)) >= extent;
            let pix: Vec<(f64, f64, f64)> = m.iter().map(|&i| (pixels[i].x as f64, pixels[i].y as f64, pixels[i].count as f64)).collect();
            let want: BTreeSet<usize> = if wide && m.len() >= 2 {
                brute_split(&pix).unwrap_or_default()
            } else {
                BTreeSet::new()
            };
            // Pixels of this component that moved to a new label.
            let got: BTreeSet<usize> = (0..m.len()).filter(|&k| split[m[k]] >= n_base).collect();
            prop_assert_eq!(got, want);
            // Pixels that stayed keep their label.
            for &i in &m {
                prop_assert!(split[i] == base[i] || split[i] >= n_base);
            }
        }
    }
}
