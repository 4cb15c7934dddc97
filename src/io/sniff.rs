//! Format detection from content, then extension (to be implemented).

use std::path::Path;

use crate::error::{Error, Result};
use crate::io::Format;

pub fn detect_format(path: &Path) -> Result<Format> {
    format_from_extension(path).ok_or_else(|| Error::UnknownFormat {
        path: path.to_path_buf(),
        why: "format detection not implemented yet".into(),
    })
}

pub fn format_from_extension(path: &Path) -> Option<Format> {
    let ext = path.extension()?.to_str()?.to_ascii_lowercase();
    Format::from_name(&ext)
}
