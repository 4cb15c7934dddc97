//! The library's error type.
//!
//! Every error names *where* it happened (file, byte offset, word index,
//! parameter name) and *what* is wrong, so that a user pointing ebptv at a
//! 10 GB recording knows which file and which byte to look at. The CLI wraps
//! these with `anyhow` only at the very edge.

use std::path::{Path, PathBuf};

/// Result alias used across the library.
pub type Result<T, E = Error> = std::result::Result<T, E>;

#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// An operating-system error while reading or writing a file.
    /// (The cause is part of the message, not a `source()`, so that error
    /// chains printed with `{:#}` do not repeat it.)
    #[error("{path}: {cause}")]
    Io {
        path: PathBuf,
        cause: std::io::Error,
    },

    /// The file is of a known format but its content is malformed.
    #[error("{path}: {what} (at byte {offset})")]
    Corrupt {
        path: PathBuf,
        offset: u64,
        what: String,
    },

    /// The file could not be recognised as any supported event format.
    #[error("{path}: not a recognised event file: {why}")]
    UnknownFormat { path: PathBuf, why: String },

    /// The file holds no events (or nothing in the requested selection).
    #[error("{path}: {why}")]
    Empty { path: PathBuf, why: String },

    /// A user-supplied parameter is out of its meaningful range.
    #[error("invalid parameter `{name}`: {why}")]
    InvalidParameter { name: String, why: String },

    /// A scenario / configuration file is malformed.
    #[error("{path}: {why}")]
    Config { path: PathBuf, why: String },

    /// The data does not allow the requested analysis (e.g. no pulses found).
    #[error("{0}")]
    Analysis(String),
}

impl Error {
    pub fn io(path: impl AsRef<Path>, source: std::io::Error) -> Self {
        Error::Io {
            path: path.as_ref().to_path_buf(),
            cause: source,
        }
    }

    pub fn corrupt(path: impl AsRef<Path>, offset: u64, what: impl Into<String>) -> Self {
        Error::Corrupt {
            path: path.as_ref().to_path_buf(),
            offset,
            what: what.into(),
        }
    }

    pub fn param(name: impl Into<String>, why: impl Into<String>) -> Self {
        Error::InvalidParameter {
            name: name.into(),
            why: why.into(),
        }
    }

    pub fn analysis(why: impl Into<String>) -> Self {
        Error::Analysis(why.into())
    }
}
