/// Open a recording, find the light pulses, cluster each pulse's events
/// into particles, link them into tracks and bin the tracks onto a grid.
fn pipeline(path: &std::path::Path) -> Result<(), Box<dyn std::error::Error>> {
    use ebptv::{cluster, grid, io, pulses, track};

    // 1. Pulse timing: from the trigger channel, or estimated from the events.
    let report = pulses::analyze(&mut *io::open(path)?, &pulses::PulseOptions::default())?;
    println!("{:?} pulses every {:.1} µs", report.timing.source, report.timing.period_us);

    // 2. Each pulse's events → particles (sub-pixel centroids).
    let params = cluster::ClusterParams::default();
    let mut particles = Vec::new();
    pulses::split_pulses(&mut *io::open(path)?, &report.timing, &mut |pulse| {
        particles.extend(cluster::cluster_pulse(&pulse, &params));
        Ok(())
    })?;

    // 3. Particles → Lagrangian tracks (positions and fitted velocities).
    let tracks = track::link(&particles, &track::TrackParams::default())?;
    assert!(tracks.len() > 100);

    // 4. Tracks → an Eulerian grid of means and Reynolds stresses.
    let samples: Vec<grid::Sample> = tracks
        .iter()
        .flat_map(|t| t.points.iter().map(|p| grid::Sample::from_track_point(t.id, p)))
        .collect();
    let lattice = grid::Lattice::new(32.0, 32.0, 0.0)?;
    let acc = grid::bin_samples(&samples, lattice, grid::Weighting::TopHat)?;
    let field = grid::estimate(&acc, &grid::EstimateOptions::default())?;
    assert!(field.bins.iter().any(|b| b.count > 0 && b.u.is_finite()));
    Ok(())
}
