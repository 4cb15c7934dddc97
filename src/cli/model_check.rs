//! `ebptv model-check`: measured recording vs simulator → the missing
//! effects, fitted, with the gap before and after.

use std::path::PathBuf;

use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};

use ebptv::modelcheck::check::{check_recording, ModelCheckOptions};

fn defaults() -> ModelCheckOptions {
    ModelCheckOptions::default()
}

#[derive(Args, Debug)]
pub struct ModelCheckArgs {
    /// The measured recording (any supported event format).
    pub measured: PathBuf,
    /// Starting model (scenario TOML, as `ebptv simulate --config` takes),
    /// for a recording made by a model you trust. Without it (the usual
    /// case) the baseline is a standard sensor calibrated to the
    /// measurement: pulse timing from the trigger channel (or, without one,
    /// from the events), the flow from
    /// ebptv's own tracks (written as `flow_baseline.csv`), seeding density,
    /// light energy and median latency fitted; latency spread, noise and
    /// image at the seed paper's standard values; an effect is named only
    /// when it halves the disagreement on held-out data and clearly beats
    /// its rivals (docs/readme/modelcheck.md).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Output directory (created if missing).
    #[arg(long)]
    pub out: PathBuf,
    /// Base seed of every simulation.
    #[arg(long, default_value_t = defaults().seed)]
    pub seed: u64,
    /// Replicate simulations per assessment.
    #[arg(long, default_value_t = defaults().replicates)]
    pub replicates: usize,
    /// Objective evaluations per parameter and fit stage.
    #[arg(long, default_value_t = defaults().evaluations)]
    pub evaluations: usize,
    /// Most effects to add.
    #[arg(long, default_value_t = defaults().max_effects)]
    pub max_effects: usize,
    /// Pulses per fit and per held-out block (and per simulated
    /// recording): at most half the recording each. The search's cost
    /// grows with it; 100 pulses of a 640x360 sensor hold ~0.4 M events.
    #[arg(long, default_value_t = defaults().block_pulses)]
    pub block_pulses: u64,
    /// Pulse frequency (Hz) of a recording without a trigger channel: the
    /// pulse train is found from the events around it (without it, over
    /// 500–50 000 Hz, as `ebptv track` does), and latencies count from the
    /// bursts' leading edge instead of the laser's trigger.
    #[arg(long)]
    pub pulse_hz: Option<f64>,
    /// Find the pulse train from the events even when the recording has
    /// trigger events.
    #[arg(long)]
    pub ignore_triggers: bool,
}

pub fn run(a: ModelCheckArgs) -> anyhow::Result<()> {
    let opts = ModelCheckOptions {
        model: a.model.clone(),
        seed: a.seed,
        replicates: a.replicates,
        evaluations: a.evaluations,
        max_effects: a.max_effects,
        block_pulses: a.block_pulses,
        pulse_hz: a.pulse_hz,
        ignore_triggers: a.ignore_triggers,
    };
    let bar = ProgressBar::new_spinner();
    bar.set_style(ProgressStyle::with_template("{spinner} {elapsed} {msg}")?);
    bar.set_message("checking the model (simulating)…");
    bar.enable_steady_tick(std::time::Duration::from_millis(200));
    let run = check_recording(&a.measured, &a.out, &opts);
    bar.finish_and_clear();
    let result = run?.result;
    println!("verdict: {:?}", result.verdict);
    for e in &result.effects {
        println!(
            "  {} {:?}: gap {:.1} -> {:.1}",
            e.name, e.parameters, e.gap_before, e.gap_after
        );
    }
    println!("wrote {}", a.out.join("model_check.json").display());
    Ok(())
}
