//! Simulator throughput: events per second of process CPU time and of wall
//! time, with 1 and 2 rayon threads.
//!
//! `cargo bench -p ebptv-benches --bench sim` (add `-- quick` for one repetition). Scenes:
//! `water_jet_5khz` (full frame, ~31 Mev/s: the paper's recording regime;
//! steady jet, exact advection), `rib_wake` (full frame, RK4 through the
//! shedding field), `demo` (640×360 vortex) and `turbulent_bl` (the most
//! expensive field: 16 Fourier modes, one cos each, per evaluation). "in memory" drains the `Simulator` (events + truth in memory,
//! as the pipeline consumes it); "to files" is `write_recording` (EVT 3.0 +
//! 80 MB/s of truth CSV per 0.1 s, into a temporary directory).
//!
//! CPU time is the whole process's (`CLOCK_PROCESS_CPUTIME_ID`, all
//! threads), so it is meaningful on a loaded machine; wall time is not.
//! Each number is the best of the repetitions.

use std::time::Instant;

use ebptv::io::{EventSource, Format};
use ebptv::sim::{presets, write_recording, Scenario, Simulator};
use ebptv::Chunk;

fn cpu_seconds() -> f64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime writes into the timespec we own.
    unsafe { libc::clock_gettime(libc::CLOCK_PROCESS_CPUTIME_ID, &mut ts) };
    ts.tv_sec as f64 + ts.tv_nsec as f64 * 1e-9
}

fn in_memory(sc: &Scenario) -> u64 {
    let mut sim = Simulator::new(sc, 1).unwrap();
    let mut chunk = Chunk::default();
    let mut n = 0u64;
    let mut truth = 0usize;
    while sim.next_chunk(&mut chunk).unwrap() {
        n += chunk.events.len() as u64;
        truth += sim.take_truth().len();
    }
    std::hint::black_box(truth);
    n
}

fn to_files(sc: &Scenario) -> u64 {
    let dir = tempfile::tempdir().unwrap();
    write_recording(sc, 1, dir.path(), Format::Evt3, |_, _| {})
        .unwrap()
        .stats
        .events
}

fn main() {
    let quick = std::env::args().any(|a| a == "quick");
    let reps = if quick { 1 } else { 3 };
    println!("| scene | path | threads | events | CPU s | Mev per CPU-s | wall s | Mev/s wall |");
    println!("|---|---|---|---|---|---|---|---|");
    for (name, secs) in [
        ("water_jet_5khz", 0.1),
        ("rib_wake", 0.05),
        ("demo", 0.05),
        ("turbulent_bl", 0.05),
    ] {
        let mut sc = presets::preset(name).unwrap();
        sc.duration_s = secs;
        #[allow(clippy::type_complexity)]
        let paths: &[(&str, fn(&Scenario) -> u64)] = if name == "water_jet_5khz" {
            &[("in memory", in_memory), ("to files", to_files)]
        } else {
            &[("in memory", in_memory)]
        };
        for &(path, run) in paths {
            for threads in [1, 2] {
                let pool = rayon::ThreadPoolBuilder::new()
                    .num_threads(threads)
                    .build()
                    .unwrap();
                let (mut cpu, mut wall, mut n) = (f64::INFINITY, f64::INFINITY, 0);
                for _ in 0..reps {
                    let (c0, w0) = (cpu_seconds(), Instant::now());
                    n = pool.install(|| run(&sc));
                    wall = wall.min(w0.elapsed().as_secs_f64());
                    cpu = cpu.min(cpu_seconds() - c0);
                }
                println!(
                    "| {name} ({secs} s) | {path} | {threads} | {n} | {cpu:.2} | {:.2} | {wall:.2} | {:.2} |",
                    n as f64 / cpu / 1e6,
                    n as f64 / wall / 1e6
                );
            }
        }
    }
}
