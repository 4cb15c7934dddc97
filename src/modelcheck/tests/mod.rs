//! Unit tests of the model check: distances and signatures against
//! references, the decision rules, the search on hidden effects.

mod baseline;
mod check;
mod decision;
mod hidden_more;
mod modelcheck_common;
mod scene;
mod signatures;
mod workflow;
