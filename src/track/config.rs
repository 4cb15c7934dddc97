//! The full set of options of a tracking run ([`TrackConfig`]): how the
//! pulses are found and the output written ([`RunParams`]), the
//! clustering ([`ClusterParams`]) and the tracker ([`TrackParams`]).
//! `ebptv track --params FILE` reads it from TOML (every key optional,
//! unknown keys an error) and every run writes the set it used to
//! `OUT/params.toml`, which can be edited and passed back.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::{SliceParams, TrackParams};
use crate::cluster::ClusterParams;
use crate::error::{Error, Result};

/// Everything a tracking run is set up with: one TOML table per part
/// (`[run]`, `[cluster]`, `[track]` with `[track.gates]`, `[track.init]`,
/// `[track.stitch]`, `[track.fit]`).
#[derive(Debug, Clone, Default, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrackConfig {
    /// Pulses, linking schedule and outputs.
    pub run: RunParams,
    /// Particle images from events.
    pub cluster: ClusterParams,
    /// Tracks from particles.
    pub track: TrackParams,
}

/// How a run finds its pulses, schedules its work and what it writes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RunParams {
    /// Nominal pulse frequency (Hz) when pulse times are estimated from
    /// the events (a recording without a trigger channel).
    pub pulse_hz: Option<f64>,
    /// Ignore the trigger channel and estimate pulse times from the events.
    pub ignore_triggers: bool,
    /// Go on even when the events show no bursts locked to pulses.
    pub force_pulses: bool,
    /// Uniform mean flow `[U, V]` (px/s) that guides the first step of new
    /// tracks ([`TrackParams::prior`]).
    pub prior: Option<[f64; 2]>,
    /// File of pixels to ignore, one `x,y` per line (added to
    /// `cluster.hot_pixels`).
    pub hot_pixels: Option<PathBuf>,
    /// A `calib.toml` ([`crate::calib::Calibration`]): `tracks.csv` gains
    /// the physical columns `X_mm,Y_mm,U_m_s,V_m_s` and its `[mask]`
    /// applies as `mask` does.
    pub calibration: Option<PathBuf>,
    /// A mask image (PNG, non-zero = not flow, the sensor's size): its
    /// events are ignored, no track is stitched across it, and it is
    /// copied to `OUT/mask.png` for `ebptv grid`.
    pub mask: Option<PathBuf>,
    /// Pulses shown in `tracks.png`, from the first pulse: a short window
    /// keeps single tracks visible at high seeding densities.
    pub plot_pulses: i64,
    /// The format of the `particles` and `tracks` tables: `parquet`,
    /// `csv` or `npy` (`ebptv --table-format`).
    pub table_format: crate::table::TableFormat,
    /// Also write `tracks.npy` (the `tracks` columns as a structured
    /// array) next to the tables.
    pub npy: bool,
    /// Pulses clustered per parallel batch.
    pub batch: usize,
    /// `sequential` (one tracker over the whole run) or `sliced`
    /// (independent trackers on time slices joined at the seams: the same
    /// result for any thread count, ~40 % more CPU and ~5× the memory).
    pub linker: Linker,
    /// Pulses per slice of the sliced linker.
    pub slice_pulses: usize,
    /// Pulses each slice's tracker also sees on both sides.
    pub slice_overlap: usize,
}

/// The linking schedule ([`RunParams::linker`]).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum Linker {
    /// One tracker over the whole run.
    #[default]
    Sequential,
    /// Independent trackers on time slices (`track::slice::SliceTracker`).
    Sliced,
}

impl Default for RunParams {
    fn default() -> Self {
        let slices = SliceParams::default();
        RunParams {
            pulse_hz: None,
            ignore_triggers: false,
            force_pulses: false,
            prior: None,
            hot_pixels: None,
            calibration: None,
            mask: None,
            plot_pulses: 20,
            table_format: crate::table::TableFormat::Parquet,
            npy: false,
            batch: 64,
            linker: Linker::Sequential,
            slice_pulses: slices.slice_pulses,
            slice_overlap: slices.overlap,
        }
    }
}

impl RunParams {
    /// `ebptv track --mask FILE`: a PNG (by its signature) becomes
    /// [`RunParams::mask`], anything else a hot-pixel list
    /// ([`RunParams::hot_pixels`]).
    pub(crate) fn set_mask_file(&mut self, path: &Path) -> Result<()> {
        use std::io::Read;
        let mut head = [0u8; 8];
        let mut f = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
        let n = f.read(&mut head).map_err(|e| Error::io(path, e))?;
        if n == 8 && head == *b"\x89PNG\r\n\x1a\n" {
            self.mask = Some(path.to_path_buf());
        } else {
            self.hot_pixels = Some(path.to_path_buf());
        }
        Ok(())
    }

    /// The slicing of the sliced linker.
    pub(crate) fn slicing(&self) -> SliceParams {
        SliceParams {
            slice_pulses: self.slice_pulses,
            overlap: self.slice_overlap,
            in_flight: 0,
        }
    }
}

impl TrackConfig {
    /// Parse a TOML text; `path` names the file in errors (which name the
    /// offending key and its line).
    pub(crate) fn from_toml(text: &str, path: &Path) -> Result<Self> {
        toml::from_str(text).map_err(|e| Error::Config {
            path: path.to_path_buf(),
            why: e.to_string().trim_end().to_string(),
        })
    }

    /// Read a TOML file.
    pub(crate) fn read(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        Self::from_toml(&text, path)
    }

    /// The set as TOML, every key written (optional ones only when set).
    pub(crate) fn to_toml(&self) -> Result<String> {
        let body = toml::to_string(self)
            .map_err(|e| Error::analysis(format!("writing the options as TOML: {e}")))?;
        Ok(format!(
            "# The options of an `ebptv track` run; pass the file back with --params.\n\
             # Keys left out take their defaults. Optional keys are written only when\n\
             # set: run.pulse_hz, run.prior = [U, V] (px/s), run.hot_pixels (a file),\n\
             # track.fit.fit_accel_rms (unset: estimated from the tracks).\n\n{body}"
        ))
    }
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;

    #[ebptv_macros::unit_test]
    fn a_partial_file_takes_the_defaults_and_round_trips() {
        let c = TrackConfig::from_toml(
            "[track]\nmax_disp = 7.5\n[track.fit]\nfit_window = 15\n[run]\nnpy = true\n",
            Path::new("p.toml"),
        )
        .unwrap();
        assert_eq!(c.track.max_disp, 7.5);
        assert_eq!(c.track.fit.fit_window, 15);
        assert_eq!(c.track.min_length, TrackParams::default().min_length);
        assert!(c.run.npy);
        let text = c.to_toml().unwrap();
        let back = TrackConfig::from_toml(&text, Path::new("p.toml")).unwrap();
        assert_eq!(back.to_toml().unwrap(), text);
        assert_eq!(back.track.fit.fit_window, 15);
    }

    #[ebptv_macros::unit_test]
    fn unknown_keys_are_refused_by_name_and_file() {
        for text in [
            "[track]\nmax_dsip = 3.0\n",
            "[track.gates]\nnsigma = 3\n",
            "[runs]\n",
        ] {
            let e = TrackConfig::from_toml(text, Path::new("my.toml"))
                .unwrap_err()
                .to_string();
            assert!(e.starts_with("my.toml:"), "{e}");
            let key = ["max_dsip", "nsigma", "runs"]
                .into_iter()
                .find(|k| text.contains(k))
                .unwrap();
            assert!(e.contains(key), "{e}");
        }
    }

    /// The stripped tracker BENCHMARKS.md measures must stay a valid file
    /// that switches off what it says it does.
    #[ebptv_macros::unit_test]
    fn the_benchmarks_stripped_tracker_parses_and_strips() {
        let text = include_str!("../../benches/stripped_tracker.toml");
        let c = TrackConfig::from_toml(text, Path::new("stripped_tracker.toml")).unwrap();
        let d = TrackParams::default();
        let t = &c.track;
        assert!(d.turn_model && !t.turn_model);
        assert!(d.gates.repair_lag > 0 && t.gates.repair_lag == 0);
        assert!(d.init.back_extend > 0 && t.init.back_extend == 0);
        assert!(d.init.ghost_check_length > 0 && t.init.ghost_check_length == 0);
        assert!(d.stitch.step_split > 0.0 && t.stitch.step_split == 0.0);
        assert!(d.fit.outlier_sigma > 0.0 && t.fit.outlier_sigma == 0.0);
        assert!(t.fit.fit_min_window == t.fit.fit_window);
        assert_eq!(t.max_disp, d.max_disp);
    }
}
