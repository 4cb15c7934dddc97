//! `ebptv spectra`: velocity spectra at points / along a line from tracks.

use std::path::PathBuf;

use clap::{Args, ValueEnum};
use serde_json::json;

use ebptv::grid::{Lattice, Weighting};
use ebptv::io::atomic::AtomicFile;
use ebptv::plot::{self, Heatmap, LinePlot, Series, SeriesStyle};
use ebptv::spectra::{
    line_points, point_spectra, PointSpectrum, SpectraOptions, WelchOptions, PEAK_FALSE_ALARM,
};

use super::grid::{parse_pair, read_track_samples};

#[derive(Copy, Clone, Debug, PartialEq, Eq, ValueEnum)]
pub enum Component {
    U,
    V,
    Sum,
}

#[derive(Args, Debug)]
pub struct SpectraArgs {
    /// A tracks table of `ebptv track` (tracks.parquet, .csv or .npy:
    /// `track_id,pulse,t_us,x,y,u,v`).
    pub tracks: PathBuf,
    /// Point "x,y" (px); repeat for several. The first gives `peak_hz`.
    #[arg(long, value_parser = parse_pair)]
    pub point: Vec<(f64, f64)>,
    /// Line "x0,y0,x1,y1" (px) for pre-multiplied spectra versus position.
    #[arg(long, value_parser = parse_line)]
    pub line: Option<(f64, f64, f64, f64)>,
    /// Number of points along --line.
    #[arg(long, default_value_t = 16)]
    pub line_points: usize,
    /// Velocity component of the line map.
    #[arg(long, value_enum, default_value_t = Component::V)]
    pub component: Component,
    /// Output folder: spectrum.json, spectra.csv, the line map and figures.
    #[arg(long)]
    pub out: PathBuf,
    /// Bin width (px) of the time series.
    #[arg(long, default_value_t = 16.0)]
    pub bin: f64,
    /// Bin height (px); default = --bin (square bins).
    #[arg(long)]
    pub bin_h: Option<f64>,
    /// One frame every K pulses.
    #[arg(long, default_value_t = 1)]
    pub every: usize,
    /// Welch segment length (frames).
    #[arg(long, default_value_t = 256)]
    pub nperseg: usize,
    /// Welch segment overlap fraction.
    #[arg(long, default_value_t = 0.5)]
    pub seg_overlap: f64,
    /// Lower end of the peak search band (Hz).
    #[arg(long, default_value_t = 1.0)]
    pub f_min: f64,
    /// Upper end of the peak search band (Hz); default = the Nyquist
    /// frequency of the series.
    #[arg(long, default_value_t = f64::INFINITY)]
    pub f_max: f64,
    /// Also report the rms about a moving average of N frames.
    #[arg(long)]
    pub moving_average: Option<usize>,
    /// Minimum samples per bin for the maximum mean speed.
    #[arg(long, default_value_t = 10)]
    pub min_count: u64,
    /// A `calib.toml`: spectra.csv gains `psd_u_K_m2_s,psd_v_K_m2_s`
    /// ((m/s)²/Hz) after the pixel columns, spectrum.json the points in mm
    /// and m/s, and the spectra figures are in (m/s)²/Hz.
    #[arg(long)]
    pub calibration: Option<PathBuf>,
    /// Write the CSV and JSON outputs only, no PNG figures.
    #[arg(long)]
    pub no_plots: bool,
}

fn parse_line(s: &str) -> Result<(f64, f64, f64, f64), String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|t| t.trim().parse::<f64>().map_err(|e| format!("{s}: {e}")))
        .collect::<Result<_, _>>()?;
    if v.len() != 4 {
        return Err(format!("expected \"x0,y0,x1,y1\", got \"{s}\""));
    }
    Ok((v[0], v[1], v[2], v[3]))
}

fn point_json(p: &PointSpectrum) -> serde_json::Value {
    json!({
        "x": p.x, "y": p.y, "bin_x": p.bin_x, "bin_y": p.bin_y,
        "peak_hz": p.peak.map(|k| k.f_hz), "peak_u_hz": p.peak_u.map(|k| k.f_hz), "peak_v_hz": p.peak_v.map(|k| k.f_hz),
        "peak_significant": p.peak.is_some(), "peak_false_alarm": p.peak_test.false_alarm,
        "strongest_hz": p.peak_test.strongest.map(|k| k.f_hz), "peak_test_dof": p.peak_test.dof, "f_resolved_hz": p.f_resolved_hz,
        "gap_fraction": p.gap_fraction, "mean_u": p.mean_u, "mean_v": p.mean_v, "rms_u": p.rms_u, "rms_v": p.rms_v,
        "noise_rms_u": p.noise_rms_u, "noise_rms_v": p.noise_rms_v, "rms_ma_u": p.rms_ma_u, "rms_ma_v": p.rms_ma_v,
    })
}

pub fn run(a: SpectraArgs) -> anyhow::Result<()> {
    anyhow::ensure!(
        !a.point.is_empty() || a.line.is_some(),
        "give at least one --point x,y or a --line"
    );
    anyhow::ensure!(
        a.line.is_none() || a.line_points >= 2,
        "--line-points must be at least 2"
    );
    let opt = SpectraOptions {
        lattice: Lattice::new(a.bin, a.bin_h.unwrap_or(a.bin), 0.0)?,
        weighting: Weighting::TopHat,
        every: a.every.max(1),
        welch: WelchOptions {
            nperseg: a.nperseg,
            overlap: a.seg_overlap,
        },
        f_min: a.f_min,
        f_max: a.f_max,
        moving_average: a.moving_average,
        min_count: a.min_count,
    };
    let calib = a
        .calibration
        .as_deref()
        .map(ebptv::calib::Calibration::from_file)
        .transpose()?;
    ebptv::io::atomic::create_output_dir(&a.out)?;
    let samples = read_track_samples(&a.tracks)?;
    // (px/s)² → (m/s)².
    let k2 = calib
        .as_ref()
        .map_or(1.0, |c| c.velocity_px_s_to_m_s(1.0, 0.0).0.powi(2));

    let mut summary = json!({});
    if !a.point.is_empty() {
        let r = point_spectra(&samples, &a.point, &opt)?;
        let first = &r.points[0];
        summary = json!({
            "peak_hz": first.peak.map(|k| k.f_hz),
            "peak_significant": first.peak.is_some(), "peak_false_alarm": first.peak_test.false_alarm,
            "false_alarm_level": PEAK_FALSE_ALARM, "strongest_hz": first.peak_test.strongest.map(|k| k.f_hz),
            "fs_hz": r.frames.rate_hz(), "frame_step_us": r.frames.step_us, "frames": r.frames.n,
            "nperseg": a.nperseg, "n_segments": first.psd_u.n_segments, "df_hz": first.psd_u.df(),
            "noise_rms": r.noise_rms, "max_speed": r.max_speed, "dynamic_range": r.dynamic_range,
            "points": r.points.iter().map(point_json).collect::<Vec<_>>(),
        });
        if let Some(c) = &calib {
            summary["px_per_mm"] = json!(c.px_per_mm);
            for (j, p) in r.points.iter().enumerate() {
                let (xm, ym) = c.px_to_mm(p.bin_x, p.bin_y);
                let (um, vm) = c.velocity_px_s_to_m_s(p.mean_u, p.mean_v);
                let pj = &mut summary["points"][j];
                pj["bin_X_mm"] = json!(xm);
                pj["bin_Y_mm"] = json!(ym);
                pj["mean_U_m_s"] = json!(um);
                pj["mean_V_m_s"] = json!(vm);
                pj["rms_u_m_s"] = json!(p.rms_u * k2.sqrt());
                pj["rms_v_m_s"] = json!(p.rms_v * k2.sqrt());
            }
        }
        let mut s = String::from("f_hz");
        for k in 0..r.points.len() {
            s.push_str(&format!(",psd_u_{k},psd_v_{k}"));
        }
        if calib.is_some() {
            for k in 0..r.points.len() {
                s.push_str(&format!(",psd_u_{k}_m2_s,psd_v_{k}_m2_s"));
            }
        }
        s.push('\n');
        for i in 0..first.psd_u.f_hz.len() {
            s.push_str(&format!("{}", first.psd_u.f_hz[i]));
            for p in &r.points {
                s.push_str(&format!(",{},{}", p.psd_u.psd[i], p.psd_v.psd[i]));
            }
            if calib.is_some() {
                for p in &r.points {
                    s.push_str(&format!(",{},{}", p.psd_u.psd[i] * k2, p.psd_v.psd[i] * k2));
                }
            }
            s.push('\n');
        }
        AtomicFile::write_all_to(a.out.join("spectra.csv"), s.as_bytes())?;
        if !a.no_plots {
            for (k, p) in r.points.iter().enumerate() {
                let f = &p.psd_u.f_hz[1..];
                let title = match p.peak {
                    Some(_) => format!("PSD at ({:.0}, {:.0}) px", p.bin_x, p.bin_y),
                    None => format!(
                        "PSD at ({:.0}, {:.0}) px: no significant peak (false alarm {:.0} %)",
                        p.bin_x,
                        p.bin_y,
                        100.0 * PEAK_FALSE_ALARM
                    ),
                };
                let peak_label = p
                    .peak
                    .map(|pk| {
                        format!(
                            "peak {:.2} Hz (false alarm {:.1e})",
                            pk.f_hz, p.peak_test.false_alarm
                        )
                    })
                    .unwrap_or_default();
                let psd_u: Vec<f64> = p.psd_u.psd[1..].iter().map(|v| v * k2).collect();
                let psd_v: Vec<f64> = p.psd_v.psd[1..].iter().map(|v| v * k2).collect();
                let plot = LinePlot {
                    title: &title,
                    x_label: "f (Hz)",
                    y_label: if calib.is_some() {
                        "PSD ((m/s)^2/Hz)"
                    } else {
                        "PSD ((px/s)^2/Hz)"
                    },
                    series: vec![
                        Series {
                            label: "u",
                            x: f,
                            y: &psd_u,
                            style: SeriesStyle::Line,
                        },
                        Series {
                            label: "v",
                            x: f,
                            y: &psd_v,
                            style: SeriesStyle::Line,
                        },
                    ],
                    log_x: true,
                    log_y: true,
                    vlines: p
                        .peak
                        .map(|pk| vec![(pk.f_hz, peak_label.as_str())])
                        .unwrap_or_default(),
                };
                plot::line_plot(&a.out.join(format!("spectrum_p{k}.png")), &plot)?;
            }
        }
        eprintln!(
            "spectra: {} at ({}, {}); noise rms {:.2} px/s, dynamic range {:.0}:1 → {}",
            first
                .peak
                .map(|k| format!("peak {:.2} Hz", k.f_hz))
                .unwrap_or_else(|| format!(
                    "no significant peak (false alarm {:.0} %)",
                    100.0 * PEAK_FALSE_ALARM
                )),
            first.bin_x,
            first.bin_y,
            r.noise_rms,
            r.dynamic_range,
            a.out.display()
        );
    }

    if let Some((x0, y0, x1, y1)) = a.line {
        let pts = line_points((x0, y0), (x1, y1), a.line_points);
        let r = point_spectra(&samples, &pts, &opt)?;
        let nf = r.points[0].psd_u.f_hz.len();
        let f = r.points[0].psd_u.f_hz.clone();
        let comp = |p: &PointSpectrum| -> Vec<f64> {
            match a.component {
                Component::U => p.psd_u.psd.clone(),
                Component::V => p.psd_v.psd.clone(),
                Component::Sum => p.psd_sum(),
            }
        };
        let mut s = String::from("s_px,x,y,f_hz,psd,f_psd\n");
        // Map: columns = positions along the line, rows = frequency (DC left out).
        let mut map = vec![f64::NAN; (nf - 1) * pts.len()];
        for (j, p) in r.points.iter().enumerate() {
            let e = comp(p);
            let sp = ((p.x - x0).powi(2) + (p.y - y0).powi(2)).sqrt();
            for i in 0..nf {
                s.push_str(&format!(
                    "{},{},{},{},{},{}\n",
                    sp,
                    p.x,
                    p.y,
                    f[i],
                    e[i],
                    f[i] * e[i]
                ));
                if i > 0 {
                    map[(i - 1) * pts.len() + j] = f[i] * e[i];
                }
            }
        }
        AtomicFile::write_all_to(a.out.join("premultiplied_line.csv"), s.as_bytes())?;
        if !a.no_plots {
            let len = ((x1 - x0).powi(2) + (y1 - y0).powi(2)).sqrt();
            plot::heatmap(
                &a.out.join("premultiplied_line.png"),
                &Heatmap {
                    title: "pre-multiplied spectrum f*E(f) along the line",
                    values: &map,
                    nx: pts.len(),
                    ny: nf - 1,
                    x_range: (0.0, len),
                    y_range: (f[1], f[nf - 1]),
                    colorbar_label: "f*E(f) ((px/s)^2)",
                    diverging: false,
                    axes_mm: None,
                },
            )?;
        }
        summary["line"] = json!({
            "from": [x0, y0], "to": [x1, y1], "component": format!("{:?}", a.component).to_lowercase(),
            "points": r.points.iter().map(point_json).collect::<Vec<_>>(),
        });
        if summary.get("noise_rms").is_none() {
            summary["noise_rms"] = json!(r.noise_rms);
            summary["max_speed"] = json!(r.max_speed);
            summary["dynamic_range"] = json!(r.dynamic_range);
            summary["peak_hz"] = json!(r.points[0].peak.map(|k| k.f_hz));
        }
    }
    // Per-sample noise and dynamic range from pairs of samples at one pulse
    // (the spectral floor above is the noise of the binned time series).
    let acc = ebptv::grid::bin_samples(&samples, opt.lattice, Weighting::TopHat)?;
    let g = ebptv::grid::estimate(
        &acc,
        &ebptv::grid::EstimateOptions {
            fit: ebptv::grid::Fit::Linear,
            min_count: a.min_count,
            noise_rms: 0.0,
        },
    )?;
    match ebptv::grid::noise::velocity_noise(&samples, &g, &Default::default()) {
        Ok(n) => {
            summary["velocity_noise_rms"] = json!(n.noise_rms);
            summary["dynamic_range_per_sample"] = json!(n.dynamic_range);
        }
        Err(e) => eprintln!("spectra: no per-sample noise estimate: {e}"),
    }
    AtomicFile::write_all_to(
        a.out.join("spectrum.json"),
        serde_json::to_string_pretty(&summary)?.as_bytes(),
    )?;
    Ok(())
}
