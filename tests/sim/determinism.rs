//! Same seed → identical output; different seed → different; streaming,
//! chunking and thread count do not change the result.

use ebptv::io::EventSource;
use ebptv::sim::{presets, simulate, Scenario, Simulator};
use ebptv::Chunk;

fn scene() -> Scenario {
    // Every effect on, so that every random stream is exercised.
    let mut s = presets::preset("demo").unwrap();
    s.duration_s = 0.01;
    s.noise.hot_pixels = Some(ebptv::sim::scenario::HotPixels {
        count: 10,
        rate_hz: 500.0,
    });
    s.noise.background_noise = Some(ebptv::sim::scenario::BackgroundNoise { rate_hz: 5.0 });
    s.pixel.off_events = Some(ebptv::sim::scenario::OffEvents {
        threshold: 0.3,
        tau_us: 20.0,
    });
    s.readout.rate_limiter = Some(ebptv::sim::scenario::RateLimiter {
        max_rate_ev_s: 1e8,
        window_us: 50.0,
    });
    s
}

#[test]
fn same_seed_same_output_different_seed_different() {
    let s = scene();
    let a = simulate(&s, 7).unwrap();
    let b = simulate(&s, 7).unwrap();
    assert_eq!(a.events, b.events);
    assert_eq!(a.truth, b.truth);
    assert_eq!(a.triggers, b.triggers);
    let c = simulate(&s, 8).unwrap();
    assert_ne!(a.events, c.events);
    assert_ne!(a.truth, c.truth);
    // Pulse timing is the scenario's, not random.
    assert_eq!(a.triggers, c.triggers);
}

#[test]
fn thread_count_does_not_change_the_output() {
    let s = scene();
    let two = simulate(&s, 3).unwrap();
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap();
    let one = pool.install(|| simulate(&s, 3).unwrap());
    assert_eq!(one.events, two.events);
    assert_eq!(one.truth, two.truth);
}

#[test]
fn streaming_matches_simulate_and_truth_can_be_taken_in_pieces() {
    let s = scene();
    let whole = simulate(&s, 5).unwrap();
    let mut sim = Simulator::new(&s, 5).unwrap();
    let mut chunk = Chunk::default();
    let mut events = ebptv::EventChunk::default();
    let mut triggers = Vec::new();
    let mut truth = Vec::new();
    let mut chunks = 0;
    let mut last_t = i64::MIN;
    while sim.next_chunk(&mut chunk).unwrap() {
        assert!(!chunk.is_empty());
        if let Some(&t) = chunk.events.t.first() {
            assert!(t >= last_t, "chunks are in time order");
        }
        last_t = chunk.events.t.last().copied().unwrap_or(last_t);
        events.extend_from(&chunk.events);
        triggers.extend_from_slice(&chunk.triggers);
        truth.extend(sim.take_truth());
        chunks += 1;
    }
    assert!(chunks > 3, "a 10 ms recording comes in several blocks");
    assert!(!sim.next_chunk(&mut chunk).unwrap() && chunk.is_empty());
    assert_eq!(events, whole.events);
    assert_eq!(triggers, whole.triggers);
    assert_eq!(truth, whole.truth);
    let st = sim.stats();
    assert_eq!(st.events, whole.events.len() as u64);
    assert_eq!(st.pulses, 50);
    assert_eq!(st.truth_samples, whole.truth.len() as u64);
}

#[test]
fn triggers_mark_both_edges_of_every_pulse() {
    let s = scene();
    let o = simulate(&s, 1).unwrap();
    assert_eq!(o.pulse_starts_us.len(), 50);
    assert_eq!(o.triggers.len(), 100);
    for (k, p) in o.pulse_starts_us.iter().enumerate() {
        let r = o.triggers[2 * k];
        let f = o.triggers[2 * k + 1];
        assert_eq!(r.edge, ebptv::Edge::Rising);
        assert_eq!(f.edge, ebptv::Edge::Falling);
        assert_eq!(r.channel, s.triggers.channel);
        assert_eq!(r.t, p.floor() as i64);
        assert_eq!(f.t, (p + s.light.pulse_width_us).floor() as i64);
        assert!((p - (s.light.first_pulse_us + k as f64 * s.period_us())).abs() < 1e-9);
    }
    let mut off = s.clone();
    off.triggers.enabled = false;
    let o2 = simulate(&off, 1).unwrap();
    assert!(o2.triggers.is_empty());
    assert_eq!(o2.events, o.events);
}

/// `ebptv simulate`'s files are byte-identical whatever the thread count
/// (the writer thread and the rayon pool only change who computes what).
#[test]
fn recording_files_are_byte_identical_for_one_and_two_threads() {
    let mut s = scene();
    s.duration_s = 0.004;
    let write = |threads: usize| {
        let dir = tempfile::tempdir().unwrap();
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        pool.install(|| {
            ebptv::sim::write_recording(&s, 9, dir.path(), ebptv::io::Format::Evt3, |_, _| {})
                .unwrap()
        });
        let read = |n: &str| std::fs::read(dir.path().join(n)).unwrap();
        (
            read("recording.raw"),
            read("truth_particles.csv"),
            read("summary.json"),
        )
    };
    let one = write(1);
    let two = write(2);
    assert!(one.0.len() > 10_000 && one.1.len() > 10_000);
    assert!(one == two, "files differ between 1 and 2 threads");
}
