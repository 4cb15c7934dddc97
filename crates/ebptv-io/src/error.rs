//! The library's error type.
//!
//! Every error names *where* it happened (file, byte offset, word index,
//! parameter name) and *what* is wrong, so that a user pointing ebptv at a
//! 10 GB recording knows which file and which byte to look at. The CLI wraps
//! these with `anyhow` only at the very edge.

use std::path::{Path, PathBuf};

/// Result alias used across the library.
pub type Result<T, E = Error> = std::result::Result<T, E>;

/// Every error of reading, writing or analysing event data; file errors name the file.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// An operating-system error while reading or writing a file.
    /// (The cause is part of the message, not a `source()`, so that error
    /// chains printed with `{:#}` do not repeat it.)
    #[error("{path}: {cause}")]
    Io {
        /// The file concerned.
        path: PathBuf,
        /// The operating-system error.
        cause: std::io::Error,
    },

    /// The file is of a known format but its content is malformed.
    #[error("{path}: {what} (at byte {offset})")]
    Corrupt {
        /// The file concerned.
        path: PathBuf,
        /// Byte offset of the malformed content.
        offset: u64,
        /// What is wrong.
        what: String,
    },

    /// The file could not be recognised as any supported event format.
    #[error("{path}: not a recognised event file: {why}")]
    UnknownFormat {
        /// The file concerned.
        path: PathBuf,
        /// Why no format matched.
        why: String,
    },

    /// The file holds no events (or nothing in the requested selection).
    #[error("{path}: {why}")]
    Empty {
        /// The file concerned.
        path: PathBuf,
        /// What is missing.
        why: String,
    },

    /// A user-supplied parameter is out of its meaningful range.
    #[error("invalid parameter `{name}`: {why}")]
    InvalidParameter {
        /// The parameter's name.
        name: String,
        /// What is wrong with its value.
        why: String,
    },

    /// A scenario / configuration file is malformed.
    #[error("{path}: {why}")]
    Config {
        /// The file concerned.
        path: PathBuf,
        /// What is wrong.
        why: String,
    },

    /// The data does not allow the requested analysis (e.g. no pulses found).
    #[error("{0}")]
    Analysis(String),
}

impl Error {
    /// An operating-system error on `path`.
    pub fn io(path: impl AsRef<Path>, source: std::io::Error) -> Self {
        Error::Io {
            path: path.as_ref().to_path_buf(),
            cause: source,
        }
    }

    /// Malformed content in `path` at byte `offset`.
    pub fn corrupt(path: impl AsRef<Path>, offset: u64, what: impl Into<String>) -> Self {
        Error::Corrupt {
            path: path.as_ref().to_path_buf(),
            offset,
            what: what.into(),
        }
    }

    /// A parameter `name` out of its meaningful range.
    pub fn param(name: impl Into<String>, why: impl Into<String>) -> Self {
        Error::InvalidParameter {
            name: name.into(),
            why: why.into(),
        }
    }

    /// The data do not allow the requested analysis.
    pub fn analysis(why: impl Into<String>) -> Self {
        Error::Analysis(why.into())
    }
}
