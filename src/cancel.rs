//! A way to stop a long run from another thread: the caller keeps a
//! [`Cancel`] and sets it (e.g. on Ctrl-C); the run looks at it between
//! chunks, pulses or simulations and stops with an error.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use crate::error::{Error, Result};

/// A flag, shared by its clones, that asks a run to stop. The default is
/// never set.
#[derive(Clone, Debug, Default)]
pub struct Cancel(Arc<AtomicBool>);

impl Cancel {
    /// A flag not set.
    pub fn new() -> Self {
        Self::default()
    }

    /// Asks every run holding a clone of this flag to stop.
    pub fn cancel(&self) {
        self.0.store(true, Ordering::Relaxed);
    }

    /// Whether [`Cancel::cancel`] was called.
    pub fn is_cancelled(&self) -> bool {
        self.0.load(Ordering::Relaxed)
    }

    /// An error (`cancelled`) once the flag is set: a run returns it to stop.
    pub(crate) fn check(&self) -> Result<()> {
        if self.is_cancelled() {
            Err(Error::analysis("cancelled"))
        } else {
            Ok(())
        }
    }
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;

    #[ebptv_macros::unit_test]
    fn a_clone_sees_the_cancel() {
        let c = Cancel::new();
        let d = c.clone();
        assert!(c.check().is_ok());
        d.cancel();
        assert!(c.is_cancelled());
        assert_eq!(c.check().unwrap_err().to_string(), "cancelled");
    }
}
