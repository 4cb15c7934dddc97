//! The model check of a recording file (`check::check_recording`).
use super::modelcheck_common::base;

use crate::events::{Chunk, Geometry};
use crate::modelcheck::check::{check_recording_capped, ModelCheckOptions};

/// A recording longer than the cap is checked on a stretch around its
/// middle (two passes): both blocks lie inside the stretch read, next to
/// the recording's middle, and the notes say so.
#[ebptv_macros::unit_test]
fn a_long_recording_is_checked_around_its_middle() {
    let dir = tempfile::tempdir().unwrap();
    let mut sc = base();
    sc.duration_s = 0.1;
    let model = dir.path().join("model.toml");
    std::fs::write(&model, sc.to_toml_string().unwrap()).unwrap();
    let rec = crate::sim::simulate(&sc, 4242).unwrap();
    let path = dir.path().join("m.raw");
    let geometry = Geometry::new(160, 120); // base()'s sensor
    let mut w = crate::io::create(&path, None, geometry).unwrap();
    w.write_chunk(&Chunk {
        events: rec.events.clone(),
        triggers: rec.triggers.clone(),
    })
    .unwrap();
    w.finish().unwrap();
    let cap = rec.events.len() / 2;
    let (t0, t1) = (
        *rec.events.t.iter().min().unwrap() as f64,
        *rec.events.t.iter().max().unwrap() as f64,
    );
    let opts = ModelCheckOptions {
        model: Some(model),
        replicates: 3,
        evaluations: 3,
        max_effects: 1,
        ..ModelCheckOptions::default()
    };
    let run = check_recording_capped(
        &path,
        &dir.path().join("out"),
        &opts,
        &crate::Cancel::new(),
        cap,
    )
    .unwrap();
    let read = run
        .notes
        .iter()
        .find(|n| n.contains("around the middle"))
        .unwrap_or_else(|| panic!("{:?}", run.notes));
    // "read N events around the middle of a recording of M (t = A..B us …".
    let n: Vec<f64> = read
        .split([' ', '(', '.'])
        .filter_map(|w| w.parse().ok())
        .collect();
    assert!(n[0] <= cap as f64 && n[0] > 0.8 * cap as f64, "{read}");
    assert_eq!(n[1], rec.events.len() as f64, "{read}");
    let (lo, hi) = (n[2], n[3]);
    // "fit on B pulses before t = S us, judged on the B after".
    let blocks = run.notes.iter().find(|n| n.starts_with("fit on")).unwrap();
    let f: Vec<f64> = blocks.split(' ').filter_map(|w| w.parse().ok()).collect();
    let (b, split) = (f[0], f[1]);
    let period = 1e6 / sc.light.pulse_hz;
    assert!(
        split - b * period >= lo - period && split + b * period <= hi + period,
        "{blocks}; read {read}"
    );
    assert!(
        (split - 0.5 * (t0 + t1)).abs() <= 2.0 * period,
        "{blocks}; the recording spans {t0}..{t1} us"
    );
}
