//! PTV stage speed: clustering (events/s), linking (particles/s) and the
//! in-memory stream pulses → particles → tracks (events/s; `PtvStream`,
//! clustering and output fits on rayon, no files) on the synthetic scene of
//! `ebptv::track::synth` (paper-like conditions).
//!
//! `cargo bench -p ebptv-benches --bench ptv`

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use std::time::Duration;

use ebptv::cluster::{
    cluster_pulse, cluster_pulses, pixel_labels_kdtree, pulse_pixels, ClusterParams,
};
use ebptv::track::synth::{generate, SynthParams};
use ebptv::track::{link, PtvSink, PtvStream, Track, TrackParams};

/// Counts what the stream hands out (no files: the stages themselves).
#[derive(Default)]
struct Count {
    particles: usize,
    points: usize,
}

impl PtvSink for Count {
    fn particles(
        &mut self,
        _pulse: i64,
        _t_us: f64,
        ps: &[ebptv::cluster::Particle],
    ) -> ebptv::Result<()> {
        self.particles += ps.len();
        Ok(())
    }
    fn tracks(&mut self, tracks: &[Track]) -> ebptv::Result<()> {
        self.points += tracks.iter().map(|t| t.points.len()).sum::<usize>();
        Ok(())
    }
}

fn bench(c: &mut Criterion) {
    // Full-frame pulses at ppp 0.01: ~9000 particles, ~16000 events each.
    let frame = generate(&SynthParams {
        width: 1280,
        height: 720,
        pulses: 8,
        ..Default::default()
    });
    let pulses: Vec<_> = frame.iter().map(|s| s.pulse.clone()).collect();
    let events: usize = pulses.iter().map(|p| p.events.len()).sum();
    let params = ClusterParams::default();
    let mut g = c.benchmark_group("cluster");
    g.sample_size(10).measurement_time(Duration::from_secs(4));
    g.throughput(Throughput::Elements(events as u64));
    g.bench_function("full_frame_pulses_1_thread", |b| {
        b.iter(|| {
            pulses
                .iter()
                .map(|p| cluster_pulse(p, &params).len())
                .sum::<usize>()
        })
    });
    g.bench_function("full_frame_pulses_kdtree_1_thread", |b| {
        b.iter(|| {
            pulses
                .iter()
                .map(|p| {
                    let px = pulse_pixels(p, &params);
                    pixel_labels_kdtree(&px, &params).len()
                })
                .sum::<usize>()
        })
    });
    g.bench_function("full_frame_pulses_rayon", |b| {
        b.iter(|| cluster_pulses(&pulses, &params).unwrap().len())
    });
    g.finish();

    let scene = generate(&SynthParams {
        width: 512,
        height: 512,
        pulses: 60,
        ..Default::default()
    });
    let particles: Vec<_> = scene
        .iter()
        .flat_map(|s| cluster_pulse(&s.pulse, &params))
        .collect();
    let tparams = TrackParams::default();
    let mut g = c.benchmark_group("link");
    g.sample_size(10).measurement_time(Duration::from_secs(6));
    g.throughput(Throughput::Elements(particles.len() as u64));
    g.bench_function("ppp0.01_512x512_60_pulses", |b| {
        b.iter(|| link(&particles, &tparams).unwrap().len())
    });
    g.finish();

    let scene_events: usize = scene.iter().map(|s| s.pulse.events.len()).sum();
    let mut g = c.benchmark_group("stream");
    g.sample_size(10).measurement_time(Duration::from_secs(6));
    g.throughput(Throughput::Elements(scene_events as u64));
    g.bench_function("events_to_tracks_512x512_60_pulses", |b| {
        b.iter(|| {
            let mut s = PtvStream::new(params.clone(), tparams.clone(), 16).unwrap();
            let mut sink = Count::default();
            for sp in &scene {
                s.push_pulse(sp.pulse.clone(), &mut sink).unwrap();
            }
            s.finish(&mut sink).unwrap();
            sink.particles + sink.points
        })
    });
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
