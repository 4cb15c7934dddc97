//! `ebptv demo`: the whole chain on a simulated recording, scored against
//! its ground truth.
//!
//! The demo runs exactly the command lines a user would type (printed as it
//! goes, so each step can be repeated by hand), then scores the files they
//! wrote with `ebptv::evaluate`.

use std::path::{Path, PathBuf};

use anyhow::Context;
use clap::{Args, Parser};
use serde_json::json;

use ebptv::evaluate::{self, Truth};
use ebptv::io::atomic::AtomicFile;
use ebptv::sim::scenario::Scenario;
use ebptv::table::TableFormat;

#[derive(Args, Debug)]
pub struct DemoArgs {
    /// Output directory.
    #[arg(long, default_value = "demo_out")]
    pub out: PathBuf,
    /// Simulator preset (see `ebptv simulate --list-presets`).
    #[arg(long, default_value = "demo", conflicts_with = "config")]
    pub preset: String,
    /// A scenario TOML file instead of a preset (as `ebptv simulate
    /// --config`): the whole chain scored on a scene of your own.
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Random seed of the simulated recording.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Override the recording's duration (s).
    #[arg(long)]
    pub seconds: Option<f64>,
}

fn step(line: &[String]) -> anyhow::Result<()> {
    eprintln!("\n$ {}", line.join(" "));
    let cli = super::Cli::try_parse_from(line)
        .with_context(|| format!("demo step `{}`", line.join(" ")))?;
    super::run(cli, line).with_context(|| format!("demo step `{}` failed", line[1]))
}

/// Largest power of two ≤ half the pulse count, between 16 and 128.
fn welch_segment_for(n_pulses: u64) -> u64 {
    let half = (n_pulses / 2).max(16);
    (1u64 << (63 - half.leading_zeros())).min(128)
}

fn p(path: &Path) -> String {
    path.display().to_string()
}

/// `tables`: the top-level `--table-format`, passed on to every step.
pub fn run(args: DemoArgs, tables: Option<TableFormat>) -> anyhow::Result<()> {
    // The scene is read (and validated) before any step runs, so a bad
    // scenario file fails at once with its name, not after a simulation.
    let (scene_name, scene_source) = match &args.config {
        Some(file) => {
            Scenario::from_toml_file(file)?;
            (p(file), vec!["--config".to_string(), p(file)])
        }
        None => {
            ebptv::sim::presets::preset(&args.preset)?;
            (
                format!("preset `{}`", args.preset),
                vec!["--preset".to_string(), args.preset.clone()],
            )
        }
    };
    let out = &args.out;
    ebptv::io::atomic::create_output_dir(out)?;
    let (sim, ptv, grid, piv, cmp) = (
        out.join("sim"),
        out.join("ptv"),
        out.join("grid"),
        out.join("piv"),
        out.join("compare"),
    );
    let rec = sim.join("recording.raw");
    let format = tables.unwrap_or_default();
    let (tracks, particles) = (
        ptv.join(format.file_name("tracks")),
        ptv.join(format.file_name("particles")),
    );
    let (grid_table, piv_table, truth_table) = (
        grid.join(format.file_name("grid")),
        piv.join(format.file_name("piv_mean")),
        sim.join(format.file_name("truth_particles")),
    );
    // `ebptv [--table-format F] CMD …`
    let s = |v: &[&str]| {
        let mut line = vec![v[0].to_string()];
        if let Some(f) = tables {
            line.extend(["--table-format".to_string(), f.ext().to_string()]);
        }
        line.extend(v[1..].iter().map(|x| x.to_string()));
        line
    };

    let mut sim_cmd = s(&["ebptv", "simulate"]);
    sim_cmd.extend(scene_source);
    sim_cmd.push("--seed".into());
    sim_cmd.push(args.seed.to_string());
    if let Some(sec) = args.seconds {
        sim_cmd.push("--seconds".into());
        sim_cmd.push(sec.to_string());
    }
    sim_cmd.extend(["--out".to_string(), p(&sim)]);
    step(&sim_cmd)?;
    step(&s(&["ebptv", "track", &p(&rec), "--out", &p(&ptv)]))?;
    step(&s(&[
        "ebptv",
        "grid",
        &p(&tracks),
        "--bin",
        "16",
        "--fit",
        "linear",
        "--out",
        &p(&grid),
    ]))?;
    // Welch segments of up to 128 pulses, at least two per recording, so a
    // short `--seconds` still gets a spectrum (coarser in frequency).
    let tracked: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(ptv.join("summary.json")).context("reading summary.json")?,
    )?;
    let n_pulses = tracked["pulses"].as_u64().unwrap_or(0);
    let nperseg = welch_segment_for(n_pulses);
    // The scenario the simulator wrote is the one it used (preset or file).
    let scenario = Scenario::from_toml_file(sim.join("scenario.toml"))?;
    let roi = scenario.roi();
    let point = format!("{},{}", roi.x + roi.width * 3 / 5, roi.y + roi.height / 2);
    step(&s(&[
        "ebptv",
        "spectra",
        &p(&tracks),
        "--point",
        &point,
        "--nperseg",
        &nperseg.to_string(),
        "--out",
        &p(&out.join("spectra")),
    ]))?;
    step(&s(&[
        "ebptv",
        "piv",
        &p(&rec),
        "--window",
        "32",
        "--frames",
        "5",
        "--out",
        &p(&piv),
    ]))?;
    step(&s(&[
        "ebptv",
        "compare",
        "--ptv",
        &p(&grid_table),
        "--piv",
        &p(&piv_table),
        "--out",
        &p(&cmp),
    ]))?;

    eprintln!(
        "\nscoring against the simulator's truth ({})",
        p(&truth_table)
    );
    let truth = Truth::read(&truth_table)?;
    let period = scenario.period_us();

    let pulses: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(ptv.join("pulses.json")).context("reading pulses.json")?,
    )?;
    let est_period = pulses["period_us"].as_f64().unwrap_or(f64::NAN);
    let est_first = pulses["first_pulse_us"].as_f64().unwrap_or(f64::NAN);
    let radius = 1.0;
    let det = evaluate::score_particles(&particles, &truth, radius)?;
    let trk = evaluate::score_tracks(&tracks, &truth, period, radius)?;
    let grid_score = evaluate::score_mean_field(&grid_table, &truth, 16.0, 16.0, 20)?;
    let piv_score = evaluate::score_mean_field(&piv_table, &truth, 32.0, 32.0, 20)?;
    let comparison: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(cmp.join("compare.json")).context("reading compare.json")?,
    )?;

    let grid_json: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(grid.join("grid.json")).context("reading grid.json")?,
    )?;
    let spectrum: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(out.join("spectra").join("spectrum.json"))
            .context("reading spectrum.json")?,
    )?;
    let report = json!({
        "preset": args.config.is_none().then_some(&args.preset),
        "config": args.config.as_ref().map(|f| p(f)),
        "seed": args.seed,
        "pulses": {
            "source": pulses["source"],
            "period_us": est_period,
            "period_error_us": est_period - period,
            "first_pulse_error_us": est_first - scenario.light.first_pulse_us,
            "latency_peak_us": pulses["latency_peak_us"],
            "latency_fwhm_us": pulses["latency_fwhm_us"],
        },
        "particles": det,
        "tracks": trk,
        "grid": grid_score,
        "piv": piv_score,
        "compare": comparison,
        "dynamic_range": {
            "max_speed": grid_json["max_mean_speed"],
            "velocity_noise_rms": grid_json["velocity_noise_rms"],
            "per_sample": grid_json["dynamic_range"],
            "spectral_floor_noise_rms": spectrum["noise_rms"],
        },
    });
    AtomicFile::write_all_to(
        out.join("demo_report.json"),
        serde_json::to_string_pretty(&report)?.as_bytes(),
    )?;

    println!(
        "\nebptv demo: {scene_name}, seed {} → {}",
        args.seed,
        out.display()
    );
    println!("{:<44} {:>14}", "quantity", "value");
    let row = |name: &str, v: String| println!("{name:<44} {v:>14}");
    row(
        "pulse period error (µs)",
        format!("{:+.4}", est_period - period),
    );
    row(
        "pulse start error (µs)",
        format!("{:+.2}", est_first - scenario.light.first_pulse_us),
    );
    row("particle detection recall", format!("{:.3}", det.recall));
    row(
        "particle detection precision",
        format!("{:.3}", det.precision),
    );
    row(
        "centroid rms error (px)",
        format!("{:.3}", det.position_rms_px),
    );
    row("tracks", format!("{}", trk.tracks));
    row("link precision", format!("{:.4}", trk.link_precision));
    row("link recall", format!("{:.4}", trk.link_recall));
    row(
        "track velocity rms error (px/pulse)",
        format!("{:.4}", trk.velocity_rms_px_per_pulse),
    );
    row(
        "PTV grid mean error (rms, % of max speed)",
        format!("{:.2}", 100.0 * grid_score.rms_error_of_max_speed),
    );
    if let Some(d) = grid_json["dynamic_range"].as_f64() {
        row(
            "dynamic velocity range, per track sample",
            format!("{d:.0}:1"),
        );
    }
    row(
        "PIV mean error (rms, % of max speed)",
        format!("{:.2}", 100.0 * piv_score.rms_error_of_max_speed),
    );
    for q in ["u", "v"] {
        if let Some(d) = comparison[q]["rms_diff"].as_f64() {
            row(
                &format!("PTV − PIV rms difference of {q} (% of max speed)"),
                format!("{:.2}", 100.0 * d / grid_score.max_true_speed),
            );
        }
    }
    println!(
        "\nfigures and data in {}; scores in {}",
        out.display(),
        p(&out.join("demo_report.json"))
    );
    Ok(())
}
