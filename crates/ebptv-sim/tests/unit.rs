//! The crate's unit tests (`#[ebptv_macros::unit_test]` in src/), under
//! their module paths, compiled into its `testkit` build: one compile of
//! the crate instead of a second one as a unit-test harness.

include!(concat!(env!("OUT_DIR"), "/unit_tests.rs"));
