//! `ebptv simulate`: a simulated recording with its ground truth.

use std::path::PathBuf;

use anyhow::Context;
use clap::Args;
use ebptv::io::Format;
use ebptv::sim::{presets, Scenario};

#[derive(Args, Debug)]
pub struct SimulateArgs {
    /// A named scenario (see --list-presets).
    #[arg(long, conflicts_with = "config", required_unless_present_any = ["config", "list_presets"])]
    pub preset: Option<String>,
    /// A scenario TOML file.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Output directory (created if needed).
    #[arg(long, required_unless_present = "list_presets")]
    pub out: Option<PathBuf>,
    /// Override the scenario's duration (s).
    #[arg(long)]
    pub seconds: Option<f64>,
    /// Random seed (every random draw derives from it).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Event file format: evt3 (default, with trigger words), evt2, csv, npy.
    #[arg(long, default_value = "evt3")]
    pub format: String,
    /// List the presets and exit.
    #[arg(long)]
    pub list_presets: bool,
}

pub fn run(a: SimulateArgs, tables: Option<ebptv::table::TableFormat>) -> anyhow::Result<()> {
    if a.list_presets {
        for (name, what) in presets::PRESETS {
            println!("{name:16} {what}");
        }
        return Ok(());
    }
    let mut sc: Scenario = match (&a.preset, &a.config) {
        (Some(p), _) => presets::preset(p)?,
        (None, Some(c)) => Scenario::from_toml_file(c)?,
        (None, None) => anyhow::bail!("give --preset NAME or --config FILE"),
    };
    if let Some(s) = a.seconds {
        sc.duration_s = s;
    }
    sc.validate()?;
    let format = Format::from_name(&a.format)
        .with_context(|| format!("unknown --format `{}` (evt3, evt2, csv, npy)", a.format))?;
    let out = a.out.expect("clap requires --out");
    let bar = indicatif::ProgressBar::new(sc.pulse_count());
    bar.set_style(super::progress::style(
        "{msg} [{bar:40}] {pos}/{len} pulses ({eta})",
    ));
    bar.set_message(format!("simulating {}", sc.name));
    let (summary, _) = ebptv::table::write_recording(
        &sc,
        a.seed,
        &out,
        format,
        tables.unwrap_or_default(),
        |done, _| bar.set_position(done),
    )?;
    bar.finish_and_clear();
    println!(
        "{}: {} events ({:.1} Mev/s), {} pulses, {:.2} events per particle per pulse -> {}",
        sc.name,
        summary.stats.events,
        summary.event_rate_ev_s / 1e6,
        summary.stats.pulses,
        summary.events_per_particle_per_pulse,
        out.display()
    );
    Ok(())
}
