//! iniVation AEDAT 4.0 — reader (to be implemented).

use std::path::Path;

use crate::error::{Error, Result};
use crate::events::Chunk;
use crate::io::{EventSource, StreamInfo};

pub struct Aedat4Reader {
    info: StreamInfo,
}

impl Aedat4Reader {
    pub fn open(path: &Path, _chunk_events: usize) -> Result<Self> {
        Err(Error::UnknownFormat {
            path: path.to_path_buf(),
            why: "iniVation AEDAT 4.0 reader not implemented yet".into(),
        })
    }
}

impl EventSource for Aedat4Reader {
    fn info(&self) -> &StreamInfo {
        &self.info
    }
    fn next_chunk(&mut self, chunk: &mut Chunk) -> Result<bool> {
        chunk.clear();
        Ok(false)
    }
}
