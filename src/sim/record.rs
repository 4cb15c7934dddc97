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
use crate::decimal::RevDigits;
use crate::error::{Error, Result};
use crate::events::{Chunk, Geometry};
use crate::io::atomic::AtomicFile;
use crate::io::{EventSource, Format};

/// Streams truth rows to `truth_particles.csv`.
pub struct TruthWriter {
    file: AtomicFile,
    line: Vec<u8>,
}

impl TruthWriter {
    pub const HEADER: &'static str = "pulse,t_us,particle_id,x,y,u,v";

    pub fn create(path: impl AsRef<Path>) -> Result<TruthWriter> {
        let mut file = AtomicFile::create(path.as_ref())?;
        writeln!(file, "{}", Self::HEADER).map_err(|e| Error::io(path.as_ref(), e))?;
        Ok(TruthWriter {
            file,
            line: Vec::with_capacity(96),
        })
    }

    /// Append `rows`, formatted in batches of ~64 kB (one `write_all`
    /// per batch rather than per row).
    pub fn write(&mut self, rows: &[TruthSample]) -> Result<()> {
        for batch in rows.chunks(1024) {
            self.line.clear();
            for r in batch {
                truth_line(&mut self.line, r);
            }
            self.file
                .write_all(&self.line)
                .map_err(|e| Error::io(self.file.target().to_path_buf(), e))?;
        }
        Ok(())
    }

    pub fn finish(self) -> Result<()> {
        self.file.commit()
    }
}

/// One CSV row of the truth (with newline), byte for byte what
/// [`truth_line_reference`] writes, but without `core::fmt`'s exact float
/// formatting (which was 40 % of the CPU time of a full-frame
/// `ebptv simulate`).
pub fn truth_line(line: &mut Vec<u8>, r: &TruthSample) {
    // Built from its end in one buffer (≤ 20 + 6·18 + 7 bytes), appended
    // with one copy; a row with a value near a rounding tie is written
    // by the reference instead.
    let mut b = RevDigits::<160>::new();
    b.byte(b'\n');
    let fast = b.fixed(r.v, 3)
        && {
            b.byte(b',');
            b.fixed(r.u, 3)
        }
        && {
            b.byte(b',');
            b.fixed(r.y, 4)
        }
        && {
            b.byte(b',');
            b.fixed(r.x, 4)
        }
        && {
            b.byte(b',');
            b.u64(r.particle_id);
            b.byte(b',');
            b.fixed(r.t_us, 3)
        };
    if fast {
        b.byte(b',');
        b.i64(r.pulse);
        line.extend_from_slice(b.as_slice());
    } else {
        truth_line_reference(line, r);
    }
}

/// The plain definition of a truth row.
pub fn truth_line_reference(line: &mut Vec<u8>, r: &TruthSample) {
    use std::io::Write as _;
    let _ = writeln!(
        line,
        "{},{:.3},{},{:.4},{:.4},{:.3},{:.3}",
        r.pulse, r.t_us, r.particle_id, r.x, r.y, r.u, r.v
    );
}

/// `summary.json`.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct RecordingSummary {
    pub scenario: String,
    pub seed: u64,
    pub recording: PathBuf,
    pub format: Format,
    /// The run's counters, as top-level keys of the JSON.
    #[serde(flatten)]
    pub stats: SimStats,
    pub event_rate_ev_s: f64,
    pub events_per_particle_per_pulse: f64,
}

impl RecordingSummary {
    fn new(sc: &Scenario, seed: u64, recording: PathBuf, format: Format, st: &SimStats) -> Self {
        RecordingSummary {
            scenario: sc.name.clone(),
            seed,
            recording,
            format,
            stats: st.clone(),
            event_rate_ev_s: st.event_rate_ev_s(),
            events_per_particle_per_pulse: st.events_per_particle_per_pulse(),
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
///
/// Simulation and writing overlap: the simulator runs on the calling
/// thread (itself parallel through rayon, in the caller's pool) while a
/// second thread encodes the events and formats the truth, one or two
/// blocks behind. Blocks are written in order, so the files do not depend
/// on this. The writer commits its files only after the last block; on
/// any error nothing appears under a final name.
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
    enum Msg {
        Block {
            chunk: Chunk,
            truth: Vec<TruthSample>,
        },
        /// All blocks sent: commit.
        End,
    }
    let stats = std::thread::scope(|scope| -> Result<SimStats> {
        // Two blocks in flight: the simulator waits only if the writer is
        // the slower side.
        let (tx, rx) = std::sync::mpsc::sync_channel::<Msg>(2);
        // Written chunks go back to the simulator for reuse.
        let (back_tx, back_rx) = std::sync::mpsc::channel::<Chunk>();
        let writer_thread = scope.spawn(move || -> Result<()> {
            let mut writer = crate::io::create(dir.join(name), Some(format), geometry)?;
            let mut truth = TruthWriter::create(dir.join("truth_particles.csv"))?;
            for msg in rx.iter() {
                match msg {
                    Msg::Block { chunk, truth: rows } => {
                        if !chunk.is_empty() {
                            writer.write_chunk(&chunk)?;
                        }
                        truth.write(&rows)?;
                        let _ = back_tx.send(chunk);
                    }
                    Msg::End => {
                        writer.finish()?;
                        return truth.finish();
                    }
                }
            }
            // The simulator stopped early: drop both files uncommitted.
            Ok(())
        });
        let mut sent_all = false;
        let mut sim_result = Ok(());
        loop {
            let mut chunk = back_rx.try_recv().unwrap_or_default();
            let more = match sim.next_chunk(&mut chunk) {
                Ok(m) => m,
                Err(e) => {
                    sim_result = Err(e);
                    break;
                }
            };
            let (done, total) = sim.progress();
            let msg = Msg::Block {
                chunk,
                truth: sim.take_truth(),
            };
            // A closed channel means the writer failed: its error is below.
            if tx.send(msg).is_err() {
                break;
            }
            progress(done, total);
            if !more {
                sent_all = tx.send(Msg::End).is_ok();
                break;
            }
        }
        drop(tx);
        let written = writer_thread
            .join()
            .map_err(|_| Error::analysis("recording writer thread panicked"))?;
        sim_result?;
        written?;
        if !sent_all {
            return Err(Error::analysis("recording writer stopped early (bug)"));
        }
        Ok(sim.stats().clone())
    })?;
    let summary = RecordingSummary::new(sc, seed, PathBuf::from(name), format, &stats);
    let toml = sc.to_toml_string()?;
    let json = serde_json::to_string_pretty(&summary)
        .map_err(|e| Error::analysis(format!("summary: {e}")))?;
    // The big files are committed; the small ones last mark completion.
    AtomicFile::write_all_to(dir.join("scenario.toml"), toml.as_bytes())?;
    AtomicFile::write_all_to(dir.join("summary.json"), json.as_bytes())?;
    Ok(summary)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::{Rng, SeedableRng};

    #[test]
    fn truth_line_matches_reference() {
        let mut rng = rand_pcg::Pcg64::seed_from_u64(4);
        let (mut a, mut b) = (Vec::new(), Vec::new());
        for _ in 0..10_000 {
            let r = TruthSample {
                pulse: rng.gen_range(-5_000_000..1_000_000),
                t_us: rng.gen_range(0.0..1e7),
                particle_id: rng.gen(),
                x: rng.gen_range(-10.0..1300.0),
                y: rng.gen_range(-10.0..730.0),
                u: rng.gen_range(-5e4..5e4),
                v: rng.gen_range(-5e4..5e4),
            };
            a.clear();
            b.clear();
            truth_line(&mut a, &r);
            truth_line_reference(&mut b, &r);
            assert_eq!(a, b);
        }
        // Values at rounding ties (the row falls back to the reference),
        // negative zero, huge and non-finite values, in every field.
        let odd = [
            0.00005,
            0.0625,
            -0.0,
            2.5e-4,
            1.0005,
            1e16,
            f64::NAN,
            -f64::INFINITY,
        ];
        for (i, &v) in odd.iter().enumerate() {
            for field in 0..5 {
                let mut r = TruthSample {
                    pulse: -(i as i64),
                    t_us: 12.5,
                    particle_id: u64::MAX - i as u64,
                    x: 3.25,
                    y: -7.125,
                    u: 1e4,
                    v: -2e4,
                };
                match field {
                    0 => r.t_us = v,
                    1 => r.x = v,
                    2 => r.y = v,
                    3 => r.u = v,
                    _ => r.v = v,
                }
                a.clear();
                b.clear();
                truth_line(&mut a, &r);
                truth_line_reference(&mut b, &r);
                assert_eq!(a, b, "{v} in field {field}");
            }
        }
    }
}
