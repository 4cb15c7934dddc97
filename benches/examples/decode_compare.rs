//! CPU time (this thread's, so that other processes on a busy machine do not
//! count) of decoding a RAW file with
//! ebptv and with the `evt3` crate.
//!
//! `cargo run --release -p ebptv-benches --example decode_compare -- FILE.raw [REPEATS]`
use ebptv::events::Chunk;
use ebptv::io::{open, EventSource};

#[path = "common/cpu.rs"]
mod cpu;
use cpu::thread_cpu_ns as cpu_ns;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let path = args
        .first()
        .ok_or_else(|| anyhow::anyhow!("usage: decode_compare FILE.raw [REPEATS]"))?;
    let reps: usize = args.get(1).map(|s| s.parse()).transpose()?.unwrap_or(3);
    let mut best_ours = f64::MAX;
    let mut best_theirs = f64::MAX;
    let mut best_cols = f64::MAX;
    let mut n = 0;
    for _ in 0..reps {
        let c0 = cpu_ns();
        let mut src = open(path)?;
        let mut chunk = Chunk::default();
        let mut count = 0usize;
        while src.next_chunk(&mut chunk)? {
            count += chunk.events.len();
        }
        best_ours = best_ours.min((cpu_ns() - c0) as f64 * 1e-9);
        n = count;
        if std::env::var_os("ONLY_EBPTV").is_some() {
            continue;
        }
        let c0 = cpu_ns();
        let r = evt3::Evt3Decoder::new().decode_file(path)?;
        best_theirs = best_theirs.min((cpu_ns() - c0) as f64 * 1e-9);
        assert_eq!(r.cd_events.len(), n);
        drop(r);
        let c0 = cpu_ns();
        let r = evt3::Evt3Decoder::new().decode_file_columns(path)?;
        best_cols = best_cols.min((cpu_ns() - c0) as f64 * 1e-9);
        assert_eq!(r.cd_events.len(), n);
    }
    let rate = |s: f64| n as f64 / s / 1e6;
    println!("events: {n}");
    println!(
        "ebptv streaming:            {:.3} s CPU, {:.0} Mev/s",
        best_ours,
        rate(best_ours)
    );
    println!(
        "evt3 crate decode_file:     {:.3} s CPU, {:.0} Mev/s",
        best_theirs,
        rate(best_theirs)
    );
    println!(
        "evt3 crate decode_file_columns: {:.3} s CPU, {:.0} Mev/s",
        best_cols,
        rate(best_cols)
    );
    println!(
        "speed-up vs evt3 (best of its two): {:.2}x",
        best_theirs.min(best_cols) / best_ours
    );
    Ok(())
}
