//! Prophesee evt3 — reader (to be implemented).

use std::path::Path;

use crate::error::{Error, Result};
use crate::events::Chunk;
use crate::io::{EventSource, StreamInfo};

pub struct Evt3Reader {
    info: StreamInfo,
}

impl Evt3Reader {
    pub fn open(path: &Path, _chunk_events: usize) -> Result<Self> {
        Err(Error::UnknownFormat {
            path: path.to_path_buf(),
            why: "Prophesee evt3 reader not implemented yet".into(),
        })
    }
}

impl EventSource for Evt3Reader {
    fn info(&self) -> &StreamInfo {
        &self.info
    }
    fn next_chunk(&mut self, chunk: &mut Chunk) -> Result<bool> {
        chunk.clear();
        Ok(false)
    }
}

pub struct Evt3Writer;

impl Evt3Writer {
    pub fn create(path: &Path, _geometry: crate::events::Geometry) -> Result<Self> {
        Err(Error::param(
            "output",
            format!("{}: writer not implemented yet", path.display()),
        ))
    }
}

impl crate::io::EventWriter for Evt3Writer {
    fn write_chunk(&mut self, _chunk: &Chunk) -> Result<()> {
        Ok(())
    }
    fn finish(self: Box<Self>) -> Result<()> {
        Ok(())
    }
}
