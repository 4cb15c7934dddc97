//! NumPy `.npy` writers (to be implemented).

use std::path::Path;

use crate::error::{Error, Result};
use crate::events::Chunk;

pub struct NpyEventWriter;

impl NpyEventWriter {
    pub fn create(path: &Path) -> Result<Self> {
        Err(Error::param(
            "output",
            format!("{}: writer not implemented yet", path.display()),
        ))
    }
}

impl crate::io::EventWriter for NpyEventWriter {
    fn write_chunk(&mut self, _chunk: &Chunk) -> Result<()> {
        Ok(())
    }
    fn finish(self: Box<Self>) -> Result<()> {
        Ok(())
    }
}
