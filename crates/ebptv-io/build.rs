//! Indexes the crate's unit tests (`#[ebptv_macros::unit_test]`) for
//! tests/unit.rs: see the `ebptv-testgen` crate.
fn main() {
    ebptv_testgen::run("ebptv_io");
}
