//! One streaming pass over a source: the numbers `ebptv info` prints.
//!
//! Everything is accumulated per chunk in O(1) memory (plus one counter per
//! trigger channel), so a 10 GB recording is summarised at decoding speed.
//! The peak event rate is the largest count in 1 ms bins (configurable):
//! bins are kept in a small ring indexed by `bin mod RING`, so events that
//! step back in time (EVT3 TIME_LOW, merged sources) still land in their
//! own bin as long as they are less than `RING` bins late; later stragglers
//! are counted in `late_for_peak` instead of corrupting the estimate.

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::time::Instant;

use serde::Serialize;

use crate::error::Result;
use crate::events::{Chunk, Edge, Geometry};
use crate::{Anomalies, EventSource, Format, StreamInfo};

const RING: usize = 256;

/// Trigger counts of one channel.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct TriggerCounts {
    /// Trigger channel id.
    pub channel: u8,
    /// Rising edges seen.
    pub rising: u64,
    /// Falling edges seen.
    pub falling: u64,
    /// Time of the first trigger, µs.
    pub first_t: i64,
    /// Time of the last trigger, µs.
    pub last_t: i64,
}

/// What `ebptv info` reports about a stream.
#[derive(Debug, Clone, Serialize)]
pub struct Summary {
    /// The file summarised.
    pub path: PathBuf,
    /// Its encoding.
    pub format: Format,
    /// The encoding's name as shown to users.
    pub format_name: String,
    /// Geometry stated (or inferred by the reader from the header).
    pub geometry: Option<Geometry>,
    /// How the geometry is known: `stated` (a header field says it),
    /// `inferred` (a RAW reader derived it, e.g. from `% system_ID`), or
    /// `unknown` (then see `geometry_from_events`).
    pub geometry_source: String,
    /// Smallest geometry holding every event seen: max x + 1, max y + 1.
    pub geometry_from_events: Option<Geometry>,
    /// The file header's key/value entries.
    pub header: Vec<(String, String)>,
    /// File size, bytes.
    pub file_bytes: Option<u64>,
    /// Number of contrast events.
    pub events: u64,
    /// Number of ON events.
    pub on_events: u64,
    /// Number of OFF events.
    pub off_events: u64,
    /// ON / (ON + OFF); `None` without events.
    pub on_fraction: Option<f64>,
    /// Trigger edge counts per channel.
    pub triggers: Vec<TriggerCounts>,
    /// Time of the first and last event in file order, µs.
    pub first_t_us: Option<i64>,
    /// Time of the last event in file order, µs.
    pub last_t_us: Option<i64>,
    /// Smallest and largest event time, µs.
    pub min_t_us: Option<i64>,
    /// Largest event time, µs.
    pub max_t_us: Option<i64>,
    /// max - min, µs.
    pub duration_us: Option<i64>,
    /// Events whose time is smaller than the previous event's.
    pub time_steps_back: u64,
    /// Events per second over the duration.
    pub mean_rate_ev_per_s: Option<f64>,
    /// Events per second in the busiest bin.
    pub peak_rate_ev_per_s: Option<f64>,
    /// Width of the bins of the peak-rate estimate, µs.
    pub peak_bin_us: i64,
    /// Start time of the bin with the peak count, µs.
    pub peak_bin_start_us: Option<i64>,
    /// Events too late (in time) to be binned for the peak estimate.
    pub late_for_peak: u64,
    /// Malformed or unexpected content met while decoding.
    pub anomalies: Anomalies,
    /// Wall-clock time the decoding took, s.
    pub decode_seconds: f64,
    /// Events decoded per second of wall time, in millions.
    pub decode_rate_mev_per_s: f64,
}

/// Incremental accumulator; feed chunks, then [`SummaryBuilder::finish`].
#[derive(Debug, Clone)]
pub(crate) struct SummaryBuilder {
    bin_us: i64,
    events: u64,
    on: u64,
    max_x: u16,
    max_y: u16,
    first_t: Option<i64>,
    last_t: i64,
    min_t: i64,
    max_t: i64,
    steps_back: u64,
    triggers: BTreeMap<u8, TriggerCounts>,
    ring_bin: Vec<i64>,
    ring_count: Vec<u64>,
    newest_bin: i64,
    peak: u64,
    peak_bin: i64,
    late: u64,
}

impl SummaryBuilder {
    /// `bin_us`: the bin width of the peak-rate estimate (1000 = 1 ms).
    pub(crate) fn new(bin_us: i64) -> Self {
        SummaryBuilder {
            bin_us: bin_us.max(1),
            events: 0,
            on: 0,
            max_x: 0,
            max_y: 0,
            first_t: None,
            last_t: 0,
            min_t: i64::MAX,
            max_t: i64::MIN,
            steps_back: 0,
            triggers: BTreeMap::new(),
            ring_bin: vec![i64::MIN; RING],
            ring_count: vec![0; RING],
            newest_bin: i64::MIN,
            peak: 0,
            peak_bin: 0,
            late: 0,
        }
    }

    #[inline]
    fn close_slot(&mut self, slot: usize) {
        if self.ring_bin[slot] != i64::MIN && self.ring_count[slot] > self.peak {
            self.peak = self.ring_count[slot];
            self.peak_bin = self.ring_bin[slot];
        }
    }

    /// Folds one chunk into the summary.
    pub(crate) fn add(&mut self, chunk: &Chunk) {
        let ev = &chunk.events;
        for i in 0..ev.len() {
            let t = ev.t[i];
            if self.first_t.is_none() {
                self.first_t = Some(t);
                self.last_t = t;
            }
            if t < self.last_t {
                self.steps_back += 1;
            }
            self.last_t = t;
            self.min_t = self.min_t.min(t);
            self.max_t = self.max_t.max(t);
            self.max_x = self.max_x.max(ev.x[i]);
            self.max_y = self.max_y.max(ev.y[i]);
            self.on += (ev.p[i] != 0) as u64;
            let bin = t.div_euclid(self.bin_us);
            if bin > self.newest_bin {
                self.newest_bin = bin;
            }
            if bin <= self.newest_bin - RING as i64 {
                self.late += 1;
                continue;
            }
            let slot = bin.rem_euclid(RING as i64) as usize;
            if self.ring_bin[slot] != bin {
                self.close_slot(slot);
                self.ring_bin[slot] = bin;
                self.ring_count[slot] = 0;
            }
            self.ring_count[slot] += 1;
        }
        self.events += ev.len() as u64;
        for tr in &chunk.triggers {
            let c = self.triggers.entry(tr.channel).or_insert(TriggerCounts {
                channel: tr.channel,
                first_t: tr.t,
                ..Default::default()
            });
            match tr.edge {
                Edge::Rising => c.rising += 1,
                Edge::Falling => c.falling += 1,
            }
            c.last_t = tr.t;
        }
    }

    /// Peak count per bin so far (closing the open bins).
    fn peak(&mut self) -> (u64, i64) {
        for s in 0..RING {
            self.close_slot(s);
        }
        (self.peak, self.peak_bin)
    }

    /// Close the summary of the stream described by `info`.
    pub(crate) fn finish(
        mut self,
        info: StreamInfo,
        anomalies: Anomalies,
        decode_seconds: f64,
    ) -> Summary {
        let geometry_source = geometry_source(&info).to_string();
        let StreamInfo {
            path,
            format,
            geometry,
            header,
            file_size: file_bytes,
            ..
        } = info;
        let (peak, peak_bin) = self.peak();
        let has = self.events > 0;
        let duration = has.then(|| self.max_t - self.min_t);
        let mean_rate = duration
            .filter(|d| *d > 0)
            .map(|d| self.events as f64 / (d as f64 * 1e-6));
        Summary {
            path,
            format,
            format_name: format.name().to_string(),
            geometry,
            geometry_source,
            geometry_from_events: has
                .then(|| Geometry::new(self.max_x.saturating_add(1), self.max_y.saturating_add(1))),
            header,
            file_bytes,
            events: self.events,
            on_events: self.on,
            off_events: self.events - self.on,
            on_fraction: has.then(|| self.on as f64 / self.events as f64),
            triggers: self.triggers.into_values().collect(),
            first_t_us: self.first_t,
            last_t_us: has.then_some(self.last_t),
            min_t_us: has.then_some(self.min_t),
            max_t_us: has.then_some(self.max_t),
            duration_us: duration,
            time_steps_back: self.steps_back,
            mean_rate_ev_per_s: mean_rate,
            peak_rate_ev_per_s: has.then(|| peak as f64 / (self.bin_us as f64 * 1e-6)),
            peak_bin_us: self.bin_us,
            peak_bin_start_us: has.then(|| peak_bin * self.bin_us),
            late_for_peak: self.late,
            anomalies,
            decode_seconds,
            decode_rate_mev_per_s: if decode_seconds > 0.0 {
                self.events as f64 / decode_seconds / 1e6
            } else {
                0.0
            },
        }
    }
}

/// Whether the geometry was stated by the file or inferred by its reader.
/// The RAW readers infer it from `% system_ID` / `% evt` when neither a
/// `% geometry` line nor a `width=` in `% format` states it; every other
/// reader only reports a geometry the file states.
pub(crate) fn geometry_source(info: &StreamInfo) -> &'static str {
    if info.geometry.is_none() {
        return "unknown";
    }
    let raw = matches!(info.format, Format::Evt2 | Format::Evt21 | Format::Evt3);
    let stated = info.header.iter().any(|(k, v)| {
        k.eq_ignore_ascii_case("geometry")
            || (k.eq_ignore_ascii_case("format") && v.to_ascii_lowercase().contains("width"))
    });
    if raw && !stated {
        "inferred"
    } else {
        "stated"
    }
}

/// Bin width (µs) of the peak event rate that `ebptv info` reports.
pub const DEFAULT_PEAK_BIN_US: i64 = 1000;

/// Summarise a whole source in one pass; `progress(bytes_read)` is called
/// after every chunk.
pub fn summarize(
    src: &mut dyn EventSource,
    bin_us: i64,
    mut progress: impl FnMut(u64),
) -> Result<Summary> {
    let start = Instant::now();
    let mut b = SummaryBuilder::new(bin_us);
    let mut chunk = Chunk::default();
    while src.next_chunk(&mut chunk)? {
        b.add(&chunk);
        progress(src.bytes_read());
    }
    let secs = start.elapsed().as_secs_f64();
    let info = src.info().clone();
    Ok(b.finish(info, src.anomalies(), secs))
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;
    use crate::events::Trigger;
    use std::collections::HashMap;

    fn dummy_info() -> StreamInfo {
        StreamInfo {
            path: PathBuf::from("x"),
            format: Format::Csv,
            geometry: None,
            header: vec![],
            payload_offset: 0,
            file_size: None,
        }
    }

    /// Brute force: count every bin in a map.
    fn reference_peak(ts: &[i64], bin: i64) -> u64 {
        let mut m: HashMap<i64, u64> = HashMap::new();
        for t in ts {
            *m.entry(t.div_euclid(bin)).or_default() += 1;
        }
        m.values().copied().max().unwrap_or(0)
    }

    #[ebptv_macros::unit_test]
    fn peak_matches_brute_force_with_steps_back() {
        use rand::{Rng, SeedableRng};
        let mut rng = rand_pcg::Pcg64::seed_from_u64(7);
        let mut ts = Vec::new();
        let mut t = -5_000i64;
        for _ in 0..200_000 {
            t += rng.gen_range(0..40);
            // Occasional steps back of up to 30 ms (within the ring).
            let jitter = if rng.gen_bool(0.05) {
                -rng.gen_range(0..30_000)
            } else {
                0
            };
            ts.push(t + jitter);
        }
        let mut chunk = Chunk::default();
        let mut b = SummaryBuilder::new(1000);
        for part in ts.chunks(4096) {
            chunk.clear();
            for &t in part {
                chunk.events.push(t, 1, 2, 1);
            }
            b.add(&chunk);
        }
        let s = b.finish(dummy_info(), Anomalies::default(), 1.0);
        assert_eq!(s.late_for_peak, 0);
        assert_eq!(
            s.peak_rate_ev_per_s.unwrap(),
            reference_peak(&ts, 1000) as f64 * 1000.0
        );
        assert_eq!(s.events, ts.len() as u64);
        assert_eq!(s.min_t_us, ts.iter().min().copied());
        assert_eq!(s.max_t_us, ts.iter().max().copied());
        let back = ts.windows(2).filter(|w| w[1] < w[0]).count() as u64;
        assert_eq!(s.time_steps_back, back);
    }

    #[ebptv_macros::unit_test]
    fn counts_triggers_and_polarity() {
        let mut chunk = Chunk::default();
        chunk.events.push(0, 3, 4, 1);
        chunk.events.push(1_000_000, 9, 2, 0);
        chunk.events.push(500_000, 1, 1, 1);
        chunk.triggers.push(Trigger {
            t: 5,
            channel: 1,
            edge: Edge::Rising,
        });
        chunk.triggers.push(Trigger {
            t: 9,
            channel: 1,
            edge: Edge::Falling,
        });
        chunk.triggers.push(Trigger {
            t: 15,
            channel: 0,
            edge: Edge::Rising,
        });
        let mut b = SummaryBuilder::new(1000);
        b.add(&chunk);
        let s = b.finish(dummy_info(), Anomalies::default(), 0.5);
        assert_eq!((s.events, s.on_events, s.off_events), (3, 2, 1));
        assert_eq!(s.duration_us, Some(1_000_000));
        assert_eq!(s.mean_rate_ev_per_s, Some(3.0));
        assert_eq!(s.geometry_from_events, Some(Geometry::new(10, 5)));
        assert_eq!(s.triggers.len(), 2);
        assert_eq!(
            (
                s.triggers[1].channel,
                s.triggers[1].rising,
                s.triggers[1].falling
            ),
            (1, 1, 1)
        );
        assert_eq!(s.time_steps_back, 1);
        assert_eq!(s.peak_rate_ev_per_s, Some(1000.0));
    }

    #[ebptv_macros::unit_test]
    fn geometry_source_rules() {
        let mut i = dummy_info();
        assert_eq!(geometry_source(&i), "unknown");
        i.geometry = Some(Geometry::new(640, 480));
        assert_eq!(geometry_source(&i), "stated");
        i.format = Format::Evt3;
        i.header = vec![
            ("evt".into(), "3.0".into()),
            ("system_ID".into(), "48".into()),
        ];
        assert_eq!(geometry_source(&i), "inferred");
        i.header
            .push(("format".into(), "EVT3;height=720;width=1280".into()));
        assert_eq!(geometry_source(&i), "stated");
    }

    #[ebptv_macros::unit_test]
    fn empty_stream() {
        let b = SummaryBuilder::new(1000);
        let s = b.finish(dummy_info(), Anomalies::default(), 0.0);
        assert_eq!(s.events, 0);
        assert!(
            s.duration_us.is_none() && s.peak_rate_ev_per_s.is_none() && s.on_fraction.is_none()
        );
    }
}
