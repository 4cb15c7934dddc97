//! Live input: `monitor` following a RAW file while another thread is still
//! writing it, and `pulses`/`monitor` reading a RAW stream from stdin.

use std::io::Write;
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use ebptv::io::live::open_growing;
use ebptv::pulses::monitor::{run, Follow, IntervalSummary};
use ebptv::pulses::PulseOptions;
use ebptv::sim::{presets::preset, simulate};

/// The simulator's demo (5 kHz, triggers) as EVT 3.0 bytes, and its event count.
fn demo_raw(dir: &std::path::Path) -> (Vec<u8>, u64) {
    let mut sc = preset("demo").unwrap();
    sc.duration_s = 0.03;
    sc.triggers.enabled = true;
    let out = simulate(&sc, 5).unwrap();
    let path = dir.join("full.raw");
    let mut w = ebptv::io::create(&path, None, out.geometry.unwrap()).unwrap();
    let chunk = ebptv::Chunk {
        events: out.events,
        triggers: out.triggers,
    };
    w.write_chunk(&chunk).unwrap();
    w.finish().unwrap();
    let mut n = 0u64;
    let mut src = ebptv::io::open(&path).unwrap();
    let mut c = ebptv::Chunk::default();
    while src.next_chunk(&mut c).unwrap() {
        n += c.events.len() as u64;
    }
    (std::fs::read(&path).unwrap(), n)
}

/// Append `bytes` to `path` in uneven pieces (cut inside words and inside
/// the header), pausing between them; set `done` at the end.
fn writer(path: std::path::PathBuf, bytes: Vec<u8>, done: Arc<AtomicBool>) {
    let mut f = std::fs::File::create(&path).unwrap();
    let cuts = [37usize, 101, 4099, 65_537, 200_001, 333_333, 500_001];
    let mut pos = 0;
    let mut k = 0;
    while pos < bytes.len() {
        let len = cuts[k % cuts.len()].min(bytes.len() - pos);
        f.write_all(&bytes[pos..pos + len]).unwrap();
        f.flush().unwrap();
        pos += len;
        k += 1;
        std::thread::sleep(Duration::from_millis(40));
    }
    done.store(true, Ordering::SeqCst);
}

#[test]
fn monitor_follows_a_growing_raw_file() {
    let dir = tempfile::tempdir().unwrap();
    let (bytes, total) = demo_raw(dir.path());
    let path = dir.path().join("growing.raw");
    let done = Arc::new(AtomicBool::new(false));
    let handle = {
        let (path, done) = (path.clone(), done.clone());
        std::thread::spawn(move || writer(path, bytes, done))
    };
    while !path.exists() {
        std::thread::sleep(Duration::from_millis(5));
    }
    let mut src = open_growing(&path, Duration::from_secs(10)).unwrap();
    assert_eq!(src.info().format, ebptv::io::Format::Evt3);
    let stop = AtomicBool::new(false);
    let mut seen: Vec<(IntervalSummary, bool)> = Vec::new();
    let n = run(
        &mut src,
        &PulseOptions::default(),
        5_000,
        Follow::UntilIdle(Duration::from_millis(600)),
        &stop,
        &mut |s| seen.push((s.clone(), done.load(Ordering::SeqCst))),
    )
    .unwrap();
    handle.join().unwrap();
    assert_eq!(n as usize, seen.len());
    // Every event written was seen once, across intervals.
    let events: u64 = seen.iter().map(|(s, _)| s.events).sum();
    assert_eq!(events, total);
    // Reports came while the file was still being written.
    let early = seen.iter().filter(|(_, d)| !d).count();
    assert!(early >= 2, "{early} reports before the writer finished");
    // Full intervals carry pulse statistics (5 kHz: 25 pulses per 5 ms).
    let with_stats: Vec<&IntervalSummary> = seen
        .iter()
        .map(|(s, _)| s)
        .filter(|s| s.note.is_none())
        .collect();
    assert!(with_stats.len() >= 3, "{seen:?}");
    for s in &with_stats {
        assert!(s.fwhm_us > 5.0 && s.fwhm_us < 200.0, "{s:?}");
        assert!(s.burst_contrast > 2.0, "{s:?}");
        assert!(!s.saturated, "{s:?}");
    }
}

#[test]
fn monitor_stops_when_told() {
    let dir = tempfile::tempdir().unwrap();
    let (bytes, total) = demo_raw(dir.path());
    let path = dir.path().join("growing.raw");
    std::fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
    let mut src = open_growing(&path, Duration::from_secs(5)).unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    let stopper = {
        let stop = stop.clone();
        std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(400));
            stop.store(true, Ordering::SeqCst);
        })
    };
    let mut events = 0u64;
    run(
        &mut src,
        &PulseOptions::default(),
        5_000,
        Follow::UntilStopped,
        &stop,
        &mut |s| events += s.events,
    )
    .unwrap();
    stopper.join().unwrap();
    assert!(events > 0 && events < total, "{events} of {total}");
}

#[test]
fn pulses_and_monitor_read_stdin() {
    let dir = tempfile::tempdir().unwrap();
    let (bytes, _) = demo_raw(dir.path());
    let file = dir.path().join("full.raw");
    let run_cli = |args: &[&str], input: &[u8]| {
        let mut child = Command::new(env!("CARGO_BIN_EXE_ebptv"))
            .args(args)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        let mut stdin = child.stdin.take().unwrap();
        let input = input.to_vec();
        let feeder = std::thread::spawn(move || {
            // In pieces, as a pipe from an acquisition program would.
            for piece in input.chunks(77_777) {
                if stdin.write_all(piece).is_err() {
                    break;
                }
            }
        });
        let out = child.wait_with_output().unwrap();
        feeder.join().unwrap();
        out
    };
    let out_pipe = dir.path().join("pipe");
    let out = run_cli(
        &["pulses", "-", "--out", out_pipe.to_str().unwrap()],
        &bytes,
    );
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let out_file = dir.path().join("file");
    let st = Command::new(env!("CARGO_BIN_EXE_ebptv"))
        .args([
            "pulses",
            file.to_str().unwrap(),
            "--out",
            out_file.to_str().unwrap(),
        ])
        .output()
        .unwrap();
    assert!(st.status.success());
    let read = |d: &std::path::Path| -> serde_json::Value {
        serde_json::from_slice(&std::fs::read(d.join("pulses.json")).unwrap()).unwrap()
    };
    let (a, b) = (read(&out_pipe), read(&out_file));
    for key in [
        "period_us",
        "first_pulse_us",
        "events",
        "latency_peak_us",
        "saturated",
    ] {
        assert_eq!(a[key], b[key], "{key}");
    }

    let out = run_cli(&["monitor", "-", "--interval-s", "0.01"], &bytes);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.lines().filter(|l| l.contains("FWHM")).count() >= 2,
        "{text}"
    );

    // A format that does not name itself in a header: a clear refusal.
    let out = run_cli(
        &[
            "pulses",
            "-",
            "--out",
            dir.path().join("csv").to_str().unwrap(),
        ],
        b"t,x,y,p\n1,2,3,1\n",
    );
    assert!(!out.status.success());
    let msg = String::from_utf8_lossy(&out.stderr);
    assert!(msg.contains("RAW header"), "{msg}");
}

/// Serves a recording in fixed chunks and, before some of them, reports
/// "no data yet" (`Ok(false)`) the way a live source does while its writer
/// pauses.
struct PausingSource {
    info: ebptv::io::StreamInfo,
    chunks: Vec<ebptv::Chunk>,
    next: usize,
    pause_before: Vec<usize>,
    paused: bool,
}

impl ebptv::io::EventSource for PausingSource {
    fn info(&self) -> &ebptv::io::StreamInfo {
        &self.info
    }
    fn next_chunk(&mut self, c: &mut ebptv::Chunk) -> ebptv::Result<bool> {
        c.clear();
        if self.next >= self.chunks.len() {
            return Ok(false);
        }
        if self.pause_before.contains(&self.next) && !self.paused {
            self.paused = true;
            return Ok(false);
        }
        self.paused = false;
        *c = self.chunks[self.next].clone();
        self.next += 1;
        Ok(true)
    }
}

/// Intervals are in recording time: a writer that pauses (the live source
/// returning "no data yet" for a while) changes nothing in what is
/// reported, and every interval but the last spans exactly the interval on
/// the grid from the first event.
#[test]
fn monitor_intervals_ignore_writer_pauses() {
    let mut sc = preset("demo").unwrap();
    sc.duration_s = 0.03;
    sc.triggers.enabled = true;
    let out = simulate(&sc, 5).unwrap();
    let n = out.events.len();
    let mut chunks = Vec::new();
    let mut a = 0;
    for k in 0.. {
        if a >= n {
            break;
        }
        // Uneven pieces, each trigger with the piece of its time.
        let b = (a + [70_000usize, 9_000, 150_000][k % 3]).min(n);
        let mut c = ebptv::Chunk::default();
        c.events.t.extend_from_slice(&out.events.t[a..b]);
        c.events.x.extend_from_slice(&out.events.x[a..b]);
        c.events.y.extend_from_slice(&out.events.y[a..b]);
        c.events.p.extend_from_slice(&out.events.p[a..b]);
        let (lo, hi) = (
            if a == 0 { i64::MIN } else { out.events.t[a] },
            if b == n { i64::MAX } else { out.events.t[b] },
        );
        c.triggers = out
            .triggers
            .iter()
            .filter(|tr| tr.t >= lo && tr.t < hi)
            .copied()
            .collect();
        chunks.push(c);
        a = b;
    }
    assert!(chunks.len() >= 6);
    let info = ebptv::io::StreamInfo {
        path: "paused".into(),
        format: ebptv::io::Format::Evt3,
        geometry: out.geometry,
        header: vec![],
        payload_offset: 0,
        file_size: None,
    };
    let report = |pause_before: Vec<usize>, follow: Follow| {
        let mut src = PausingSource {
            info: info.clone(),
            chunks: chunks.clone(),
            next: 0,
            pause_before,
            paused: false,
        };
        let mut seen: Vec<IntervalSummary> = Vec::new();
        run(
            &mut src,
            &PulseOptions::default(),
            5_000,
            follow,
            &AtomicBool::new(false),
            &mut |s| seen.push(s.clone()),
        )
        .unwrap();
        seen
    };
    let steady = report(vec![], Follow::No);
    // Each pause is one poll (100 ms): far more than two 5 ms intervals of
    // wall time, which used to close the interval in progress.
    let paused = report(
        vec![1, 2, 4, chunks.len() - 1],
        Follow::UntilIdle(Duration::from_millis(300)),
    );
    assert_eq!(paused, steady);
    let t0 = out.events.t.iter().copied().min().unwrap();
    assert_eq!(steady[0].t_start_us, out.events.t[0]);
    assert!(steady.len() >= 5, "{steady:?}");
    for s in &steady[..steady.len() - 1] {
        assert_eq!(s.t_end_us - s.t_start_us, 5_000, "{s:?}");
        assert_eq!((s.t_start_us - steady[0].t_start_us) % 5_000, 0);
        assert!(s.note.is_none(), "{s:?}");
    }
    let events: u64 = steady.iter().map(|s| s.events).sum();
    assert_eq!(events as usize, n);
    assert!(t0 >= steady[0].t_start_us - 10, "time steps back little");
}
