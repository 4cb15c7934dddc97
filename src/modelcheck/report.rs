//! Outputs of a model check: `model_check.json`, the fitted scenario
//! (`model.toml`, accepted by `ebptv simulate --config`), `report.md` and
//! one PNG per histogram signature (measured vs starting model vs fitted
//! model, held-out data).

use std::path::Path;

use serde::Serialize;

use super::distance::DiscrepancyTable;
use super::scene::SceneSimulator;
use super::signatures::{SignatureConfig, Signatures};
use super::workflow::{
    signatures_of, EffectSetting, FoundEffect, ModelCheckResult, Recording, Round, Simulator,
    Verdict,
};
use crate::error::{Error, Result};
use crate::io::atomic::AtomicFile;
use crate::plot::{histogram_plot, HistogramPlot};

/// The JSON document (`model_check.json`).
#[derive(Debug, Serialize)]
pub(crate) struct ModelCheckJson<'a> {
    /// In the order found; empty when the model already explains the data.
    pub effects: &'a [FoundEffect],
    pub verdict: Verdict,
    /// Effects of the starting model (fixed, not searched).
    pub start_model: &'a [EffectSetting],
    /// The final model's effects (start + found).
    pub model: &'a [EffectSetting],
    /// Remaining discrepancies, worst first.
    pub discrepancies: &'a DiscrepancyTable,
    pub rounds: &'a [Round],
    /// Honest notes on how the baseline was made.
    pub notes: &'a [String],
}

/// Histogram signatures shown as figures.
const FIGURES: [(&str, &str, bool); 6] = [
    ("latency", "folded latency (us)", false),
    ("pixel_count", "events per pixel (bin)", true),
    (
        "split_half_min",
        "min(even, odd) events per pixel (bin)",
        true,
    ),
    ("min_iei", "min inter-event interval per pixel (bin)", true),
    ("group_size", "(row, timestamp) group size (bin)", true),
    ("events_per_cluster", "events per cluster", true),
];

/// Write all outputs into `dir` (created if missing).
#[allow(clippy::too_many_arguments)]
pub(crate) fn write_outputs(
    dir: &Path,
    sim: &SceneSimulator,
    cfg: &SignatureConfig,
    measured_holdout: &Recording,
    start_model: &[EffectSetting],
    result: &ModelCheckResult,
    notes: &[String],
    seed: u64,
) -> Result<()> {
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let doc = ModelCheckJson {
        effects: &result.effects,
        verdict: result.verdict,
        start_model,
        model: &result.model,
        discrepancies: &result.final_table,
        rounds: &result.rounds,
        notes,
    };
    let json = serde_json::to_vec_pretty(&doc)
        .map_err(|e| Error::analysis(format!("cannot serialise model_check.json: {e}")))?;
    AtomicFile::write_all_to(dir.join("model_check.json"), &json)?;

    let fitted = sim.scenario_with(&result.model)?;
    AtomicFile::write_all_to(dir.join("model.toml"), fitted.to_toml_string()?.as_bytes())?;

    // Figures: one simulation of each model with a seed of its own.
    let measured = signatures_of(cfg, measured_holdout)?;
    let before = signatures_of(cfg, &sim.simulate(start_model, seed)?)?;
    let after = signatures_of(cfg, &sim.simulate(&result.model, seed)?)?;
    let mut figures = Vec::new();
    for (name, label, log_y) in FIGURES {
        let (Some(m), Some(b), Some(a)) = (
            measured.histogram(name),
            before.histogram(name),
            after.histogram(name),
        ) else {
            continue;
        };
        // Show only the populated range of the bins, as fractions.
        let used = |h: &super::signatures::Histogram| {
            h.counts
                .iter()
                .rposition(|c| *c > 0.0)
                .map(|k| k + 1)
                .unwrap_or(0)
        };
        let n = used(m).max(used(b)).max(used(a)).max(2);
        let frac = |h: &super::signatures::Histogram| -> Vec<f64> {
            let t = h.total().max(1.0);
            h.counts[..n].iter().map(|c| c / t).collect()
        };
        let edges: Vec<f64> = if m.scale == super::signatures::BinScale::Index {
            (0..=n).map(|k| k as f64).collect()
        } else {
            m.edges[..=n].to_vec()
        };
        let (fm, fb, fa) = (frac(m), frac(b), frac(a));
        // Log axes cannot show empty bins; lift zeros to a floor below the
        // smallest non-zero fraction.
        let lift = |v: &[f64]| -> Vec<f64> {
            if !log_y {
                return v.to_vec();
            }
            v.iter().map(|x| x.max(1e-7)).collect()
        };
        let (fm, fb, fa) = (lift(&fm), lift(&fb), lift(&fa));
        let file = format!("signature_{name}.png");
        histogram_plot(
            &dir.join(&file),
            &HistogramPlot {
                title: &format!("{name}: measured (held-out) vs models"),
                x_label: label,
                y_label: "fraction",
                edges: &edges,
                histograms: vec![
                    ("measured", &fm),
                    ("start model", &fb),
                    ("fitted model", &fa),
                ],
                log_y,
            },
        )?;
        figures.push(file);
    }

    let md = markdown(
        result,
        start_model,
        notes,
        &figures,
        &measured,
        &before,
        &after,
    );
    AtomicFile::write_all_to(dir.join("report.md"), md.as_bytes())?;
    Ok(())
}

fn fmt_params(p: &std::collections::BTreeMap<String, f64>) -> String {
    p.iter()
        .map(|(k, v)| format!("{k} = {v:.4}"))
        .collect::<Vec<_>>()
        .join(", ")
}

fn markdown(
    r: &ModelCheckResult,
    start: &[EffectSetting],
    notes: &[String],
    figures: &[String],
    measured: &Signatures,
    before: &Signatures,
    after: &Signatures,
) -> String {
    let mut s = String::from("# Model check\n\n");
    s.push_str(&format!(
        "**Verdict: {}**\n\n",
        match r.verdict {
            Verdict::Consistent => "consistent — the starting model explains the data",
            Verdict::Explained => "explained — the effects below close the gap",
            Verdict::Unexplained =>
                "unexplained — a discrepancy remains that no candidate reduces beyond chance",
        }
    ));
    for n in notes {
        s.push_str(&format!("- {n}\n"));
    }
    s.push_str("\n## Starting model\n\n");
    if start.is_empty() {
        s.push_str("Ideal sensor (no effect switched on).\n");
    }
    for e in start {
        s.push_str(&format!("- `{}`: {}\n", e.name, fmt_params(&e.parameters)));
    }
    s.push_str("\n## Effects found (in order)\n\n");
    if r.effects.is_empty() {
        s.push_str("None.\n");
    } else {
        s.push_str("| effect | parameters | gap before | gap after |\n|---|---|---|---|\n");
        for e in &r.effects {
            s.push_str(&format!(
                "| `{}` | {} | {:.1} | {:.1} |\n",
                e.name,
                fmt_params(&e.parameters),
                e.gap_before,
                e.gap_after
            ));
        }
    }
    s.push_str(
        "\nThe gap sums the standardised disagreement of the signature rows on held-out data. \
         With a starting model (`--model`) it is Σ max(z, 0), z against simulation-vs-simulation \
         replicates; against the standard sensor (no `--model`) it is Σ max(z − 1, 0), z against \
         the replicates and the range a well-behaved sensor covers, over the rows that are not a \
         structural mismatch (listed in each round's note).\n",
    );
    for (i, round) in r.rounds.iter().enumerate() {
        s.push_str(&format!(
            "\n## Round {} — gap {:.1} (chance spread {:.2})\n\n{}\n\n",
            i + 1,
            round.gap_before,
            round.gap_null_sd,
            round.note
        ));
        if !round.candidates.is_empty() {
            s.push_str("| candidate | parameters | gap after | improvement |\n|---|---|---|---|\n");
            for c in &round.candidates {
                s.push_str(&format!(
                    "| `{}` | {} | {:.1} | {:.1} |\n",
                    c.name,
                    fmt_params(&c.parameters),
                    c.gap_after,
                    c.improvement
                ));
            }
        }
        s.push_str("\nDiscrepancies before this round:\n\n");
        s.push_str(&round.table_before.to_markdown());
    }
    s.push_str("\n## Remaining discrepancies\n\n");
    s.push_str(&r.final_table.to_markdown());
    s.push_str("\n## Scalar signatures (held-out measurement, start model, fitted model)\n\n");
    s.push_str("| signature | measured | start | fitted |\n|---|---|---|---|\n");
    for item in &measured.items {
        if let Some(m) = measured.scalar(&item.name) {
            s.push_str(&format!(
                "| {} | {:.4e} | {:.4e} | {:.4e} |\n",
                item.name,
                m,
                before.scalar(&item.name).unwrap_or(f64::NAN),
                after.scalar(&item.name).unwrap_or(f64::NAN)
            ));
        }
    }
    s.push_str("\n## Signatures before and after\n\n");
    for f in figures {
        s.push_str(&format!("![{f}]({f})\n\n"));
    }
    s
}
