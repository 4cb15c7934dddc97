//! How an output was made: the ebptv version and commit, the command line,
//! every parameter of the run (defaults included), the input files with a
//! fingerprint, the pulse source and the date.
//!
//! Each command that writes a folder records one `Provenance`: under the
//! key `"provenance"` of its JSON outputs (`summary.json`, `grid.json`, …),
//! in `provenance.json` beside its tables, and in the key/value metadata
//! of its Parquet tables (key `PARQUET_KEY`, the same JSON). CSV tables
//! carry none of it in the file: their first line stays the header row,
//! which header-first readers (`numpy.loadtxt(skiprows=1)`, spreadsheet
//! imports, the scorers of the evaluation) rely on; `provenance.json`
//! beside them says how they were made. `ebptv info OUT_DIR` prints it.
//!
//! The input fingerprint is the file's size and the SHA-256 of its first
//! and of its last MiB (the whole file may be many GB), so a user can check
//! a recording against an output with standard tools:
//! `head -c 1048576 FILE | sha256sum` and `tail -c 1048576 FILE | sha256sum`.

use std::fs::File;
use std::io::{Read, Seek, SeekFrom};
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::{Error, Result};

/// The key of the provenance record in a Parquet file's key/value metadata.
#[ebptv_macros::testkit]
pub(crate) const PARQUET_KEY: &str = "ebptv.provenance";

/// The file the record is written to in an output folder.
pub(crate) const FILE_NAME: &str = "provenance.json";

/// Bytes hashed at each end of an input file.
const HASHED_BYTES: u64 = 1 << 20;

/// How an output was made (see the module doc).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[ebptv_macros::testkit]
pub(crate) struct Provenance {
    /// The ebptv version (`Cargo.toml`).
    pub ebptv_version: String,
    /// The git commit ebptv was built from (`unknown` outside a checkout).
    pub commit: String,
    /// The command line, program name first.
    pub command_line: Vec<String>,
    /// When the run started, UTC, ISO 8601 (`2026-11-27T13:45:07Z`).
    pub created_utc: String,
    /// The input files, with their fingerprints.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub inputs: Vec<InputFingerprint>,
    /// Where the pulse times came from (`triggers`, `estimated`, `forced`…),
    /// for the commands that time pulses.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pulse_source: Option<String>,
    /// Every parameter of the run, defaults included.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub parameters: Option<serde_json::Value>,
}

/// An input file: its path, size and the SHA-256 of its first and last MiB.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[ebptv_macros::testkit]
pub(crate) struct InputFingerprint {
    /// The path as given on the command line.
    pub path: String,
    /// Size in bytes.
    pub size_bytes: u64,
    /// SHA-256 (hex) of the first MiB (the whole file if smaller).
    pub sha256_first_mib: String,
    /// SHA-256 (hex) of the last MiB (the whole file if smaller).
    pub sha256_last_mib: String,
}

impl InputFingerprint {
    /// Fingerprint the file at `path`.
    pub(crate) fn of(path: &Path) -> Result<Self> {
        let io_err = |e: std::io::Error| Error::io(path, e);
        let mut f = File::open(path).map_err(io_err)?;
        let size = f.metadata().map_err(io_err)?.len();
        let first = hash_range(&mut f, 0, size.min(HASHED_BYTES)).map_err(io_err)?;
        let tail = size.min(HASHED_BYTES);
        let last = hash_range(&mut f, size - tail, tail).map_err(io_err)?;
        Ok(Self {
            path: path.display().to_string(),
            size_bytes: size,
            sha256_first_mib: first,
            sha256_last_mib: last,
        })
    }
}

fn hash_range(f: &mut File, start: u64, len: u64) -> std::io::Result<String> {
    f.seek(SeekFrom::Start(start))?;
    let mut h = Sha256::new();
    let mut left = len;
    let mut buf = vec![0u8; 64 * 1024];
    while left > 0 {
        let n = (left as usize).min(buf.len());
        f.read_exact(&mut buf[..n])?;
        h.update(&buf[..n]);
        left -= n as u64;
    }
    Ok(h.finalize().iter().map(|b| format!("{b:02x}")).collect())
}

impl Provenance {
    /// A record for a run started now with `command_line` (program name
    /// first), this build's version and commit.
    pub(crate) fn new<I, S>(command_line: I) -> Self
    where
        I: IntoIterator<Item = S>,
        S: Into<String>,
    {
        Self {
            ebptv_version: env!("CARGO_PKG_VERSION").to_string(),
            commit: env!("EBPTV_COMMIT").to_string(),
            command_line: command_line.into_iter().map(Into::into).collect(),
            created_utc: utc_now(),
            inputs: Vec::new(),
            pulse_source: None,
            parameters: None,
        }
    }

    /// Add an input file's fingerprint.
    pub(crate) fn with_input(mut self, path: &Path) -> Result<Self> {
        self.inputs.push(InputFingerprint::of(path)?);
        Ok(self)
    }

    /// Record the run's parameters (any serialisable settings struct).
    pub(crate) fn with_parameters<T: Serialize>(mut self, params: &T) -> Result<Self> {
        let v = serde_json::to_value(params)
            .map_err(|e| Error::analysis(format!("recording the parameters: {e}")))?;
        self.parameters = Some(v);
        Ok(self)
    }

    /// Record where the pulse times came from.
    pub(crate) fn with_pulse_source(mut self, source: impl Into<String>) -> Self {
        self.pulse_source = Some(source.into());
        self
    }

    /// The record as one JSON value (for a `"provenance"` key).
    #[ebptv_macros::testkit]
    pub(crate) fn to_json(&self) -> serde_json::Value {
        serde_json::to_value(self).expect("a provenance record serialises")
    }

    /// Write `provenance.json` into `dir` (atomically).
    pub(crate) fn write_to_dir(&self, dir: &Path) -> Result<PathBuf> {
        let path = dir.join(FILE_NAME);
        let text = serde_json::to_string_pretty(self)
            .map_err(|e| Error::analysis(format!("writing {}: {e}", path.display())))?;
        crate::io::atomic::AtomicFile::write_all_to(&path, format!("{text}\n").as_bytes())?;
        Ok(path)
    }

    /// Read the record of an output folder: its `provenance.json`, else
    /// the `"provenance"` key of the first JSON file in it that has one.
    /// `Ok(None)` when the folder holds none.
    #[ebptv_macros::testkit]
    pub(crate) fn read_from_dir(dir: &Path) -> Result<Option<Self>> {
        let file = dir.join(FILE_NAME);
        if file.is_file() {
            return Self::read_json_file(&file, false);
        }
        let mut jsons: Vec<PathBuf> = std::fs::read_dir(dir)
            .map_err(|e| Error::io(dir, e))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| p.extension().is_some_and(|x| x == "json"))
            .collect();
        jsons.sort();
        for p in jsons {
            if let Some(r) = Self::read_json_file(&p, true)? {
                return Ok(Some(r));
            }
        }
        Ok(None)
    }

    /// A record from a JSON file: the whole file, or (`nested`) its
    /// `"provenance"` key.
    fn read_json_file(path: &Path, nested: bool) -> Result<Option<Self>> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        let v: serde_json::Value = serde_json::from_str(&text)
            .map_err(|e| Error::analysis(format!("{}: not JSON: {e}", path.display())))?;
        let v = if nested {
            match v.get("provenance") {
                Some(p) => p.clone(),
                None => return Ok(None),
            }
        } else {
            v
        };
        serde_json::from_value(v).map(Some).map_err(|e| {
            Error::analysis(format!(
                "{}: not an ebptv provenance record: {e}",
                path.display()
            ))
        })
    }

    /// A few lines for a terminal (what `ebptv info OUT_DIR` prints).
    pub(crate) fn describe(&self) -> String {
        let mut s = String::new();
        s.push_str(&format!(
            "made by            ebptv {} (commit {})\n",
            self.ebptv_version, self.commit
        ));
        s.push_str(&format!("on                 {}\n", self.created_utc));
        s.push_str(&format!(
            "command            {}\n",
            self.command_line.join(" ")
        ));
        for i in &self.inputs {
            s.push_str(&format!(
                "input              {} ({} bytes; sha256 first MiB {}, last MiB {})\n",
                i.path, i.size_bytes, i.sha256_first_mib, i.sha256_last_mib
            ));
        }
        if let Some(p) = &self.pulse_source {
            s.push_str(&format!("pulse source       {p}\n"));
        }
        match &self.parameters {
            Some(serde_json::Value::Object(o)) => {
                let groups: Vec<&str> = o.keys().map(String::as_str).collect();
                s.push_str(&format!(
                    "parameters         [{}] (every default included; `ebptv info --json DIR` lists them)\n",
                    groups.join("], [")
                ));
            }
            Some(serde_json::Value::String(p)) => {
                s.push_str(&format!("parameters         {p}\n"));
            }
            Some(_) => s.push_str("parameters         recorded\n"),
            None => {}
        }
        s
    }
}

/// Now, UTC, ISO 8601 to the second.
fn utc_now() -> String {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs() as i64)
        .unwrap_or(0);
    iso8601_utc(secs)
}

/// `secs` since the Unix epoch as `YYYY-MM-DDThh:mm:ssZ` (proleptic
/// Gregorian calendar; days to civil date after H. Hinnant's algorithm).
fn iso8601_utc(secs: i64) -> String {
    let days = secs.div_euclid(86_400);
    let sod = secs.rem_euclid(86_400);
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z.rem_euclid(146_097);
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let d = doy - (153 * mp + 2) / 5 + 1;
    let m = if mp < 10 { mp + 3 } else { mp - 9 };
    let y = yoe + era * 400 + i64::from(m <= 2);
    format!(
        "{y:04}-{m:02}-{d:02}T{:02}:{:02}:{:02}Z",
        sod / 3600,
        (sod / 60) % 60,
        sod % 60
    )
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;

    #[ebptv_macros::unit_test]
    fn dates_match_known_instants() {
        assert_eq!(iso8601_utc(0), "1970-01-01T00:00:00Z");
        // 2000-02-29 (a leap day of a century leap year) 12:34:56.
        assert_eq!(iso8601_utc(951_827_696), "2000-02-29T12:34:56Z");
        assert_eq!(iso8601_utc(4_102_444_799), "2099-12-31T23:59:59Z");
        assert_eq!(iso8601_utc(-1), "1969-12-31T23:59:59Z");
    }

    #[ebptv_macros::unit_test]
    fn fingerprint_hashes_both_ends() {
        let dir = tempfile::tempdir().unwrap();
        // Known digest: SHA-256 of "abc".
        let small = dir.path().join("abc");
        std::fs::write(&small, b"abc").unwrap();
        let f = InputFingerprint::of(&small).unwrap();
        let abc = "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad";
        assert_eq!((f.size_bytes, f.sha256_first_mib.as_str()), (3, abc));
        assert_eq!(f.sha256_last_mib, abc);
        // A file over 1 MiB: the two ends differ, and a change in the
        // middle is not seen (only the ends are hashed).
        let big = dir.path().join("big");
        let mut data: Vec<u8> = (0..3 << 20).map(|i| (i % 251) as u8).collect();
        std::fs::write(&big, &data).unwrap();
        let a = InputFingerprint::of(&big).unwrap();
        assert_ne!(a.sha256_first_mib, a.sha256_last_mib);
        data[3 << 19] ^= 1;
        std::fs::write(&big, &data).unwrap();
        assert_eq!(InputFingerprint::of(&big).unwrap(), a);
        data[0] ^= 1;
        std::fs::write(&big, &data).unwrap();
        assert_ne!(
            InputFingerprint::of(&big).unwrap().sha256_first_mib,
            a.sha256_first_mib
        );
        let missing = InputFingerprint::of(&dir.path().join("nope")).unwrap_err();
        assert!(missing.to_string().contains("nope"), "{missing}");
    }

    #[ebptv_macros::unit_test]
    fn a_folder_record_reads_back() {
        let dir = tempfile::tempdir().unwrap();
        assert_eq!(Provenance::read_from_dir(dir.path()).unwrap(), None);
        let p = Provenance::new(["ebptv", "grid", "tracks.csv"])
            .with_pulse_source("triggers")
            .with_parameters(&serde_json::json!({"grid": {"bin": 16}}))
            .unwrap();
        assert_eq!(p.ebptv_version, env!("CARGO_PKG_VERSION"));
        assert!(!p.commit.is_empty());
        // Nested in a JSON output …
        let summary = serde_json::json!({"tracks": 3, "provenance": p.to_json()});
        std::fs::write(dir.path().join("summary.json"), summary.to_string()).unwrap();
        assert_eq!(
            Provenance::read_from_dir(dir.path()).unwrap(),
            Some(p.clone())
        );
        // … and provenance.json, which takes precedence.
        let q = Provenance::new(["ebptv", "track"]);
        q.write_to_dir(dir.path()).unwrap();
        assert_eq!(Provenance::read_from_dir(dir.path()).unwrap(), Some(q));
        assert!(p.describe().contains("ebptv grid tracks.csv"));
    }
}
