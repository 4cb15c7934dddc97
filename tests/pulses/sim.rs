//! Pulse timing, assignment and diagnostics on generated pulsed recordings
//! with known truth (a small generator here; the full simulator is tested
//! in `pulses_simulator.rs` once it exists).

use ebptv::events::{Chunk, Edge, EventChunk, Trigger};
use ebptv::io::{EventSource, Format, StreamInfo};
use ebptv::pulses::{analyze, split_pulses, PulseOptions, PulseSource, PulseTiming};
use rand::{Rng, SeedableRng};
use rand_distr::{Distribution, Gamma, Poisson};
use rand_pcg::Pcg64;

/// A recording held in memory, served in chunks.
struct MemSource {
    info: StreamInfo,
    events: EventChunk,
    triggers: Vec<Trigger>,
    pos: usize,
    tpos: usize,
    chunk: usize,
}

impl MemSource {
    fn new(events: EventChunk, triggers: Vec<Trigger>) -> Self {
        MemSource {
            info: StreamInfo {
                path: "generated".into(),
                format: Format::Csv,
                geometry: Some(ebptv::Geometry::new(640, 480)),
                header: vec![],
                payload_offset: 0,
                file_size: None,
            },
            events,
            triggers,
            pos: 0,
            tpos: 0,
            chunk: 65_536,
        }
    }
}

impl EventSource for MemSource {
    fn info(&self) -> &StreamInfo {
        &self.info
    }
    fn next_chunk(&mut self, c: &mut Chunk) -> ebptv::Result<bool> {
        c.clear();
        let end = (self.pos + self.chunk).min(self.events.len());
        for i in self.pos..end {
            c.events.push(
                self.events.t[i],
                self.events.x[i],
                self.events.y[i],
                self.events.p[i],
            );
        }
        let t_end = if end < self.events.len() {
            self.events.t[end]
        } else {
            i64::MAX
        };
        while self.tpos < self.triggers.len() && self.triggers[self.tpos].t < t_end {
            c.triggers.push(self.triggers[self.tpos]);
            self.tpos += 1;
        }
        self.pos = end;
        Ok(!c.is_empty())
    }
}

#[derive(Clone)]
struct Scene {
    period_us: f64,
    first_us: f64,
    duration_us: f64,
    /// Minimum sensor latency: no event before pulse start + this.
    min_latency_us: f64,
    /// Gamma-distributed latency beyond the minimum.
    lat_shape: f64,
    lat_scale: f64,
    particles_per_pulse: f64,
    noise_hz: f64,
    trigger_channel: Option<u8>,
    missing_every: Option<usize>,
    saturated: bool,
    /// Time-order jitter (EVT3-like small steps back), µs.
    disorder_us: i64,
    seed: u64,
}

impl Scene {
    fn new(hz: f64) -> Self {
        Scene {
            period_us: 1e6 / hz,
            first_us: 37.3,
            duration_us: 400_000.0,
            min_latency_us: 0.0,
            lat_shape: 3.0,
            lat_scale: 2.5,
            particles_per_pulse: 60.0,
            noise_hz: 200_000.0,
            trigger_channel: None,
            missing_every: None,
            saturated: false,
            disorder_us: 0,
            seed: 7,
        }
    }
}

struct Truth {
    starts: Vec<f64>,
    /// Generating pulse of each event (-1 = noise), aligned with the sorted events.
    pulse_of: Vec<i64>,
    particles: u64,
    particle_events: u64,
}

fn generate(s: &Scene) -> (EventChunk, Vec<Trigger>, Truth) {
    let mut rng = Pcg64::seed_from_u64(s.seed);
    let gamma = Gamma::new(s.lat_shape, s.lat_scale).unwrap();
    let npart = Poisson::new(s.particles_per_pulse.max(1e-9)).unwrap();
    let nev = Poisson::new(0.6).unwrap();
    let mut ev: Vec<(i64, u16, u16, u8, i64)> = Vec::new();
    let mut triggers = Vec::new();
    let mut starts = Vec::new();
    let (mut particles, mut particle_events) = (0u64, 0u64);
    let mut k = 0i64;
    loop {
        let t0 = s.first_us + k as f64 * s.period_us;
        if t0 > s.duration_us {
            break;
        }
        starts.push(t0);
        if let Some(c) = s.trigger_channel {
            if s.missing_every.is_none_or(|m| k as usize % m != 3) {
                triggers.push(Trigger {
                    t: t0.round() as i64,
                    channel: c,
                    edge: Edge::Rising,
                });
                triggers.push(Trigger {
                    t: (t0 + 5.0).round() as i64,
                    channel: c,
                    edge: Edge::Falling,
                });
            }
        }
        if !s.saturated {
            let n = npart.sample(&mut rng) as usize;
            particles += n as u64;
            for _ in 0..n {
                let x = rng.gen_range(2..630u16);
                let y = rng.gen_range(2..470u16);
                let m = 1 + nev.sample(&mut rng) as usize;
                particle_events += m as u64;
                for _ in 0..m {
                    let lat = s.min_latency_us + gamma.sample(&mut rng);
                    let t = (t0 + lat).floor() as i64;
                    let dx = rng.gen_range(0..2u16);
                    ev.push((t, x + dx, y, 1, k));
                }
            }
        }
        k += 1;
    }
    if s.saturated {
        // Arbiter saturation: rows dumped with one timestamp, at times no
        // longer tied to the pulses.
        let groups = (s.duration_us * 0.2) as usize;
        for _ in 0..groups {
            let t = rng.gen_range(0.0..s.duration_us) as i64;
            let y = rng.gen_range(0..480u16);
            let g = rng.gen_range(4..16u16);
            let x0 = rng.gen_range(0..600u16);
            for i in 0..g {
                ev.push((t, x0 + i * 2, y, 1, -1));
            }
        }
    }
    let n_noise = (s.noise_hz * s.duration_us * 1e-6) as usize;
    for _ in 0..n_noise {
        let t = rng.gen_range(0.0..s.duration_us) as i64;
        ev.push((
            t,
            rng.gen_range(0..640),
            rng.gen_range(0..480),
            rng.gen_range(0..2),
            -1,
        ));
    }
    ev.sort_by_key(|e| (e.0, e.2, e.1));
    if s.disorder_us > 0 {
        // Timestamps stepping back a little, as EVT 3 TIME_LOW does.
        for e in ev.iter_mut() {
            if rng.gen_bool(0.05) {
                e.0 -= rng.gen_range(1..=s.disorder_us);
            }
        }
    }
    let mut out = EventChunk::default();
    let mut pulse_of = Vec::new();
    for e in &ev {
        out.push(e.0, e.1, e.2, e.3);
        pulse_of.push(e.4);
    }
    (
        out,
        triggers,
        Truth {
            starts,
            pulse_of,
            particles,
            particle_events,
        },
    )
}

fn run(s: &Scene, opts: &PulseOptions) -> (ebptv::Result<ebptv::pulses::PulseReport>, Truth) {
    let (ev, tr, truth) = generate(s);
    let mut src = MemSource::new(ev, tr);
    (analyze(&mut src, opts), truth)
}

/// Error of the fitted start of pulse 0 against the truth (the truth's
/// pulse 0 must be the report's pulse 0).
fn start_error(t: &PulseTiming, truth: &Truth) -> f64 {
    let last = truth.starts.len() as i64 - 1;
    let e0 = t.pulse_start(0) - truth.starts[0];
    let e1 = t.pulse_start(last) - truth.starts[last as usize];
    if e0.abs() > e1.abs() {
        e0
    } else {
        e1
    }
}

#[test]
fn triggers_at_2_5_10_20_khz() {
    for hz in [2_000.0, 5_000.0, 10_000.0, 20_000.0] {
        let mut s = Scene::new(hz);
        s.trigger_channel = Some(1);
        s.period_us *= 1.0 + 40e-6; // clock drift
        let (r, truth) = run(&s, &PulseOptions::default());
        let r = r.unwrap();
        assert_eq!(r.timing.source, PulseSource::Trigger);
        assert!(
            (r.timing.period_us - s.period_us).abs() < 0.01,
            "{hz}: period {} vs {}",
            r.timing.period_us,
            s.period_us
        );
        let e = start_error(&r.timing, &truth);
        assert!(e.abs() < 1.0, "{hz}: start error {e}");
        // Gamma(3, 2.5) latency after flooring: mode 5 µs, FWHM ≈ 8.5 µs.
        assert!(
            (r.latency_peak_us - 4.5).abs() < 1.5,
            "{hz}: peak {}",
            r.latency_peak_us
        );
        assert!(
            (r.latency_fwhm_us - 8.5).abs() < 2.5,
            "{hz}: fwhm {}",
            r.latency_fwhm_us
        );
        assert_eq!(r.timing.pulse_width_us, Some(5.0));
        assert!(!r.saturated, "{hz}: flagged saturated");
        // Noise after the last pulse's window opens one more (extrapolated) pulse.
        let n = truth.starts.len() as u64;
        assert!(
            r.pulses == n || r.pulses == n + 1,
            "{hz}: {} pulses, truth {n}",
            r.pulses
        );
    }
}

#[test]
fn estimated_at_2_5_10_20_khz_with_drift() {
    for (i, hz) in [2_000.0, 5_000.0, 10_000.0, 20_000.0]
        .into_iter()
        .enumerate()
    {
        let mut s = Scene::new(hz);
        s.period_us *= 1.0 + 60e-6; // laser vs camera clock
        s.min_latency_us = 12.0;
        s.seed = 11 + i as u64;
        let opts = PulseOptions {
            pulse_hz: Some(hz),
            onset_latency_us: Some(12.0),
            ..Default::default()
        };
        let (r, truth) = run(&s, &opts);
        let r = r.unwrap();
        assert_eq!(r.timing.source, PulseSource::Estimated);
        let dp = r.timing.period_us - s.period_us;
        assert!(
            dp.abs() < 0.01,
            "{hz}: period {} vs {} (err {dp})",
            r.timing.period_us,
            s.period_us
        );
        let e = start_error(&r.timing, &truth);
        assert!(e.abs() < 5.0, "{hz}: start error {e}");
        let n = truth.starts.len() as u64;
        assert!(
            r.pulses == n || r.pulses == n + 1,
            "{hz}: {} pulses, truth {n}",
            r.pulses
        );
    }
}

#[test]
fn frequency_range_search_finds_the_fundamental() {
    let mut s = Scene::new(7_300.0);
    s.period_us *= 1.0 - 30e-6;
    let opts = PulseOptions {
        pulse_hz_range: Some((1_000.0, 25_000.0)),
        ..Default::default()
    };
    let (r, _) = run(&s, &opts);
    let r = r.unwrap();
    assert!(
        (r.timing.period_us - s.period_us).abs() < 0.01,
        "{} vs {}",
        r.timing.period_us,
        s.period_us
    );
}

#[test]
fn missing_and_spurious_triggers_keep_numbering() {
    let mut s = Scene::new(10_000.0);
    s.trigger_channel = Some(0);
    s.missing_every = Some(50);
    let (mut ev, mut tr, truth) = generate(&s);
    // A glitch edge between two pulses.
    tr.push(Trigger {
        t: (truth.starts[100] + 31.0) as i64,
        channel: 0,
        edge: Edge::Rising,
    });
    tr.sort_by_key(|t| t.t);
    ev.t.iter_mut().for_each(|_| ());
    let mut src = MemSource::new(ev, tr);
    let r = analyze(&mut src, &PulseOptions::default()).unwrap();
    let fit = r.triggers.fit.clone().unwrap();
    let n = truth.starts.len();
    assert_eq!(
        fit.missing as usize,
        (0..n - 1).filter(|k| k % 50 == 3).count()
    );
    assert_eq!(fit.spurious, 1);
    assert!(start_error(&r.timing, &truth).abs() < 1.0);
}

#[test]
fn saturated_recording_is_flagged() {
    let mut s = Scene::new(10_000.0);
    s.trigger_channel = Some(1);
    s.saturated = true;
    let (r, _) = run(&s, &PulseOptions::default());
    let r = r.unwrap();
    assert!(
        r.saturated,
        "not flagged: {:?}",
        (r.saturation.large_group_fraction, r.random_event_fraction)
    );
    assert!(r.saturation_shared_fraction > 0.5);
    assert!(
        r.histogram_flatness > 0.7,
        "flatness {} {:?}",
        r.histogram_flatness,
        r.latency.histogram
    );
}

#[test]
fn noisy_but_unsaturated_is_not_flagged() {
    let mut s = Scene::new(10_000.0);
    s.trigger_channel = Some(1);
    s.noise_hz = 4e6;
    let (r, _) = run(&s, &PulseOptions::default());
    let r = r.unwrap();
    assert!(r.random_event_fraction > 0.6, "{}", r.random_event_fraction);
    assert!(!r.saturated);
}

#[test]
fn continuous_illumination_is_refused_clearly() {
    let mut s = Scene::new(10_000.0);
    s.particles_per_pulse = 0.0;
    s.noise_hz = 3e6;
    let (r, _) = run(
        &s,
        &PulseOptions {
            pulse_hz: Some(10_000.0),
            ..Default::default()
        },
    );
    let msg = r.unwrap_err().to_string();
    assert!(msg.contains("no pulses detectable"), "{msg}");
}

#[test]
fn frequency_far_off_names_what_was_found() {
    let s = Scene::new(10_000.0);
    let (r, _) = run(
        &s,
        &PulseOptions {
            pulse_hz: Some(3_100.0),
            ..Default::default()
        },
    );
    let msg = r.unwrap_err().to_string();
    assert!(msg.contains("no pulse train between"), "{msg}");
    assert!(msg.contains("10000.") || msg.contains("9999."), "{msg}");
}

#[test]
fn trigger_on_other_channel_is_named() {
    let mut s = Scene::new(5_000.0);
    s.trigger_channel = Some(1);
    let (r, _) = run(
        &s,
        &PulseOptions {
            trigger_channel: Some(0),
            ..Default::default()
        },
    );
    let msg = r.unwrap_err().to_string();
    assert!(
        msg.contains("channel 0") && msg.contains("channel 1") && msg.contains("regular train"),
        "{msg}"
    );
}

/// The simple, obviously-correct splitter: assign every event, group.
fn naive_split(ev: &EventChunk, t: &PulseTiming) -> (Vec<Vec<usize>>, u64) {
    let mut pulses: Vec<Vec<usize>> = Vec::new();
    let mut un = 0;
    for i in 0..ev.len() {
        match t.assign(ev.t[i]) {
            None => un += 1,
            Some(k) => {
                let k = k as usize;
                if pulses.len() <= k {
                    pulses.resize(k + 1, Vec::new());
                }
                pulses[k].push(i);
            }
        }
    }
    (pulses, un)
}

#[test]
fn split_matches_naive_and_truth_with_disorder() {
    let mut s = Scene::new(10_000.0);
    s.trigger_channel = Some(1);
    s.disorder_us = 4;
    s.duration_us = 200_000.0;
    let (ev, tr, truth) = generate(&s);
    let report = analyze(
        &mut MemSource::new(ev.clone(), tr.clone()),
        &PulseOptions::default(),
    )
    .unwrap();
    let timing = report.timing;
    let mut got: Vec<(i64, f64, EventChunk)> = Vec::new();
    let un = split_pulses(&mut MemSource::new(ev.clone(), tr), &timing, &mut |p| {
        got.push((p.index, p.start_us, p.events));
        Ok(())
    })
    .unwrap();
    let (naive, naive_un) = naive_split(&ev, &timing);
    assert_eq!(un, naive_un);
    assert_eq!(got.len(), naive.len());
    let mut burst_ok = 0u64;
    let mut burst_all = 0u64;
    for (k, (idx, start, chunk)) in got.iter().enumerate() {
        assert_eq!(*idx, k as i64, "pulses in order, none skipped");
        assert!((start - timing.pulse_start(k as i64)).abs() < 1e-9);
        let mut a: Vec<_> = chunk.iter().collect();
        let mut b: Vec<_> = naive[k]
            .iter()
            .map(|&i| ebptv::Event {
                t: ev.t[i],
                x: ev.x[i],
                y: ev.y[i],
                p: ev.p[i],
            })
            .collect();
        a.sort();
        b.sort();
        assert_eq!(a, b, "pulse {k}");
    }
    for i in 0..ev.len() {
        if truth.pulse_of[i] >= 0 {
            burst_all += 1;
            burst_ok += (timing.assign(ev.t[i]) == Some(truth.pulse_of[i])) as u64;
        }
    }
    assert!(
        burst_ok as f64 > 0.999 * burst_all as f64,
        "{burst_ok}/{burst_all}"
    );
}

#[test]
fn particle_image_statistics() {
    let mut s = Scene::new(5_000.0);
    s.trigger_channel = Some(1);
    s.noise_hz = 0.0;
    let (r, truth) = run(&s, &PulseOptions::default());
    let r = r.unwrap();
    let ppp_true = truth.particles as f64 / truth.starts.len() as f64 / (640.0 * 480.0);
    assert!(
        r.particles.pulses_sampled >= 8,
        "{}",
        r.particles.pulses_sampled
    );
    // Overlapping images merge rarely at this density.
    assert!(
        (r.particles.ppp / ppp_true - 1.0).abs() < 0.2,
        "{} vs {}",
        r.particles.ppp,
        ppp_true
    );
    let epp = truth.particle_events as f64 / truth.particles as f64;
    assert!(
        (r.particles.events_per_particle / epp - 1.0).abs() < 0.2,
        "{} vs {epp}",
        r.particles.events_per_particle
    );
    assert!(r.particles.mean_image_size_px > 1.0 && r.particles.mean_image_size_px < 1.5);
}

#[test]
fn hot_pixel_is_listed_and_json_is_flat() {
    let s = Scene::new(10_000.0);
    let (mut ev, _, _) = generate(&s);
    let mut all: Vec<ebptv::Event> = ev.iter().collect();
    for t in (0..400_000).step_by(100) {
        all.push(ebptv::Event {
            t,
            x: 77,
            y: 55,
            p: 1,
        });
    }
    all.sort_by_key(|e| e.t);
    ev.clear();
    for e in all {
        ev.push(e.t, e.x, e.y, e.p);
    }
    let r = analyze(
        &mut MemSource::new(ev, vec![]),
        &PulseOptions {
            pulse_hz: Some(10_000.0),
            ..Default::default()
        },
    )
    .unwrap();
    assert_eq!(
        (r.rate_map.hot_pixels[0].x, r.rate_map.hot_pixels[0].y),
        (77, 55)
    );
    assert!((r.rate_map.hot_pixels[0].rate_hz - 10_000.0).abs() < 300.0);
    let v: serde_json::Value = serde_json::to_value(&r).unwrap();
    for key in [
        "period_us",
        "first_pulse_us",
        "source",
        "latency_peak_us",
        "latency_fwhm_us",
        "saturated",
        "saturation_shared_fraction",
    ] {
        assert!(v.get(key).is_some(), "missing {key}");
    }
    assert_eq!(v["source"], "estimated");
}

#[test]
fn saturation_that_comes_and_goes_is_flagged_per_window() {
    // The same pulse train; the first half of the recording clean, the
    // second half saturated (as when seeding or laser power rises
    // mid-recording). Only windows of the second half may be flagged.
    let mut clean = Scene::new(10_000.0);
    clean.trigger_channel = Some(1);
    let mut sat = Scene::new(10_000.0);
    sat.trigger_channel = Some(1);
    sat.saturated = true;
    let (a, tr, _) = generate(&clean);
    let (b, _, _) = generate(&sat);
    let half = (clean.duration_us / 2.0) as i64;
    let mut merged: Vec<(i64, u16, u16, u8)> = Vec::new();
    for i in 0..a.len() {
        if a.t[i] < half {
            merged.push((a.t[i], a.x[i], a.y[i], a.p[i]));
        }
    }
    for i in 0..b.len() {
        if b.t[i] >= half {
            merged.push((b.t[i], b.x[i], b.y[i], b.p[i]));
        }
    }
    merged.sort_by_key(|e| e.0);
    let mut ev = EventChunk::default();
    for (t, x, y, p) in merged {
        ev.push(t, x, y, p);
    }
    let mut src = MemSource::new(ev, tr);
    let r = analyze(&mut src, &PulseOptions::default()).unwrap();
    let w = &r.saturation.windows;
    assert!(w.len() >= 4, "{} windows", w.len());
    // Windows straddling the switch may go either way.
    let early: Vec<_> = w.iter().filter(|w| w.t_end_us <= half).collect();
    let late: Vec<_> = w.iter().filter(|w| w.t_start_us >= half).collect();
    assert!(!early.is_empty() && !late.is_empty());
    assert!(
        early.iter().all(|w| !w.saturated),
        "clean windows flagged: {early:?}"
    );
    assert!(
        late.iter().all(|w| w.saturated),
        "saturated windows missed: {late:?}"
    );
    let f = r.saturation.saturated_event_fraction;
    assert!(f > 0.3 && f < 0.99, "saturated event fraction {f}");
}

/// Absurd options are refused before any event is read, naming the option.
#[test]
fn absurd_options_are_refused_by_name() {
    let s = Scene::new(10_000.0);
    let cases = [
        (
            PulseOptions {
                onset_latency_us: Some(-5.0),
                ..Default::default()
            },
            "onset_latency_us",
        ),
        (
            PulseOptions {
                onset_latency_us: Some(1e12),
                ..Default::default()
            },
            "onset_latency_us",
        ),
        (
            PulseOptions {
                pulse_hz: Some(0.0),
                ..Default::default()
            },
            "pulse_hz",
        ),
        (
            PulseOptions {
                pulse_hz_range: Some((5000.0, 100.0)),
                ..Default::default()
            },
            "pulse_hz_range",
        ),
    ];
    for (opts, name) in cases {
        let msg = run(&s, &opts).0.unwrap_err().to_string();
        assert!(msg.contains(name), "{name}: {msg}");
    }
}
