//! A simulated recording replayed from memory through the whole chain
//! (pulses → clustering → tracking), for the tests that score the chain's
//! track samples against the simulator's flow. Simulating once and
//! replaying twice (pulse analysis, then tracking) halves the test time.
#![allow(dead_code)]

use crate::cluster::{ClusterParams, Particle};
use crate::events::Chunk;
use crate::grid::noise::velocity_noise;
use crate::grid::{
    estimate, EstimateOptions, Fit, GridAccumulator, GridSpec, GridStats, Lattice, Sample,
    Weighting,
};
use crate::io::{EventSource, StreamInfo};
use crate::pulses::PulseOptions;
use crate::sim::scenario::{Roi, Scenario};
use crate::sim::{Flow, Simulator, TruthSample};
use crate::track::{track_recording, PtvSink, PtvStream, Track, TrackParams};

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
    fn next_chunk(&mut self, chunk: &mut Chunk) -> crate::Result<bool> {
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

/// A scene simulated into memory: its event chunks, stream description,
/// flow and truth.
pub(crate) struct Recorded {
    pub chunks: Vec<Chunk>,
    pub info: StreamInfo,
    pub flow: Flow,
    pub truth: Vec<TruthSample>,
}

/// Simulate `sc` with `seed` into memory.
pub(crate) fn record(sc: &Scenario, seed: u64) -> Recorded {
    let mut sim = Simulator::new(sc, seed).unwrap();
    let info = sim.info().clone();
    let flow = sim.flow().clone();
    let mut chunks = Vec::new();
    let mut c = Chunk::default();
    while sim.next_chunk(&mut c).unwrap() {
        chunks.push(std::mem::take(&mut c));
    }
    let truth = sim.take_truth();
    Recorded {
        chunks,
        info,
        flow,
        truth,
    }
}

/// The turbulent boundary-layer preset on the 256×128 ROI near the wall,
/// 0.1 s: the turbulent scene of the chain tests.
pub(crate) fn turbulent_roi_scenario() -> Scenario {
    let mut sc = crate::sim::presets::preset("turbulent_bl").unwrap();
    sc.sensor.roi = Some(Roi {
        x: 0,
        y: 296,
        width: 256,
        height: 128,
    });
    sc.duration_s = 0.1;
    sc
}

#[derive(Default)]
struct Collect(Vec<Track>);

impl PtvSink for Collect {
    fn particles(&mut self, _: i64, _: f64, _: &[Particle]) -> crate::Result<()> {
        Ok(())
    }
    fn tracks(&mut self, t: &[Track]) -> crate::Result<()> {
        self.0.extend_from_slice(t);
        Ok(())
    }
}

/// Track the replayed recording with `track` and return its track samples,
/// grouped by track as in tracks.csv.
pub(crate) fn track_samples(
    info: &StreamInfo,
    chunks: &[Chunk],
    track: TrackParams,
) -> Vec<Sample> {
    let open = || -> crate::Result<Box<dyn EventSource>> {
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

/// The 16 px grids of the `turbulent_bl` scene's 256 × 128 ROI (x 0–255,
/// y 296–423; linear fit, bins of ≥ 50 samples): the measured samples with
/// the pair estimator's noise correction, and the analytic velocity at the
/// same samples (the truth binned exactly like the measurement).
pub(crate) struct TurbulentGrids {
    pub spec: GridSpec,
    /// The samples with their velocity replaced by the flow's.
    pub at_samples: Vec<Sample>,
    /// The pair estimator's velocity noise (px/s).
    pub noise_rms: f64,
    pub measured: GridStats,
    pub truth: GridStats,
}

pub(crate) fn turbulent_roi_grids(samples: &[Sample], flow: &Flow) -> TurbulentGrids {
    let spec = GridSpec::covering(
        Lattice::new(16.0, 16.0, 0.0).unwrap(),
        Weighting::TopHat,
        0.0,
        255.0,
        296.0,
        423.0,
    )
    .unwrap();
    let est = |s: &[Sample], noise_rms: f64| -> GridStats {
        let mut a = GridAccumulator::new(spec);
        a.add_all(s);
        estimate(
            &a,
            &EstimateOptions {
                fit: Fit::Linear,
                min_count: 50,
                noise_rms,
            },
        )
        .unwrap()
    };
    let noise = velocity_noise(samples, &est(samples, 0.0), &Default::default()).unwrap();
    let at_samples: Vec<Sample> = samples
        .iter()
        .map(|s| {
            let (u, v) = flow.velocity(s.x, s.y, s.t_us * 1e-6);
            Sample { u, v, ..*s }
        })
        .collect();
    TurbulentGrids {
        spec,
        measured: est(samples, noise.noise_rms),
        truth: est(&at_samples, 0.0),
        at_samples,
        noise_rms: noise.noise_rms,
    }
}
