//! Writes a synthetic scene as `particles.csv` + `truth_particles.csv` for
//! the peer comparison (benches/peers/trackpy_compare.py):
//!
//! ```text
//! PTV_SYNTH_OUT=/tmp/ptv PTV_SYNTH_PPP=0.01 PTV_SYNTH_DISP=8 PTV_SYNTH_NOISE=0.01 \
//!   cargo run --release -p ebptv-benches --example ptv_synth_export
//! ```

use std::io::Write;

use ebptv::cluster::{cluster_pulse, ClusterParams};
use ebptv::track::synth::{generate, SynthParams};

fn env_f64(name: &str, default: f64) -> f64 {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

fn main() {
    let Ok(out) = std::env::var("PTV_SYNTH_OUT") else {
        println!("set PTV_SYNTH_OUT to a directory");
        return;
    };
    let out = std::path::PathBuf::from(out);
    std::fs::create_dir_all(&out).unwrap();
    let sp = SynthParams {
        width: env_f64("PTV_SYNTH_SIZE", 512.0) as u16,
        height: env_f64("PTV_SYNTH_SIZE", 512.0) as u16,
        pulses: env_f64("PTV_SYNTH_PULSES", 100.0) as usize,
        ppp: env_f64("PTV_SYNTH_PPP", 0.01),
        max_disp: env_f64("PTV_SYNTH_DISP", 8.0),
        noise_fraction: env_f64("PTV_SYNTH_NOISE", 0.01),
        seed: env_f64("PTV_SYNTH_SEED", 1.0) as u64,
        ..Default::default()
    };
    let scene = generate(&sp);
    let particles: Vec<_> = scene
        .iter()
        .flat_map(|s| cluster_pulse(&s.pulse, &ClusterParams::default()))
        .collect();
    ebptv::track::write_particles_csv(&out.join("particles.csv"), &particles).unwrap();
    let mut f = ebptv::io::atomic::AtomicFile::create(out.join("truth_particles.csv")).unwrap();
    writeln!(f, "pulse,t_us,particle_id,x,y,u,v").unwrap();
    for t in scene.iter().flat_map(|s| &s.truth) {
        writeln!(
            f,
            "{},{},{},{:.4},{:.4},{:.3},{:.3}",
            t.pulse, t.t_us, t.particle_id, t.x, t.y, t.u, t.v
        )
        .unwrap();
    }
    f.commit().unwrap();
    println!(
        "{} particles over {} pulses → {}",
        particles.len(),
        sp.pulses,
        out.display()
    );
}
