//! Records the git commit the binary is built from (`EBPTV_COMMIT`, read by
//! `ebptv::provenance`), or `unknown` outside a git checkout. The build
//! script runs again when the checkout's HEAD moves.
//!
//! It also indexes the library's unit tests (`#[ebptv_macros::unit_test]`)
//! for the integration-test binary: see the `ebptv-testgen` crate.

use std::process::Command;

fn git(args: &[&str]) -> Option<String> {
    let out = Command::new("git").args(args).output().ok()?;
    if !out.status.success() {
        return None;
    }
    let s = String::from_utf8(out.stdout).ok()?.trim().to_string();
    (!s.is_empty()).then_some(s)
}

fn main() {
    println!("cargo:rerun-if-changed=build.rs");
    println!("cargo:rerun-if-env-changed=EBPTV_COMMIT");
    let commit = std::env::var("EBPTV_COMMIT")
        .ok()
        .filter(|s| !s.is_empty())
        .or_else(|| git(&["rev-parse", "HEAD"]))
        .unwrap_or_else(|| "unknown".into());
    // Rebuild when HEAD, the branch it names or the packed refs change.
    for path in ["HEAD", "packed-refs"] {
        if let Some(p) = git(&["rev-parse", "--git-path", path]) {
            println!("cargo:rerun-if-changed={p}");
        }
    }
    if let Some(branch) = git(&["symbolic-ref", "-q", "HEAD"]) {
        if let Some(p) = git(&["rev-parse", "--git-path", &branch]) {
            println!("cargo:rerun-if-changed={p}");
        }
    }
    println!("cargo:rustc-env=EBPTV_COMMIT={commit}");
    ebptv_testgen::run("ebptv");
}
