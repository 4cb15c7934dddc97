//! The baseline model built from the measurement itself, for a model check
//! without a scenario file: an ideal sensor that reproduces what ebptv can
//! read off the recording.
//!
//! What is estimated, in this order (each step uses the ones before):
//! 1. **Pulse timing**: the period from the median spacing of the trigger
//!    channel's rising edges, the phase from the first edge; without
//!    triggers, the pulse analysis of `ebptv pulses` on the events (around
//!    a nominal frequency when one is given; pulse 0 at the bursts' leading
//!    edge: latencies then count from there, in the measurement and the
//!    simulations alike).
//! 2. **Flow**: ebptv's own PTV on the measurement (pulse split →
//!    [`crate::track::PtvStream`]: clustering and tracking) → track points
//!    binned with [`crate::grid`] (top-hat bins, `bin_px` wide) → the mean
//!    field, empty bins filled from their neighbours → a regular
//!    `x,y,u,v` grid that the simulator replays as its `gridded` flow.
//! 3. **Brightness / pixels per particle**: the light energy that makes
//!    the simulator's clusters light as many pixels on average as the
//!    measured ones (bisection on log energy with the simulator on a small
//!    crop, common random numbers so the search is monotone). Pixels, not
//!    events: the image size is the light's and the optics'; the events
//!    each lit pixel gives are the pixel's response, which effects change.
//! 4. **Seeding density**: the seeded density scaled until the simulator's
//!    clusters per pulse and pixel match the measured ones (some seeded
//!    particles are too dim to be found, some overlap).
//! 5. **Latency median**: the fixed pixel latency shifted until the median
//!    latency of all events (time after their pulse's start) matches the
//!    measured. All events, not each cluster's first: a symmetric latency
//!    jitter leaves the median of all events in place but pulls every
//!    cluster's first event earlier, and a baseline calibrated on first
//!    events would absorb part of the jitter it is meant to reveal.
//!
//! Everything else is the simulator's ideal sensor; the effects are what
//! the model check then searches for. The particle-image diameter and the
//! brightness spread stay at their defaults (noted in [`Baseline::notes`]).

use std::path::{Path, PathBuf};

use super::scene::{median_event_latency, particles_of, pulses_of, timing_of};
use crate::cluster::{ClusterParams, Particle};
use crate::error::{Error, Result};
use crate::events::{EventChunk, Geometry};
use crate::grid::{
    estimate, EstimateOptions, GridAccumulator, GridSpec, Lattice, Sample, Weighting,
};
use crate::io::atomic::AtomicFile;
use crate::sim::scenario::{FlowSpec, Scenario, Sensor};
use crate::track::{PtvSink, PtvStream, Track, TrackParams};

/// Options of [`baseline_from_measurement`].
#[derive(Debug, Clone)]
pub(crate) struct BaselineOptions {
    /// Bin size of the flow grid (px).
    pub bin_px: f64,
    /// Track points a bin needs to count as measured.
    pub min_count: u64,
    /// Seed of the calibration simulations.
    pub seed: u64,
}

impl Default for BaselineOptions {
    fn default() -> Self {
        BaselineOptions {
            bin_px: 32.0,
            min_count: 5,
            seed: 1,
        }
    }
}

/// The baseline scenario, the flow it replays, and what was estimated.
#[derive(Debug, Clone)]
pub(crate) struct Baseline {
    /// The simulator scenario estimated from the measurement.
    pub scenario: Scenario,
    /// How each part of the scenario was estimated, one line each.
    pub notes: Vec<String>,
}

/// Write the flow grid as the simulator's `gridded` CSV (`x,y,u,v`).
pub(crate) fn write_flow_csv(path: &Path, flow: &[(f64, f64, f64, f64)]) -> Result<()> {
    let mut s = String::from("x,y,u,v\n");
    for (x, y, u, v) in flow {
        s.push_str(&format!("{x},{y},{u},{v}\n"));
    }
    AtomicFile::write_all_to(path, s.as_bytes())
}

struct Collect {
    particles: Vec<Particle>,
    tracks: Vec<Track>,
}

impl PtvSink for Collect {
    fn particles(&mut self, _pulse: i64, _t: f64, ps: &[Particle]) -> Result<()> {
        self.particles.extend_from_slice(ps);
        Ok(())
    }
    fn tracks(&mut self, tracks: &[Track]) -> Result<()> {
        self.tracks.extend_from_slice(tracks);
        Ok(())
    }
}

/// The measurement's pulse train, as the baseline replays it.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct PulseTrain {
    /// Pulse period (µs).
    pub period_us: f64,
    /// A pulse start (µs, sensor clock).
    pub start_us: f64,
    /// Where the train came from, for the notes.
    pub source: String,
}

impl PulseTrain {
    /// From rising trigger edges (µs): the median spacing, the first edge.
    pub(crate) fn from_triggers(rising: &[i64]) -> Result<Self> {
        if rising.len() < 3 {
            return Err(Error::analysis(format!(
                "{} rising trigger edges: a pulse train from the triggers needs at least 3",
                rising.len()
            )));
        }
        let mut d: Vec<i64> = rising.windows(2).map(|w| w[1] - w[0]).collect();
        d.sort_unstable();
        let period = d[d.len() / 2] as f64;
        if period <= 0.0 {
            return Err(Error::analysis("trigger edges are not increasing in time"));
        }
        Ok(PulseTrain {
            period_us: period,
            start_us: rising[0] as f64,
            source: "from the trigger channel".into(),
        })
    }

    /// From the pulse analysis of the events (no triggers): its period and
    /// the start of its pulse 0, the burst's leading edge. The latencies
    /// the check then measures count from that edge, in the measurement
    /// and in every simulation alike.
    pub(crate) fn estimated(timing: &crate::pulses::PulseTiming, nominal_hz: Option<f64>) -> Self {
        let searched = match nominal_hz {
            Some(hz) => format!("around {hz} Hz"),
            None => "over the default band".into(),
        };
        PulseTrain {
            period_us: timing.period_us,
            start_us: timing.first_pulse_us,
            source: format!(
                "found from the events {searched} (no trigger used; latencies count from the bursts' leading edge)"
            ),
        }
    }
}

/// Build the baseline from measured `events` (time-ordered), their pulse
/// train and the sensor geometry. The flow grid is written to `flow_csv`
/// (the scenario's `flow.path` points there).
pub(crate) fn baseline_from_measurement(
    events: &EventChunk,
    train: &PulseTrain,
    geometry: Geometry,
    flow_csv: &Path,
    opts: &BaselineOptions,
) -> Result<Baseline> {
    if !(opts.bin_px.is_finite() && opts.bin_px >= 2.0) {
        return Err(Error::param(
            "bin_px",
            format!("{} must be at least 2 px", opts.bin_px),
        ));
    }
    let period = train.period_us;
    if !(period.is_finite() && period > 0.0 && train.start_us.is_finite()) {
        return Err(Error::analysis(format!(
            "pulse train of period {period} us starting at {} us: not a pulse train",
            train.start_us
        )));
    }
    let mut sc = Scenario {
        name: "baseline-from-measurement".into(),
        sensor: Sensor {
            width: geometry.width as u32,
            height: geometry.height as u32,
            roi: None,
        },
        ..Scenario::default()
    };
    sc.light.pulse_hz = 1e6 / period;
    sc.light.first_pulse_us = train.start_us.rem_euclid(period);
    sc.validate()?;
    let timing = timing_of(&sc);
    let cluster = ClusterParams {
        radius: ClusterParams::radius_for_image_diameter(sc.optics.particle_diameter_px),
        ..ClusterParams::default()
    };
    let mut notes = vec![format!(
        "baseline from the measurement: {}x{} px, pulses {:.1} Hz {}",
        geometry.width, geometry.height, sc.light.pulse_hz, train.source
    )];

    // Particles and tracks: ebptv's own PTV.
    let pulses = pulses_of(events, &timing)?;
    let n_pulses = pulses.len();
    let mut stream = PtvStream::new(cluster.clone(), TrackParams::default(), 64)?;
    let mut sink = Collect {
        particles: Vec::new(),
        tracks: Vec::new(),
    };
    for p in pulses {
        stream.push_pulse(p, &mut sink)?;
    }
    stream.finish(&mut sink)?;
    if sink.particles.is_empty() || n_pulses == 0 {
        return Err(Error::analysis(
            "no particles found in the measurement: cannot build a baseline model",
        ));
    }

    // Flow.
    let flow = flow_grid(&sink.tracks, geometry, opts)?;
    match &flow {
        Some((nodes, measured_bins)) => {
            write_flow_csv(flow_csv, nodes)?;
            sc.flow = FlowSpec::Gridded {
                path: PathBuf::from(flow_csv),
                scale: 1.0,
            };
            notes.push(format!(
                "flow: mean field of {} tracks on {:.0} px bins ({} of {} bins measured, the rest filled from neighbours), replayed from {}",
                sink.tracks.len(),
                opts.bin_px,
                measured_bins,
                nodes.len(),
                flow_csv.display()
            ));
        }
        None => notes.push(format!(
            "flow: too few tracks ({}) for a field; the simulator's default flow is used",
            sink.tracks.len()
        )),
    }

    // Seeding density.
    sc.seeding.ppp =
        (sink.particles.len() as f64 / n_pulses as f64 / geometry.pixels() as f64).clamp(1e-5, 0.1);
    notes.push(format!(
        "seeding: {:.5} particles per pixel ({} particles over {} pulses)",
        sc.seeding.ppp,
        sink.particles.len(),
        n_pulses
    ));

    // Light energy, seeding and latency, calibrated with the simulator on a
    // crop (a uniform flow at the measured median speed: only the pixels'
    // response and the clustering matter here).
    //
    // The energy is matched on the pixels a particle lights, not on its
    // events: how large a particle image is depends on the light and the
    // optics, how many events each lit pixel gives is the pixel's response,
    // which effects change (a refractory pixel fires once per pulse). An
    // energy matched on events would absorb such an effect into smaller
    // images.
    let measured_ppc = mean_pixels(&sink.particles);
    let measured_epc = mean_events(&sink.particles);
    let measured_density = sink.particles.len() as f64 / n_pulses as f64 / geometry.pixels() as f64;
    let measured_lat = median_event_latency(events, &timing);
    let speeds = median_velocity(&sink.tracks);
    let calib = |sc: &Scenario| -> Result<(f64, f64, f64)> {
        let mut c = sc.clone();
        c.sensor = Sensor {
            width: sc.sensor.width.min(192),
            height: sc.sensor.height.min(144),
            roi: None,
        };
        c.flow = FlowSpec::Uniform {
            u: speeds.0,
            v: speeds.1,
        };
        let pulses = 60.0;
        c.duration_s = (sc.period_us() * pulses + sc.light.first_pulse_us) * 1e-6;
        c.validate()?;
        let out = crate::sim::simulate(&c, opts.seed)?;
        let t = timing_of(&c);
        let parts = particles_of(&out.events, &t, &cluster)?;
        if parts.is_empty() {
            return Ok((0.0, 0.0, f64::NAN));
        }
        let density =
            parts.len() as f64 / pulses / (c.sensor.width as f64 * c.sensor.height as f64);
        Ok((
            mean_pixels(&parts),
            density,
            median_event_latency(&out.events, &t),
        ))
    };
    let (mut lo, mut hi) = (0.2f64.ln(), 500f64.ln());
    for _ in 0..14 {
        let mid = 0.5 * (lo + hi);
        let mut c = sc.clone();
        c.light.energy = mid.exp();
        let (ppc, _, _) = calib(&c)?;
        if ppc < measured_ppc {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    sc.light.energy = (0.5 * (lo + hi)).exp();
    // The seeded density is more than the density of particles found
    // (some are too dim or overlap): scale it until the simulator's found
    // density matches the measured one (the count is proportional to it).
    for _ in 0..2 {
        let (_, density, _) = calib(&sc)?;
        if density > 0.0 && measured_density > 0.0 {
            sc.seeding.ppp = (sc.seeding.ppp * measured_density / density).clamp(1e-5, 0.1);
        }
    }
    for _ in 0..2 {
        let (_, _, lat) = calib(&sc)?;
        if lat.is_finite() && measured_lat.is_finite() {
            sc.pixel.latency_us = (sc.pixel.latency_us + measured_lat - lat).max(0.0);
        }
    }
    notes.push(format!(
        "brightness: light energy {:.3} for {:.2} pixels per particle ({:.2} events); seeding {:.5} per pixel for {:.5} particles found per pixel and pulse; latency: fixed part {:.1} us for a median event latency of {:.1} us; particle image diameter and brightness spread are the simulator defaults",
        sc.light.energy, measured_ppc, measured_epc, sc.seeding.ppp, measured_density, sc.pixel.latency_us, measured_lat
    ));
    sc.validate()?;
    Ok(Baseline {
        scenario: sc,
        notes,
    })
}

fn mean_pixels(ps: &[Particle]) -> f64 {
    ps.iter().map(|p| p.n_pixels as f64).sum::<f64>() / ps.len().max(1) as f64
}

fn mean_events(ps: &[Particle]) -> f64 {
    ps.iter().map(|p| p.n_events as f64).sum::<f64>() / ps.len().max(1) as f64
}

/// Median (u, v) over all track points (0 without tracks).
fn median_velocity(tracks: &[Track]) -> (f64, f64) {
    let mut u: Vec<f64> = Vec::new();
    let mut v: Vec<f64> = Vec::new();
    for p in tracks.iter().flat_map(|t| &t.points) {
        if p.u.is_finite() && p.v.is_finite() {
            u.push(p.u);
            v.push(p.v);
        }
    }
    if u.is_empty() {
        return (0.0, 0.0);
    }
    u.sort_by(f64::total_cmp);
    v.sort_by(f64::total_cmp);
    (u[u.len() / 2], v[v.len() / 2])
}

/// The mean field of the tracks on a regular grid covering the sensor,
/// empty bins filled by repeated neighbour averaging. Returns the nodes and
/// how many bins were measured; `None` when no bin has `min_count` points.
#[allow(clippy::type_complexity)]
pub(crate) fn flow_grid(
    tracks: &[Track],
    geometry: Geometry,
    opts: &BaselineOptions,
) -> Result<Option<(Vec<(f64, f64, f64, f64)>, usize)>> {
    let lattice = Lattice::new(opts.bin_px, opts.bin_px, 0.0)?;
    let spec = GridSpec::covering(
        lattice,
        Weighting::TopHat,
        0.0,
        geometry.width as f64 - 1.0,
        0.0,
        geometry.height as f64 - 1.0,
    )?;
    let mut acc = GridAccumulator::new(spec);
    for t in tracks {
        for p in t.points.iter().filter(|p| !p.interpolated) {
            acc.add(&Sample::from_track_point(t.id, p));
        }
    }
    let stats = estimate(
        &acc,
        &EstimateOptions {
            min_count: opts.min_count.max(1),
            ..EstimateOptions::default()
        },
    )?;
    let (nx, ny) = (stats.xs.len(), stats.ys.len());
    let mut u: Vec<f64> = stats.bins.iter().map(|b| b.u).collect();
    let mut v: Vec<f64> = stats.bins.iter().map(|b| b.v).collect();
    let measured = u
        .iter()
        .zip(&v)
        .filter(|(a, b)| a.is_finite() && b.is_finite())
        .count();
    if measured == 0 {
        return Ok(None);
    }
    fill_from_neighbours(&mut u, &mut v, nx, ny);
    let mut nodes = Vec::with_capacity(nx * ny);
    for (iy, &y) in stats.ys.iter().enumerate() {
        for (ix, &x) in stats.xs.iter().enumerate() {
            let k = iy * nx + ix;
            nodes.push((x, y, u[k], v[k]));
        }
    }
    Ok(Some((nodes, measured)))
}

/// Fill NaN cells with the mean of their known 8-neighbours, sweep after
/// sweep, until every cell is known (needs at least one known cell).
fn fill_from_neighbours(u: &mut [f64], v: &mut [f64], nx: usize, ny: usize) {
    loop {
        let unknown: Vec<usize> = (0..u.len()).filter(|&k| !u[k].is_finite()).collect();
        if unknown.is_empty() {
            return;
        }
        let mut updates = Vec::new();
        for &k in &unknown {
            let (ix, iy) = ((k % nx) as i64, (k / nx) as i64);
            let (mut su, mut sv, mut n) = (0.0, 0.0, 0.0);
            for dy in -1..=1 {
                for dx in -1..=1 {
                    let (x, y) = (ix + dx, iy + dy);
                    if (dx, dy) == (0, 0) || x < 0 || y < 0 || x >= nx as i64 || y >= ny as i64 {
                        continue;
                    }
                    let j = y as usize * nx + x as usize;
                    if u[j].is_finite() && v[j].is_finite() {
                        su += u[j];
                        sv += v[j];
                        n += 1.0;
                    }
                }
            }
            if n > 0.0 {
                updates.push((k, su / n, sv / n));
            }
        }
        if updates.is_empty() {
            return; // no known cell at all (caller checked)
        }
        for (k, a, b) in updates {
            u[k] = a;
            v[k] = b;
        }
    }
}
