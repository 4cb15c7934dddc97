//! The model check's decision rule on synthetic discrepancy tables (no
//! simulation): which candidate is named, when a lead is "clear", how rows
//! a model cannot produce are counted, and explaining away.

use ebptv::modelcheck::distance::{DiscrepancyRow, DiscrepancyTable, Standardised, Z_CAP};
use ebptv::modelcheck::workflow::{explain_away, judge_candidates, PairOutcome, RowSet};

/// A table with the given (signature, z) rows.
fn table(rows: &[(&str, f64)]) -> DiscrepancyTable {
    DiscrepancyTable {
        rows: rows
            .iter()
            .map(|&(name, z)| DiscrepancyRow {
                signature: name.to_string(),
                stats: Standardised {
                    observed: z,
                    replicate_mean: 0.0,
                    replicate_sd: 1.0,
                    z,
                    p_value: if z > 4.0 { 0.1 } else { 0.5 },
                    replicate_max: 1.0,
                },
                disagrees: z > 4.0,
            })
            .collect(),
        z_threshold: 4.0,
    }
}

/// Eight far-off components (as with seven hidden effects plus a baseline
/// deficiency), each a signature row.
const ROWS: [&str; 8] = ["a", "b", "c", "d", "e", "f", "g", "h"];

fn far_off() -> Vec<(&'static str, f64)> {
    ROWS.iter().map(|&n| (n, Z_CAP)).collect()
}

/// `far_off` with some rows replaced.
fn with(rows: &[(&'static str, f64)]) -> DiscrepancyTable {
    let mut t = far_off();
    for &(n, z) in rows {
        t.iter_mut().find(|r| r.0 == n).unwrap().1 = z;
    }
    table(&t)
}

/// Many effects at once: the best candidate removes two components, its
/// rival one of the same two and less of it. On the disputed rows (a, b)
/// the best leaves 200, the rival 1300: clear. The whole-gap rule
/// (`judge_candidates_whole_gap`, the default without the paired judgement) asks for a lead of 0.25 × (8000 − 700) = 1825 (a quarter of all the
/// rival leaves, other effects' rows included) and named nothing.
#[test]
fn a_clear_winner_among_many_effects_is_named() {
    let before = table(&far_off());
    let best = with(&[("a", 100.0), ("b", 100.0)]); // removes 1800
    let rival = with(&[("a", 300.0)]); // removes 700, all in `a`
    let other = with(&[("g", 500.0)]); // another effect's component
    let noop = with(&[]);
    let names = ["rival", "other", "best", "noop"];
    let j = judge_candidates(&before, &names, &[&rival, &other, &best, &noop], 2.0, 3.0);
    assert_eq!(names[j.best()], "best");
    assert_eq!(j.rival.map(|r| names[r]), Some("rival"));
    assert!((j.improvement[2] - 1800.0).abs() < 1e-9);
    assert!((j.contested - 700.0).abs() < 1e-9, "{j:?}");
    assert_eq!((j.left_best, j.left_rival), (200.0, 1300.0));
    assert!(j.clear(), "{j:?}");
    // The old margin on the whole gap would not have been met.
    assert!(j.lead < 0.25 * (8.0 * Z_CAP - 700.0));
}

/// Two explanations of the same component that remove nearly the same
/// amount: no clear winner, however large the gap.
#[test]
fn a_near_tie_on_one_component_is_not_clear() {
    let before = table(&far_off());
    let x = with(&[("a", 50.0)]);
    let y = with(&[("a", 60.0)]);
    let j = judge_candidates(&before, &["x", "y"], &[&x, &y], 2.0, 3.0);
    assert!(j.beats_chance);
    assert_eq!(j.rival, Some(1 - j.best()));
    assert!(!j.clear(), "{j:?}");
    // One effect explains nearly all: leaving 9 where the rival leaves 41
    // is clear (the CLI test's hidden jitter vs intensity latency).
    let small = table(&[("a", 1000.0), ("b", 1000.0)]);
    let jitter = table(&[("a", 5.0), ("b", 4.0)]);
    let intensity = table(&[("a", 21.0), ("b", 20.0)]);
    let j = judge_candidates(&small, &["j", "i"], &[&jitter, &intensity], 2.0, 3.0);
    assert!(j.clear(), "{j:?}");
    // Candidates that remove different components are not rivals: each is
    // a real effect of its own, named one per round.
    let z = with(&[("c", 40.0)]);
    let j = judge_candidates(&before, &["x", "z"], &[&x, &z], 2.0, 3.0);
    assert_eq!(j.rival, None);
    assert!(j.clear(), "{j:?}");
}

/// Nothing beyond chance: not named, whatever the lead.
#[test]
fn an_improvement_within_chance_is_not_named() {
    let before = table(&[("a", 30.0), ("b", 2.0)]);
    let x = table(&[("a", 25.0), ("b", 2.0)]);
    let j = judge_candidates(&before, &["x"], &[&x], 2.0, 3.0);
    assert!(!j.beats_chance && !j.clear(), "{j:?}");
}

/// Candidates are compared on the current model's rows. A row the
/// current model cannot produce (no OFF events: no OFF latency histogram)
/// neither rewards nor penalises the candidate that brings it (it is
/// judged from the next round on); a row a candidate loses counts at the
/// cap (it cannot make what was measured).
#[test]
fn candidates_are_compared_on_the_current_models_rows() {
    let before = table(&[("a", 500.0), ("b", 20.0)]);
    let brings_row = table(&[("a", 500.0), ("b", 20.0), ("off_latency", 80.0)]);
    let matches_a = table(&[("a", 10.0), ("b", 20.0)]);
    let loses_b = table(&[("a", 0.0)]);
    let rows = RowSet::of(&before);
    assert_eq!(rows.names, vec!["a", "b"]);
    assert_eq!(rows.gap(&brings_row), 520.0);
    assert_eq!(rows.gap(&loses_b), Z_CAP);
    let j = judge_candidates(
        &before,
        &["brings_row", "matches_a", "loses_b"],
        &[&brings_row, &matches_a, &loses_b],
        1.0,
        3.0,
    );
    assert_eq!(j.improvement, vec![0.0, 490.0, 520.0 - Z_CAP]);
    assert_eq!(j.best(), 1);
    // Negative z is no gap.
    let neg = table(&[("a", -3.0)]);
    assert_eq!(RowSet::of(&neg).gap(&neg), 0.0);
}

#[test]
fn explaining_away() {
    let chance = 10.0;
    // (gap A alone, B alone, A then B fitted on top, B then A on top)
    // Each adds to the other: two real effects.
    assert_eq!(
        explain_away(600.0, 700.0, 400.0, 420.0, chance),
        PairOutcome::Both
    );
    // B adds nothing once A is in, A adds to B: A explains B's part.
    assert_eq!(
        explain_away(400.0, 700.0, 395.0, 398.0, chance),
        PairOutcome::FirstOnly
    );
    assert_eq!(
        explain_away(700.0, 400.0, 398.0, 395.0, chance),
        PairOutcome::SecondOnly
    );
    // Interchangeable: neither adds to the other.
    assert_eq!(
        explain_away(402.0, 405.0, 398.0, 400.0, chance),
        PairOutcome::Ambiguous
    );
}
