//! A simulated recording replayed from memory through the whole chain
//! (pulses → clustering → tracking), for the tests that score the chain's
//! track samples against the simulator's flow. Simulating once and
//! replaying twice (pulse analysis, then tracking) halves the test time.
#![allow(dead_code)]

use ebptv::cluster::{ClusterParams, Particle};
use ebptv::events::Chunk;
use ebptv::grid::Sample;
use ebptv::io::{EventSource, StreamInfo};
use ebptv::pulses::PulseOptions;
use ebptv::track::{track_recording, PtvSink, PtvStream, Track, TrackParams};

/// The chunks of one simulated recording, served again on every open.
struct Replay {
    info: StreamInfo,
    chunks: Vec<Chunk>,
    next: usize,
}

impl EventSource for Replay {
    fn info(&self) -> &StreamInfo {
        &self.info
    }
    fn next_chunk(&mut self, chunk: &mut Chunk) -> ebptv::Result<bool> {
        match self.chunks.get(self.next) {
            Some(c) => {
                *chunk = c.clone();
                self.next += 1;
                Ok(true)
            }
            None => {
                chunk.clear();
                Ok(false)
            }
        }
    }
}

#[derive(Default)]
struct Collect(Vec<Track>);

impl PtvSink for Collect {
    fn particles(&mut self, _: i64, _: f64, _: &[Particle]) -> ebptv::Result<()> {
        Ok(())
    }
    fn tracks(&mut self, t: &[Track]) -> ebptv::Result<()> {
        self.0.extend_from_slice(t);
        Ok(())
    }
}

/// Track the replayed recording with `track` and return its track samples,
/// grouped by track as in tracks.csv.
pub fn track_samples(info: &StreamInfo, chunks: &[Chunk], track: TrackParams) -> Vec<Sample> {
    let open = || -> ebptv::Result<Box<dyn EventSource>> {
        Ok(Box::new(Replay {
            info: info.clone(),
            chunks: chunks.to_vec(),
            next: 0,
        }))
    };
    let stream = PtvStream::new(ClusterParams::default(), track, 64).unwrap();
    let mut sink = Collect::default();
    track_recording(
        &open,
        &PulseOptions::default(),
        stream,
        &mut sink,
        &mut |_| {},
    )
    .unwrap();
    sink.0
        .iter()
        .flat_map(|t| {
            t.points
                .iter()
                .map(move |p| Sample::from_track_point(t.id, p))
        })
        .collect()
}
