//! Prophesee EVT 2.1 — reader (to be implemented).

use std::path::Path;

use crate::error::{Error, Result};
use crate::events::Chunk;
use crate::io::{EventSource, StreamInfo};

pub struct Evt21Reader {
    info: StreamInfo,
}

impl Evt21Reader {
    pub fn open(path: &Path, _chunk_events: usize) -> Result<Self> {
        Err(Error::UnknownFormat {
            path: path.to_path_buf(),
            why: "Prophesee EVT 2.1 reader not implemented yet".into(),
        })
    }
}

impl EventSource for Evt21Reader {
    fn info(&self) -> &StreamInfo {
        &self.info
    }
    fn next_chunk(&mut self, chunk: &mut Chunk) -> Result<bool> {
        chunk.clear();
        Ok(false)
    }
}
