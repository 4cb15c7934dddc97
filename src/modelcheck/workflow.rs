//! The model-check search: name the missing effect, fit it, show the gap
//! shrink, repeat.
//!
//! The engine is independent of any particular simulator: it talks to a
//! [`Simulator`] that offers a catalogue of switchable, parameterised
//! effects and simulates a recording for a list of effect settings and a
//! seed. (`crate::sim` is wired in through this trait.)
//!
//! One round:
//! 1. **Assess** the current model: simulate a reference and `replicates`
//!    more recordings (different seeds); the distance of the held-out
//!    measurement to the reference is standardised against the replicates'
//!    distances ([`super::distance::rank`]). The *gap* is Σ max(z, 0). The
//!    gap's own chance spread comes from treating each replicate in turn as
//!    the measurement (leave-one-out).
//! 2. If no signature disagrees beyond chance, stop: the model is
//!    consistent.
//! 3. **Fit** every candidate effect not yet in the model to the *fit*
//!    measurement with common random numbers (one seed for all parameter
//!    values, so the objective changes with the parameters, not with the
//!    noise): a grid then golden-section refinement for one parameter,
//!    Nelder–Mead for more, in a box (log-scaled where the parameter spans
//!    decades). The objective is Σ d_s / spread_s,
//!    the distances scaled by replicate spreads: first those of the
//!    current model, then (second, narrower stage) those of the model
//!    with the stage-1 fit added, since an effect changes the noise of the
//!    signatures it drives.
//! 4. **Judge on held-out data** ([`judge_candidates`], the whole-gap
//!    rule): assess each fitted candidate against the *held-out*
//!    measurement with fresh replicate seeds per round. Accept the best if
//!    - its gap reduction beats chance: more than `chance_factor` × the
//!      gap's null spread (leave-one-out over the replicates), and
//!    - it beats its best *rival* clearly: a rival is a candidate that
//!      removes mostly the same part of the gap (at least
//!      `RIVAL_OVERLAP` of its per-signature reductions lie where the
//!      winner reduces as much); the lead must exceed one null spread and
//!      `RUNNER_UP_MARGIN` × the gap the rival leaves. A candidate that
//!      removes another part is a second real effect, not a competing
//!      explanation: it does not block the winner and is tried again next
//!      round.
//!
//!    When the lead is not clear, the search stops with "unexplained"
//!    (the round's note names best and rival).
//! 5. After an acceptance with two or more effects found, the found effects
//!    are refitted jointly (see `joint_refit`), kept only if the held-out
//!    gap does not grow.
//!
//! Fit and held-out measurements are different time blocks of the recording
//! (the caller splits), so a candidate cannot win by fitting noise.

use std::collections::{BTreeMap, HashMap};

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use super::distance::{distances, rank, DiscrepancyTable, Z_CAP};
use super::signatures::{latency_drift, SignatureAccumulator, SignatureConfig, Signatures};
use crate::cluster::Particle;
use crate::error::{Error, Result};
use crate::events::EventChunk;
use crate::track::Track;

mod judge;
mod search;

pub(crate) use judge::*;
pub(crate) use search::*;

/// One parameter of an effect, searched in `[lo, hi]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(crate) struct ParamSpec {
    /// Name of the parameter, as the simulator knows it.
    pub name: String,
    /// Lower bound of the search.
    pub lo: f64,
    /// Upper bound of the search.
    pub hi: f64,
    /// Search in log space (the parameter spans decades; needs lo > 0).
    pub log: bool,
}

/// A catalogue entry: a switchable effect of the simulator.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(crate) struct EffectSpec {
    /// Name of the effect, as the simulator knows it.
    pub name: String,
    /// Its parameters and their search ranges.
    pub params: Vec<ParamSpec>,
}

/// An effect switched on with parameter values.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EffectSetting {
    /// Name of the effect.
    pub name: String,
    /// Parameter values by parameter name.
    pub parameters: BTreeMap<String, f64>,
}

/// What the signatures are computed from: events, and optionally the
/// particles and tracks ebptv's own pipeline found in them.
#[derive(Debug, Clone, Default)]
pub(crate) struct Recording {
    /// The events.
    pub events: EventChunk,
    /// The particles found in the events.
    pub particles: Vec<Particle>,
    /// The tracks found, when tracking ran.
    pub tracks: Option<Vec<Track>>,
}

/// A simulator the workflow can drive.
pub(crate) trait Simulator: Sync {
    /// The effects it can switch on.
    fn catalogue(&self) -> Vec<EffectSpec>;
    /// Simulate the base scene with `effects` on, from `seed`, and run the
    /// same processing the measurement went through.
    fn simulate(&self, effects: &[EffectSetting], seed: u64) -> Result<Recording>;
}

/// Options of [`run`].
#[derive(Debug, Clone, Serialize, Deserialize)]
pub(crate) struct WorkflowOptions {
    /// Replicate simulations per assessment (besides the reference).
    pub replicates: usize,
    /// A signature disagrees when z exceeds this (and every replicate).
    pub z_threshold: f64,
    /// Most effects to add.
    pub max_effects: usize,
    /// Objective evaluations per candidate fit (per parameter).
    pub max_evaluations: usize,
    /// Accept only if the gap reduction exceeds this many null spreads.
    pub chance_factor: f64,
    /// Base seed; every simulation seed derives from it.
    pub seed: u64,
}

impl Default for WorkflowOptions {
    fn default() -> Self {
        WorkflowOptions {
            replicates: 5,
            z_threshold: 4.0,
            max_effects: 3,
            max_evaluations: 30,
            chance_factor: 3.0,
            seed: 1,
        }
    }
}

/// An effect added to the model.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FoundEffect {
    /// Name of the effect.
    pub name: String,
    /// Fitted parameter values by parameter name.
    pub parameters: BTreeMap<String, f64>,
    /// Gap (Σ max(z, 0), held-out data) before and after adding it.
    pub gap_before: f64,
    /// Gap after adding it (see `gap_before`).
    pub gap_after: f64,
}

/// One candidate's result in one round.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CandidateResult {
    /// Name of the candidate effect.
    pub name: String,
    /// Fitted parameter values by parameter name.
    pub parameters: BTreeMap<String, f64>,
    /// Fit objective at the optimum (fit data).
    pub objective: f64,
    /// Gap on held-out data with the candidate added.
    pub gap_after: f64,
    /// What the decision uses: the gap before minus after on the current
    /// model's rows ([`RowSet`]; equal to `gap_before − gap_after` unless
    /// the candidate brings or loses a signature row).
    pub improvement: f64,
    /// Objective evaluations the fit used.
    pub evaluations: usize,
    /// z of every signature row on held-out data with the candidate added
    /// (the components of `gap_after`: which part of the gap it removes).
    #[serde(default)]
    pub z_after: BTreeMap<String, f64>,
}

/// One round of the search: the current model's gap and every candidate tried.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Round {
    /// Gap (Σ max(z, 0), held-out data) of the current model.
    pub gap_before: f64,
    /// Chance spread of the gap (leave-one-out over replicates).
    pub gap_null_sd: f64,
    /// Discrepancy table of the current model (held-out data).
    pub table_before: DiscrepancyTable,
    /// Best first.
    pub candidates: Vec<CandidateResult>,
    /// The effect added this round, if any.
    pub accepted: Option<String>,
    /// How the round was decided.
    pub note: String,
}

/// Outcome of the model check.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Verdict {
    /// The starting model already explains the data.
    Consistent,
    /// Effects were added and the model now explains the data.
    Explained,
    /// A discrepancy remains that no candidate reduces beyond chance.
    Unexplained,
}

/// What [`run`] found.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ModelCheckResult {
    /// In the order found.
    pub effects: Vec<FoundEffect>,
    /// Whether the data are explained, and how.
    pub verdict: Verdict,
    /// The final model: starting effects plus the ones found.
    pub model: Vec<EffectSetting>,
    /// Discrepancy table of the final model.
    pub final_table: DiscrepancyTable,
    /// Every round of the search, in order.
    pub rounds: Vec<Round>,
}

/// Signatures of a recording under a fixed configuration.
pub(crate) fn signatures_of(cfg: &SignatureConfig, rec: &Recording) -> Result<Signatures> {
    let mut acc = SignatureAccumulator::new(cfg.clone())?;
    acc.add_events(&rec.events);
    acc.add_particles(&rec.particles);
    if let Some(t) = &rec.tracks {
        acc.add_tracks(t, &rec.particles)?;
    }
    let mut sigs = acc.finish()?;
    // Clock drift: the slope of the burst's latency over the recording
    // (its own pass: it needs the events of each time block together).
    sigs.items.push(latency_drift(cfg, &rec.events)?);
    Ok(sigs)
}

/// Seeds: disjoint streams per purpose so that nothing reuses another's
/// random numbers by accident.
pub(crate) fn seed_for(base: u64, purpose: u64, k: u64) -> u64 {
    // splitmix64 of the triple.
    let mut z = base
        .wrapping_add(purpose.wrapping_mul(0x9E37_79B9_7F4A_7C15))
        .wrapping_add(k.wrapping_mul(0xBF58_476D_1CE4_E5B9));
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// The current model simulated with a reference seed and replicates.
struct Assessment {
    reference: Signatures,
    /// Distances replicate ↔ reference.
    replicate_distances: Vec<Vec<(String, f64)>>,
    /// Gap of each replicate treated as the measurement.
    null_gaps: Vec<f64>,
}

impl Assessment {
    fn new(
        sim: &dyn Simulator,
        cfg: &SignatureConfig,
        model: &[EffectSetting],
        seeds: &[u64],
        z: f64,
    ) -> Result<Self> {
        let sigs: Vec<Signatures> = seeds
            .par_iter()
            .map(|&s| signatures_of(cfg, &sim.simulate(model, s)?))
            .collect::<Result<_>>()?;
        let reference = sigs[0].clone();
        let replicate_distances: Vec<Vec<(String, f64)>> = sigs[1..]
            .iter()
            .map(|s| distances(s, &reference))
            .collect::<Result<_>>()?;
        let mut null_gaps = Vec::new();
        for i in 0..replicate_distances.len() {
            let others: Vec<Vec<(String, f64)>> = replicate_distances
                .iter()
                .enumerate()
                .filter(|(j, _)| *j != i)
                .map(|(_, d)| d.clone())
                .collect();
            null_gaps.push(rank(&replicate_distances[i], &others, z)?.gap());
        }
        Ok(Assessment {
            reference,
            replicate_distances,
            null_gaps,
        })
    }

    fn table(&self, measured: &Signatures, z: f64) -> Result<DiscrepancyTable> {
        rank(
            &distances(measured, &self.reference)?,
            &self.replicate_distances,
            z,
        )
    }

    /// Σ d_s / spread_s: the fit objective. Unlike the gap it keeps
    /// decreasing below chance level, so the optimum is well defined.
    ///
    /// `floors` (from [`Assessment::spread_floors`]) keep a signature whose
    /// replicates all agree exactly (no off-burst events in any simulation
    /// of a clean model) from getting an unbounded weight: such a term
    /// starts at [`Z_CAP`], as the capped z of the gap does, instead of
    /// drowning every other signature and leaving the fit to one scalar.
    fn scaled_sum(&self, d: &[(String, f64)], floors: &BTreeMap<String, f64>) -> f64 {
        d.iter()
            .filter_map(|(name, v)| {
                let (m, sd) = self.replicate_spread(name)?;
                let floor = floors.get(name).copied().unwrap_or(0.0);
                // A relative floor too, so that a signature that happens to
                // agree closely in every replicate is not over-weighted.
                Some(v / sd.max(0.05 * m).max(floor).max(1e-12))
            })
            .sum()
    }

    /// Mean and standard deviation of the replicate distances of `name`.
    fn replicate_spread(&self, name: &str) -> Option<(f64, f64)> {
        let reps: Vec<f64> = self
            .replicate_distances
            .iter()
            .filter_map(|r| r.iter().find(|(n, _)| n == name).map(|x| x.1))
            .collect();
        if reps.len() < 2 {
            return None;
        }
        let m = reps.iter().sum::<f64>() / reps.len() as f64;
        let sd =
            (reps.iter().map(|r| (r - m).powi(2)).sum::<f64>() / (reps.len() - 1) as f64).sqrt();
        Some((m, sd))
    }

    /// Per-signature spread floors for [`Assessment::scaled_sum`]: the
    /// measured distance to this model's reference over [`Z_CAP`].
    fn spread_floors(&self, measured: &Signatures) -> Result<BTreeMap<String, f64>> {
        Ok(distances(measured, &self.reference)?
            .into_iter()
            .map(|(n, d)| (n, d / Z_CAP))
            .collect())
    }

    fn null_sd(&self) -> f64 {
        let n = self.null_gaps.len() as f64;
        if n < 2.0 {
            return 0.0;
        }
        let m = self.null_gaps.iter().sum::<f64>() / n;
        (self.null_gaps.iter().map(|g| (g - m).powi(2)).sum::<f64>() / (n - 1.0)).sqrt()
    }
}

fn validate_catalogue(cat: &[EffectSpec]) -> Result<()> {
    for e in cat {
        if e.params.is_empty() {
            return Err(Error::param(
                format!("effect `{}`", e.name),
                "has no parameter to fit",
            ));
        }
        for p in &e.params {
            let ok = p.lo.is_finite() && p.hi.is_finite() && p.hi > p.lo && (!p.log || p.lo > 0.0);
            if !ok {
                return Err(Error::param(
                    format!("effect `{}` parameter `{}`", e.name, p.name),
                    format!(
                        "range [{}, {}] must be finite, lo < hi (lo > 0 on a log scale)",
                        p.lo, p.hi
                    ),
                ));
            }
        }
    }
    Ok(())
}

/// Unit-cube coordinate ↔ parameter value.
pub(crate) fn to_value(p: &ParamSpec, u: f64) -> f64 {
    let u = u.clamp(0.0, 1.0);
    if p.log {
        (p.lo.ln() + u * (p.hi.ln() - p.lo.ln())).exp()
    } else {
        p.lo + u * (p.hi - p.lo)
    }
}

/// Parameter value → unit-cube coordinate (inverse of [`to_value`],
/// clamped to the box).
fn to_unit(p: &ParamSpec, v: f64) -> f64 {
    let u = if p.log {
        (v.max(p.lo).ln() - p.lo.ln()) / (p.hi.ln() - p.lo.ln())
    } else {
        (v - p.lo) / (p.hi - p.lo)
    };
    if u.is_finite() {
        u.clamp(0.0, 1.0)
    } else {
        0.5
    }
}

/// Unit-cube coordinates of an effect setting (a parameter missing from
/// the setting sits at the box centre).
fn unit_of(spec: &EffectSpec, set: &EffectSetting) -> Vec<f64> {
    spec.params
        .iter()
        .map(|p| set.parameters.get(&p.name).map_or(0.5, |&v| to_unit(p, v)))
        .collect()
}

pub(crate) fn setting(spec: &EffectSpec, u: &[f64]) -> EffectSetting {
    EffectSetting {
        name: spec.name.clone(),
        parameters: spec
            .params
            .iter()
            .zip(u)
            .map(|(p, &x)| (p.name.clone(), to_value(p, x)))
            .collect(),
    }
}

/// Rows of the standard check that the search with a starting model leaves
/// out besides the range rows. `latency_vs_yield` (how a visit's first
/// latency depends on its events) is there to tell a brightness-dependent
/// latency from a standard sensor whose latency shape nobody knows; against
/// a trusted model judged by chance alone its term misleads the fit of the
/// effect's parameters (a hidden intensity latency of the simulator,
/// `src/modelcheck/tests/scene.rs`: exponent fitted 0.77 for 0.55 with it,
/// the row still 5 z off after the fit; 0.554 without).
const STANDARD_CHECK_ONLY_ROWS: &[&str] = &["latency_vs_yield"];

/// `s` without the standard check's range rows
/// ([`super::standard::RANGE_ROWS`]) and [`STANDARD_CHECK_ONLY_ROWS`]:
/// against a starting model judged by chance alone, `burst_repeat_share`
/// would only repeat `min_iei`, whose distribution it summarises, with a
/// replicate spread that is tiny where most pixels repeat. A row absent
/// from the measurement is left out of every distance, table and objective
/// of the search.
fn without_range_rows(mut s: Signatures) -> Signatures {
    s.items.retain(|x| {
        !STANDARD_CHECK_ONLY_ROWS.contains(&x.name.as_str())
            && !super::standard::RANGE_ROWS
                .iter()
                .any(|(n, _)| *n == x.name)
    });
    s
}

/// Fit one candidate effect on top of `model` to the fit measurement.
#[allow(clippy::too_many_arguments)]
fn fit_candidate(
    sim: &dyn Simulator,
    cfg: &SignatureConfig,
    model: &[EffectSetting],
    spec: &EffectSpec,
    measured_fit: &Signatures,
    base: &Assessment,
    max_evaluations: usize,
    crn_seed: u64,
    refine_from: Option<&[f64]>,
) -> Result<(Vec<f64>, f64, usize)> {
    let floors = base.spread_floors(measured_fit)?;
    let mut memo = FitMemo::default();
    let mut objective = |u: &[f64]| -> Result<f64> {
        memo.value(setting(spec, u), |candidate| {
            let mut m = model.to_vec();
            m.push(candidate);
            let rec = sim.simulate(&m, crn_seed)?;
            if rec.events.is_empty() {
                // Parameters that silence the sensor (a rate limit of less
                // than one event per window) are as far from any measurement
                // as can be.
                return Ok(f64::INFINITY);
            }
            let s = signatures_of(cfg, &rec)?;
            // Distances to the candidate's simulation, judged by the current
            // model's replicate spreads.
            let d = distances(measured_fit, &s)?;
            Ok(base.scaled_sum(&d, &floors))
        })
    };
    if spec.params.len() == 1 {
        let (lo, hi) = match refine_from {
            Some(u) => (u[0] - REFINE_HALF_WIDTH, u[0] + REFINE_HALF_WIDTH),
            None => (0.0, 1.0),
        };
        let (u, v, e) = minimise_1d_in(&mut |x| objective(&[x]), lo, hi, max_evaluations)?;
        Ok((vec![u], v, e))
    } else {
        let (start, step) = match refine_from {
            Some(u) => (u.to_vec(), REFINE_HALF_WIDTH),
            None => (vec![0.5; spec.params.len()], 0.3),
        };
        // Nelder–Mead needs more steps per dimension than a line search.
        nelder_mead(
            &mut objective,
            &start,
            step,
            max_evaluations * spec.params.len(),
        )
    }
}

/// Joint refit of the effects found so far, after a new one was accepted:
/// each in turn is refitted (second-stage search around its current
/// value, common random numbers, the others held) with the current model's
/// replicate spreads as weights; two sweeps. An effect accepted early may
/// have absorbed part of a later one's signature (latency jitter widening
/// to mimic an intensity-dependent latency spread): once the later effect
/// is in the model, the earlier one's parameters move back.
///
/// Returns the refitted model, its held-out assessment and gap, or `None`
/// when no found effect is in the catalogue (nothing to refit).
#[allow(clippy::too_many_arguments)]
fn joint_refit(
    sim: &dyn Simulator,
    cfg: &SignatureConfig,
    catalogue: &[EffectSpec],
    model: &[EffectSetting],
    effects: &[FoundEffect],
    m_fit: &Signatures,
    m_hold: &Signatures,
    current: &Assessment,
    opts: &WorkflowOptions,
    round_no: u64,
) -> Result<Option<(Vec<EffectSetting>, Assessment, f64)>> {
    let mut model = model.to_vec();
    let crn = seed_for(opts.seed, 5000 + round_no, 0);
    let mut refitted = false;
    for _sweep in 0..JOINT_REFIT_SWEEPS {
        for e in effects {
            let Some(spec) = catalogue.iter().find(|c| c.name == e.name) else {
                continue;
            };
            let Some(pos) = model.iter().position(|m| m.name == e.name) else {
                continue;
            };
            let u0 = unit_of(spec, &model[pos]);
            let mut others = model.clone();
            others.remove(pos);
            let (u, _, _) = fit_candidate(
                sim,
                cfg,
                &others,
                spec,
                m_fit,
                current,
                opts.max_evaluations,
                crn,
                Some(&u0),
            )?;
            model[pos] = setting(spec, &u);
            refitted = true;
        }
    }
    if !refitted {
        return Ok(None);
    }
    let seeds: Vec<u64> = (0..opts.replicates as u64 + 1)
        .map(|k| seed_for(opts.seed, 6000 + round_no, k))
        .collect();
    let a = Assessment::new(sim, cfg, &model, &seeds, opts.z_threshold)?;
    let gap = a.table(m_hold, opts.z_threshold)?.gap();
    Ok(Some((model, a, gap)))
}

/// See [`rivals`].
pub(crate) const RIVAL_OVERLAP: f64 = 0.5;

/// "Clearly beats the runner-up": the winner's held-out gap must be below
/// (1 − this) × the best rival's (and the lead at least one null spread),
/// when that rival removes part of the gap at all.
pub(crate) const RUNNER_UP_MARGIN: f64 = 0.25;

/// Sweeps over the found effects in [`joint_refit`].
const JOINT_REFIT_SWEEPS: usize = 2;

/// The most replicates (simulations per model judged) a search takes.
pub(crate) const MAX_REPLICATES: usize = 100;
/// The most objective evaluations per parameter of a candidate fit.
pub(crate) const MAX_EVALUATIONS: usize = 1000;

/// Refuses (at `check::check_recording`, before the recording is read) a
/// search budget that would run for days (every replicate and
/// evaluation is a full simulation) or hold thousands of signature sets.
pub(crate) fn check_budget(replicates: usize, evaluations: usize) -> Result<()> {
    if replicates > MAX_REPLICATES {
        return Err(Error::param(
            "replicates",
            format!(
                "{replicates}: at most {MAX_REPLICATES} (each is one simulation per model judged)"
            ),
        ));
    }
    if evaluations > MAX_EVALUATIONS {
        return Err(Error::param(
            "evaluations",
            format!(
                "{evaluations}: at most {MAX_EVALUATIONS} per parameter (each is one simulation)"
            ),
        ));
    }
    Ok(())
}

/// Run the search. `measured_fit` and `measured_holdout` are two disjoint
/// time blocks of the measurement, each as long as one simulated recording.
pub(crate) fn run(
    sim: &dyn Simulator,
    cfg: &SignatureConfig,
    measured_fit: &Recording,
    measured_holdout: &Recording,
    start_model: &[EffectSetting],
    opts: &WorkflowOptions,
) -> Result<ModelCheckResult> {
    if opts.replicates < 3 {
        return Err(Error::param(
            "replicates",
            format!("{}: need at least 3 for a chance estimate", opts.replicates),
        ));
    }
    let catalogue = sim.catalogue();
    validate_catalogue(&catalogue)?;
    let m_fit = without_range_rows(signatures_of(cfg, measured_fit)?);
    let m_hold = without_range_rows(signatures_of(cfg, measured_holdout)?);
    let z = opts.z_threshold;

    let mut model = start_model.to_vec();
    let mut effects = Vec::new();
    let mut rounds = Vec::new();
    let mut round_no = 0u64;
    let seeds = |purpose: u64, n: usize| -> Vec<u64> {
        (0..n as u64)
            .map(|k| seed_for(opts.seed, purpose, k))
            .collect()
    };
    let start_seeds = seeds(1000, opts.replicates + 1);
    let mut current = Assessment::new(sim, cfg, &model, &start_seeds, z)?;
    loop {
        let table = current.table(&m_hold, z)?;
        let gap_before = table.gap();
        let null_sd = current.null_sd();
        if !table.any_disagreement() {
            let verdict = if effects.is_empty() {
                Verdict::Consistent
            } else {
                Verdict::Explained
            };
            return Ok(ModelCheckResult {
                effects,
                verdict,
                model,
                final_table: table,
                rounds,
            });
        }
        let remaining: Vec<&EffectSpec> = catalogue
            .iter()
            .filter(|c| !model.iter().any(|m| m.name == c.name))
            .collect();
        if effects.len() >= opts.max_effects || remaining.is_empty() {
            rounds.push(Round {
                gap_before,
                gap_null_sd: null_sd,
                table_before: table.clone(),
                candidates: vec![],
                accepted: None,
                note: "no candidate left to try".into(),
            });
            return Ok(ModelCheckResult {
                effects,
                verdict: Verdict::Unexplained,
                model,
                final_table: table,
                rounds,
            });
        }
        round_no += 1;
        let crn = seed_for(opts.seed, 2000 + round_no, 0);
        let hold_seeds = seeds(3000 + round_no, opts.replicates + 1);
        let scale_seeds = seeds(4000 + round_no, opts.replicates + 1);
        // Candidates in parallel; each fit is sequential (its evaluations
        // share the common random numbers).
        let fitted: Vec<(CandidateResult, Assessment, EffectSetting, DiscrepancyTable)> = remaining
            .par_iter()
            .map(|spec| {
                // Stage 1: weights from the current model's replicate spreads.
                let (u1, _, e1) = fit_candidate(
                    sim,
                    cfg,
                    &model,
                    spec,
                    &m_fit,
                    &current,
                    opts.max_evaluations,
                    crn,
                    None,
                )?;
                // Stage 2: the effect changes the noise of the signatures it
                // drives (hot pixels make the off-burst rate noisy), so take
                // the weights from replicates of the stage-1 model and refine.
                let mut m1 = model.clone();
                m1.push(setting(spec, &u1));
                let a1 = Assessment::new(sim, cfg, &m1, &scale_seeds, z)?;
                let (u, objective, e2) = fit_candidate(
                    sim,
                    cfg,
                    &model,
                    spec,
                    &m_fit,
                    &a1,
                    opts.max_evaluations,
                    crn,
                    Some(&u1),
                )?;
                let evaluations = e1 + e2;
                let set = setting(spec, &u);
                let mut m = model.clone();
                m.push(set.clone());
                let a = Assessment::new(sim, cfg, &m, &hold_seeds, z)?;
                let table_after = a.table(&m_hold, z)?;
                let gap_after = table_after.gap();
                Ok((
                    CandidateResult {
                        name: spec.name.clone(),
                        parameters: set.parameters.clone(),
                        objective,
                        gap_after,
                        improvement: gap_before - gap_after,
                        evaluations,
                        z_after: table_after.z_by_row(),
                    },
                    a,
                    set,
                    table_after,
                ))
            })
            .collect::<Result<_>>()?;
        let mut fitted = fitted;
        let names: Vec<&str> = fitted.iter().map(|f| f.0.name.as_str()).collect();
        let tables: Vec<&DiscrepancyTable> = fitted.iter().map(|f| &f.3).collect();
        let j = judge_candidates(&table, &names, &tables, null_sd, opts.chance_factor);
        let candidates: Vec<CandidateResult> = j
            .order
            .iter()
            .map(|&i| CandidateResult {
                improvement: j.improvement[i],
                ..fitted[i].0.clone()
            })
            .collect();
        let chance = opts.chance_factor * null_sd;
        let best_i = j.best();
        let rival_name = j
            .rival
            .map_or("", |r| fitted[r].0.name.as_str())
            .to_string();
        let judged = format!(
            "best `{}` improves the gap by {:.2} (chance {:.2}); rival `{}` by {:.2}: \
             lead {:.2} (needs {:.2}), contested {:.2}",
            fitted[best_i].0.name,
            j.improvement[best_i],
            chance,
            rival_name,
            j.rival.map_or(0.0, |r| j.improvement[r]),
            j.lead,
            j.needed,
            j.contested,
        );
        let mut note = judged.clone();
        if j.clear() {
            note.push_str("; clear");
            let (found, assessment, set, _) = fitted.swap_remove(best_i);
            effects.push(FoundEffect {
                name: set.name.clone(),
                parameters: set.parameters.clone(),
                gap_before,
                gap_after: found.gap_after,
            });
            model.push(set);
            current = assessment;
            rounds.push(Round {
                gap_before,
                gap_null_sd: null_sd,
                table_before: table,
                candidates,
                accepted: Some(found.name),
                note,
            });
            if effects.len() >= 2 {
                let refit = joint_refit(
                    sim, cfg, &catalogue, &model, &effects, &m_fit, &m_hold, &current, opts,
                    round_no,
                )?;
                if let Some((new_model, new_assessment, gap)) = refit {
                    let gap_now = current.table(&m_hold, z)?.gap();
                    let round = rounds.last_mut().expect("pushed above");
                    round.note.push_str(&format!(
                        "; joint refit of the {} effects found: held-out gap {:.2} -> {:.2}",
                        effects.len(),
                        gap_now,
                        gap
                    ));
                    // Keep the refit only when the held-out data agree.
                    if gap <= gap_now {
                        for e in effects.iter_mut() {
                            if let Some(m) = new_model.iter().find(|m| m.name == e.name) {
                                e.parameters = m.parameters.clone();
                            }
                        }
                        if let Some(last) = effects.last_mut() {
                            last.gap_after = gap;
                        }
                        model = new_model;
                        current = new_assessment;
                    } else {
                        round.note.push_str(" (kept the greedy fit)");
                    }
                }
            }
        } else {
            let note = if !j.beats_chance {
                format!("{note}; not beyond chance")
            } else {
                format!("{note}; no clear winner")
            };
            rounds.push(Round {
                gap_before,
                gap_null_sd: null_sd,
                table_before: table.clone(),
                candidates,
                accepted: None,
                note,
            });
            return Ok(ModelCheckResult {
                effects,
                verdict: Verdict::Unexplained,
                model,
                final_table: table,
                rounds,
            });
        }
    }
}
