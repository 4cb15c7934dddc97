//! Event Stream (.es) — reader (to be implemented).

use std::path::Path;

use crate::error::{Error, Result};
use crate::events::Chunk;
use crate::io::{EventSource, StreamInfo};

pub struct EsReader {
    info: StreamInfo,
}

impl EsReader {
    pub fn open(path: &Path, _chunk_events: usize) -> Result<Self> {
        Err(Error::UnknownFormat {
            path: path.to_path_buf(),
            why: "Event Stream (.es) reader not implemented yet".into(),
        })
    }
}

impl EventSource for EsReader {
    fn info(&self) -> &StreamInfo {
        &self.info
    }
    fn next_chunk(&mut self, chunk: &mut Chunk) -> Result<bool> {
        chunk.clear();
        Ok(false)
    }
}
