//! What `ebptv spectra` does, as one call: a tracks table → the spectra
//! folder ([`spectra_to_dir`]).

use std::path::{Path, PathBuf};

use super::{RunOptions, SpectraRun, PEAK_FALSE_ALARM};
use crate::error::{Error, Result};
use crate::io::atomic::AtomicFile;
use crate::plot::{self, Heatmap, LinePlot, Series, SeriesStyle};

/// Everything [`spectra_to_dir`] needs besides the input and the output
/// folder.
#[derive(Debug, Clone)]
pub struct SpectraDirOptions {
    /// Points, line, binning and Welch settings (its `calibration` is
    /// replaced by the one read from `calibration`).
    pub spectra: RunOptions,
    /// A `calib.toml`: physical units added to the tables and figures.
    pub calibration: Option<PathBuf>,
    /// Draw the PNG figures.
    pub plots: bool,
}

/// The spectra of a tracks table at points and along a line, written into
/// `out` (created if missing) as `ebptv spectra` writes them:
/// `spectrum.json`, `spectra.csv`, `premultiplied_line.csv` and figures.
pub fn spectra_to_dir(tracks: &Path, opts: &SpectraDirOptions, out: &Path) -> Result<SpectraRun> {
    let mut opt = opts.spectra.clone();
    opt.calibration = None;
    opt.validate()?;
    opt.calibration = opts
        .calibration
        .as_deref()
        .map(crate::calib::Calibration::from_file)
        .transpose()?;
    crate::io::atomic::create_output_dir(out)?;
    let samples = crate::grid::read_track_samples(tracks)?;
    let run = super::run_on_samples(&samples, &opt)?;
    let calibrated = opt.calibration.is_some();
    let k2 = opt.psd_factor();

    if let (Some(r), Some(csv)) = (&run.points, &run.spectra_csv) {
        AtomicFile::write_all_to(out.join("spectra.csv"), csv.as_bytes())?;
        if opts.plots {
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
                    y_label: if calibrated {
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
                plot::line_plot(&out.join(format!("spectrum_p{k}.png")), &plot)?;
            }
        }
    }

    if let Some(l) = &run.line {
        let (x0, y0, x1, y1) = opt.line.expect("a line was given");
        AtomicFile::write_all_to(
            out.join("premultiplied_line.csv"),
            run.line_csv.as_deref().unwrap_or_default().as_bytes(),
        )?;
        let (f, nf, pts, map) = (&l.f_hz, l.f_hz.len(), &l.points, &l.map);
        if opts.plots {
            let len = ((x1 - x0).powi(2) + (y1 - y0).powi(2)).sqrt();
            plot::heatmap(
                &out.join("premultiplied_line.png"),
                &Heatmap {
                    title: "pre-multiplied spectrum f*E(f) along the line",
                    values: map,
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
    }
    let text = serde_json::to_string_pretty(&run.summary)
        .map_err(|e| Error::analysis(format!("spectrum.json: {e}")))?;
    AtomicFile::write_all_to(out.join("spectrum.json"), text.as_bytes())?;
    Ok(run)
}
