//! Every command's `--help` teaches: an example section, a description
//! for every option and argument, and nothing about how the code came to
//! be.

use std::process::Command;

fn help(args: &[&str]) -> String {
    let out = Command::new(env!("CARGO_BIN_EXE_ebptv"))
        .args(args)
        .arg("--help")
        .output()
        .unwrap();
    assert!(out.status.success(), "{args:?}");
    String::from_utf8(out.stdout).unwrap()
}

/// The subcommands listed by `ebptv --help`.
fn subcommands() -> Vec<String> {
    let top = help(&[]);
    let mut v = Vec::new();
    let mut inside = false;
    for l in top.lines() {
        if l.starts_with("Commands:") {
            inside = true;
        } else if inside && l.trim().is_empty() {
            break;
        } else if inside {
            let name = l.split_whitespace().next().unwrap().to_string();
            if name != "help" {
                v.push(name);
            }
        }
    }
    v
}

/// Option and argument lines of a help text that carry no description:
/// neither text after the signature on the same line nor an indented
/// description on the next (a bare `[default: …]` does not count).
fn undescribed(h: &str) -> Vec<String> {
    let lines: Vec<&str> = h.lines().collect();
    let mut missing = Vec::new();
    for (i, l) in lines.iter().enumerate() {
        let t = l.trim_start();
        let indent = l.len() - t.len();
        let option = t.starts_with('-') && !t.starts_with("- ");
        if indent == 0 || !(option || t.starts_with('<') || t.starts_with('[')) {
            continue;
        }
        if t.starts_with("[default") || t.starts_with("[possible") {
            continue;
        }
        // Signature, then two or more spaces, then the description.
        let sig_end = t.find("  ");
        if let Some(k) = sig_end {
            let rest = t[k..].trim();
            if !rest.is_empty() && !rest.starts_with("[default") {
                continue;
            }
        }
        let next = lines.get(i + 1).copied().unwrap_or("");
        let nt = next.trim_start();
        let n_indent = next.len() - nt.len();
        if !nt.is_empty() && n_indent > indent && !nt.starts_with("[default") {
            continue;
        }
        missing.push(t.to_string());
    }
    missing
}

#[test]
fn every_help_has_examples_descriptions_and_no_history() {
    let cmds = subcommands();
    assert!(cmds.len() >= 10, "{cmds:?}");
    let top = help(&[]);
    assert!(top.contains("ebptv demo"), "{top}");
    let mut problems = Vec::new();
    for c in std::iter::once(String::new()).chain(cmds) {
        let args: Vec<&str> = if c.is_empty() { vec![] } else { vec![&c] };
        let h = help(&args);
        if !h.contains("\nExamples:\n  ebptv ") {
            problems.push(format!("{c}: no Examples section"));
        }
        for m in undescribed(&h) {
            problems.push(format!("{c}: no description for {m}"));
        }
        for w in ["session", "Session", "TrackParams", "before"] {
            if h.contains(w) {
                problems.push(format!("{c}: the help mentions {w:?}"));
            }
        }
    }
    assert!(problems.is_empty(), "{}", problems.join("\n"));
}

#[test]
fn the_description_check_finds_a_bare_option() {
    let h = "Options:\n      --out <OUT>\n      --bin <BIN>  Bin width [default: 16]\n      --f-max <F>\n          [default: inf]\n      --seed <S>\n          Random seed\n";
    assert_eq!(undescribed(h), ["--out <OUT>", "--f-max <F>"]);
}
