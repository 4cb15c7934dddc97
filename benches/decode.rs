//! RAW decode throughput: ebptv's streaming EVT 3.0 / EVT 2.0 readers against
//! the `evt3` crate, on the same synthetic particle-like files (built by
//! ebptv's own writers, 20 M+ events, in the OS temp dir, from the page
//! cache after the first pass) and on the real EVT 3.0 sample.
//!
//! Time is this thread's CPU time (`CLOCK_THREAD_CPUTIME_ID`, ns), not
//! wall time: the benchmark machine is shared, and the claim is about one
//! core's work. Both decoders are measured the same way in the same run.
//! Numbers and the command: BENCHMARKS.md.
//!
//! `cargo bench -p ebptv-benches --bench decode`

#[path = "examples/common/cpu.rs"]
mod cpu;
#[path = "examples/synth_raw/gen.rs"]
mod gen;

use cpu::thread_cpu_ns;

use std::path::{Path, PathBuf};
use std::time::Duration;

use criterion::measurement::{Measurement, ValueFormatter};
use criterion::{criterion_group, criterion_main, BenchmarkId, Criterion, Throughput};
use ebptv::events::{Chunk, Geometry};
use ebptv::io::{create, open, EventSource, Format};

/// CPU time of the calling thread, from the scheduler's statistics.
struct ThreadCpuTime;

impl Measurement for ThreadCpuTime {
    type Intermediate = u64;
    type Value = u64;
    fn start(&self) -> u64 {
        thread_cpu_ns()
    }
    fn end(&self, i: u64) -> u64 {
        thread_cpu_ns() - i
    }
    fn add(&self, a: &u64, b: &u64) -> u64 {
        a + b
    }
    fn zero(&self) -> u64 {
        0
    }
    fn to_f64(&self, v: &u64) -> f64 {
        *v as f64
    }
    fn formatter(&self) -> &dyn ValueFormatter {
        &CpuNsFormatter
    }
}

struct CpuNsFormatter;

impl ValueFormatter for CpuNsFormatter {
    fn scale_values(&self, typical: f64, values: &mut [f64]) -> &'static str {
        let (f, unit) = if typical < 1e3 {
            (1.0, "ns cpu")
        } else if typical < 1e6 {
            (1e-3, "µs cpu")
        } else if typical < 1e9 {
            (1e-6, "ms cpu")
        } else {
            (1e-9, "s cpu")
        };
        values.iter_mut().for_each(|v| *v *= f);
        unit
    }
    fn scale_throughputs(&self, typical: f64, tp: &Throughput, values: &mut [f64]) -> &'static str {
        let n = match *tp {
            Throughput::Elements(n) | Throughput::Bytes(n) | Throughput::BytesDecimal(n) => {
                n as f64
            }
        };
        let _ = typical;
        values.iter_mut().for_each(|v| *v = n / *v * 1e3);
        "Mev/s (cpu)"
    }
    fn scale_for_machines(&self, _values: &mut [f64]) -> &'static str {
        "ns"
    }
}

const N_EVENTS: u64 = 20_000_000;

/// Write a synthetic particle-like file of at least N_EVENTS events.
fn synth_file(dir: &Path, format: Format) -> (PathBuf, u64) {
    let path = dir.join(format!(
        "bench-{}.raw",
        if format == Format::Evt3 {
            "evt3"
        } else {
            "evt2"
        }
    ));
    let mut w = create(&path, Some(format), Geometry::new(1280, 720)).unwrap();
    let mut stream = gen::ParticleStream::new(42, 2000, (1 << 24) - 200_000);
    let mut chunk = Chunk::default();
    let mut n = 0;
    while n < N_EVENTS {
        chunk.clear();
        for _ in 0..50 {
            stream.next_pulse(&mut chunk);
        }
        n += chunk.events.len() as u64;
        w.write_chunk(&chunk).unwrap();
    }
    w.finish().unwrap();
    (path, n)
}

fn ebptv_stream(path: &Path) -> usize {
    let mut src = open(path).unwrap();
    let mut chunk = Chunk::default();
    let mut n = 0;
    while src.next_chunk(&mut chunk).unwrap() {
        n += chunk.events.len();
    }
    n
}

fn bench(c: &mut Criterion<ThreadCpuTime>) {
    let dir = tempfile::tempdir().unwrap();
    let (evt3_path, n3) = synth_file(dir.path(), Format::Evt3);
    let (evt2_path, n2) = synth_file(dir.path(), Format::Evt2);

    let mut g = c.benchmark_group("evt3_synthetic_20M");
    g.sample_size(10)
        .measurement_time(Duration::from_secs(8))
        .throughput(Throughput::Elements(n3));
    g.bench_function(BenchmarkId::new("ebptv", "stream"), |b| {
        b.iter(|| assert_eq!(ebptv_stream(&evt3_path) as u64, n3))
    });
    g.bench_function(BenchmarkId::new("evt3_crate", "decode_file"), |b| {
        b.iter(|| {
            assert_eq!(
                evt3::Evt3Decoder::new()
                    .decode_file(&evt3_path)
                    .unwrap()
                    .cd_events
                    .len() as u64,
                n3
            )
        })
    });
    g.bench_function(BenchmarkId::new("evt3_crate", "decode_file_columns"), |b| {
        b.iter(|| {
            assert_eq!(
                evt3::Evt3Decoder::new()
                    .decode_file_columns(&evt3_path)
                    .unwrap()
                    .cd_events
                    .len() as u64,
                n3
            )
        })
    });
    g.finish();

    let mut g = c.benchmark_group("evt2_synthetic_20M");
    g.sample_size(10)
        .measurement_time(Duration::from_secs(6))
        .throughput(Throughput::Elements(n2));
    g.bench_function(BenchmarkId::new("ebptv", "stream"), |b| {
        b.iter(|| assert_eq!(ebptv_stream(&evt2_path) as u64, n2))
    });
    g.finish();

    let real = Path::new(env!("CARGO_MANIFEST_DIR")).join("../shared/data/real/evt3_sample.raw");
    if real.exists() {
        let n = ebptv_stream(&real) as u64;
        let mut g = c.benchmark_group("evt3_real_sample");
        g.sample_size(10)
            .measurement_time(Duration::from_secs(3))
            .throughput(Throughput::Elements(n));
        g.bench_function(BenchmarkId::new("ebptv", "stream"), |b| {
            b.iter(|| ebptv_stream(&real))
        });
        g.bench_function(BenchmarkId::new("evt3_crate", "decode_file"), |b| {
            b.iter(|| {
                evt3::Evt3Decoder::new()
                    .decode_file(&real)
                    .unwrap()
                    .cd_events
                    .len()
            })
        });
        g.finish();
    }
}

criterion_group! {
    name = benches;
    config = Criterion::default().with_measurement(ThreadCpuTime);
    targets = bench
}
criterion_main!(benches);
