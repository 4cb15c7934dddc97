//! Judging the fitted candidates of a round: the ranking, rivals that
//! explain the same rows, and [`judge_candidates`] (the whole-gap rule).

use super::*;

/// The candidates from most to least of the gap removed (ties by name),
/// and the best one's closest rival: the next best that removes part of
/// the same rows.
pub(super) fn ranking(
    improvement: &[f64],
    red: &[Vec<f64>],
    names: &[&str],
) -> (Vec<usize>, Option<usize>) {
    let mut order: Vec<usize> = (0..improvement.len()).collect();
    order.sort_by(|&a, &b| {
        improvement[b]
            .total_cmp(&improvement[a])
            .then_with(|| names[a].cmp(names[b]))
    });
    let best = order[0];
    let rival = order[1..]
        .iter()
        .copied()
        .find(|&o| rivals(&red[best], &red[o]));
    (order, rival)
}

/// Is `ro` (a candidate's per-row reductions) a rival of `rb` (the best
/// one's): does at least [`RIVAL_OVERLAP`] of what it removes from the
/// gap (summed over the rows it improves) lie in rows the best improves
/// as much? Complementary candidates (two real effects seen by different
/// signatures) are not rivals.
pub(super) fn rivals(rb: &[f64], ro: &[f64]) -> bool {
    let total: f64 = ro.iter().map(|r| r.max(0.0)).sum();
    if total <= 0.0 {
        // It removes nothing: as a runner-up it is harmless either way,
        // and counting it keeps the chance check of the lead.
        return true;
    }
    shared_reduction(rb, ro) >= RIVAL_OVERLAP * total
}

/// Σ min(rb⁺, ro⁺): the part of the gap both remove (the contested part).
pub(super) fn shared_reduction(rb: &[f64], ro: &[f64]) -> f64 {
    rb.iter()
        .zip(ro)
        .map(|(b, o)| b.max(0.0).min(o.max(0.0)))
        .sum()
}

/// How the candidates of one round compare (see [`judge_candidates`]).
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Judgement {
    /// Candidate indices, best first (by `improvement`, ties by name).
    pub order: Vec<usize>,
    /// Improvement of each candidate (input order): held-out gap before
    /// minus after.
    pub improvement: Vec<f64>,
    /// The best candidate's closest rival, if any.
    pub rival: Option<usize>,
    /// The best's improvement exceeds `chance_factor` null spreads.
    pub beats_chance: bool,
    /// The best's lead over its rival.
    pub lead: f64,
    /// The lead needed over the rival.
    pub needed: f64,
    /// The part of the gap best and rival both remove.
    pub contested: f64,
}

impl Judgement {
    /// Index of the best candidate (`order[0]`).
    pub(crate) fn best(&self) -> usize {
        self.order[0]
    }
    /// The best clearly beats chance and its rival.
    pub(crate) fn clear(&self) -> bool {
        self.beats_chance && self.lead > self.needed
    }
}

/// Rank a round's candidates and judge the best against chance and its
/// rival (the whole-gap rule): improvement = held-out gap before − gap
/// after (each table on its own rows); a rival's overlap counted on the
/// rows of `before` (a row missing after counts as unchanged); clear when
/// the improvement exceeds `chance_factor` null spreads and the lead over
/// the rival exceeds one null spread and [`RUNNER_UP_MARGIN`] × the gap
/// the rival leaves (when the rival removes anything).
pub(crate) fn judge_candidates(
    before: &DiscrepancyTable,
    names: &[&str],
    after: &[&DiscrepancyTable],
    null_sd: f64,
    chance_factor: f64,
) -> Judgement {
    let gap_before = before.gap();
    let red: Vec<Vec<f64>> = after
        .iter()
        .map(|a| {
            before
                .rows
                .iter()
                .map(|r| {
                    let b = r.stats.z.max(0.0);
                    let x = a
                        .rows
                        .iter()
                        .find(|x| x.signature == r.signature)
                        .map_or(b, |x| x.stats.z.max(0.0));
                    b - x
                })
                .collect()
        })
        .collect();
    let improvement: Vec<f64> = after.iter().map(|a| gap_before - a.gap()).collect();
    let (order, rival) = ranking(&improvement, &red, names);
    let best = order[0];
    let chance = chance_factor * null_sd;
    let beats_chance = improvement[best] > chance && improvement[best] > 0.0;
    let runner_up = rival.map_or(0.0, |r| improvement[r]);
    let lead = improvement[best] - runner_up.max(0.0);
    let needed = if runner_up > 0.0 {
        null_sd.max(RUNNER_UP_MARGIN * (gap_before - runner_up))
    } else {
        null_sd
    };
    Judgement {
        order,
        improvement,
        rival,
        beats_chance,
        lead,
        needed,
        contested: rival.map_or(0.0, |r| shared_reduction(&red[best], &red[r])),
    }
}
