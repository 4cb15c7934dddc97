use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use clap::Args;
use ebptv::piv::output::{write_mean_csv_calibrated, NpyStack};
use ebptv::piv::{PivOptions, PivStream, PixelMode, PseudoOptions, StreamOptions};
use ebptv::plot::{heatmap, Heatmap};
use ebptv::pulses::{analyze, split_pulses, PulseOptions};

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
        let mut o = PivOptions::new(
            self.window,
            self.spacing.unwrap_or((self.window / 2).max(1)),
        );
        o.window_h = self.window_h.unwrap_or(self.window);
        o.spacing_y = self.spacing.unwrap_or((o.window_h / 2).max(1));
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
    /// A `calib.toml`: piv_mean.csv gains `X_mm,Y_mm,U_m_s,V_m_s,uu_m2_s2,
    /// vv_m2_s2,uv_m2_s2` after the pixel columns, the maps are in m/s,
    /// and its [mask] applies as --mask does.
    #[arg(long)]
    pub calibration: Option<PathBuf>,
    /// Mask image (PNG of the sensor's size, non-zero = not flow): masked
    /// pixels carry no signal and windows more than half masked give no
    /// vector (NaN, flag 4).
    #[arg(long)]
    pub mask: Option<PathBuf>,
    /// Output folder: piv_mean.csv, piv_steps.csv and the per-step fields
    /// piv_u.npy, piv_v.npy, piv_flag.npy.
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(a: PivArgs) -> anyhow::Result<()> {
    let src = ebptv::io::open_for_analysis(&a.recording)?;
    super::print_warnings(&src);
    let geom = src.info().geometry.ok_or_else(|| {
        anyhow::anyhow!(
            "{}: the sensor size is not stated in the file; PIV needs it for the pseudo-images",
            a.recording.display()
        )
    })?;
    let mut src = super::progress::Reading::with_bar(src, "pulse timing");
    let report = analyze(
        &mut src,
        &PulseOptions {
            pulse_hz: a.pulse_hz,
            require_pulsed: !a.force_pulses,
            ..Default::default()
        },
    )?;
    let (calib, mask) = ebptv::calib::load(a.calibration.as_deref(), a.mask.as_deref())?;
    let mut piv = a.correlation.options();
    if let Some(m) = &mask {
        if let Some(p) = &a.mask {
            let (mw, mh) = ebptv::calib::PixelMask::from_png(p)?.size();
            anyhow::ensure!(
                (mw, mh) == (geom.width as u32, geom.height as u32),
                "{}: mask of {mw} x {mh} pixels, the sensor has {} x {}",
                p.display(),
                geom.width,
                geom.height
            );
        }
        let (w, h) = (geom.width as u32, geom.height as u32);
        piv.mask = Some(
            (0..h)
                .flat_map(|y| (0..w).map(move |x| (x, y)))
                .map(|(x, y)| m.is_masked_px(x, y))
                .collect(),
        );
    }
    let opts = StreamOptions {
        piv,
        pseudo: PseudoOptions {
            mode: if a.counts {
                PixelMode::Counts
            } else {
                PixelMode::Binary
            },
            both_polarities: a.both_polarities,
            sigma: a.sigma,
        },
        frames: a.frames,
        step: a.step.unwrap_or(a.frames.saturating_sub(1).max(1)),
    };
    let (w, h) = (geom.width as usize, geom.height as usize);
    let mut stream = PivStream::new(w, h, report.timing, opts)?;
    let g = *stream.grid();
    ebptv::io::atomic::create_output_dir(&a.out)?;
    let mut su = NpyStack::create(&a.out.join("piv_u.npy"), "<f4", g.ny, g.nx)?;
    let mut sv = NpyStack::create(&a.out.join("piv_v.npy"), "<f4", g.ny, g.nx)?;
    let mut sf = NpyStack::create(&a.out.join("piv_flag.npy"), "|u1", g.ny, g.nx)?;
    let mut times = Vec::new();
    let hz = stream.pulse_hz();
    // Second pass over the recording: the bar restarts, with the fields so far.
    let bar = src.bar().clone();
    bar.reset();
    bar.set_prefix("PIV");
    let fields = Arc::new(AtomicU64::new(0));
    let shown = fields.clone();
    let mut src = super::progress::Reading::new(ebptv::io::open_for_analysis(&a.recording)?, bar)
        .with_note(Arc::new(move || {
            format!("{} fields", shown.load(Ordering::Relaxed))
        }));
    stream.set_batch(a.batch.unwrap_or_else(rayon::current_num_threads))?;
    let mut emit = |f: ebptv::piv::StepField| -> ebptv::Result<()> {
        su.push_f32(f.field.u.iter().map(|&x| (x * hz) as f32))?;
        sv.push_f32(f.field.v.iter().map(|&x| (x * hz) as f32))?;
        sf.push_u8(&f.field.flags)?;
        times.push((f.first_pulse, f.t_us));
        fields.store(times.len() as u64, Ordering::Relaxed);
        Ok(())
    };
    split_pulses(&mut src, &report.timing, &mut |pe| {
        stream.feed(&pe, &mut emit)
    })?;
    stream.flush(&mut emit)?;
    src.bar().finish_and_clear();
    if times.is_empty() {
        anyhow::bail!(
            "{}: no PIV field: fewer than {} consecutive pulses with events",
            a.recording.display(),
            a.frames
        );
    }
    su.finish()?;
    sv.finish()?;
    sf.finish()?;
    let mut t = String::from("step,first_pulse,t_us\n");
    for (k, (p, tu)) in times.iter().enumerate() {
        t.push_str(&format!("{k},{p},{tu}\n"));
    }
    ebptv::io::atomic::AtomicFile::write_all_to(a.out.join("piv_steps.csv"), t.as_bytes())?;
    let rows = stream.stats.rows();
    write_mean_csv_calibrated(&a.out.join("piv_mean.csv"), &rows, calib.as_ref())?;
    let xr = (g.x(0), g.x(g.nx - 1));
    let yr = (g.y(0), g.y(g.ny - 1));
    // With a calibration the maps are in m/s (and m²/s²).
    let phys = |r: &ebptv::piv::MeanRow| match &calib {
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
    if mask.is_some() {
        let masked = rows
            .iter()
            .filter(|r| r.valid == 0.0 && r.u.is_nan())
            .count();
        eprintln!("{masked} of {} nodes masked or without a vector", g.len());
    }
    eprintln!("{} PIV fields, {} nodes each", times.len(), g.len());
    Ok(())
}
