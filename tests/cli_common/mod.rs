//! Running the `ebptv` binary from integration tests.

use std::process::{Command, Output};

/// The binary under test.
pub fn ebptv() -> Command {
    Command::new(env!("CARGO_BIN_EXE_ebptv"))
}

/// Run `cmd`; fail the test with the command's stderr if it does not succeed.
pub fn run_ok(cmd: &mut Command) -> Output {
    let out = cmd.output().expect("starting ebptv");
    assert!(
        out.status.success(),
        "{:?} failed:\n{}",
        cmd,
        String::from_utf8_lossy(&out.stderr)
    );
    out
}
