//! The whole `ebptv spectra` run on a tracks table: spectra at points and
//! along a line, the summary of `spectrum.json` and the CSV tables; the
//! command line writes them and draws the figures.

use serde_json::{json, Value};

use super::{
    line_points, point_spectra, PointSpectrum, SpectraOptions, SpectraResult, WelchOptions,
    PEAK_FALSE_ALARM,
};
use crate::calib::Calibration;
use crate::error::{Error, Result};
use crate::grid::{Lattice, Sample, Weighting};

/// Velocity component of the line map.
#[derive(Copy, Clone, Debug, PartialEq, Eq, Default)]
pub enum Component {
    /// Horizontal component u (along x).
    U,
    /// Vertical component v (along y).
    #[default]
    V,
    /// The sum of the u and v spectra.
    Sum,
}

impl Component {
    /// The name in `spectrum.json` (`u`, `v`, `sum`).
    pub(crate) fn name(self) -> &'static str {
        match self {
            Component::U => "u",
            Component::V => "v",
            Component::Sum => "sum",
        }
    }
}

impl std::str::FromStr for Component {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "u" => Ok(Component::U),
            "v" => Ok(Component::V),
            "sum" => Ok(Component::Sum),
            _ => Err(Error::param(
                "component",
                format!("\"{s}\": expected u, v or sum"),
            )),
        }
    }
}

/// Options of `run_on_samples`; the defaults are those of `ebptv spectra`.
#[derive(Debug, Clone)]
pub struct RunOptions {
    /// Points (px); the first gives `peak_hz`.
    pub points: Vec<(f64, f64)>,
    /// Line (x0, y0, x1, y1) (px) for pre-multiplied spectra.
    pub line: Option<(f64, f64, f64, f64)>,
    /// Number of points along the line.
    pub line_points: usize,
    /// Velocity component of the pre-multiplied line map.
    pub component: Component,
    /// Bin width (px); `bin_h` the height (default = `bin`).
    pub bin: f64,
    /// Bin height (px); `None`: square bins of `bin`.
    pub bin_h: Option<f64>,
    /// One frame every `every` pulses.
    pub every: usize,
    /// Welch segment length (frames) and overlap fraction.
    pub nperseg: usize,
    /// Overlap of consecutive Welch segments (fraction of a segment, in [0, 1)).
    pub seg_overlap: f64,
    /// Peak search band (Hz); `f_max` infinite = the Nyquist frequency.
    pub f_min: f64,
    /// Upper end of the peak search band (Hz).
    pub f_max: f64,
    /// Also report the rms about a moving average of this many frames.
    pub moving_average: Option<usize>,
    /// Minimum samples per bin for the maximum mean speed.
    pub min_count: u64,
    /// Physical units added to the outputs.
    pub calibration: Option<Calibration>,
}

impl Default for RunOptions {
    fn default() -> Self {
        RunOptions {
            points: Vec::new(),
            line: None,
            line_points: 16,
            component: Component::V,
            bin: 16.0,
            bin_h: None,
            every: 1,
            nperseg: 256,
            seg_overlap: 0.5,
            f_min: 1.0,
            f_max: f64::INFINITY,
            moving_average: None,
            min_count: 10,
            calibration: None,
        }
    }
}

impl RunOptions {
    /// The checks made before any input is read.
    #[ebptv_macros::testkit]
    pub(crate) fn validate(&self) -> Result<()> {
        if self.points.is_empty() && self.line.is_none() {
            return Err(Error::analysis("give at least one --point x,y or a --line"));
        }
        if self.line.is_some() && !(2..=MAX_LINE_POINTS).contains(&self.line_points) {
            // Each point is a spectrum of its own bin (10^8 aborted).
            return Err(Error::param(
                "line-points",
                format!("{}: must be in 2..={MAX_LINE_POINTS}", self.line_points),
            ));
        }
        if self.every == 0 {
            return Err(Error::param(
                "every",
                "a frame every 0 pulses: must be at least 1",
            ));
        }
        if !(self.f_min.is_finite() && self.f_min >= 0.0 && self.f_max > self.f_min) {
            // (`f_max` may be infinite: no upper limit.)
            return Err(Error::param(
                "f-min/f-max",
                format!(
                    "the peak search band {}..{} Hz: need 0 <= f-min < f-max",
                    self.f_min, self.f_max
                ),
            ));
        }
        self.spectra_options().map(|_| ())
    }

    fn spectra_options(&self) -> Result<SpectraOptions> {
        Ok(SpectraOptions {
            lattice: Lattice::new(self.bin, self.bin_h.unwrap_or(self.bin), 0.0)?,
            weighting: Weighting::TopHat,
            every: self.every,
            welch: WelchOptions {
                nperseg: self.nperseg,
                overlap: self.seg_overlap,
            },
            f_min: self.f_min,
            f_max: self.f_max,
            moving_average: self.moving_average,
            min_count: self.min_count,
        })
    }

    /// (px/s)² → (m/s)² factor of the calibration (1 without).
    pub(crate) fn psd_factor(&self) -> f64 {
        self.calibration
            .as_ref()
            .map_or(1.0, |c| c.velocity_px_s_to_m_s(1.0, 0.0).0.powi(2))
    }
}

/// Most points along a `--line`.
const MAX_LINE_POINTS: usize = 4096;

/// The spectra along the line.
#[derive(Debug, Clone)]
pub struct LineSpectra {
    /// The points along the line (px).
    pub points: Vec<(f64, f64)>,
    /// The spectra at those points.
    pub result: SpectraResult,
    /// Frequencies (Hz) of the spectra.
    pub f_hz: Vec<f64>,
    /// f·E(f) of the chosen component: rows = frequency without DC,
    /// columns = positions along the line.
    pub map: Vec<f64>,
}

/// Everything one `ebptv spectra` run computes.
#[derive(Debug, Clone)]
pub struct SpectraRun {
    /// The content of `spectrum.json`.
    pub summary: Value,
    /// The spectra at the points, and `spectra.csv`.
    pub points: Option<SpectraResult>,
    /// The content of `spectra.csv`.
    pub spectra_csv: Option<String>,
    /// The spectra along the line, and `premultiplied_line.csv`.
    pub line: Option<LineSpectra>,
    /// The content of `premultiplied_line.csv`.
    pub line_csv: Option<String>,
    /// Why the per-sample noise estimate is missing, when it is.
    pub noise_warning: Option<String>,
}

fn point_json(p: &PointSpectrum) -> Value {
    json!({
        "x": p.x, "y": p.y, "bin_x": p.bin_x, "bin_y": p.bin_y,
        "peak_hz": p.peak.map(|k| k.f_hz), "peak_u_hz": p.peak_u.map(|k| k.f_hz), "peak_v_hz": p.peak_v.map(|k| k.f_hz),
        "peak_significant": p.peak.is_some(), "peak_false_alarm": p.peak_test.false_alarm,
        "strongest_hz": p.peak_test.strongest.map(|k| k.f_hz), "peak_test_dof": p.peak_test.dof, "f_resolved_hz": p.f_resolved_hz,
        "gap_fraction": p.gap_fraction, "mean_u": p.mean_u, "mean_v": p.mean_v, "rms_u": p.rms_u, "rms_v": p.rms_v,
        "noise_rms_u": p.noise_rms_u, "noise_rms_v": p.noise_rms_v, "rms_ma_u": p.rms_ma_u, "rms_ma_v": p.rms_ma_v,
    })
}

/// Samples of a tracks table and `run_on_samples` on them.
pub fn run_on_tracks(path: &std::path::Path, opt: &RunOptions) -> Result<SpectraRun> {
    opt.validate()?;
    let samples = crate::grid::read_track_samples(path)?;
    run_on_samples(&samples, opt)
}

/// `ebptv spectra` on track samples: the spectra at the points and along
/// the line, the per-sample noise, `spectrum.json` and the CSV tables.
pub(crate) fn run_on_samples(samples: &[Sample], a: &RunOptions) -> Result<SpectraRun> {
    a.validate()?;
    let opt = a.spectra_options()?;
    let calib = a.calibration.as_ref();
    let k2 = a.psd_factor();
    let mut out = SpectraRun {
        summary: json!({}),
        points: None,
        spectra_csv: None,
        line: None,
        line_csv: None,
        noise_warning: None,
    };
    let summary = &mut out.summary;

    if !a.points.is_empty() {
        let r = point_spectra(samples, &a.points, &opt)?;
        let first = &r.points[0];
        *summary = json!({
            "peak_hz": first.peak.map(|k| k.f_hz),
            "peak_significant": first.peak.is_some(), "peak_false_alarm": first.peak_test.false_alarm,
            "false_alarm_level": PEAK_FALSE_ALARM, "strongest_hz": first.peak_test.strongest.map(|k| k.f_hz),
            "fs_hz": r.frames.rate_hz(), "frame_step_us": r.frames.step_us, "frames": r.frames.n,
            "nperseg": a.nperseg, "n_segments": first.psd_u.n_segments, "df_hz": first.psd_u.df(),
            "noise_rms": r.noise_rms, "max_speed": r.max_speed, "dynamic_range": r.dynamic_range,
            "points": r.points.iter().map(point_json).collect::<Vec<_>>(),
        });
        if let Some(c) = calib {
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
        out.spectra_csv = Some(s);
        out.points = Some(r);
    }

    if let Some((x0, y0, x1, y1)) = a.line {
        let pts = line_points((x0, y0), (x1, y1), a.line_points);
        let r = point_spectra(samples, &pts, &opt)?;
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
        summary["line"] = json!({
            "from": [x0, y0], "to": [x1, y1], "component": a.component.name(),
            "points": r.points.iter().map(point_json).collect::<Vec<_>>(),
        });
        if summary.get("noise_rms").is_none() {
            summary["noise_rms"] = json!(r.noise_rms);
            summary["max_speed"] = json!(r.max_speed);
            summary["dynamic_range"] = json!(r.dynamic_range);
            summary["peak_hz"] = json!(r.points[0].peak.map(|k| k.f_hz));
        }
        out.line_csv = Some(s);
        out.line = Some(LineSpectra {
            points: pts,
            result: r,
            f_hz: f,
            map,
        });
    }
    // Per-sample noise and dynamic range from pairs of samples at one pulse
    // (the spectral floor above is the noise of the binned time series).
    let acc = crate::grid::bin_samples(samples, opt.lattice, Weighting::TopHat)?;
    let g = crate::grid::estimate(
        &acc,
        &crate::grid::EstimateOptions {
            fit: crate::grid::Fit::Linear,
            min_count: a.min_count,
            noise_rms: 0.0,
        },
    )?;
    match crate::grid::noise::velocity_noise(samples, &g, &Default::default()) {
        Ok(n) => {
            out.summary["velocity_noise_rms"] = json!(n.noise_rms);
            out.summary["dynamic_range_per_sample"] = json!(n.dynamic_range);
        }
        Err(e) => out.noise_warning = Some(e.to_string()),
    }
    Ok(out)
}
