//! Stream a RAW (or any supported) event file and print counts, time range,
//! anomalies, decode rate and nothing else: the tool behind the peak-memory
//! measurement in BENCHMARKS.md.
//!
//! `cargo run --release -p ebptv-benches --example decode_raw -- FILE [CHUNK_EVENTS]`
use std::time::Instant;

use ebptv::events::Chunk;
use ebptv::io::{open_with, EventSource, OpenOptions};

fn main() -> anyhow::Result<()> {
    let mut args = std::env::args().skip(1);
    let path = args
        .next()
        .ok_or_else(|| anyhow::anyhow!("usage: decode_raw FILE [CHUNK_EVENTS]"))?;
    let chunk_events = args.next().map(|s| s.parse()).transpose()?;
    let opts = OpenOptions {
        chunk_events,
        ..Default::default()
    };
    let start = Instant::now();
    let mut src = open_with(&path, &opts)?;
    let mut chunk = Chunk::default();
    let (mut n, mut ntrig, mut on) = (0u64, 0u64, 0u64);
    let (mut first, mut last) = (None, None);
    while src.next_chunk(&mut chunk)? {
        n += chunk.events.len() as u64;
        ntrig += chunk.triggers.len() as u64;
        on += chunk.events.p.iter().map(|&p| p as u64).sum::<u64>();
        if first.is_none() {
            first = chunk.events.iter().next();
        }
        if let Some(e) = chunk.events.iter().last() {
            last = Some(e);
        }
    }
    let secs = start.elapsed().as_secs_f64();
    let info = src.info();
    println!("file      {}", path);
    println!(
        "format    {} geometry {:?}",
        info.format.name(),
        info.geometry
    );
    println!("events    {n} ({on} ON), triggers {ntrig}");
    println!("first     {first:?}");
    println!("last      {last:?}");
    println!("anomalies {:?}", src.anomalies());
    println!(
        "decoded in {:.3} s: {:.1} Mev/s",
        secs,
        n as f64 / secs / 1e6
    );
    Ok(())
}
