//! Runs a crate's unit tests from its integration-test binary.
//!
//! A unit test (`#[ebptv_macros::unit_test]`) is a `pub(crate)` function
//! in a `testkit`-only module next to the code it tests. A crate's build
//! script calls [`run`], which scans the crate's `src/` for the attribute
//! and writes two files to `OUT_DIR`:
//!
//! - `unit_index.rs`, included at the crate root under `testkit`: a
//!   hidden `pub mod unit_tests` with, for every test, a `pub fn` of the
//!   same module path that calls it (the tests themselves stay
//!   crate-private);
//! - `unit_tests.rs`, included by the crate's integration-test binary:
//!   for every test a `#[test]` of the same module path (and the same
//!   `#[ignore]`) that calls the index.
//!
//! So the crate is compiled once, with its test kit, instead of once more
//! as a unit-test harness.
//!
//! The scan reads rustfmt-formatted source line by line: a file's module
//! path follows from its place under `src/` (`a/mod.rs` and `a.rs` are
//! `a`), inline modules (`mod name {`) nest by their indentation, and the
//! attribute is followed by further attributes and then `fn name`. A
//! plain `#[test]` or `cfg(test)` in `src/` is an error: without a
//! unit-test build it would never run.

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::fs;
use std::io;
use std::path::{Path, PathBuf};

/// The marker the scan looks for.
const MARKER: &str = "#[ebptv_macros::unit_test]";

/// One unit test: its module path in the crate and its function name.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord)]
struct UnitTest {
    /// Module path from the crate root (empty for the root).
    module: Vec<String>,
    /// Name of the function.
    name: String,
    /// Its `#[ignore]` or `#[ignore = "why"]` attribute, if any: run only
    /// on request.
    ignore: Option<String>,
}

/// For a build script: scan `$CARGO_MANIFEST_DIR/src`, write both files
/// to `$OUT_DIR` for the crate `crate_name` (as the integration tests
/// name it, e.g. `ebptv_io`).
pub fn run(crate_name: &str) {
    let manifest = std::env::var_os("CARGO_MANIFEST_DIR").expect("CARGO_MANIFEST_DIR");
    let out = std::env::var_os("OUT_DIR").expect("OUT_DIR");
    let src = Path::new(&manifest).join("src");
    println!("cargo:rerun-if-changed={}", src.display());
    let tests = match scan(&src) {
        Ok(t) => t,
        Err(e) => panic!("scanning {} for unit tests: {e}", src.display()),
    };
    let out = Path::new(&out);
    write(&out.join("unit_index.rs"), &index(&tests));
    write(&out.join("unit_tests.rs"), &wrappers(&tests, crate_name));
}

fn write(path: &Path, text: &str) {
    if let Err(e) = fs::write(path, text) {
        panic!("writing {}: {e}", path.display());
    }
}

/// Every unit test under `src` (a crate's source folder), sorted.
fn scan(src: &Path) -> io::Result<Vec<UnitTest>> {
    let mut files = Vec::new();
    collect(src, &mut files)?;
    let mut tests = Vec::new();
    for f in files {
        let rel = f.strip_prefix(src).expect("under src");
        let Some(module) = file_module(rel) else {
            continue;
        };
        let text = fs::read_to_string(&f)?;
        scan_text(&text, &module, &mut tests).map_err(|e| {
            io::Error::new(io::ErrorKind::InvalidData, format!("{}: {e}", f.display()))
        })?;
    }
    tests.sort();
    Ok(tests)
}

fn collect(dir: &Path, files: &mut Vec<PathBuf>) -> io::Result<()> {
    for entry in fs::read_dir(dir)? {
        let p = entry?.path();
        if p.is_dir() {
            collect(&p, files)?;
        } else if p.extension().is_some_and(|e| e == "rs") {
            files.push(p);
        }
    }
    Ok(())
}

/// The module path of a file under `src/`; `None` for a binary's root.
fn file_module(rel: &Path) -> Option<Vec<String>> {
    let mut parts: Vec<String> = rel
        .iter()
        .map(|c| c.to_string_lossy().into_owned())
        .collect();
    let last = parts.pop()?;
    match last.as_str() {
        "lib.rs" if parts.is_empty() => {}
        "main.rs" if parts.is_empty() => return None,
        "mod.rs" => {}
        _ => parts.push(last.trim_end_matches(".rs").to_string()),
    }
    Some(parts)
}

/// The unit tests of one file whose module path is `module`.
fn scan_text(text: &str, module: &[String], tests: &mut Vec<UnitTest>) -> Result<(), String> {
    // Open inline modules: (indentation of the `mod` line, name).
    let mut open: Vec<(usize, String)> = Vec::new();
    let mut pending: Option<(usize, Option<String>)> = None;
    for (no, line) in text.lines().enumerate() {
        let indent = line.len() - line.trim_start().len();
        let t = line.trim();
        if let Some(&(ind, _)) = open.last() {
            if indent == ind && t.starts_with('}') {
                open.pop();
                continue;
            }
        }
        if let Some((at, ignore)) = pending.take() {
            if t.starts_with("#[ignore") {
                pending = Some((at, Some(t.to_string())));
            } else if let Some(name) = fn_name(t) {
                let mut m = module.to_vec();
                m.extend(open.iter().map(|(_, n)| n.clone()));
                tests.push(UnitTest {
                    module: m,
                    name,
                    ignore,
                });
            } else if t.starts_with("#[") || t.starts_with("//") {
                pending = Some((at, ignore));
            } else {
                return Err(format!(
                    "line {}: `{MARKER}` is not followed by a `fn`",
                    at + 1
                ));
            }
            continue;
        }
        let code = !t.starts_with("//");
        if code && (t == "#[test]" || t.contains("cfg(test)") || t.contains("cfg(not(test))")) {
            return Err(format!(
                "line {}: the crate has no unit-test build, so `{t}` would never run; \
                 write `{MARKER}` or `cfg(feature = \"testkit\")`",
                no + 1
            ));
        }
        if t == MARKER {
            pending = Some((no, None));
        } else if let Some(name) = inline_mod(t) {
            open.push((indent, name));
        }
    }
    match pending {
        Some((at, _)) => Err(format!("line {}: `{MARKER}` at the end", at + 1)),
        None => Ok(()),
    }
}

/// `name` of `fn name(` (no visibility: the attribute adds it).
fn fn_name(t: &str) -> Option<String> {
    let rest = t.strip_prefix("fn ")?;
    let end = rest.find(|c: char| !(c.is_alphanumeric() || c == '_'))?;
    Some(rest[..end].to_string())
}

/// `name` of an inline module's opening line, `[pub(..)] mod name {`.
fn inline_mod(t: &str) -> Option<String> {
    let t = t
        .strip_prefix("pub(crate) ")
        .or_else(|| t.strip_prefix("pub "))
        .unwrap_or(t);
    let rest = t.strip_prefix("mod ")?;
    let name = rest.strip_suffix('{')?.trim();
    (!name.is_empty() && name.chars().all(|c| c.is_alphanumeric() || c == '_'))
        .then(|| name.to_string())
}

/// A module tree of tests, for writing nested `mod` blocks.
#[derive(Default)]
struct Tree<'a> {
    tests: Vec<&'a UnitTest>,
    children: BTreeMap<&'a str, Tree<'a>>,
}

fn tree(tests: &[UnitTest]) -> Tree<'_> {
    let mut root = Tree::default();
    for t in tests {
        let mut node = &mut root;
        for m in &t.module {
            node = node.children.entry(m.as_str()).or_default();
        }
        node.tests.push(t);
    }
    root
}

/// Writes `node` as nested `{vis}mod` blocks, each test by `leaf(test, indentation)`.
fn emit(
    node: &Tree,
    depth: usize,
    vis: &str,
    out: &mut String,
    leaf: &dyn Fn(&UnitTest, &str) -> String,
) {
    let pad = "    ".repeat(depth);
    for t in &node.tests {
        for line in leaf(t, &pad).lines() {
            let _ = writeln!(out, "{line}");
        }
    }
    for (name, child) in &node.children {
        let _ = writeln!(out, "{pad}{vis}mod {name} {{");
        emit(child, depth + 1, vis, out, leaf);
        let _ = writeln!(out, "{pad}}}");
    }
}

/// The crate-side index: `pub fn` per test calling it.
fn index(tests: &[UnitTest]) -> String {
    let mut out = String::from(
        "// Written by ebptv-testgen from the crate's #[unit_test] functions.\n\
         /// The crate's unit tests, for its integration-test binary.\n\
         #[doc(hidden)]\npub mod unit_tests {\n",
    );
    emit(&tree(tests), 1, "pub ", &mut out, &|t, pad| {
        let path: String = t.module.iter().map(|m| format!("{m}::")).collect();
        format!(
            "{pad}pub fn {n}() {{\n{pad}    crate::{path}{n}()\n{pad}}}",
            n = t.name
        )
    });
    out.push_str("}\n");
    out
}

/// The integration-test side: a `#[test]` per test calling the index.
fn wrappers(tests: &[UnitTest], crate_name: &str) -> String {
    let mut out =
        String::from("// Written by ebptv-testgen from the crate's #[unit_test] functions.\n");
    emit(&tree(tests), 0, "", &mut out, &|t, pad| {
        let path: String = t.module.iter().map(|m| format!("{m}::")).collect();
        let ignore = match &t.ignore {
            Some(attr) => format!("{pad}{attr}\n"),
            None => String::new(),
        };
        format!(
            "{pad}#[test]\n{ignore}{pad}fn {n}() {{\n{pad}    {crate_name}::unit_tests::{path}{n}()\n{pad}}}",
            n = t.name
        )
    });
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scan_one(text: &str, module: &[&str]) -> Result<Vec<UnitTest>, String> {
        let module: Vec<String> = module.iter().map(|m| m.to_string()).collect();
        let mut out = Vec::new();
        scan_text(text, &module, &mut out)?;
        Ok(out)
    }

    #[test]
    fn finds_tests_in_nested_inline_modules_with_their_ignore() {
        let text = r#"
fn add(a: u32, b: u32) -> u32 { a + b }

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;

    /// Adds.
    #[ebptv_macros::unit_test]
    fn sums() {}

    mod inner {
        #[ebptv_macros::unit_test]
        #[ignore = "slow"]
        fn slow_one() {}
    }

    #[ebptv_macros::unit_test]
    #[allow(clippy::unit_cmp)]
    fn after_inner() {}
}
"#;
        let got = scan_one(text, &["grid", "noise"]).unwrap();
        let names: Vec<(String, &str, Option<&str>)> = got
            .iter()
            .map(|t| (t.module.join("::"), t.name.as_str(), t.ignore.as_deref()))
            .collect();
        assert_eq!(
            names,
            [
                ("grid::noise::tests".to_string(), "sums", None),
                (
                    "grid::noise::tests::inner".to_string(),
                    "slow_one",
                    Some("#[ignore = \"slow\"]")
                ),
                ("grid::noise::tests".to_string(), "after_inner", None),
            ]
        );
    }

    #[test]
    fn a_plain_test_or_cfg_test_is_an_error() {
        for bad in [
            "#[cfg(test)]\nmod tests {}",
            "mod t {\n    #[test]\n    fn x() {}\n}",
        ] {
            let e = scan_one(bad, &[]).unwrap_err();
            assert!(e.contains("never run"), "{e}");
        }
        // A comment may name them.
        assert!(scan_one("//! Not under `cfg(test)`: see #[test].", &[]).is_ok());
        let e = scan_one("#[ebptv_macros::unit_test]\nconst X: u8 = 1;", &[]).unwrap_err();
        assert!(e.contains("not followed by a `fn`"), "{e}");
    }

    #[test]
    fn file_paths_give_module_paths() {
        let m = |p: &str| file_module(Path::new(p));
        assert_eq!(m("lib.rs"), Some(vec![]));
        assert_eq!(m("main.rs"), None);
        assert_eq!(m("grid/mod.rs"), Some(vec!["grid".to_string()]));
        assert_eq!(
            m("track/tests/slice.rs"),
            Some(vec!["track".into(), "tests".into(), "slice".into()])
        );
    }

    #[test]
    fn index_and_wrappers_mirror_the_module_paths() {
        let tests = vec![UnitTest {
            module: vec!["a".into(), "tests".into()],
            name: "works".into(),
            ignore: Some("#[ignore]".into()),
        }];
        let index = index(&tests);
        assert!(
            index.contains("pub mod unit_tests {\n    pub mod a {"),
            "{index}"
        );
        assert!(index.contains("crate::a::tests::works()"), "{index}");
        let w = wrappers(&tests, "my_crate");
        assert!(
            w.contains("#[test]\n        #[ignore]\n        fn works()"),
            "{w}"
        );
        assert!(w.contains("my_crate::unit_tests::a::tests::works()"), "{w}");
    }
}
