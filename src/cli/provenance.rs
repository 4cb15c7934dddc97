//! After a command succeeded: record how its outputs were made
//! (`ebptv::provenance`) in `OUT/provenance.json` and under the key
//! `"provenance"` of the command's JSON report. `track` records its own
//! (the library knows the pulse source and writes the Parquet metadata).

use std::path::{Path, PathBuf};

use ebptv::io::atomic::AtomicFile;
use ebptv::provenance::Provenance;

use super::Command;

/// Where a command writes, what it reads, its report and its parameters.
pub struct Plan {
    out: PathBuf,
    inputs: Vec<PathBuf>,
    reports: &'static [&'static str],
    parameters: String,
}

/// The plan of `cmd`, or `None` for commands that write no folder
/// (`info`, `convert`, `monitor`) or record their own (`track`, `demo`).
pub fn plan(cmd: &Command) -> Option<Plan> {
    let p = |out: &Path, inputs: Vec<PathBuf>, reports, params: String| {
        Some(Plan {
            out: out.to_path_buf(),
            inputs,
            reports,
            parameters: params,
        })
    };
    match cmd {
        Command::Grid(a) => p(&a.out, a.tracks.to_vec(), &["grid.json"], format!("{a:?}")),
        Command::Spectra(a) => p(
            &a.out,
            vec![a.tracks.clone()],
            &["spectrum.json"],
            format!("{a:?}"),
        ),
        Command::Piv(a) => p(&a.out, vec![a.recording.clone()], &[], format!("{a:?}")),
        Command::PivImages(a) => p(&a.out, a.images.clone(), &[], format!("{a:?}")),
        Command::Compare(a) => p(&a.out, vec![], &["compare.json"], format!("{a:?}")),
        Command::Pulses(a) => p(
            &a.out,
            vec![a.file.clone()],
            &["pulses.json"],
            format!("{a:?}"),
        ),
        Command::ModelCheck(a) => p(
            &a.out,
            vec![a.measured.clone()],
            &["model_check.json"],
            format!("{a:?}"),
        ),
        Command::Simulate(a) => a
            .out
            .as_ref()
            .and_then(|out| p(out, vec![], &["summary.json"], format!("{a:?}"))),
        _ => None,
    }
}

impl Plan {
    /// Write `provenance.json` and add the record to the reports.
    pub fn record(self, command_line: &[String]) -> anyhow::Result<()> {
        let mut prov = Provenance::new(command_line.iter().cloned());
        for input in &self.inputs {
            // A folder or a pattern given as input is named, not hashed.
            if input.is_file() {
                prov = prov.with_input(input)?;
            }
        }
        // The parsed options, defaults included, as the command saw them.
        prov.parameters = Some(serde_json::Value::String(self.parameters));
        prov.write_to_dir(&self.out)?;
        for name in self.reports {
            let path = self.out.join(name);
            if !path.is_file() {
                continue;
            }
            let text = std::fs::read_to_string(&path).map_err(|e| ebptv::Error::io(&path, e))?;
            let mut v: serde_json::Value = serde_json::from_str(&text)?;
            if let Some(o) = v.as_object_mut() {
                o.insert("provenance".into(), prov.to_json());
                AtomicFile::write_all_to(
                    &path,
                    (serde_json::to_string_pretty(&v)? + "\n").as_bytes(),
                )?;
            }
        }
        Ok(())
    }
}
