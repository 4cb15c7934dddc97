//! Throughput of the one-pass pulse analysis and of split_pulses on
//! in-memory recordings (no file reads), against EVT 3.0 decoding of the
//! same events in the same run (the target: analysis ≥ ½ decode).
//!
//! Two inputs:
//! - `uniform`: 16 M events (4 M under criterion), 10 kHz pulses, 3500 events per pulse at uniformly random
//!   pixels of 1280×720 — the worst case for the per-pixel rate map (every
//!   increment a cache miss); triggers on channel 1.
//! - `demo`: the simulator's `demo` preset over 0.2 s (4.4 M events; particles, EVT 3 row vectors,
//!   noise, camera latency), the realistic case.
//!
//! `cargo bench -p ebptv-benches --bench pulses` runs criterion (wall time). On a shared
//! machine use `EBPTV_BENCH_CPU=1 cargo bench -p ebptv-benches --bench pulses`: each stage is
//! run a few times and timed by this thread's CPU time
//! (`CLOCK_THREAD_CPUTIME_ID`); the table printed is what BENCHMARKS.md
//! records. `EBPTV_BENCH_CPU=profile` runs only the analysis, for
//! `valgrind --tool=callgrind`.

use criterion::{Criterion, Throughput};
use ebptv::events::{Chunk, Edge, Trigger};
use ebptv::pulses::{Analyzer, PulseOptions, Splitter};
use ebptv::Geometry;
use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;

/// 10 kHz pulses, ~35 Mev/s-like density: `n` events (4 M: ~0.11 s), in
/// 1 M-event chunks as the readers deliver them.
fn uniform_recording(n: usize) -> Vec<Chunk> {
    let mut rng = Pcg64::seed_from_u64(1);
    let mut ev: Vec<(i64, u16, u16)> = Vec::with_capacity(n);
    let mut k = 0i64;
    while ev.len() < n {
        let t0 = 20.0 + k as f64 * 100.0;
        for _ in 0..3500 {
            let t = t0 + 10.0 + rng.gen::<f64>() * 15.0;
            ev.push((t as i64, rng.gen_range(0..1280), rng.gen_range(0..720)));
        }
        k += 1;
    }
    ev.sort_by_key(|e| e.0);
    let mut chunks = Vec::new();
    for (i, part) in ev.chunks(1 << 20).enumerate() {
        let mut c = Chunk::default();
        for e in part {
            c.events.push(e.0, e.1, e.2, 1);
        }
        if i == 0 {
            for j in 0..k {
                c.triggers.push(Trigger {
                    t: 20 + j * 100,
                    channel: 1,
                    edge: Edge::Rising,
                });
            }
        }
        chunks.push(c);
    }
    chunks
}

/// The simulator's demo recording (with triggers), in 1 M-event chunks.
fn demo_recording() -> (Vec<Chunk>, Geometry) {
    let mut sc = ebptv::sim::presets::preset("demo").unwrap();
    sc.triggers.enabled = true;
    sc.duration_s = 0.2;
    let out = ebptv::sim::simulate(&sc, 1).unwrap();
    let mut chunks = Vec::new();
    let ev = &out.events;
    let mut i = 0;
    while i < ev.len() {
        let j = (i + (1 << 20)).min(ev.len());
        let mut c = Chunk::default();
        c.events.t.extend_from_slice(&ev.t[i..j]);
        c.events.x.extend_from_slice(&ev.x[i..j]);
        c.events.y.extend_from_slice(&ev.y[i..j]);
        c.events.p.extend_from_slice(&ev.p[i..j]);
        if i == 0 {
            c.triggers = out.triggers.clone();
        }
        chunks.push(c);
        i = j;
    }
    (chunks, out.geometry.unwrap())
}

fn analyze(chunks: &[Chunk], geometry: Geometry, estimated: bool) -> ebptv::pulses::PulseReport {
    let opts = if estimated {
        PulseOptions {
            pulse_hz: Some(10_000.0),
            ignore_triggers: true,
            ..Default::default()
        }
    } else {
        PulseOptions::default()
    };
    let mut an = Analyzer::new(opts, Some(geometry)).unwrap();
    for c in chunks {
        an.push(c).unwrap();
    }
    an.finish().unwrap()
}

/// The events encoded as an EVT 3.0 payload (through the crate's writer).
fn evt3_payload(chunks: &[Chunk], geometry: Geometry) -> Vec<u8> {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("b.raw");
    let mut w = ebptv::io::create(&path, None, geometry).unwrap();
    for c in chunks {
        w.write_chunk(c).unwrap();
    }
    w.finish().unwrap();
    let h = ebptv::io::raw_header::read_raw_header(&path).unwrap();
    let bytes = std::fs::read(&path).unwrap();
    bytes[h.payload_offset as usize..].to_vec()
}

fn decode(payload: &[u8]) -> usize {
    let mut d = ebptv::io::evt3::Evt3Decoder::new();
    let mut chunk = Chunk::default();
    let (mut pos, mut n) = (0, 0);
    while pos + 1 < payload.len() {
        chunk.clear();
        let used = d.decode(&payload[pos..], &mut chunk, 1 << 20);
        if used == 0 {
            break;
        }
        pos += used;
        n += chunk.events.len();
    }
    n
}

fn split(chunks: &[Chunk], timing: ebptv::pulses::PulseTiming) -> usize {
    let mut sp = Splitter::new(timing);
    let mut count = 0usize;
    let mut on = |p: ebptv::pulses::PulseEvents| {
        count += p.events.len();
        Ok(())
    };
    for c in chunks {
        sp.push(&c.events, &mut on).unwrap();
    }
    sp.finish(&mut on).unwrap();
    count
}

fn thread_cpu_ns() -> u64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: a valid out-pointer to a timespec; the clock id is a constant.
    let rc = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut ts) };
    assert_eq!(rc, 0);
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}

/// Best-of-`reps` CPU time (s) of `f`.
fn cpu_best(reps: usize, mut f: impl FnMut()) -> f64 {
    let mut best = f64::MAX;
    for _ in 0..reps {
        let c0 = thread_cpu_ns();
        f();
        best = best.min((thread_cpu_ns() - c0) as f64 * 1e-9);
    }
    best
}

fn cpu_table() {
    let (demo, demo_geo) = demo_recording();
    let inputs = [
        (
            "uniform",
            uniform_recording(16_000_000),
            Geometry::new(1280, 720),
        ),
        ("demo", demo, demo_geo),
    ];
    println!("| input | events | EVT3 decode | analyze (triggers) | analyze (estimated) | ratio (triggers / decode) | split_pulses |");
    println!("|---|---|---|---|---|---|---|");
    for (name, chunks, geo) in &inputs {
        let n: usize = chunks.iter().map(|c| c.events.len()).sum();
        let payload = evt3_payload(chunks, *geo);
        let mev = |s: f64| n as f64 / s / 1e6;
        let dec = cpu_best(5, || assert_eq!(decode(&payload), n));
        let trig = cpu_best(5, || {
            analyze(chunks, *geo, false);
        });
        // The demo runs at 5 kHz; the uniform input at 10 kHz.
        let est = if *name == "demo" {
            cpu_best(3, || {
                let opts = PulseOptions {
                    pulse_hz: Some(5_000.0),
                    ignore_triggers: true,
                    ..Default::default()
                };
                let mut an = Analyzer::new(opts, Some(*geo)).unwrap();
                for c in chunks {
                    an.push(c).unwrap();
                }
                an.finish().unwrap();
            })
        } else {
            cpu_best(3, || {
                analyze(chunks, *geo, true);
            })
        };
        let timing = analyze(chunks, *geo, false).timing;
        let sp = cpu_best(3, || assert_eq!(split(chunks, timing), n));
        println!(
            "| {name} | {:.2} M | {:.0} Mev/s | {:.0} Mev/s | {:.0} Mev/s | {:.2} | {:.0} Mev/s |",
            n as f64 * 1e-6,
            mev(dec),
            mev(trig),
            mev(est),
            dec / trig,
            mev(sp)
        );
    }
}

fn criterion_benches(c: &mut Criterion) {
    let chunks = uniform_recording(4_000_000);
    let geo = Geometry::new(1280, 720);
    let n: usize = chunks.iter().map(|c| c.events.len()).sum();
    let mut g = c.benchmark_group("pulses");
    g.sample_size(10)
        .measurement_time(std::time::Duration::from_secs(5));
    g.throughput(Throughput::Elements(n as u64));
    g.bench_function("analyze_triggers", |b| {
        b.iter(|| analyze(&chunks, geo, false))
    });
    g.bench_function("analyze_estimated", |b| {
        b.iter(|| analyze(&chunks, geo, true))
    });
    let timing = analyze(&chunks, geo, false).timing;
    g.bench_function("split_pulses", |b| b.iter(|| split(&chunks, timing)));
    g.finish();
}

fn main() {
    match std::env::var("EBPTV_BENCH_CPU").as_deref() {
        Ok("profile") => {
            let only = std::env::var("EBPTV_BENCH_INPUT").unwrap_or_default();
            let mut inputs = Vec::new();
            if only != "demo" {
                inputs.push((
                    "uniform",
                    uniform_recording(16_000_000),
                    Geometry::new(1280, 720),
                ));
            }
            if only != "uniform" {
                let (demo, geo) = demo_recording();
                inputs.push(("demo", demo, geo));
            }
            for (name, chunks, geo) in inputs {
                for _ in 0..std::env::var("EBPTV_BENCH_REPS")
                    .ok()
                    .and_then(|s| s.parse().ok())
                    .unwrap_or(5)
                {
                    let opts = if std::env::var("EBPTV_BENCH_ESTIMATED").is_ok() {
                        PulseOptions {
                            pulse_hz: Some(if name == "demo" { 5_000.0 } else { 10_000.0 }),
                            ignore_triggers: true,
                            ..Default::default()
                        }
                    } else {
                        PulseOptions::default()
                    };
                    let mut an = Analyzer::new(opts, Some(geo)).unwrap();
                    let c0 = thread_cpu_ns();
                    for c in &chunks {
                        an.push(c).unwrap();
                    }
                    let c1 = thread_cpu_ns();
                    let r = an.finish().unwrap();
                    let c2 = thread_cpu_ns();
                    println!(
                        "{name}: {} events, push {:.1} ms, finish {:.1} ms, groups {:?}",
                        r.events,
                        (c1 - c0) as f64 * 1e-6,
                        (c2 - c1) as f64 * 1e-6,
                        &r.saturation.group_sizes[..8]
                    );
                }
            }
        }
        Ok(_) => cpu_table(),
        Err(_) => {
            let mut c = Criterion::default().configure_from_args();
            criterion_benches(&mut c);
            c.final_summary();
        }
    }
}
