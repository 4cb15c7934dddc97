//! `ebptv spectra`: velocity spectra at points / along a line from tracks.

use std::path::PathBuf;

use clap::{Args, ValueEnum};
use ebptv::spectra::{self, RunOptions, SpectraDirOptions, PEAK_FALSE_ALARM};

use super::grid::parse_pair;

#[derive(Copy, Clone, Debug, PartialEq, Eq, ValueEnum)]
pub enum Component {
    U,
    V,
    Sum,
}

impl From<Component> for spectra::Component {
    fn from(c: Component) -> Self {
        match c {
            Component::U => spectra::Component::U,
            Component::V => spectra::Component::V,
            Component::Sum => spectra::Component::Sum,
        }
    }
}

fn defaults() -> RunOptions {
    RunOptions::default()
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
    #[arg(long, default_value_t = defaults().line_points)]
    pub line_points: usize,
    /// Velocity component of the line map.
    #[arg(long, value_enum, default_value_t = Component::V)]
    pub component: Component,
    /// Output folder: spectrum.json, spectra.csv, the line map and figures.
    #[arg(long)]
    pub out: PathBuf,
    /// Bin width (px) of the time series.
    #[arg(long, default_value_t = defaults().bin)]
    pub bin: f64,
    /// Bin height (px); default = --bin (square bins).
    #[arg(long)]
    pub bin_h: Option<f64>,
    /// One frame every K pulses.
    #[arg(long, default_value_t = defaults().every)]
    pub every: usize,
    /// Welch segment length (frames).
    #[arg(long, default_value_t = defaults().nperseg)]
    pub nperseg: usize,
    /// Welch segment overlap fraction.
    #[arg(long, default_value_t = defaults().seg_overlap)]
    pub seg_overlap: f64,
    /// Lower end of the peak search band (Hz).
    #[arg(long, default_value_t = defaults().f_min)]
    pub f_min: f64,
    /// Upper end of the peak search band (Hz); default = the Nyquist
    /// frequency of the series.
    #[arg(long, default_value_t = defaults().f_max)]
    pub f_max: f64,
    /// Also report the rms about a moving average of N frames.
    #[arg(long)]
    pub moving_average: Option<usize>,
    /// Minimum samples per bin for the maximum mean speed.
    #[arg(long, default_value_t = defaults().min_count)]
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

pub fn run(a: SpectraArgs) -> anyhow::Result<()> {
    let opts = SpectraDirOptions {
        spectra: RunOptions {
            points: a.point.clone(),
            line: a.line,
            line_points: a.line_points,
            component: a.component.into(),
            bin: a.bin,
            bin_h: a.bin_h,
            every: a.every,
            nperseg: a.nperseg,
            seg_overlap: a.seg_overlap,
            f_min: a.f_min,
            f_max: a.f_max,
            moving_average: a.moving_average,
            min_count: a.min_count,
            calibration: None,
        },
        calibration: a.calibration,
        plots: !a.no_plots,
    };
    let run = spectra::spectra_to_dir(&a.tracks, &opts, &a.out)?;
    if let Some(r) = &run.points {
        let first = &r.points[0];
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
    if let Some(w) = &run.noise_warning {
        eprintln!("spectra: no per-sample noise estimate: {w}");
    }
    Ok(())
}
