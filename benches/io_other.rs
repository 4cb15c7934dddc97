//! Decoding speed of the DAT, CSV, AEDAT 4.0 (LZ4) and Event Stream readers
//! on 2 M synthetic events from the page cache, one core.
//! Run: `cargo bench -p ebptv-benches --bench io_other`.

use std::path::Path;
use std::time::Duration;

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use ebptv::io::aedat4::{encode_aedat4, lz4_frame, Compression};
use ebptv::io::dat::encode_dat_cd;
use ebptv::io::es::encode_es_dvs;
use ebptv::io::{self, EventSource, EventWriter, Format, OpenOptions};
use ebptv::{Chunk, Event, Geometry};

const N: usize = 2_000_000;

fn events() -> Vec<Event> {
    (0..N as i64)
        .map(|i| Event {
            t: i / 4,
            x: ((i * 7919) % 1280) as u16,
            y: ((i * 104_729) % 720) as u16,
            p: (i % 3 != 0) as u8,
        })
        .collect()
}

fn drain(path: &Path, format: Format) -> usize {
    let opts = OpenOptions {
        format: Some(format),
        ..Default::default()
    };
    let mut src = io::open_with(path, &opts).unwrap();
    let mut c = Chunk::default();
    let mut n = 0;
    while src.next_chunk(&mut c).unwrap() {
        n += c.events.len();
    }
    n
}

fn bench(c: &mut Criterion) {
    let dir = tempfile::tempdir().unwrap();
    let ev = events();
    let g = Geometry::new(1280, 720);
    let dat = dir.path().join("b.dat");
    std::fs::write(&dat, encode_dat_cd(&ev, Some(g))).unwrap();
    let es = dir.path().join("b.es");
    std::fs::write(&es, encode_es_dvs(&ev, g)).unwrap();
    let aedat = dir.path().join("b.aedat4");
    std::fs::write(
        &aedat,
        encode_aedat4(&ev, &[], g, Compression::Lz4, 8192, &lz4_frame),
    )
    .unwrap();
    let csv = dir.path().join("b.csv");
    let mut w = io::create(&csv, Some(Format::Csv), g).unwrap();
    let mut chunk = Chunk::default();
    for e in &ev {
        chunk.events.push(e.t, e.x, e.y, e.p);
    }
    w.write_chunk(&chunk).unwrap();
    w.finish().unwrap();

    let mut group = c.benchmark_group("decode");
    group
        .sample_size(10)
        .measurement_time(Duration::from_secs(4))
        .throughput(Throughput::Elements(N as u64));
    for (name, path, format) in [
        ("dat", &dat, Format::Dat),
        ("es", &es, Format::Es),
        ("aedat4_lz4", &aedat, Format::Aedat4),
        ("csv", &csv, Format::Csv),
    ] {
        group.bench_function(name, |b| b.iter(|| assert_eq!(drain(path, format), N)));
    }
    group.finish();

    let mut group = c.benchmark_group("write");
    group
        .sample_size(10)
        .measurement_time(Duration::from_secs(4))
        .throughput(Throughput::Elements(N as u64));
    for (name, ext) in [("csv", "csv"), ("npy", "npy")] {
        let out = dir.path().join(format!("w.{ext}"));
        group.bench_function(name, |b| {
            b.iter(|| {
                let mut w: Box<dyn EventWriter> = io::create(&out, None, g).unwrap();
                w.write_chunk(&chunk).unwrap();
                w.finish().unwrap();
            })
        });
    }
    group.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
