//! Writing a simulated recording to a directory: the event file, the truth,
//! the scenario actually used and a summary — each through `AtomicFile`, so
//! an interrupted run leaves no half-written file under a final name.
//!
//! Files (the contract of `ebptv simulate`):
//! - `recording.raw` (EVT 3.0 with trigger words; EVT 2.0 also `.raw`),
//!   `recording.csv` or `recording.npy`, depending on the format;
//! - `truth_particles.csv`: `pulse,t_us,particle_id,x,y,u,v` — one row per
//!   lit particle per pulse with its image centre in the ROI (px, px/s;
//!   `t_us` the pulse start);
//! - `scenario.toml`: the scenario as simulated (after `--seconds`);
//! - `summary.json`: see [`RecordingSummary`].

use std::io::Write;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::{Scenario, SimStats, Simulator, TruthSample};
use crate::error::{Error, Result};
use crate::events::{Chunk, Geometry};
use crate::io::atomic::AtomicFile;
use crate::io::{EventSource, Format};

/// Streams truth rows to `truth_particles.csv`.
pub struct TruthWriter {
    file: AtomicFile,
    line: String,
}

impl TruthWriter {
    pub const HEADER: &'static str = "pulse,t_us,particle_id,x,y,u,v";

    pub fn create(path: impl AsRef<Path>) -> Result<TruthWriter> {
        let mut file = AtomicFile::create(path.as_ref())?;
        writeln!(file, "{}", Self::HEADER).map_err(|e| Error::io(path.as_ref(), e))?;
        Ok(TruthWriter {
            file,
            line: String::with_capacity(96),
        })
    }

    pub fn write(&mut self, rows: &[TruthSample]) -> Result<()> {
        use std::fmt::Write as _;
        for r in rows {
            self.line.clear();
            let _ = writeln!(
                self.line,
                "{},{:.3},{},{:.4},{:.4},{:.3},{:.3}",
                r.pulse, r.t_us, r.particle_id, r.x, r.y, r.u, r.v
            );
            self.file
                .write_all(self.line.as_bytes())
                .map_err(|e| Error::io(self.file.target().to_path_buf(), e))?;
        }
        Ok(())
    }

    pub fn finish(self) -> Result<()> {
        self.file.commit()
    }
}

/// `summary.json`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RecordingSummary {
    pub scenario: String,
    pub seed: u64,
    pub recording: PathBuf,
    pub format: Format,
    pub events: u64,
    pub on_events: u64,
    pub off_events: u64,
    pub triggers: u64,
    pub pulses: u64,
    /// Particle slots simulated (slab over ROI plus margin).
    pub particles: u64,
    /// Lit particles in the ROI summed over pulses (= truth rows).
    pub truth_samples: u64,
    pub duration_s: f64,
    pub event_rate_ev_s: f64,
    pub events_per_particle_per_pulse: f64,
    pub lost_in_readout: u64,
}

impl RecordingSummary {
    fn new(sc: &Scenario, seed: u64, recording: PathBuf, format: Format, st: &SimStats) -> Self {
        RecordingSummary {
            scenario: sc.name.clone(),
            seed,
            recording,
            format,
            events: st.events,
            on_events: st.on_events,
            off_events: st.off_events,
            triggers: st.triggers,
            pulses: st.pulses,
            particles: st.particles,
            truth_samples: st.truth_samples,
            duration_s: st.duration_s,
            event_rate_ev_s: st.event_rate_ev_s(),
            events_per_particle_per_pulse: st.events_per_particle_per_pulse(),
            lost_in_readout: st.lost_in_readout,
        }
    }
}

/// File name of the recording for `format`.
pub fn recording_name(format: Format) -> Result<&'static str> {
    Ok(match format {
        Format::Evt3 | Format::Evt2 => "recording.raw",
        Format::Csv => "recording.csv",
        Format::Npy => "recording.npy",
        other => {
            return Err(Error::param(
                "format",
                format!(
                    "simulate cannot write {}; use evt3, evt2, csv or npy",
                    other.name()
                ),
            ))
        }
    })
}

/// Simulate `sc` and write the recording and its truth into `dir`.
/// `progress(pulses_done, pulses_total)` is called after every block.
pub fn write_recording(
    sc: &Scenario,
    seed: u64,
    dir: &Path,
    format: Format,
    mut progress: impl FnMut(u64, u64),
) -> Result<RecordingSummary> {
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let mut sim = Simulator::new(sc, seed)?;
    let name = recording_name(format)?;
    let geometry = Geometry::new(sc.sensor.width as u16, sc.sensor.height as u16);
    let mut writer = crate::io::create(dir.join(name), Some(format), geometry)?;
    let mut truth = TruthWriter::create(dir.join("truth_particles.csv"))?;
    let mut chunk = Chunk::default();
    while sim.next_chunk(&mut chunk)? {
        writer.write_chunk(&chunk)?;
        truth.write(&sim.take_truth())?;
        let (done, total) = sim.progress();
        progress(done, total);
    }
    truth.write(&sim.take_truth())?;
    let summary = RecordingSummary::new(sc, seed, PathBuf::from(name), format, sim.stats());
    let toml = sc.to_toml_string()?;
    let json = serde_json::to_string_pretty(&summary)
        .map_err(|e| Error::analysis(format!("summary: {e}")))?;
    // Commit the big files first; the small ones last mark completion.
    writer.finish()?;
    truth.finish()?;
    AtomicFile::write_all_to(dir.join("scenario.toml"), toml.as_bytes())?;
    AtomicFile::write_all_to(dir.join("summary.json"), json.as_bytes())?;
    Ok(summary)
}
