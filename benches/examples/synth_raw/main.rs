//! Write a synthetic particle-like EVT 3.0 (or EVT 2.0) file of at least N
//! events, for decode benchmarks and the peak-memory measurement.
//!
//! `cargo run --release -p ebptv-benches --example synth_raw -- OUT.raw N_EVENTS [evt2]`
mod gen;

use ebptv::events::{Chunk, Geometry};
use ebptv::io::{create, Format};

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let (out, n): (&str, u64) = match args.as_slice() {
        [o, n, ..] => (o, n.parse()?),
        _ => anyhow::bail!("usage: synth_raw OUT.raw N_EVENTS [evt2]"),
    };
    let format = if args.get(2).map(|s| s == "evt2").unwrap_or(false) {
        Format::Evt2
    } else {
        Format::Evt3
    };
    let mut w = create(out, Some(format), Geometry::new(1280, 720))?;
    let mut stream = gen::ParticleStream::new(42, 2000, (1 << 24) - 200_000);
    let mut chunk = Chunk::default();
    let mut written = 0u64;
    while written < n {
        chunk.clear();
        for _ in 0..50 {
            stream.next_pulse(&mut chunk);
        }
        written += chunk.events.len() as u64;
        w.write_chunk(&chunk)?;
    }
    w.finish()?;
    println!(
        "{out}: {written} events, {} bytes",
        std::fs::metadata(out)?.len()
    );
    Ok(())
}
