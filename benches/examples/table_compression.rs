//! Size and write time of a `tracks` / `particles` table in Parquet with
//! each compression (the measurement behind the default, BENCHMARKS.md):
//!
//! cargo run --release -p ebptv-benches --example table_compression -- RUN_DIR
//!
//! measures uncompressed and snappy; with `--features parquet-zstd` (a C
//! build of zstd, not part of the default build) zstd levels 1 and 3 too.
//!
//! RUN_DIR holds the tables of an `ebptv track` run (any format).
use std::path::Path;
use std::time::Instant;

use ebptv::table::{Col, TableFormat, TableWriter};
use ebptv::track::{read_particles, read_tracks, TrackRow, PARTICLE_COLUMNS, TRACK_COLUMNS};
use parquet::basic::Compression;

fn find(dir: &Path, stem: &str) -> std::path::PathBuf {
    for f in [TableFormat::Parquet, TableFormat::Csv, TableFormat::Npy] {
        let p = dir.join(f.file_name(stem));
        if p.is_file() {
            return p;
        }
    }
    panic!("no {stem} table in {}", dir.display());
}

fn measure<R>(name: &str, rows: &[R], cols: &'static [Col<R>], out: &Path) {
    #[allow(unused_mut)]
    let mut codecs = vec![
        ("uncompressed", Compression::UNCOMPRESSED),
        ("snappy", Compression::SNAPPY),
    ];
    #[cfg(feature = "parquet-zstd")]
    {
        use parquet::basic::ZstdLevel;
        codecs.push(("zstd(1)", Compression::ZSTD(ZstdLevel::try_new(1).unwrap())));
        codecs.push(("zstd(3)", Compression::ZSTD(ZstdLevel::try_new(3).unwrap())));
    }
    for (label, c) in codecs {
        let path = out.join(format!("{name}.{label}.parquet"));
        let mut best = f64::INFINITY;
        for _ in 0..3 {
            let t0 = Instant::now();
            let mut w = TableWriter::parquet_with(&path, cols, c).unwrap();
            w.write(rows).unwrap();
            w.finish().unwrap();
            best = best.min(t0.elapsed().as_secs_f64());
        }
        let size = std::fs::metadata(&path).unwrap().len();
        println!(
            "{name:10} {label:13} {:9.2} MB {:7.3} s  ({} rows)",
            size as f64 / 1e6,
            best,
            rows.len()
        );
        std::fs::remove_file(&path).unwrap();
    }
}

fn main() {
    let dir = std::env::args()
        .nth(1)
        .expect("usage: table_compression RUN_DIR");
    let dir = Path::new(&dir);
    let out = tempfile::tempdir_in(dir).unwrap();
    let tracks = read_tracks(&find(dir, "tracks")).unwrap();
    let rows: Vec<TrackRow> = tracks
        .iter()
        .flat_map(|t| {
            t.points.iter().map(|&p| TrackRow {
                id: t.id,
                p,
                phys: [f64::NAN; 4],
            })
        })
        .collect();
    measure("tracks", &rows, TRACK_COLUMNS, out.path());
    let particles = read_particles(&find(dir, "particles")).unwrap();
    measure("particles", &particles, &PARTICLE_COLUMNS, out.path());
}
