//! Checks between a decoder and the stages: what a damaged or mislabelled
//! file must not be allowed to do downstream.
//!
//! - `Checked` wraps every source [`super::open_with`] returns. A stated
//!   geometry no sensor has (a side of 0 or above [`MAX_SENSOR_SIDE`]) is
//!   dropped (the stages then use the extent of the events, capped the
//!   same way) and reported ([`EventSource::warnings`]); a `% format`
//!   line contradicting `% evt` is refused unless the caller names the
//!   format (`check_header`); a RAW file without any header
//!   whose first chunk is mostly words of undefined types is refused (the
//!   same bytes on standard input are refused for lacking a header).
//! - [`TimeGuard`] is put in front of the stages that map time to pulses
//!   (`pulses`, `track`, `piv`). One corrupted time word moves the clock by
//!   hours; the events stamped with it would make hours of empty pulses. An
//!   event or trigger more than [`TIME_JUMP_US`] away from the last accepted
//!   time is dropped and counted (`Anomalies::time_jump_events`, one
//!   `time_jumps` per run of them). When such a run goes on for
//!   `JUMP_PERSIST_US` of its own clock the clock did not come back: the
//!   recording is discontinuous and the stage stops with an error naming
//!   the time and size of the jump, instead of guessing which side is right.
//!   An event camera's clock runs continuously and its noise alone fires
//!   every pixel row within milliseconds, so a silent gap of seconds in a
//!   pulsed recording is not data.

use super::{Anomalies, EventSource, Format, StreamInfo};
use crate::error::{Error, Result};
use crate::events::{Chunk, Geometry};

/// Largest sensor side ebptv accepts as stated (the largest event sensors
/// have 1280×720 … 2048×2048 pixels).
pub const MAX_SENSOR_SIDE: u16 = 4096;
/// A time step larger than this against the last accepted time is a jump.
pub const TIME_JUMP_US: i64 = 5_000_000;
/// A run of jumped events spanning this much of its own clock means the
/// clock stayed where it jumped.
pub(crate) const JUMP_PERSIST_US: i64 = 100_000;

/// True for a geometry some sensor can have.
pub(crate) fn plausible_geometry(g: Geometry) -> bool {
    g.width > 0 && g.height > 0 && g.width <= MAX_SENSOR_SIDE && g.height <= MAX_SENSOR_SIDE
}

/// The checks of the module doc on a freshly opened source.
pub(crate) struct Checked {
    inner: Box<dyn EventSource>,
    info: StreamInfo,
    rejected: Option<Geometry>,
    warnings: Vec<String>,
    /// The headerless-RAW content check is still to be done.
    check_content: bool,
}

impl Checked {
    /// Wraps `inner`.
    pub(crate) fn new(inner: Box<dyn EventSource>) -> Self {
        let mut info = inner.info().clone();
        let mut warnings = Vec::new();
        let mut rejected = None;
        if let Some(g) = info.geometry {
            if !plausible_geometry(g) {
                info.geometry = None;
                rejected = Some(g);
                warnings.push(format!(
                    "{}: the stated geometry {}x{} is impossible (a side of 0 or above {MAX_SENSOR_SIDE}): ignored, the extent of the events is used instead",
                    info.path.display(),
                    g.width,
                    g.height
                ));
            }
        }
        let raw = matches!(info.format, Format::Evt2 | Format::Evt21 | Format::Evt3);
        let check_content = raw && info.header.is_empty() && info.payload_offset == 0;
        Checked {
            inner,
            info,
            rejected,
            warnings,
            check_content,
        }
    }
}

/// A RAW header whose `% format` line names another encoding than its
/// `% evt` line: an error (decoding with the wrong one makes garbage that
/// can even look periodic), unless the caller named the format.
pub(crate) fn check_header(info: &StreamInfo) -> Result<()> {
    if !matches!(info.format, Format::Evt2 | Format::Evt21 | Format::Evt3) {
        return Ok(());
    }
    match contradiction(info) {
        Some(why) => Err(Error::UnknownFormat {
            path: info.path.clone(),
            why,
        }),
        None => Ok(()),
    }
}

/// `% format` naming another encoding than `% evt`.
fn contradiction(info: &StreamInfo) -> Option<String> {
    let get = |k: &str| {
        info.header
            .iter()
            .find(|(key, _)| key.eq_ignore_ascii_case(k))
            .map(|(_, v)| v.trim().to_string())
    };
    let fmt = get("format")?;
    let evt = get("evt")?;
    let named = fmt
        .split(';')
        .next()
        .unwrap_or("")
        .trim()
        .to_ascii_lowercase();
    let by_evt = match evt.as_str() {
        "2.0" | "2" => "evt2",
        "2.1" => "evt21",
        "3.0" | "3" => "evt3",
        _ => return None,
    };
    let named_norm = named.replace(['.', ' '], "");
    let by_evt_ok = match by_evt {
        "evt2" => named_norm == "evt2" || named_norm == "evt20",
        "evt21" => named_norm == "evt21",
        _ => named_norm == "evt3" || named_norm == "evt30",
    };
    (!by_evt_ok).then(|| {
        format!(
            "the header contradicts itself: `% format {fmt}` but `% evt {evt}`; name the format (ebptv info --format, ebptv convert --in-format) or correct the header"
        )
    })
}

impl EventSource for Checked {
    fn info(&self) -> &StreamInfo {
        &self.info
    }

    fn next_chunk(&mut self, chunk: &mut Chunk) -> Result<bool> {
        let more = self.inner.next_chunk(chunk)?;
        if self.check_content {
            self.check_content = false;
            let a = self.inner.anomalies();
            let bytes = self.inner.bytes_read().max(1);
            let word = match self.info.format {
                Format::Evt3 => 2,
                Format::Evt2 => 4,
                _ => 8,
            };
            let words = (bytes / word).max(1);
            // Valid RAW data holds no word of an undefined type; random bytes
            // hold 5 in 16 (EVT 3.0) and more in the other encodings.
            if a.unknown_word_types * 20 > words {
                return Err(Error::UnknownFormat {
                    path: self.info.path.clone(),
                    why: format!(
                        "no RAW header, and {:.0} % of the first {words} words are of types {} does not define: not {} data",
                        100.0 * a.unknown_word_types as f64 / words as f64,
                        self.info.format.name(),
                        self.info.format.name()
                    ),
                });
            }
        }
        Ok(more)
    }

    fn anomalies(&self) -> Anomalies {
        self.inner.anomalies()
    }

    fn bytes_read(&self) -> u64 {
        self.inner.bytes_read()
    }

    fn warnings(&self) -> Vec<String> {
        self.warnings.clone()
    }

    fn rejected_geometry(&self) -> Option<Geometry> {
        self.rejected
    }
}

/// Drops events and triggers that jumped in time (see the module doc).
pub struct TimeGuard<S: EventSource> {
    inner: S,
    /// Last accepted time.
    clock: Option<i64>,
    /// The run of jumped items in progress: (first time, min, max).
    run: Option<(i64, i64, i64)>,
    jumps: u64,
    dropped: u64,
}

impl<S: EventSource> TimeGuard<S> {
    /// Wraps `inner`.
    pub fn new(inner: S) -> Self {
        TimeGuard {
            inner,
            clock: None,
            run: None,
            jumps: 0,
            dropped: 0,
        }
    }

    /// Jumps met so far and the events and triggers dropped with them.
    pub fn jumps(&self) -> (u64, u64) {
        (self.jumps, self.dropped)
    }

    /// Accept `t` or count it as jumped; an error when the jump stays.
    #[inline]
    fn accept(&mut self, t: i64) -> Result<bool> {
        let clock = *self.clock.get_or_insert(t);
        if (t - clock).abs() <= TIME_JUMP_US {
            self.clock = Some(t);
            self.run = None;
            return Ok(true);
        }
        self.dropped += 1;
        let (first, lo, hi) = match self.run {
            Some((f, lo, hi)) if (t - f).abs() <= TIME_JUMP_US => (f, lo.min(t), hi.max(t)),
            _ => {
                self.jumps += 1;
                (t, t, t)
            }
        };
        self.run = Some((first, lo, hi));
        if hi - lo >= JUMP_PERSIST_US {
            return Err(Error::analysis(format!(
                "{}: the clock jumps by {:+.3} s at {clock} µs (from {clock} to {first} µs) and stays there ({} events and triggers since): the recording is discontinuous, a damaged file? Convert the parts on either side separately (ebptv convert --from-us/--to-us)",
                self.inner.info().path.display(),
                (first - clock) as f64 * 1e-6,
                self.dropped
            )));
        }
        Ok(false)
    }
}

impl<S: EventSource> EventSource for TimeGuard<S> {
    fn info(&self) -> &StreamInfo {
        self.inner.info()
    }

    fn next_chunk(&mut self, chunk: &mut Chunk) -> Result<bool> {
        loop {
            if !self.inner.next_chunk(chunk)? {
                return Ok(false);
            }
            // Fast path: the whole chunk within the jump limit of the clock
            // and of itself (the usual case: one comparison per event).
            let ev = &chunk.events;
            let clock = self.clock.or_else(|| ev.t.first().copied());
            let fine = match clock {
                Some(c) if self.run.is_none() => {
                    let mut prev = c;
                    let mut ok = true;
                    for &t in &ev.t {
                        ok &= (t - prev).abs() <= TIME_JUMP_US;
                        prev = t;
                    }
                    ok
                }
                _ => false,
            };
            let last = ev.t.last().copied().or(clock);
            let fine = fine
                && chunk.triggers.iter().all(|tr| match last {
                    Some(c) => (tr.t - c).abs() <= TIME_JUMP_US,
                    None => true,
                });
            if fine {
                if let Some(&t) = ev.t.last() {
                    self.clock = Some(t);
                }
            } else {
                let mut keep = Vec::with_capacity(ev.len());
                let ts = ev.t.clone();
                let mut err = None;
                for t in ts {
                    match self.accept(t) {
                        Ok(k) => keep.push(k),
                        Err(e) => {
                            err = Some(e);
                            break;
                        }
                    }
                }
                if let Some(e) = err {
                    return Err(e);
                }
                let mut i = 0;
                chunk.events.retain(|_, _, _, _| {
                    i += 1;
                    keep[i - 1]
                });
                let clock = self.clock;
                let mut dropped = 0;
                chunk.triggers.retain(|tr| {
                    // Triggers are checked against the events' clock, not
                    // each other: a train's period is far below the limit.
                    let ok = match clock {
                        Some(c) => (tr.t - c).abs() <= TIME_JUMP_US,
                        None => true,
                    };
                    dropped += (!ok) as u64;
                    ok
                });
                self.dropped += dropped;
            }
            if !chunk.events.is_empty() || !chunk.triggers.is_empty() {
                return Ok(true);
            }
        }
    }

    fn anomalies(&self) -> Anomalies {
        let mut a = self.inner.anomalies();
        a.time_jumps += self.jumps;
        a.time_jump_events += self.dropped;
        a
    }

    fn bytes_read(&self) -> u64 {
        self.inner.bytes_read()
    }

    fn warnings(&self) -> Vec<String> {
        self.inner.warnings()
    }

    fn rejected_geometry(&self) -> Option<Geometry> {
        self.inner.rejected_geometry()
    }
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;
    use crate::events::EventChunk;

    /// A source serving prepared chunks.
    struct Vecs(StreamInfo, Vec<Chunk>);
    impl EventSource for Vecs {
        fn info(&self) -> &StreamInfo {
            &self.0
        }
        fn next_chunk(&mut self, chunk: &mut Chunk) -> Result<bool> {
            if self.1.is_empty() {
                chunk.clear();
                return Ok(false);
            }
            *chunk = self.1.remove(0);
            Ok(true)
        }
    }

    fn info() -> StreamInfo {
        StreamInfo {
            path: "x.raw".into(),
            format: Format::Evt3,
            geometry: None,
            header: vec![],
            payload_offset: 0,
            file_size: None,
        }
    }

    fn chunk(ts: &[i64]) -> Chunk {
        let mut c = Chunk::default();
        for &t in ts {
            c.events.push(t, 1, 1, 1);
        }
        c
    }

    #[ebptv_macros::unit_test]
    fn observed_reports_each_chunk_and_a_hook_error_ends_the_read() {
        let chunks = vec![chunk(&[1, 2, 3]), chunk(&[4]), chunk(&[5, 6])];
        let mut seen = Vec::new();
        let mut src = crate::Observed::new(Vecs(info(), chunks.clone()), |r| {
            seen.push((r.events, r.done));
            Ok(())
        });
        let mut c = Chunk::default();
        while src.next_chunk(&mut c).unwrap() {}
        drop(src);
        assert_eq!(seen, [(3, false), (4, false), (6, false), (6, true)]);
        // An error from the hook is the read's error, after that chunk.
        let mut n = 0;
        let mut src = crate::Observed::new(Vecs(info(), chunks), |_| {
            n += 1;
            if n == 2 {
                Err(crate::error::Error::analysis("stop"))
            } else {
                Ok(())
            }
        });
        assert!(src.next_chunk(&mut c).unwrap());
        assert!(src
            .next_chunk(&mut c)
            .unwrap_err()
            .to_string()
            .contains("stop"));
    }

    fn drain(g: &mut dyn EventSource) -> Result<Vec<i64>> {
        let mut out = Vec::new();
        let mut c = Chunk::default();
        while g.next_chunk(&mut c)? {
            out.extend_from_slice(&c.events.t);
        }
        Ok(out)
    }

    #[ebptv_macros::unit_test]
    fn a_glitch_is_dropped_and_counted() {
        let h = 16_000_000_000i64;
        let src = Vecs(
            info(),
            vec![
                chunk(&[10, 20, 30]),
                chunk(&[40, h, h + 3, 50]),
                chunk(&[60, 70]),
                chunk(&[h - 5, 80]),
            ],
        );
        let mut g = TimeGuard::new(src);
        assert_eq!(drain(&mut g).unwrap(), vec![10, 20, 30, 40, 50, 60, 70, 80]);
        assert_eq!(g.jumps(), (2, 3));
        assert_eq!(g.anomalies().time_jumps, 2);
    }

    #[ebptv_macros::unit_test]
    fn a_lasting_jump_is_an_error() {
        let mut ts: Vec<i64> = (0..1000).collect();
        ts.extend((0..1000).map(|k| 3_600_000_000 + k * 200));
        let mut g = TimeGuard::new(Vecs(info(), vec![chunk(&ts)]));
        let e = drain(&mut g).unwrap_err().to_string();
        assert!(
            e.contains("x.raw") && e.contains("jumps by +3599.999") && e.contains("stays"),
            "{e}"
        );
    }

    #[ebptv_macros::unit_test]
    fn a_continuous_clock_passes_untouched() {
        let ts: Vec<i64> = (0..10_000).map(|k| k * 4_000).collect();
        let mut g = TimeGuard::new(Vecs(info(), vec![chunk(&ts[..5000]), chunk(&ts[5000..])]));
        assert_eq!(drain(&mut g).unwrap(), ts);
        assert_eq!(g.jumps(), (0, 0));
        let _ = EventChunk::default();
    }

    #[ebptv_macros::unit_test]
    fn impossible_geometry_is_dropped_with_a_warning() {
        for (g, ok) in [
            (Geometry::new(1280, 720), true),
            (Geometry::new(0, 720), false),
            (Geometry::new(65535, 65535), false),
            (Geometry::new(4096, 4096), true),
            (Geometry::new(4097, 10), false),
        ] {
            let mut i = info();
            i.geometry = Some(g);
            let c = Checked::new(Box::new(Vecs(i, vec![])));
            assert_eq!(c.info().geometry.is_some(), ok, "{g:?}");
            assert_eq!(c.warnings().is_empty(), ok);
            assert_eq!(c.rejected_geometry(), (!ok).then_some(g));
        }
    }

    #[ebptv_macros::unit_test]
    fn contradicting_format_lines_are_refused() {
        let mut i = info();
        i.header = vec![
            ("format".into(), "EVT2;height=720;width=1280".into()),
            ("evt".into(), "3.0".into()),
        ];
        i.format = Format::Evt2;
        let e = check_header(&i).unwrap_err().to_string();
        assert!(e.contains("contradicts") && e.contains("x.raw"), "{e}");
        i.header[1].1 = "2.0".into();
        assert!(check_header(&i).is_ok());
        i.header[0].1 = "EVT3".into();
        i.header[1].1 = "3.0".into();
        assert!(check_header(&i).is_ok());
    }
}
