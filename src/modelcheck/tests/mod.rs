//! Unit tests of the model check: distances and signatures against
//! references, the decision rules, the search on hidden effects.

pub(crate) mod baseline;
pub(crate) mod check;
pub(crate) mod decision;
pub(crate) mod hidden_more;
pub(crate) mod modelcheck_common;
pub(crate) mod scene;
pub(crate) mod signatures;
pub(crate) mod workflow;
