//! Prophesee evt2 — reader (to be implemented).

use std::path::Path;

use crate::error::{Error, Result};
use crate::events::Chunk;
use crate::io::{EventSource, StreamInfo};

pub struct Evt2Reader {
    info: StreamInfo,
}

impl Evt2Reader {
    pub fn open(path: &Path, _chunk_events: usize) -> Result<Self> {
        Err(Error::UnknownFormat {
            path: path.to_path_buf(),
            why: "Prophesee evt2 reader not implemented yet".into(),
        })
    }
}

impl EventSource for Evt2Reader {
    fn info(&self) -> &StreamInfo {
        &self.info
    }
    fn next_chunk(&mut self, chunk: &mut Chunk) -> Result<bool> {
        chunk.clear();
        Ok(false)
    }
}

pub struct Evt2Writer;

impl Evt2Writer {
    pub fn create(path: &Path, _geometry: crate::events::Geometry) -> Result<Self> {
        Err(Error::param(
            "output",
            format!("{}: writer not implemented yet", path.display()),
        ))
    }
}

impl crate::io::EventWriter for Evt2Writer {
    fn write_chunk(&mut self, _chunk: &Chunk) -> Result<()> {
        Ok(())
    }
    fn finish(self: Box<Self>) -> Result<()> {
        Ok(())
    }
}
