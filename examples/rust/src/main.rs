//! ebptv as a user's dependency sees it (default features, no `testkit`):
//! the crate documentation's pipeline (`pipeline.rs`, which `src/lib.rs`
//! shows as its runnable example) run on a simulated recording, and the
//! stage entry points named once, so that this build fails when one of
//! them stops being public. `tools/test-all` runs it.

use std::error::Error;
use std::path::Path;

include!("pipeline.rs");

fn main() -> Result<(), Box<dyn Error>> {
    let dir = std::env::temp_dir().join(format!("ebptv-example-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let path = dir.join("vortex.raw");
    let result = simulated_recording(&path).and_then(|()| pipeline(&path));
    std::fs::remove_dir_all(&dir)?;
    result
}

/// 50 pulses of the `demo` preset (a vortex at 5 kHz) as EVT 3.0.
fn simulated_recording(path: &Path) -> Result<(), Box<dyn Error>> {
    let mut scenario = ebptv::sim::presets::preset("demo")?;
    scenario.duration_s = 0.01;
    let rec = ebptv::sim::simulate(&scenario, 1)?;
    let geometry = rec
        .geometry
        .ok_or("the simulation has no sensor geometry")?;
    let mut w = ebptv::io::create(path, None, geometry)?;
    let mut chunk = ebptv::Chunk::default();
    chunk.events = rec.events;
    chunk.triggers = rec.triggers;
    w.write_chunk(&chunk)?;
    w.finish()?;
    Ok(())
}

/// The entry points and types a program calls beyond the pipeline: the
/// folders the command line writes, PIV, the model check, the simulator,
/// cancellation and calibration. Never run; it only has to compile.
#[allow(dead_code, unused_imports)]
fn entry_points() -> ebptv::Result<()> {
    use ebptv::io::{create, open, Format};
    use ebptv::sim::write_recording;
    let _ = ebptv::pulses::pulses_to_dir;
    let _ = ebptv::pulses::file_info;
    let _: Option<ebptv::pulses::PulsesDirOptions> = None;
    let _ = ebptv::cluster::cluster_pulses;
    let _ = ebptv::track::track_to_dir;
    let _: Option<ebptv::track::TrackConfig> = None;
    let _ = ebptv::grid::grid_to_dir;
    let _: Option<ebptv::grid::GridDirOptions> = None;
    let _ = ebptv::spectra::spectra_to_dir;
    let _ = ebptv::spectra::run_on_tracks;
    let _: Option<ebptv::spectra::SpectraDirOptions> = None;
    let _ = ebptv::compare::compare_to_dir;
    let _: Option<ebptv::compare::CompareOptions> = None;
    let _ = ebptv::piv::run_recording;
    let _ = ebptv::piv::piv_frames;
    let _: Option<ebptv::piv::PivOptions> = None;
    let _ = ebptv::modelcheck::check::check_recording;
    let _: Option<ebptv::modelcheck::check::ModelCheckOptions> = None;
    let _: Option<ebptv::sim::Scenario> = None;
    let cancel = ebptv::Cancel::new();
    cancel.cancel();
    let _ = cancel.is_cancelled();
    let c = ebptv::calib::Calibration::from_file(Path::new("calibration.toml"))?;
    let _ = c.px_to_mm(1.0, 2.0);
    let _ = c.velocity_px_s_to_m_s(1.0, 2.0);
    let _ = c.stress_px2_s2_to_m2_s2(1.0, 2.0, 3.0);
    Ok(())
}
