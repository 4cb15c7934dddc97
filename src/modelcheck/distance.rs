//! Distances between signatures, and their standardisation against chance.
//!
//! A raw distance between a measured and a simulated signature means
//! nothing on its own: two simulations with different seeds also differ. So
//! each distance is judged against *replicate* distances — the same distance
//! between the reference simulation and simulations of the same model with
//! other seeds. Under the hypothesis "the model explains the data" the
//! measured recording is just another replicate, and its distance falls
//! among the replicate distances. [`standardise`] expresses the observed
//! distance as a z-score and an empirical p-value over the replicates;
//! [`rank`] builds the table of where measurement and model disagree,
//! worst first.
//!
//! Distances:
//! - histograms: 1-D Wasserstein (earth mover's) distance between the two
//!   normalised histograms, with bin masses at [`Histogram::positions`]
//!   (centres in the quantity's unit, or the bin index for geometric
//!   binnings). It compares shapes; totals are compared by scalar signatures
//!   (`event_rate`). [`chi_square`] (two-sample, unequal totals) is there for
//!   count data where shape and total both matter.
//! - profiles: count-weighted mean absolute difference of the bin means over
//!   the bins both sides populate.
//! - scalars: absolute difference.

use serde::{Deserialize, Serialize};

use super::signatures::{Histogram, Profile, Signature, SignatureValue, Signatures};
use crate::error::{Error, Result};

/// 1-D Wasserstein distance between two histograms given as masses at
/// increasing `positions`. Each side is normalised to unit mass.
///
/// With cumulative masses `A_i`, `B_i` the transport cost is
/// `Σ_i |A_i − B_i| (x_{i+1} − x_i)`: the mass that must cross each gap.
pub(crate) fn wasserstein_1d(positions: &[f64], a: &[f64], b: &[f64]) -> Result<f64> {
    let n = positions.len();
    if a.len() != n || b.len() != n {
        return Err(Error::param(
            "wasserstein",
            format!(
                "{} positions but histograms of {} and {} bins",
                n,
                a.len(),
                b.len()
            ),
        ));
    }
    if positions.iter().any(|p| !p.is_finite())
        || positions
            .windows(2)
            .any(|w| w[1].partial_cmp(&w[0]) != Some(std::cmp::Ordering::Greater))
    {
        return Err(Error::param(
            "wasserstein",
            "positions must be finite and increasing",
        ));
    }
    let total = |h: &[f64], side: &str| -> Result<f64> {
        if h.iter().any(|c| !(c.is_finite() && *c >= 0.0)) {
            return Err(Error::param(
                "wasserstein",
                format!("{side} histogram has negative or non-finite counts"),
            ));
        }
        let t: f64 = h.iter().sum();
        if t <= 0.0 {
            return Err(Error::param(
                "wasserstein",
                format!("{side} histogram is empty"),
            ));
        }
        Ok(t)
    };
    let (ta, tb) = (total(a, "first")?, total(b, "second")?);
    let (mut ca, mut cb, mut w) = (0.0, 0.0, 0.0);
    for i in 0..n.saturating_sub(1) {
        ca += a[i] / ta;
        cb += b[i] / tb;
        w += (ca - cb).abs() * (positions[i + 1] - positions[i]);
    }
    Ok(w)
}

/// Wasserstein distance of two histograms on the same bins.
pub(crate) fn histogram_wasserstein(a: &Histogram, b: &Histogram) -> Result<f64> {
    if !a.same_bins(b) {
        return Err(Error::param(
            "wasserstein",
            "histograms have different bins (signatures must share one configuration)",
        ));
    }
    wasserstein_1d(&a.positions(), &a.counts, &b.counts)
}

/// Two-sample chi-square on binned counts.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub(crate) struct ChiSquare {
    /// The chi-square statistic.
    pub statistic: f64,
    /// Bins with data on either side, minus one (the totals are matched).
    pub dof: usize,
}

impl ChiSquare {
    /// Statistic per degree of freedom (≈ 1 when both are draws of one law).
    pub(crate) fn reduced(&self) -> f64 {
        if self.dof == 0 {
            0.0
        } else {
            self.statistic / self.dof as f64
        }
    }
}

/// Two-sample chi-square for counts `r`, `s` with possibly different totals:
/// `Σ (√(S/R)·r_i − √(R/S)·s_i)² / (r_i + s_i)` over bins with data
/// (Numerical Recipes' `chstwo`).
pub(crate) fn chi_square(r: &[f64], s: &[f64]) -> Result<ChiSquare> {
    if r.len() != s.len() {
        return Err(Error::param(
            "chi_square",
            format!("histograms of {} and {} bins", r.len(), s.len()),
        ));
    }
    if r.iter().chain(s).any(|c| !(c.is_finite() && *c >= 0.0)) {
        return Err(Error::param("chi_square", "counts must be finite and ≥ 0"));
    }
    let (tr, ts): (f64, f64) = (r.iter().sum(), s.iter().sum());
    if tr <= 0.0 || ts <= 0.0 {
        return Err(Error::param("chi_square", "a histogram is empty"));
    }
    let (fr, fs) = ((ts / tr).sqrt(), (tr / ts).sqrt());
    let mut stat = 0.0;
    let mut bins = 0usize;
    for (&a, &b) in r.iter().zip(s) {
        if a + b > 0.0 {
            stat += (fr * a - fs * b).powi(2) / (a + b);
            bins += 1;
        }
    }
    Ok(ChiSquare {
        statistic: stat,
        dof: bins.saturating_sub(1),
    })
}

/// Count-weighted mean |difference| of two profiles over their common bins;
/// `None` when no bin has data on both sides.
pub(crate) fn profile_distance(a: &Profile, b: &Profile) -> Result<Option<f64>> {
    if a.edges != b.edges {
        return Err(Error::param(
            "profile distance",
            "profiles have different bins",
        ));
    }
    let (mut num, mut den) = (0.0, 0.0);
    for i in 0..a.mean.len() {
        let w = a.count[i].min(b.count[i]);
        if w > 0.0 && a.mean[i].is_finite() && b.mean[i].is_finite() {
            num += w * (a.mean[i] - b.mean[i]).abs();
            den += w;
        }
    }
    Ok(if den > 0.0 { Some(num / den) } else { None })
}

/// Distance between two signatures of the same name and kind; `None` when
/// they cannot be compared (an empty histogram, a profile without common
/// bins, a non-finite scalar).
pub(crate) fn signature_distance(a: &Signature, b: &Signature) -> Result<Option<f64>> {
    match (&a.value, &b.value) {
        (SignatureValue::Histogram(x), SignatureValue::Histogram(y)) => {
            if x.total() <= 0.0 || y.total() <= 0.0 {
                return Ok(None);
            }
            histogram_wasserstein(x, y).map(Some)
        }
        (SignatureValue::Profile(x), SignatureValue::Profile(y)) => profile_distance(x, y),
        (SignatureValue::Scalar { value: x }, SignatureValue::Scalar { value: y }) => {
            Ok(if x.is_finite() && y.is_finite() {
                Some((x - y).abs())
            } else {
                None
            })
        }
        _ => Err(Error::param(
            "signature distance",
            format!("`{}` and `{}` are of different kinds", a.name, b.name),
        )),
    }
}

/// Distances for every signature present (and comparable) in both sets, in
/// the order of `a`. Histograms give two rows: `name` (Wasserstein: where
/// the bulk sits) and `name.chi2` (reduced chi-square: sensitive to sparse
/// tails, e.g. a few hot pixels far out in the per-pixel counts, that move
/// little mass and so barely move the Wasserstein distance).
pub(crate) fn distances(a: &Signatures, b: &Signatures) -> Result<Vec<(String, f64)>> {
    let mut out = Vec::new();
    for s in &a.items {
        if let Some(t) = b.get(&s.name) {
            if let Some(d) = signature_distance(s, t)? {
                out.push((s.name.clone(), d));
            }
            if let (SignatureValue::Histogram(x), SignatureValue::Histogram(y)) =
                (&s.value, &t.value)
            {
                if x.same_bins(y) && x.total() > 0.0 && y.total() > 0.0 {
                    let c = chi_square(&x.counts, &y.counts)?;
                    out.push((format!("{}.chi2", s.name), c.reduced()));
                }
            }
        }
    }
    Ok(out)
}

/// |z| is capped here: beyond it the replicates (often all exactly zero,
/// e.g. no shared timestamps in any simulation) say only "far beyond
/// chance", and an uncapped 1e9 would swamp every other row of a sum.
pub(crate) const Z_CAP: f64 = 1000.0;

/// Floor of the replicate spread, relative to the replicate mean.
pub(crate) const SD_FLOOR_REL: f64 = 0.5;

/// An observed distance judged against replicate distances.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Standardised {
    /// The observed distance.
    pub observed: f64,
    /// Mean of the replicate distances.
    pub replicate_mean: f64,
    /// Sample standard deviation of the replicate distances (not floored).
    pub replicate_sd: f64,
    /// (observed − mean) / sd, the sd floored at `SD_FLOOR_REL` × mean
    /// (and above zero), capped at ±[`Z_CAP`].
    pub z: f64,
    /// Empirical p-value: (1 + #replicates ≥ observed) / (1 + n).
    pub p_value: f64,
    /// Largest replicate distance.
    pub replicate_max: f64,
}

/// Standardise `observed` against at least two replicate distances.
pub(crate) fn standardise(observed: f64, replicates: &[f64]) -> Result<Standardised> {
    if replicates.len() < 2 {
        return Err(Error::param(
            "replicates",
            format!("{} replicate distances: need at least 2", replicates.len()),
        ));
    }
    if !observed.is_finite() || replicates.iter().any(|r| !r.is_finite()) {
        return Err(Error::param("replicates", "distances must be finite"));
    }
    let n = replicates.len() as f64;
    let mean = replicates.iter().sum::<f64>() / n;
    let sd = (replicates.iter().map(|r| (r - mean).powi(2)).sum::<f64>() / (n - 1.0)).sqrt();
    // The spread of a handful of replicates is itself uncertain and, for
    // heavy-tailed distances (few particles recycled through a small scene),
    // often underestimated; a floor at half the replicate mean keeps
    // "beyond chance" honest. Distances are ≥ 0, so under the null an
    // observed value beyond (1 + z/2) × mean is rare.
    let floor =
        (SD_FLOOR_REL * mean.abs()).max(1e-9 * (mean.abs() + observed.abs())) + f64::MIN_POSITIVE;
    let z = ((observed - mean) / sd.max(floor)).clamp(-Z_CAP, Z_CAP);
    let above = replicates.iter().filter(|&&r| r >= observed).count() as f64;
    Ok(Standardised {
        observed,
        replicate_mean: mean,
        replicate_sd: sd,
        z,
        p_value: (1.0 + above) / (1.0 + n),
        replicate_max: replicates.iter().cloned().fold(f64::NEG_INFINITY, f64::max),
    })
}

/// One line of the discrepancy table.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DiscrepancyRow {
    /// Name of the signature.
    pub signature: String,
    /// The observed distance against the replicates.
    #[serde(flatten)]
    pub stats: Standardised,
    /// Beyond chance: z above the threshold and beyond every replicate.
    pub disagrees: bool,
}

/// Where measurement and model disagree, worst first.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DiscrepancyTable {
    /// One row per ranked signature, largest z first.
    pub rows: Vec<DiscrepancyRow>,
    /// z above which a row disagrees (if also beyond every replicate).
    pub z_threshold: f64,
}

/// Rank the observed (measured vs reference simulation) distances against
/// the replicate (replicate simulation vs reference simulation) distances.
/// Signatures missing from some replicate are ranked over the replicates
/// that have them; with fewer than two they are left out.
pub(crate) fn rank(
    observed: &[(String, f64)],
    replicates: &[Vec<(String, f64)>],
    z_threshold: f64,
) -> Result<DiscrepancyTable> {
    if !(z_threshold.is_finite() && z_threshold > 0.0) {
        return Err(Error::param(
            "z_threshold",
            format!("{z_threshold} must be > 0"),
        ));
    }
    let mut rows = Vec::new();
    for (name, d) in observed {
        let reps: Vec<f64> = replicates
            .iter()
            .filter_map(|r| r.iter().find(|(n, _)| n == name).map(|(_, v)| *v))
            .collect();
        if reps.len() < 2 {
            continue;
        }
        let stats = standardise(*d, &reps)?;
        rows.push(DiscrepancyRow {
            signature: name.clone(),
            disagrees: stats.z > z_threshold && stats.observed > stats.replicate_max,
            stats,
        });
    }
    rows.sort_by(|a, b| b.stats.z.total_cmp(&a.stats.z));
    Ok(DiscrepancyTable { rows, z_threshold })
}

impl DiscrepancyTable {
    /// z of every row, by signature name.
    pub(crate) fn z_by_row(&self) -> std::collections::BTreeMap<String, f64> {
        self.rows
            .iter()
            .map(|r| (r.signature.clone(), r.stats.z))
            .collect()
    }

    /// Some signature disagrees beyond chance.
    pub(crate) fn any_disagreement(&self) -> bool {
        self.rows.iter().any(|r| r.disagrees)
    }

    /// Total excess over chance: Σ max(z, 0) over the signatures. Near
    /// 0.4 per signature when the model explains the data; the yardstick
    /// for "the gap before and after".
    pub(crate) fn gap(&self) -> f64 {
        self.rows.iter().map(|r| r.stats.z.max(0.0)).sum()
    }

    /// The table as Markdown, one row per signature.
    pub(crate) fn to_markdown(&self) -> String {
        let mut s = String::from(
            "| signature | distance | replicates mean ± sd | z | p | disagrees |\n|---|---|---|---|---|---|\n",
        );
        for r in &self.rows {
            s.push_str(&format!(
                "| {} | {:.4e} | {:.4e} ± {:.2e} | {:.1} | {:.3} | {} |\n",
                r.signature,
                r.stats.observed,
                r.stats.replicate_mean,
                r.stats.replicate_sd,
                r.stats.z,
                r.stats.p_value,
                if r.disagrees { "**yes**" } else { "no" }
            ));
        }
        s
    }
}
