use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use clap::Args;
use ebptv::piv::output::{write_mean_table, write_steps_table, NpyStack};
use ebptv::piv::{
    run_recording, NodeGrid, PivOptions, PivProgress, PivRunOptions, PivSink, PivStage, PixelMode,
    PseudoOptions, StepField,
};
use ebptv::plot::{heatmap, Heatmap};

/// The correlation options `ebptv piv` and `ebptv piv-images` share.
#[derive(Args, Debug)]
pub struct CorrelationArgs {
    /// Final interrogation window width (px).
    #[arg(long, default_value_t = 32)]
    pub window: usize,
    /// Window height (px); default = width (e.g. 64 x 8 for a boundary layer).
    #[arg(long)]
    pub window_h: Option<usize>,
    /// Node spacing (px); default = half the window.
    #[arg(long)]
    pub spacing: Option<usize>,
    /// Multi-pass refinement with window deformation.
    #[arg(long, default_value_t = 3)]
    pub passes: usize,
    /// Pyramid correlation: also correlate frames 2..S apart (pairs k, k+s),
    /// each plane scaled to the unit separation; lowers the random error.
    /// 1 = off; needs S < frames and at least 2 passes.
    #[arg(long, default_value_t = 1, value_name = "S")]
    pub pyramid: usize,
    /// Keep window values below the window mean (no background clipping):
    /// plain mean-removed correlation.
    #[arg(long)]
    pub no_clip: bool,
}

impl CorrelationArgs {
    pub fn options(&self) -> PivOptions {
        let mut o = PivOptions::sized(self.window, self.window_h, self.spacing);
        o.passes = self.passes;
        o.pyramid = self.pyramid;
        o.clip_background = !self.no_clip;
        o
    }
}

#[derive(Args, Debug)]
pub struct PivArgs {
    /// Event recording.
    pub recording: PathBuf,
    #[command(flatten)]
    pub correlation: CorrelationArgs,
    /// Frames (pulses) per evaluation, N_f.
    #[arg(long, default_value_t = 5)]
    pub frames: usize,
    /// Pulses between evaluations; default N_f - 1.
    #[arg(long)]
    pub step: Option<usize>,
    /// Gaussian blur of the pseudo-images (px).
    #[arg(long, default_value_t = 1.0)]
    pub sigma: f64,
    /// Event counts instead of binary pseudo-images.
    #[arg(long)]
    pub counts: bool,
    /// Use OFF events too.
    #[arg(long)]
    pub both_polarities: bool,
    /// Nominal pulse frequency (Hz) when the recording has no triggers.
    #[arg(long)]
    pub pulse_hz: Option<f64>,
    /// Time steps evaluated in parallel (default: the number of rayon
    /// threads); the fields do not depend on it, memory grows with it.
    #[arg(long)]
    pub batch: Option<usize>,
    /// Go on even when the events show no bursts locked to pulses (see
    /// `ebptv pulses`).
    #[arg(long)]
    pub force_pulses: bool,
    /// A `calib.toml`: the piv_mean table gains `X_mm,Y_mm,U_m_s,V_m_s,uu_m2_s2,
    /// vv_m2_s2,uv_m2_s2` after the pixel columns, the maps are in m/s,
    /// and its `[mask]` table applies as --mask does.
    #[arg(long)]
    pub calibration: Option<PathBuf>,
    /// Mask image (PNG of the sensor's size, non-zero = not flow): masked
    /// pixels carry no signal and windows more than half masked give no
    /// vector (NaN, flag 4).
    #[arg(long)]
    pub mask: Option<PathBuf>,
    /// Output folder: the piv_mean and piv_steps tables (.parquet; .csv,
    /// .npy with --table-format) and the per-step fields piv_u.npy,
    /// piv_v.npy, piv_flag.npy.
    #[arg(long)]
    pub out: PathBuf,
}

impl PivArgs {
    /// The library's options of this command line.
    fn options(&self) -> PivRunOptions {
        PivRunOptions {
            correlation: self.correlation.options(),
            frames: self.frames,
            step: self.step,
            pseudo: PseudoOptions {
                mode: if self.counts {
                    PixelMode::Counts
                } else {
                    PixelMode::Binary
                },
                both_polarities: self.both_polarities,
                sigma: self.sigma,
            },
            pulse_hz: self.pulse_hz,
            batch: self.batch,
            force_pulses: self.force_pulses,
            calibration: self.calibration.clone(),
            mask: self.mask.clone(),
        }
    }
}

/// The per-step fields as `.npy` stacks in OUT (px/s).
struct NpySink<'a> {
    out: &'a Path,
    stacks: Option<[NpyStack; 3]>,
    pulse_hz: f64,
}

impl PivSink for NpySink<'_> {
    fn start(&mut self, g: &NodeGrid, pulse_hz: f64) -> ebptv::Result<()> {
        ebptv::io::atomic::create_output_dir(self.out)?;
        self.pulse_hz = pulse_hz;
        self.stacks = Some([
            NpyStack::create(&self.out.join("piv_u.npy"), "<f4", g.ny, g.nx)?,
            NpyStack::create(&self.out.join("piv_v.npy"), "<f4", g.ny, g.nx)?,
            NpyStack::create(&self.out.join("piv_flag.npy"), "|u1", g.ny, g.nx)?,
        ]);
        Ok(())
    }

    fn field(&mut self, f: &StepField) -> ebptv::Result<()> {
        let hz = self.pulse_hz;
        let Some([su, sv, sf]) = self.stacks.as_mut() else {
            return Err(ebptv::Error::analysis("PIV field before its grid"));
        };
        su.push_f32(f.field.u.iter().map(|&x| (x * hz) as f32))?;
        sv.push_f32(f.field.v.iter().map(|&x| (x * hz) as f32))?;
        sf.push_u8(&f.field.flags)
    }
}

/// The bar's state: when it was last drawn and when the pass started.
#[derive(Default)]
struct Shown {
    started: Option<Instant>,
    shown: Option<Instant>,
}

pub fn run(a: PivArgs, tables: Option<ebptv::table::TableFormat>) -> anyhow::Result<()> {
    let size = std::fs::metadata(&a.recording).ok().map(|m| m.len());
    let bar = super::progress::file_bar(size, "pulse timing");
    let shown = Mutex::new(Shown::default());
    let on_progress = |p: PivProgress<'_>| match p {
        PivProgress::Stage { stage, file_size } => {
            // Second pass over the recording: the bar restarts, with the fields so far.
            if stage == PivStage::Correlation {
                bar.reset();
                bar.set_prefix("PIV");
            }
            if let Some(s) = file_size {
                bar.set_length(s);
            }
            bar.set_message("");
            *shown.lock().unwrap_or_else(|e| e.into_inner()) = Shown::default();
        }
        PivProgress::Read {
            stage,
            bytes,
            events,
            fields,
        } => {
            if bar.is_hidden() {
                return;
            }
            let now = Instant::now();
            let mut s = shown.lock().unwrap_or_else(|e| e.into_inner());
            let started = *s.started.get_or_insert(now);
            let due = s.shown.is_none_or(|t| {
                now.duration_since(t)
                    >= Duration::from_millis(1000 / super::progress::REFRESH_HZ as u64)
            });
            if !due {
                return;
            }
            s.shown = Some(now);
            bar.set_position(bytes);
            let secs = now.duration_since(started).as_secs_f64();
            let rate = if secs > 0.0 {
                events as f64 / secs
            } else {
                0.0
            };
            let count = super::progress::count;
            let mut msg = format!("{}ev, {}ev/s", count(events as f64), count(rate));
            if stage == PivStage::Correlation {
                msg.push_str(&format!(", {fields} fields"));
            }
            bar.set_message(msg);
        }
        PivProgress::Warning(w) => bar.suspend(|| eprintln!("warning: {w}")),
    };
    let mut sink = NpySink {
        out: &a.out,
        stacks: None,
        pulse_hz: 0.0,
    };
    let result = run_recording(
        &a.recording,
        &a.options(),
        &mut sink,
        &on_progress,
        &ebptv::Cancel::new(),
    );
    bar.finish_and_clear();
    let run = result?;
    if let Some(stacks) = sink.stacks {
        for s in stacks {
            s.finish()?;
        }
    }
    let g = run.grid;
    let format = tables.unwrap_or_default();
    write_steps_table(&a.out, format, &run.steps)?;
    let rows = &run.mean;
    let calib = &run.calibration;
    write_mean_table(&a.out, format, rows, calib.as_ref())?;
    let xr = (g.x(0), g.x(g.nx - 1));
    let yr = (g.y(0), g.y(g.ny - 1));
    // With a calibration the maps are in m/s (and m²/s²).
    let phys = |r: &ebptv::piv::MeanRow| match calib {
        Some(c) => {
            let (u, v) = c.velocity_px_s_to_m_s(r.u, r.v);
            let (uu, _, _) = c.stress_px2_s2_to_m2_s2(r.uu, r.vv, r.uv);
            (u, v, uu)
        }
        None => (r.u, r.v, r.uu),
    };
    let (lu, lv, luu) = if calib.is_some() {
        ("u (m/s)", "v (m/s)", "u'u' ((m/s)^2)")
    } else {
        ("u (px/s)", "v (px/s)", "u'u' ((px/s)^2)")
    };
    let maps: [(&str, &str, bool, Vec<f64>); 4] = [
        ("u", lu, true, rows.iter().map(|r| phys(r).0).collect()),
        ("v", lv, true, rows.iter().map(|r| phys(r).1).collect()),
        ("uu", luu, false, rows.iter().map(|r| phys(r).2).collect()),
        (
            "valid",
            "valid fraction",
            false,
            rows.iter().map(|r| r.valid).collect(),
        ),
    ];
    for (name, label, div, vals) in &maps {
        heatmap(
            &a.out.join(format!("piv_{name}.png")),
            &Heatmap {
                title: &format!("PIV mean {name}"),
                values: vals,
                nx: g.nx,
                ny: g.ny,
                x_range: xr,
                y_range: yr,
                colorbar_label: label,
                diverging: *div,
                axes_mm: calib.as_ref(),
            },
        )?;
    }
    if run.masked {
        eprintln!(
            "{} of {} nodes masked or without a vector",
            run.nodes_without_vector(),
            g.len()
        );
    }
    eprintln!("{} PIV fields, {} nodes each", run.steps.len(), g.len());
    Ok(())
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::super::{Cli, Command};
    use super::*;

    #[ebptv_macros::unit_test]
    fn the_command_line_defaults_are_the_library_defaults() {
        let cli = <Cli as clap::Parser>::try_parse_from(["ebptv", "piv", "r.raw", "--out", "o"])
            .expect("parses");
        let Command::Piv(a) = cli.command else {
            panic!("not the piv command");
        };
        assert_eq!(a.options(), PivRunOptions::default());
    }
}
