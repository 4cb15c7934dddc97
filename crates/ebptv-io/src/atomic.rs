//! Files that appear under their final name only when complete.
//!
//! Every output of ebptv (event files, CSV, JSON, PNG) goes through
//! [`AtomicFile`]: bytes go to a hidden temporary file in the same directory,
//! which is renamed over the target on [`AtomicFile::commit`]. Dropped without
//! commit (an error, a panic, Ctrl-C unwinding), the temporary is removed, so
//! a failed run never leaves a half-written file that looks like a result.
//!
//! A whole run can be made to leave nothing either: after [`track_run`]
//! every temporary, every committed target and every directory made by
//! [`create_output_dir`] is recorded, and [`rollback`] (the command line
//! calls it on an error and on Ctrl-C) removes them: committed outputs,
//! temporaries still open, then the directories the run created if they are
//! empty. Errors name the target, never the hidden temporary.

use std::fs::File;
use std::io::{BufWriter, Seek, SeekFrom, Write};
use std::path::{Path, PathBuf};

use crate::error::{Error, Result};

/// What the current run made (recorded once [`track_run`] was called).
#[derive(Default)]
struct Made {
    active: bool,
    temps: Vec<PathBuf>,
    committed: Vec<PathBuf>,
    dirs: Vec<PathBuf>,
}

static MADE: std::sync::Mutex<Made> = std::sync::Mutex::new(Made {
    active: false,
    temps: Vec::new(),
    committed: Vec::new(),
    dirs: Vec::new(),
});

fn made() -> std::sync::MutexGuard<'static, Made> {
    MADE.lock().unwrap_or_else(|e| e.into_inner())
}

/// Record what this process writes, for [`rollback`].
pub fn track_run() {
    made().active = true;
}

/// Create the output directory `dir` (and missing parents); the
/// directories created are recorded for [`rollback`].
pub fn create_output_dir(dir: impl AsRef<Path>) -> Result<()> {
    let dir = dir.as_ref();
    let mut missing = Vec::new();
    let mut p = Some(dir);
    while let Some(d) = p {
        if d.as_os_str().is_empty() || d.exists() {
            break;
        }
        missing.push(d.to_path_buf());
        p = d.parent();
    }
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let mut m = made();
    if m.active {
        // Outermost last: removed after the inner ones.
        m.dirs.extend(missing);
    }
    Ok(())
}

/// Remove everything the run made (see the module doc); returns the number
/// of files removed. Holds the record's lock: no new temporary appears
/// meanwhile (a Ctrl-C handler calls this, then exits).
pub fn rollback() -> usize {
    let mut m = made();
    let mut n = 0;
    let mut files = std::mem::take(&mut m.temps);
    files.append(&mut m.committed);
    for f in files {
        n += std::fs::remove_file(&f).is_ok() as usize;
    }
    for d in std::mem::take(&mut m.dirs) {
        let _ = std::fs::remove_dir(&d);
    }
    n
}

/// Rollback, keeping the lock until the process exits (Ctrl-C).
pub fn rollback_and_exit(code: i32) -> ! {
    rollback();
    let _hold = made();
    std::process::exit(code)
}

/// A file written under a temporary name and renamed onto its target only when complete, so a failed run never leaves a truncated output.
pub struct AtomicFile {
    target: PathBuf,
    tmp: PathBuf,
    writer: Option<BufWriter<File>>,
}

impl AtomicFile {
    /// Starts writing to a temporary file next to `target`.
    pub fn create(target: impl AsRef<Path>) -> Result<Self> {
        let target = target.as_ref().to_path_buf();
        let dir = match target.parent() {
            Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
            _ => PathBuf::from("."),
        };
        let name = target
            .file_name()
            .ok_or_else(|| {
                Error::param("output", format!("{} is not a file path", target.display()))
            })?
            .to_string_lossy()
            .into_owned();
        let tmp = dir.join(format!(".{}.{}.partial", name, std::process::id()));
        let file = {
            let mut m = made();
            let file = File::create(&tmp).map_err(|e| Error::io(&target, e))?;
            if m.active {
                m.temps.push(tmp.clone());
            }
            file
        };
        Ok(AtomicFile {
            target,
            tmp,
            writer: Some(BufWriter::with_capacity(1 << 20, file)),
        })
    }

    /// The path the file gets when it is committed.
    pub fn target(&self) -> &Path {
        &self.target
    }

    /// Flush, sync and rename onto the target.
    pub fn commit(mut self) -> Result<()> {
        let w = self.writer.take().expect("writer present until commit");
        let file = w
            .into_inner()
            .map_err(|e| Error::io(&self.target, e.into_error()))?;
        file.sync_all().map_err(|e| Error::io(&self.target, e))?;
        drop(file);
        let mut m = made();
        let renamed = std::fs::rename(&self.tmp, &self.target);
        if m.active {
            m.temps.retain(|t| t != &self.tmp);
            if renamed.is_ok() {
                m.committed.push(self.target.clone());
            }
        }
        drop(m);
        if let Err(e) = renamed {
            let _ = std::fs::remove_file(&self.tmp);
            return Err(Error::io(&self.target, e));
        }
        Ok(())
    }

    /// Ask the OS to start writing the bytes written so far (up to the
    /// last buffer flush) to disk, without waiting for it. Large streamed
    /// outputs call this now and then, so [`Self::commit`]'s sync finds
    /// little left to write instead of stalling the end of the run on
    /// hundreds of MB (Linux `sync_file_range`; elsewhere nothing). A
    /// hint: errors are ignored (the commit's sync reports real ones).
    pub fn start_writeback(&self) {
        #[cfg(target_os = "linux")]
        if let Some(w) = &self.writer {
            use std::os::fd::AsRawFd;
            // SAFETY: a plain syscall on a file descriptor we own; offset 0
            // and length 0 mean the whole file.
            unsafe {
                libc::sync_file_range(w.get_ref().as_raw_fd(), 0, 0, libc::SYNC_FILE_RANGE_WRITE);
            }
        }
    }

    /// Convenience: write a whole byte buffer atomically.
    pub fn write_all_to(target: impl AsRef<Path>, bytes: &[u8]) -> Result<()> {
        let mut f = AtomicFile::create(target)?;
        f.write_all(bytes)
            .map_err(|e| Error::io(f.target.clone(), e))?;
        f.commit()
    }
}

impl Write for AtomicFile {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        self.writer.as_mut().expect("not committed").write(buf)
    }
    fn write_all(&mut self, buf: &[u8]) -> std::io::Result<()> {
        self.writer.as_mut().expect("not committed").write_all(buf)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        self.writer.as_mut().expect("not committed").flush()
    }
}

/// Seeking (flushes the buffer first) lets streaming writers patch a header
/// whose content is known only at the end (the `.npy` shape).
impl Seek for AtomicFile {
    fn seek(&mut self, pos: SeekFrom) -> std::io::Result<u64> {
        self.writer.as_mut().expect("not committed").seek(pos)
    }
}

impl Drop for AtomicFile {
    fn drop(&mut self) {
        if self.writer.take().is_some() {
            let _ = std::fs::remove_file(&self.tmp);
            let mut m = made();
            if m.active {
                m.temps.retain(|t| t != &self.tmp);
            }
        }
    }
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;

    #[ebptv_macros::unit_test]
    fn uncommitted_file_leaves_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("out.csv");
        {
            let mut f = AtomicFile::create(&target).unwrap();
            f.write_all(b"half").unwrap();
        }
        assert!(!target.exists());
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
    }

    /// A directory that cannot be written: the error names the target the
    /// user asked for, not the hidden temporary.
    #[ebptv_macros::unit_test]
    fn errors_name_the_target() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("missing").join("out.csv");
        let e = AtomicFile::create(&target).err().unwrap().to_string();
        assert!(e.contains("out.csv") && !e.contains(".partial"), "{e}");
    }

    #[ebptv_macros::unit_test]
    fn committed_file_has_content() {
        let dir = tempfile::tempdir().unwrap();
        let target = dir.path().join("out.csv");
        AtomicFile::write_all_to(&target, b"a,b\n").unwrap();
        assert_eq!(std::fs::read(&target).unwrap(), b"a,b\n");
    }
}
