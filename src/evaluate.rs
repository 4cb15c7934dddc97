//! Scoring ebptv's outputs against the simulator's ground truth.
//!
//! The demo, the accuracy tests and the benchmarks all need the same
//! question answered: *how close is what ebptv wrote to what really
//! happened?* This module reads the files the stages write
//! (`pulses.json`, the particles, tracks, `grid` and `piv_mean` tables in
//! any format) and the truth the simulator writes (the `truth_particles`
//! table, any format: `pulse,t_us,particle_id,x,y,u,v`), and scores
//! them. It works on files on purpose: what is scored is exactly what a
//! user gets.
//!
//! Matching rule: a detection (particle or track point) at pulse k is the
//! image of the truth particle nearest to it at pulse k when that one lies
//! within `match_radius_px` (default 1 px, below the mean spacing of the
//! particle images at paper seeding). Each truth particle is claimed by at
//! most one detection (the nearest), so merged images count once.
//!
//! Definitions (the link definition of `track::synth::score`, which scores
//! in-memory detections with event-level truth; why this file-level score
//! is more lenient on merged images of two close particles is explained in
//! `track::synth`'s docs — here a track point is its *fitted* position, so
//! a link through a merged image counts as correct when the fit still puts
//! the point on the track's own particle):
//! - detection recall = matched truth samples / truth samples;
//!   detection precision = matched detections / detections;
//! - a *link* is two consecutive points of one track; it is correct when
//!   both ends match the same truth id. Link precision = correct links /
//!   links; link recall = truth links found / truth links, where a truth
//!   link is a truth particle *present* in the truth at pulses k and k+1,
//!   whether or not it was detected — so link recall includes the
//!   detection losses (the stricter of the two usual readings; `synth`
//!   reports it as `recall_present` next to its tracker-only `recall`);
//! - velocity error: rms over matched track points and over both
//!   components of (u − u_true) · Δt, in px per pulse interval;
//! - Eulerian error: the truth samples binned exactly like the tracks (the
//!   same lattice, a top-hat bin) give a truth mean per bin; the error is
//!   the rms of (u − u_true, v − v_true) over bins with data, as a fraction
//!   of the largest true speed.

use std::collections::{HashMap, HashSet};
use std::path::Path;

use kiddo::{KdTree, SquaredEuclidean};
use serde::Serialize;

use crate::compare::{read_table, Table};
use crate::error::{Error, Result};

/// Truth samples grouped by pulse, with a k-d tree per pulse for matching.
#[ebptv_macros::testkit]
pub(crate) struct Truth {
    /// Per pulse: (particle_id, x, y, u, v).
    #[allow(clippy::type_complexity)]
    by_pulse: HashMap<i64, Vec<(u64, f64, f64, f64, f64)>>,
    trees: HashMap<i64, KdTree<f64, 2>>,
    /// Truth samples (rows of the `truth_particles` table).
    pub samples: usize,
}

impl Truth {
    /// Read the `truth_particles` table (Parquet, CSV or `.npy`).
    #[ebptv_macros::testkit]
    pub(crate) fn read(path: &Path) -> Result<Truth> {
        let t = read_table(path, &["pulse", "particle_id", "x", "y", "u", "v"])?;
        Self::from_table(&t)
    }

    fn from_table(t: &Table) -> Result<Truth> {
        let col = |n: &str| t.col(n).expect("required column checked by read_table");
        let (pulse, id, x, y, u, v) = (
            col("pulse"),
            col("particle_id"),
            col("x"),
            col("y"),
            col("u"),
            col("v"),
        );
        #[allow(clippy::type_complexity)]
        let mut by_pulse: HashMap<i64, Vec<(u64, f64, f64, f64, f64)>> = HashMap::new();
        for i in 0..t.rows() {
            by_pulse.entry(pulse[i] as i64).or_default().push((
                id[i] as u64,
                x[i],
                y[i],
                u[i],
                v[i],
            ));
        }
        let trees = by_pulse
            .iter()
            .map(|(&k, pts)| {
                let mut tree: KdTree<f64, 2> = KdTree::new();
                for (j, p) in pts.iter().enumerate() {
                    tree.add(&[p.1, p.2], j as u64);
                }
                (k, tree)
            })
            .collect();
        Ok(Truth {
            by_pulse,
            trees,
            samples: t.rows(),
        })
    }

    /// Index (within its pulse) of the truth particle nearest to (x, y) at
    /// `pulse`, if within `radius`.
    fn nearest(&self, pulse: i64, x: f64, y: f64, radius: f64) -> Option<usize> {
        let tree = self.trees.get(&pulse)?;
        let nn = tree.nearest_one::<SquaredEuclidean>(&[x, y]);
        (nn.distance <= radius * radius).then_some(nn.item as usize)
    }

    fn get(&self, pulse: i64, idx: usize) -> (u64, f64, f64, f64, f64) {
        self.by_pulse[&pulse][idx]
    }

    /// Largest true speed over all samples (px/s).
    pub(crate) fn max_speed(&self) -> f64 {
        self.by_pulse
            .values()
            .flatten()
            .map(|p| p.3.hypot(p.4))
            .fold(0.0, f64::max)
    }

    /// Truth samples in pulse order. The order matters: the field score
    /// sums floating-point errors in this order, and a `HashMap`'s order
    /// changes from one process to the next (the report then differed in
    /// its last digits between identical runs).
    fn all(&self) -> impl Iterator<Item = &(u64, f64, f64, f64, f64)> {
        let mut pulses: Vec<&i64> = self.by_pulse.keys().collect();
        pulses.sort_unstable();
        pulses.into_iter().flat_map(move |p| &self.by_pulse[p])
    }
}

/// Match detections (pulse, x, y) to truth; returns per detection the
/// (pulse, index-in-pulse) of its truth particle. A truth particle claimed
/// by several detections keeps only the nearest.
fn match_detections(
    truth: &Truth,
    det: &[(i64, f64, f64)],
    radius: f64,
) -> Vec<Option<(i64, usize)>> {
    let mut best: HashMap<(i64, usize), (usize, f64)> = HashMap::new();
    for (i, &(k, x, y)) in det.iter().enumerate() {
        if let Some(j) = truth.nearest(k, x, y, radius) {
            let t = truth.get(k, j);
            let d2 = (t.1 - x).powi(2) + (t.2 - y).powi(2);
            let e = best.entry((k, j)).or_insert((i, d2));
            if d2 < e.1 {
                *e = (i, d2);
            }
        }
    }
    let mut out = vec![None; det.len()];
    for ((k, j), (i, _)) in best {
        out[i] = Some((k, j));
    }
    out
}

/// Detection scores of a particles table (any format).
#[derive(Debug, Clone, Serialize)]
pub(crate) struct DetectionScore {
    /// Detections in the table (rows).
    pub detections: usize,
    /// Truth samples (particle images over all pulses).
    pub truth_samples: usize,
    /// Matched detections / detections.
    pub precision: f64,
    /// Matched truth samples / truth samples.
    pub recall: f64,
    /// Rms centroid error of matched detections (px, per component).
    pub position_rms_px: f64,
}

/// Score the particles table `particles_csv` (any format, columns
/// `pulse,x,y`) against `truth`, a detection matching the nearest truth
/// particle of its pulse within `radius` px. Fails when the table cannot be
/// read or lacks a column.
pub(crate) fn score_particles(
    particles_csv: &Path,
    truth: &Truth,
    radius: f64,
) -> Result<DetectionScore> {
    let t = read_table(particles_csv, &["pulse", "x", "y"])?;
    let (k, x, y) = (
        t.col("pulse").unwrap(),
        t.col("x").unwrap(),
        t.col("y").unwrap(),
    );
    let det: Vec<(i64, f64, f64)> = (0..t.rows()).map(|i| (k[i] as i64, x[i], y[i])).collect();
    let m = match_detections(truth, &det, radius);
    let mut matched = 0usize;
    let mut sq = 0.0;
    for (d, mm) in det.iter().zip(&m) {
        if let Some((kk, j)) = mm {
            let tr = truth.get(*kk, *j);
            matched += 1;
            sq += (d.1 - tr.1).powi(2) + (d.2 - tr.2).powi(2);
        }
    }
    Ok(DetectionScore {
        detections: det.len(),
        truth_samples: truth.samples,
        precision: ratio(matched, det.len()),
        recall: ratio(matched, truth.samples),
        position_rms_px: if matched > 0 {
            (sq / (2 * matched) as f64).sqrt()
        } else {
            f64::NAN
        },
    })
}

/// Link and velocity scores of a tracks table (any format).
#[derive(Debug, Clone, Serialize)]
#[ebptv_macros::testkit]
pub(crate) struct TrackScore {
    /// Distinct track ids.
    pub tracks: usize,
    /// Track points (rows of the table).
    pub track_points: usize,
    /// Links: pairs of consecutive points of one track.
    pub links: usize,
    /// Correct links / links.
    pub link_precision: f64,
    /// Truth links found / truth links (detection losses included).
    pub link_recall: f64,
    /// Rms velocity error (px per pulse interval, per component) over
    /// matched track points.
    pub velocity_rms_px_per_pulse: f64,
    /// Track points matched to a truth particle.
    pub matched_points: usize,
}

/// Score the tracks table `tracks_csv` (any format, columns
/// `track_id,pulse,x,y,u,v`, u and v in px/s) against `truth`; `period_us` is
/// the pulse period (µs) that turns velocities into px per pulse interval,
/// `radius` the matching radius (px). Fails when the table cannot be read or
/// lacks a column.
#[ebptv_macros::testkit]
pub(crate) fn score_tracks(
    tracks_csv: &Path,
    truth: &Truth,
    period_us: f64,
    radius: f64,
) -> Result<TrackScore> {
    let t = read_table(tracks_csv, &["track_id", "pulse", "x", "y", "u", "v"])?;
    let c = |n: &str| t.col(n).unwrap();
    let (id, k, x, y, u, v) = (c("track_id"), c("pulse"), c("x"), c("y"), c("u"), c("v"));
    let det: Vec<(i64, f64, f64)> = (0..t.rows()).map(|i| (k[i] as i64, x[i], y[i])).collect();
    let m = match_detections(truth, &det, radius);

    // Rows of one track are consecutive in tracks.csv, sorted by pulse.
    let dt = period_us * 1e-6;
    let (mut links, mut correct, mut sq, mut matched) = (0usize, 0usize, 0.0, 0usize);
    let mut found: HashSet<(i64, u64)> = HashSet::new();
    let mut ids: HashSet<u64> = HashSet::new();
    for i in 0..t.rows() {
        ids.insert(id[i] as u64);
        if let Some((kk, j)) = m[i] {
            let tr = truth.get(kk, j);
            sq += ((u[i] - tr.3) * dt).powi(2) + ((v[i] - tr.4) * dt).powi(2);
            matched += 1;
        }
        if i + 1 < t.rows() && id[i + 1] == id[i] {
            links += 1;
            if let (Some((ka, ja)), Some((kb, jb))) = (m[i], m[i + 1]) {
                let (ta, tb) = (truth.get(ka, ja).0, truth.get(kb, jb).0);
                if ta == tb {
                    correct += 1;
                    if kb == ka + 1 {
                        found.insert((ka, ta));
                    }
                }
            }
        }
    }
    // Truth links: truth particles present at k and k+1.
    let mut truth_links = 0usize;
    for (&kk, pts) in &truth.by_pulse {
        if let Some(next) = truth.by_pulse.get(&(kk + 1)) {
            let next_ids: HashSet<u64> = next.iter().map(|p| p.0).collect();
            truth_links += pts.iter().filter(|p| next_ids.contains(&p.0)).count();
        }
    }
    Ok(TrackScore {
        tracks: ids.len(),
        track_points: t.rows(),
        links,
        link_precision: ratio(correct, links),
        link_recall: ratio(found.len(), truth_links),
        velocity_rms_px_per_pulse: if matched > 0 {
            (sq / (2 * matched) as f64).sqrt()
        } else {
            f64::NAN
        },
        matched_points: matched,
    })
}

/// Error of a mean-velocity field (the `grid` or `piv_mean` table, any
/// format) against the truth binned at the same nodes.
#[derive(Debug, Clone, Serialize)]
pub(crate) struct FieldScore {
    /// Nodes scored.
    pub nodes_compared: usize,
    /// Rms of the vector error over nodes, as a fraction of the largest
    /// true speed.
    pub rms_error_of_max_speed: f64,
    /// Mean error (bias) of u and v, fraction of the largest true speed.
    pub mean_error_u: f64,
    /// Mean error (bias) of v, fraction of the largest true speed.
    pub mean_error_v: f64,
    /// Largest true speed over all truth samples (px/s).
    pub max_true_speed: f64,
}

/// Score a mean field given as a CSV with columns `x,y,u,v` (plus a
/// `count` or `valid` column used to skip empty nodes). Truth samples are
/// averaged in a `bin_w × bin_h` top-hat box around each node; nodes where
/// the truth has fewer than `min_truth` samples, or the field is NaN, are
/// skipped.
pub(crate) fn score_mean_field(
    field_csv: &Path,
    truth: &Truth,
    bin_w: f64,
    bin_h: f64,
    min_truth: usize,
) -> Result<FieldScore> {
    let t = read_table(field_csv, &["x", "y", "u", "v"])?;
    let c = |n: &str| t.col(n).unwrap();
    let (x, y, u, v) = (c("x"), c("y"), c("u"), c("v"));
    if !(bin_w > 0.0 && bin_h > 0.0) {
        return Err(Error::param(
            "bin",
            "box size for truth averaging must be positive",
        ));
    }
    // Hash truth samples on a bin-sized lattice for box queries.
    #[allow(clippy::type_complexity)]
    let mut cells: HashMap<(i64, i64), Vec<(f64, f64, f64, f64)>> = HashMap::new();
    for p in truth.all() {
        let key = ((p.1 / bin_w).floor() as i64, (p.2 / bin_h).floor() as i64);
        cells.entry(key).or_default().push((p.1, p.2, p.3, p.4));
    }
    let vmax = truth.max_speed();
    let (mut n, mut sq, mut su, mut sv) = (0usize, 0.0, 0.0, 0.0);
    for i in 0..t.rows() {
        if !(u[i].is_finite() && v[i].is_finite()) {
            continue;
        }
        let (cx, cy) = ((x[i] / bin_w).floor() as i64, (y[i] / bin_h).floor() as i64);
        let (mut cnt, mut tu, mut tv) = (0usize, 0.0, 0.0);
        for dx in -1..=1 {
            for dy in -1..=1 {
                if let Some(pts) = cells.get(&(cx + dx, cy + dy)) {
                    for p in pts {
                        if (p.0 - x[i]).abs() <= bin_w / 2.0 && (p.1 - y[i]).abs() <= bin_h / 2.0 {
                            cnt += 1;
                            tu += p.2;
                            tv += p.3;
                        }
                    }
                }
            }
        }
        if cnt < min_truth.max(1) {
            continue;
        }
        let (eu, ev) = (u[i] - tu / cnt as f64, v[i] - tv / cnt as f64);
        n += 1;
        sq += eu * eu + ev * ev;
        su += eu;
        sv += ev;
    }
    if n == 0 {
        return Err(Error::analysis(format!(
            "{}: no node with data overlaps the truth",
            field_csv.display()
        )));
    }
    Ok(FieldScore {
        nodes_compared: n,
        rms_error_of_max_speed: (sq / n as f64).sqrt() / vmax,
        mean_error_u: su / n as f64 / vmax,
        mean_error_v: sv / n as f64 / vmax,
        max_true_speed: vmax,
    })
}

fn ratio(a: usize, b: usize) -> f64 {
    if b == 0 {
        f64::NAN
    } else {
        a as f64 / b as f64
    }
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;
    use std::io::Write;

    fn write(dir: &Path, name: &str, text: &str) -> std::path::PathBuf {
        let p = dir.join(name);
        std::fs::File::create(&p)
            .unwrap()
            .write_all(text.as_bytes())
            .unwrap();
        p
    }

    /// Two particles over three pulses; one track right, one track that
    /// jumps between the particles.
    fn scene(dir: &Path) -> Truth {
        let p = write(
            dir,
            "truth.csv",
            "pulse,t_us,particle_id,x,y,u,v\n\
             0,0,1,10,10,1000,0\n0,0,2,50,50,0,1000\n\
             1,200,1,10.2,10,1000,0\n1,200,2,50,50.2,0,1000\n\
             2,400,1,10.4,10,1000,0\n2,400,2,50,50.4,0,1000\n",
        );
        Truth::read(&p).unwrap()
    }

    #[ebptv_macros::unit_test]
    fn links_and_velocity_are_scored_against_truth() {
        let dir = tempfile::tempdir().unwrap();
        let truth = scene(dir.path());
        let tracks = write(
            dir.path(),
            "tracks.csv",
            "track_id,pulse,t_us,x,y,u,v\n\
             0,0,0,10,10,1000,0\n0,1,200,10.2,10,1000,0\n0,2,400,10.4,10,1100,0\n\
             1,0,0,50,50,0,1000\n1,1,200,50,50.2,0,1000\n1,2,400,10.4,10.1,0,1000\n",
        );
        let s = score_tracks(&tracks, &truth, 200.0, 1.0).unwrap();
        assert_eq!(s.links, 4);
        // Track 1's second link jumps to particle 1: 3 of 4 links correct.
        assert!((s.link_precision - 0.75).abs() < 1e-12);
        // 4 truth links; found: (0,1), (1,1), (0,2) → 3/4.
        assert!((s.link_recall - 0.75).abs() < 1e-12);
        // Particle 1 at pulse 2 is claimed by two points; only the nearest
        // (track 0's) is matched: 5 matched points.
        assert_eq!(s.matched_points, 5);
        // Errors (px/pulse): track 0 pulse 2: du = 100 px/s → 0.02 px.
        let want = ((0.02f64).powi(2) / (2.0 * 5.0)).sqrt();
        assert!((s.velocity_rms_px_per_pulse - want).abs() < 1e-12);
    }

    #[ebptv_macros::unit_test]
    fn detections_unmatched_beyond_radius() {
        let dir = tempfile::tempdir().unwrap();
        let truth = scene(dir.path());
        let parts = write(
            dir.path(),
            "particles.csv",
            "pulse,t_us,x,y,n_events\n0,0,10.3,10,2\n0,0,80,80,1\n1,200,50,50.2,2\n",
        );
        let s = score_particles(&parts, &truth, 1.0).unwrap();
        assert_eq!(s.detections, 3);
        assert!((s.precision - 2.0 / 3.0).abs() < 1e-12);
        assert!((s.recall - 2.0 / 6.0).abs() < 1e-12);
        assert!((s.position_rms_px - (0.09f64 / 4.0).sqrt()).abs() < 1e-12);
    }

    #[ebptv_macros::unit_test]
    fn mean_field_error_relative_to_max_speed() {
        let dir = tempfile::tempdir().unwrap();
        let truth = scene(dir.path());
        let grid = write(
            dir.path(),
            "grid.csv",
            "x,y,count,u,v,uu,vv,uv\n10,10,3,1100,0,0,0,0\n50,50,3,0,1000,0,0,0\n200,200,0,nan,nan,nan,nan,nan\n",
        );
        let s = score_mean_field(&grid, &truth, 4.0, 4.0, 1).unwrap();
        assert_eq!(s.nodes_compared, 2);
        let want = ((100.0f64 * 100.0) / 2.0).sqrt() / 1000.0;
        assert!((s.rms_error_of_max_speed - want).abs() < 1e-12);
    }

    /// The field score must not depend on a hash map's per-process order:
    /// truth samples whose float sum changes with the order (values over
    /// many magnitudes, one per pulse), loaded afresh several times, must
    /// give bit-identical scores.
    #[ebptv_macros::unit_test]
    fn mean_field_error_is_bit_identical_across_truth_loads() {
        let dir = tempfile::tempdir().unwrap();
        let mut text = String::from("pulse,t_us,particle_id,x,y,u,v\n");
        for k in 0..64 {
            let u = 1000.0 + 1e-3 * (k as f64 * 0.7).sin() * 10f64.powi(k % 9);
            text += &format!("{k},{},1,10,10,{u},0.{k}\n", k * 200);
        }
        let truth_csv = write(dir.path(), "truth.csv", &text);
        let grid = write(
            dir.path(),
            "grid.csv",
            "x,y,count,u,v,uu,vv,uv\n10,10,3,1001,0,0,0,0\n",
        );
        let scores: Vec<(u64, u64)> = (0..8)
            .map(|_| {
                let truth = Truth::read(&truth_csv).unwrap();
                let s = score_mean_field(&grid, &truth, 4.0, 4.0, 1).unwrap();
                (s.mean_error_u.to_bits(), s.mean_error_v.to_bits())
            })
            .collect();
        assert!(scores.iter().all(|s| *s == scores[0]), "{scores:?}");
    }
}
