//! Exact, mergeable per-bin accumulators.
//!
//! Each bin keeps weighted power sums — never running means — so that two
//! accumulators over disjoint sample sets add up to the accumulator of their
//! union: `merge` is plain addition and a long recording split into time
//! slices (one process each, e.g. a Slurm array) merges to the same numbers
//! as one run. The sums are those every estimator needs:
//!
//! * the Gram matrix `Σ w φφᵀ` of the quadratic basis
//!   `φ = (1, ξ, η, ξ², ξη, η²)` in bin-local normalised coordinates
//!   (`ξ = (x − x_c)/bin_w`, so the fit's constant term *is* the value at the
//!   centre), and the moments `Σ w φ u`, `Σ w φ v`: enough for the top-hat
//!   mean (first entry) and the in-bin linear / quadratic fits;
//! * `Σ w u²`, `Σ w v²`, `Σ w uv` for stresses (residual sums of squares of
//!   any fit follow from these and the fit: `Σ w r² = Σ w u² − aᵀ Σ w φ u`);
//! * `Σ w²` for the effective sample count of weighted estimators;
//! * per-track cluster sums for honest standard errors (see below).
//!
//! Precision: positions are bin-local and O(1); velocities are not centred
//! (a fixed reference would have to be agreed by every slice), so the power
//! sums use Neumaier-compensated summation: a sum of 10⁸ samples keeps
//! ~1e-16 relative accuracy instead of ~1e-8, and `Σu² − n·ū²` stays exact
//! enough for stresses 10⁴ times smaller than ū².
//!
//! Independent samples: consecutive samples of one track are strongly
//! correlated, so the standard error of a bin mean uses the track as the
//! independent unit (a cluster-robust variance). Per bin, the samples of the
//! track currently passing are summed into an open cluster, closed when
//! another track arrives. Input grouped by track (as `tracks.csv` is) thus
//! yields one cluster per (track, bin). The first and the last cluster of a
//! bin are kept open so that merging a file cut into consecutive row chunks
//! re-joins the track cut at the boundary: merged == single run, including
//! the number of distinct tracks.

use serde::{Deserialize, Serialize};

use super::spec::GridSpec;
use super::Sample;
use crate::error::{Error, Result};

/// Compensated sum (Kahan–Babuška–Neumaier accuracy via TwoSum).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[serde(from = "(f64, f64)", into = "(f64, f64)")]
pub(crate) struct KSum {
    s: f64,
    c: f64,
}

impl From<(f64, f64)> for KSum {
    fn from(t: (f64, f64)) -> Self {
        KSum { s: t.0, c: t.1 }
    }
}
impl From<KSum> for (f64, f64) {
    fn from(k: KSum) -> Self {
        (k.s, k.c)
    }
}

impl KSum {
    /// Knuth's branch-free TwoSum: the rounding error of `s + x` is exact
    /// and goes into `c` (same accuracy as Neumaier's branching form,
    /// without an unpredictable branch per add).
    #[inline(always)]
    pub(crate) fn add(&mut self, x: f64) {
        let t = self.s + x;
        let z = t - self.s;
        self.c += (self.s - (t - z)) + (x - z);
        self.s = t;
    }
    #[inline]
    pub(crate) fn merge(&mut self, o: &KSum) {
        self.add(o.s);
        self.add(o.c);
    }
    #[inline]
    pub(crate) fn value(&self) -> f64 {
        self.s + self.c
    }
}

/// Number of basis functions of the quadratic in-bin model.
pub(crate) const NB: usize = 6;
/// Entries of the upper triangle of the NB×NB Gram matrix.
pub(crate) const NG: usize = NB * (NB + 1) / 2;

/// Index of Gram entry (a, b), a ≤ b, in the packed upper triangle.
#[inline]
pub(crate) fn gidx(a: usize, b: usize) -> usize {
    let (a, b) = if a <= b { (a, b) } else { (b, a) };
    a * NB - a * (a + 1) / 2 + b
}

/// The quadratic in-bin basis `φ = (1, ξ, η, ξ², ξη, η²)` at the
/// bin-local normalised offsets `(ξ, η)` (units of bin size).
#[inline]
pub(crate) fn basis(xi: f64, eta: f64) -> [f64; NB] {
    [1.0, xi, eta, xi * xi, xi * eta, eta * eta]
}

/// The samples of one track inside one bin.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub(crate) struct Cluster {
    /// The track.
    pub track_id: u64,
    /// Σ w: the summed weight of its samples.
    pub w: f64,
    /// Σ w u (weight × px/s).
    pub su: f64,
    /// Σ w v (weight × px/s).
    pub sv: f64,
}

/// Sums over closed clusters: Σ W_k², Σ W_k S_k, Σ S_k² (u and v).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub(crate) struct ClusterSums {
    /// Number of closed clusters.
    pub n: u64,
    /// Σ W_k² over closed clusters (W_k = a cluster's Σ w).
    pub ww: KSum,
    /// Σ W_k S_k for u (S_k = a cluster's Σ w u).
    pub wsu: KSum,
    /// Σ W_k S_k for v (S_k = a cluster's Σ w v).
    pub wsv: KSum,
    /// Σ S_k² for u.
    pub susu: KSum,
    /// Σ S_k² for v.
    pub svsv: KSum,
}

impl ClusterSums {
    fn close(&mut self, c: &Cluster) {
        self.n += 1;
        self.ww.add(c.w * c.w);
        self.wsu.add(c.w * c.su);
        self.wsv.add(c.w * c.sv);
        self.susu.add(c.su * c.su);
        self.svsv.add(c.sv * c.sv);
    }
    fn merge(&mut self, o: &ClusterSums) {
        self.n += o.n;
        self.ww.merge(&o.ww);
        self.wsu.merge(&o.wsu);
        self.wsv.merge(&o.wsv);
        self.susu.merge(&o.susu);
        self.svsv.merge(&o.svsv);
    }
}

/// Everything one bin knows.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub(crate) struct BinAcc {
    /// Number of samples (unweighted).
    pub n: u64,
    /// Σ w².
    pub w2: KSum,
    /// Packed upper triangle of Σ w φφᵀ; entry 0 is Σ w.
    pub gram: [KSum; NG],
    /// Moments Σ w φ u of the basis with u (weight × px/s).
    pub pu: [KSum; NB],
    /// Moments Σ w φ v of the basis with v (weight × px/s).
    pub pv: [KSum; NB],
    /// Σ w u² ((px/s)²).
    pub uu: KSum,
    /// Σ w v² ((px/s)²).
    pub vv: KSum,
    /// Σ w u v ((px/s)²).
    pub uv: KSum,
    /// Sums over the closed per-track clusters (for standard errors).
    pub closed: ClusterSums,
    /// First cluster seen (kept open for merging).
    pub head: Option<Cluster>,
    /// Last cluster seen, if different from `head` (kept open).
    pub tail: Option<Cluster>,
}

impl BinAcc {
    #[inline]
    pub(crate) fn add(&mut self, xi: f64, eta: f64, w: f64, u: f64, v: f64, track_id: u64) {
        let phi = basis(xi, eta);
        self.n += 1;
        self.w2.add(w * w);
        let mut k = 0;
        for a in 0..NB {
            let wa = w * phi[a];
            for b in a..NB {
                self.gram[k].add(wa * phi[b]);
                k += 1;
            }
            self.pu[a].add(wa * u);
            self.pv[a].add(wa * v);
        }
        self.uu.add(w * u * u);
        self.vv.add(w * v * v);
        self.uv.add(w * u * v);
        self.add_to_cluster(track_id, w, u, v);
    }

    fn add_to_cluster(&mut self, id: u64, w: f64, u: f64, v: f64) {
        let fresh = Cluster {
            track_id: id,
            w,
            su: w * u,
            sv: w * v,
        };
        let grow = |c: &mut Cluster| {
            c.w += w;
            c.su += w * u;
            c.sv += w * v;
        };
        match (&mut self.head, &mut self.tail) {
            (None, _) => self.head = Some(fresh),
            (Some(h), None) => {
                if h.track_id == id {
                    grow(h)
                } else {
                    self.tail = Some(fresh)
                }
            }
            (Some(_), Some(t)) => {
                if t.track_id == id {
                    grow(t)
                } else {
                    let old = *t;
                    self.closed.close(&old);
                    *t = fresh;
                }
            }
        }
    }

    /// Number of track clusters (distinct tracks when input is grouped by track).
    pub(crate) fn n_tracks(&self) -> u64 {
        self.closed.n + self.head.is_some() as u64 + self.tail.is_some() as u64
    }

    /// All cluster sums including the open head and tail.
    pub(crate) fn all_clusters(&self) -> ClusterSums {
        let mut c = self.closed;
        for k in [self.head, self.tail].into_iter().flatten() {
            c.close(&k);
        }
        c
    }

    /// Add `o` (a later slice) into `self`.
    pub(crate) fn merge(&mut self, o: &BinAcc) {
        if o.n == 0 {
            return;
        }
        if self.n == 0 {
            *self = o.clone();
            return;
        }
        self.n += o.n;
        self.w2.merge(&o.w2);
        for k in 0..NG {
            self.gram[k].merge(&o.gram[k]);
        }
        for a in 0..NB {
            self.pu[a].merge(&o.pu[a]);
            self.pv[a].merge(&o.pv[a]);
        }
        self.uu.merge(&o.uu);
        self.vv.merge(&o.vv);
        self.uv.merge(&o.uv);
        self.closed.merge(&o.closed);
        // Ordered open clusters of self then o; join the boundary pair when
        // it is the same track, keep first and last open, close the rest.
        let mut seq: Vec<Cluster> = Vec::with_capacity(4);
        for c in [self.head, self.tail, o.head, o.tail].into_iter().flatten() {
            match seq.last_mut() {
                Some(l) if l.track_id == c.track_id => {
                    l.w += c.w;
                    l.su += c.su;
                    l.sv += c.sv;
                }
                _ => seq.push(c),
            }
        }
        self.head = seq.first().copied();
        self.tail = if seq.len() > 1 {
            seq.last().copied()
        } else {
            None
        };
        if seq.len() > 2 {
            for c in &seq[1..seq.len() - 1] {
                self.closed.close(c);
            }
        }
    }
}

/// A grid of bin accumulators.
#[derive(Debug, Clone, PartialEq)]
pub struct GridAccumulator {
    /// The window of bins.
    pub spec: GridSpec,
    /// One accumulator per bin, at the flat index `j·nx + i` of `spec`.
    pub(crate) bins: Vec<BinAcc>,
    /// Samples with a non-finite coordinate or velocity (skipped).
    pub rejected: u64,
    /// Samples that fell outside the window (skipped).
    pub outside: u64,
}

impl GridAccumulator {
    /// An empty accumulator for the bins of `spec`.
    #[ebptv_macros::testkit]
    pub(crate) fn new(spec: GridSpec) -> GridAccumulator {
        GridAccumulator {
            spec,
            bins: vec![BinAcc::default(); spec.n_bins()],
            rejected: 0,
            outside: 0,
        }
    }

    /// Bin one sample into every bin whose support holds it.
    #[inline]
    pub(crate) fn add(&mut self, s: &Sample) {
        if !(s.x.is_finite() && s.y.is_finite() && s.u.is_finite() && s.v.is_finite()) {
            self.rejected += 1;
            return;
        }
        let spec = self.spec;
        let lat = &spec.lattice;
        let ((ilo, ihi), (jlo, jhi)) = lat.candidates(s.x, s.y, spec.weighting);
        let mut any = false;
        for j in jlo..=jhi {
            let eta = (s.y - lat.centre_y(j)) / lat.bin_h;
            for i in ilo..=ihi {
                let xi = (s.x - lat.centre_x(i)) / lat.bin_w;
                let Some(w) = spec.weighting.weight(xi, eta) else {
                    continue;
                };
                let Some(k) = spec.flat(i, j) else { continue };
                any = true;
                self.bins[k].add(xi, eta, w, s.u, s.v, s.track_id);
            }
        }
        if !any {
            self.outside += 1;
        }
    }

    /// Bin every sample (one thread); non-finite samples count as
    /// `rejected`, those outside the window as `outside`.
    #[ebptv_macros::testkit]
    pub(crate) fn add_all<'a>(&mut self, samples: impl IntoIterator<Item = &'a Sample>) {
        for s in samples {
            self.add(s);
        }
    }

    /// Bin samples on all cores: contiguous chunks (one per thread, fewer for huge grids) are
    /// binned into private accumulators and merged in order, which by the
    /// merge rules gives the sequential result to rounding (the track cut at
    /// a chunk boundary is re-joined, so track counts are exact).
    pub(crate) fn add_par(&mut self, samples: &[Sample]) {
        use rayon::prelude::*;
        // Each part holds a whole grid: cap their total memory at ~512 MB.
        let grid_bytes = self.spec.n_bins() * std::mem::size_of::<BinAcc>();
        let threads = rayon::current_num_threads()
            .min((512 << 20) / grid_bytes.max(1))
            .max(1);
        if threads == 1 || samples.len() < 100_000 {
            self.add_all(samples);
            return;
        }
        let chunk = samples.len().div_ceil(threads);
        let spec = self.spec;
        let part = samples
            .par_chunks(chunk)
            .map(|c| {
                let mut a = GridAccumulator::new(spec);
                a.add_all(c);
                a
            })
            .reduce_with(|mut a, b| {
                a.merge(&b).expect("same spec");
                a
            });
        if let Some(p) = part {
            self.merge(&p).expect("same spec");
        }
    }

    /// Total number of samples binned (a sample in k overlapping bins counts k times).
    #[ebptv_macros::testkit]
    pub(crate) fn total_count(&self) -> u64 {
        self.bins.iter().map(|b| b.n).sum()
    }

    /// Merge a later slice into this one. Lattices and weightings must be
    /// identical; the window grows to hold both.
    pub(crate) fn merge(&mut self, o: &GridAccumulator) -> Result<()> {
        if !self.spec.compatible(&o.spec) {
            return Err(Error::param(
                "merge",
                format!(
                    "incompatible grids: bin {}x{} overlap {} origin ({}, {}) {:?} vs bin {}x{} overlap {} origin ({}, {}) {:?}",
                    self.spec.lattice.bin_w,
                    self.spec.lattice.bin_h,
                    self.spec.lattice.overlap,
                    self.spec.lattice.origin_x,
                    self.spec.lattice.origin_y,
                    self.spec.weighting,
                    o.spec.lattice.bin_w,
                    o.spec.lattice.bin_h,
                    o.spec.lattice.overlap,
                    o.spec.lattice.origin_x,
                    o.spec.lattice.origin_y,
                    o.spec.weighting
                ),
            ));
        }
        let union = self.spec.union(&o.spec)?;
        if union != self.spec {
            let mut grown = GridAccumulator::new(union);
            grown.rejected = self.rejected;
            grown.outside = self.outside;
            for b in 0..self.spec.ny {
                for a in 0..self.spec.nx {
                    let k = union
                        .flat(self.spec.i0 + a as i64, self.spec.j0 + b as i64)
                        .expect("union holds self");
                    grown.bins[k] = std::mem::take(&mut self.bins[b * self.spec.nx + a]);
                }
            }
            *self = grown;
        }
        for b in 0..o.spec.ny {
            for a in 0..o.spec.nx {
                let src = &o.bins[b * o.spec.nx + a];
                if src.n == 0 {
                    continue;
                }
                let k = self
                    .spec
                    .flat(o.spec.i0 + a as i64, o.spec.j0 + b as i64)
                    .expect("union holds other");
                self.bins[k].merge(src);
            }
        }
        self.rejected += o.rejected;
        self.outside += o.outside;
        Ok(())
    }
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;

    #[ebptv_macros::unit_test]
    fn gram_index_packs_upper_triangle() {
        let mut seen = [false; NG];
        for a in 0..NB {
            for b in a..NB {
                let k = gidx(a, b);
                assert!(!seen[k]);
                seen[k] = true;
                assert_eq!(gidx(b, a), k);
            }
        }
        assert!(seen.iter().all(|&s| s));
        // The packing order must match the loop order used in `add`.
        let mut k = 0;
        for a in 0..NB {
            for b in a..NB {
                assert_eq!(gidx(a, b), k);
                k += 1;
            }
        }
    }

    #[ebptv_macros::unit_test]
    fn compensated_sum_beats_naive() {
        let mut k = KSum::default();
        let mut naive = 0.0f64;
        k.add(1e16);
        naive += 1e16;
        for _ in 0..1000 {
            k.add(1.0);
            naive += 1.0;
        }
        k.add(-1e16);
        naive -= 1e16;
        assert_eq!(k.value(), 1000.0);
        assert_ne!(naive, 1000.0);
    }

    #[ebptv_macros::unit_test]
    fn clusters_count_tracks_and_rejoin_on_merge() {
        let ids = [1u64, 1, 1, 2, 2, 3, 4, 4, 4, 5];
        let mut whole = BinAcc::default();
        for &id in &ids {
            whole.add(0.0, 0.0, 1.0, id as f64, 0.0, id);
        }
        assert_eq!(whole.n_tracks(), 5);
        for cut in 0..=ids.len() {
            let mut a = BinAcc::default();
            let mut b = BinAcc::default();
            for &id in &ids[..cut] {
                a.add(0.0, 0.0, 1.0, id as f64, 0.0, id);
            }
            for &id in &ids[cut..] {
                b.add(0.0, 0.0, 1.0, id as f64, 0.0, id);
            }
            a.merge(&b);
            assert_eq!(a.n_tracks(), 5, "cut {cut}");
            let (x, y) = (a.all_clusters(), whole.all_clusters());
            assert_eq!(x.susu.value(), y.susu.value(), "cut {cut}");
            assert_eq!(x.ww.value(), y.ww.value());
        }
    }
}
