//! CSV — reader (to be implemented).

use std::path::Path;

use crate::error::{Error, Result};
use crate::events::Chunk;
use crate::io::{EventSource, StreamInfo};

pub struct CsvReader {
    info: StreamInfo,
}

impl CsvReader {
    pub fn open(path: &Path, _chunk_events: usize, _unit: Option<TimeUnit>) -> Result<Self> {
        Err(Error::UnknownFormat {
            path: path.to_path_buf(),
            why: "CSV reader not implemented yet".into(),
        })
    }
}

impl EventSource for CsvReader {
    fn info(&self) -> &StreamInfo {
        &self.info
    }
    fn next_chunk(&mut self, chunk: &mut Chunk) -> Result<bool> {
        chunk.clear();
        Ok(false)
    }
}

/// Unit of a CSV time column.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TimeUnit {
    Microseconds,
    Seconds,
}

pub struct CsvWriter;

impl CsvWriter {
    pub fn create(path: &Path) -> Result<Self> {
        Err(Error::param(
            "output",
            format!("{}: writer not implemented yet", path.display()),
        ))
    }
}

impl crate::io::EventWriter for CsvWriter {
    fn write_chunk(&mut self, _chunk: &Chunk) -> Result<()> {
        Ok(())
    }
    fn finish(self: Box<Self>) -> Result<()> {
        Ok(())
    }
}
