//! The model check of a recording file (`check::check_recording`).
use super::modelcheck_common::base;

use crate::events::{Chunk, Geometry};
use crate::modelcheck::check::{check_recording_capped, ModelCheckOptions};

/// A recording longer than the cap is checked on its first events only:
/// both blocks lie before the last event read, and the notes say so.
#[test]
fn a_long_recording_is_checked_on_its_first_events() {
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
    let t_cap = rec.events.t[..cap].iter().copied().max().unwrap() as f64;
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
    assert!(
        run.notes
            .iter()
            .any(|n| n.contains(&format!("first {cap} events"))),
        "{:?}",
        run.notes
    );
    // "fit on B pulses before t = S us, judged on the B after".
    let blocks = run.notes.iter().find(|n| n.starts_with("fit on")).unwrap();
    let f: Vec<f64> = blocks.split(' ').filter_map(|w| w.parse().ok()).collect();
    let (b, split) = (f[0], f[1]);
    let period = 1e6 / sc.light.pulse_hz;
    assert!(
        split + b * period <= t_cap + period,
        "{blocks}; last event read at {t_cap}"
    );
}
