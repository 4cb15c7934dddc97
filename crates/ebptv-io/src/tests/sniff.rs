//! Format detection on the real recordings (every format), on renamed
//! copies (content beats extension), and on things that are not event data.

use std::path::Path;

use ebptv_io::sniff::detect_format;
use ebptv_io::Format;

fn real_dir() -> Option<std::path::PathBuf> {
    let p = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../..")
        .join("../shared/data/real");
    if p.exists() {
        Some(p)
    } else {
        eprintln!("skipping: {} not found", p.display());
        None
    }
}

#[ebptv_macros::unit_test]
fn real_files_are_recognised_by_content_even_when_renamed() {
    let Some(dir) = real_dir() else { return };
    let tmp = tempfile::tempdir().unwrap();
    for (name, want) in [
        ("evt3_sample.raw", Format::Evt3),
        ("evt2_sample.raw", Format::Evt2),
        ("faery_evt2.raw", Format::Evt2),
        ("ncars_sample.dat", Format::Dat),
        ("davis346_test.aedat4", Format::Aedat4),
        ("atis_dvs.es", Format::Es),
    ] {
        let src = dir.join(name);
        if !src.exists() {
            eprintln!("skipping {name}");
            continue;
        }
        assert_eq!(detect_format(&src).unwrap(), want, "{name}");
        // The same bytes under a misleading name.
        let renamed = tmp.path().join(format!("{name}.csv"));
        std::fs::copy(&src, &renamed).unwrap();
        assert_eq!(
            detect_format(&renamed).unwrap(),
            want,
            "{name} renamed .csv"
        );
    }
}

#[ebptv_macros::unit_test]
fn text_and_foreign_files() {
    let tmp = tempfile::tempdir().unwrap();
    let write = |name: &str, bytes: &[u8]| {
        let p = tmp.path().join(name);
        std::fs::write(&p, bytes).unwrap();
        p
    };
    assert_eq!(
        detect_format(&write("a.raw", b"x,y,p,t\n3,4,1,100\n")).unwrap(),
        Format::Csv
    );
    assert_eq!(
        detect_format(&write("b.dat", b"0.000001 3 4 1\n0.000002 5 6 0\n")).unwrap(),
        Format::Csv
    );
    let e = detect_format(&write("c.raw", b"%PDF-1.7\n%\xe2\xe3\xcf\xd3\n"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("PDF") && e.contains("c.raw"), "{e}");
    let e = detect_format(&write("d.bin", b"\x00\x01\x02\x03\x04\x05"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("00 01 02 03") && e.contains("d.bin"), "{e}");
    let e = detect_format(&tmp.path().join("missing.raw"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("missing.raw"), "{e}");
}
