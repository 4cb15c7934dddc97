//! Live monitor (below).
