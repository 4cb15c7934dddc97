//! Decode-only timing: a RAW payload already in memory, decoded chunk after
//! chunk by the EVT 3.0 / EVT 2.0 decoder (no file reads), CPU time of this
//! thread. For profiling the hot loop.
//!
//! `cargo run --release -p ebptv-benches --example decode_mem -- FILE.raw [REPEATS]`
use ebptv::events::Chunk;
use ebptv::io::raw_header::read_raw_header;
use ebptv::io::Format;

#[path = "common/cpu.rs"]
mod cpu;
use cpu::thread_cpu_ns as cpu_ns;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let path = std::path::Path::new(&args[0]);
    let reps: usize = args.get(1).map(|s| s.parse()).transpose()?.unwrap_or(5);
    let chunk_events: usize = args
        .get(2)
        .map(|s| s.parse())
        .transpose()?
        .unwrap_or(1 << 20);
    let h = read_raw_header(path)?;
    let bytes = std::fs::read(path)?;
    let payload = &bytes[h.payload_offset as usize..];
    let mut chunk = Chunk::default();
    let mut best = f64::MAX;
    let mut n = 0;
    for _ in 0..reps {
        let c0 = cpu_ns();
        n = 0;
        let mut pos = 0;
        match h.format {
            Some(Format::Evt2) => {
                let mut d = ebptv::io::evt2::Evt2Decoder::new();
                while pos < payload.len() {
                    chunk.clear();
                    pos += d.decode(&payload[pos..], &mut chunk, chunk_events);
                    n += chunk.events.len();
                }
            }
            _ => {
                let mut d = ebptv::io::evt3::Evt3Decoder::new();
                while pos + 1 < payload.len() {
                    chunk.clear();
                    pos += d.decode(&payload[pos..], &mut chunk, chunk_events);
                    n += chunk.events.len();
                }
            }
        }
        best = best.min((cpu_ns() - c0) as f64 * 1e-9);
    }
    println!(
        "{n} events, {:.3} s CPU, {:.0} Mev/s",
        best,
        n as f64 / best / 1e6
    );
    Ok(())
}
