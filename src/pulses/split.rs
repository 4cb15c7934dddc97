//! Splitting a recording's events into pulses with known timing
//! ([`split_pulses`], the streaming [`Splitter`]).

use super::*;

/// Stream `source` and hand the events of each pulse, in pulse order, to
/// `on_pulse`: every pulse from 0 to the last one holding events, empty
/// ones included. Returns the number of events that could not be
/// attributed (before pulse 0, or arriving more than `REORDER_MARGIN_US`
/// after their pulse was handed over).
pub fn split_pulses(
    source: &mut dyn crate::io::EventSource,
    timing: &PulseTiming,
    on_pulse: &mut dyn FnMut(PulseEvents) -> Result<()>,
) -> Result<u64> {
    if !(timing.period_us.is_finite() && timing.period_us > 0.0) {
        return Err(Error::param(
            "period_us",
            format!("{} µs: must be positive", timing.period_us),
        ));
    }
    let mut sp = Splitter::new(*timing);
    let mut chunk = Chunk::default();
    while source.next_chunk(&mut chunk)? {
        sp.push(&chunk.events, on_pulse)?;
    }
    sp.finish(on_pulse)
}

/// Incremental form of [`split_pulses`].
#[ebptv_macros::testkit]
pub(crate) struct Splitter {
    pub(super) timing: PulseTiming,
    pub(super) pending: VecDeque<EventChunk>,
    /// Pulse index of `pending[0]`.
    pub(super) base: i64,
    /// Once an event at or after this time is seen, pulse `base` is complete.
    pub(super) emit_after: i64,
    pub(super) unattributed: u64,
    /// Events of the last pulse handed over: the capacity new pulses start
    /// with (growing each of the four vectors from empty cost ~13
    /// reallocations and copies per pulse).
    pub(super) typical_len: usize,
}

impl Splitter {
    /// A splitter for the pulse train `timing`.
    #[ebptv_macros::testkit]
    pub(crate) fn new(timing: PulseTiming) -> Self {
        let mut s = Splitter {
            timing,
            pending: VecDeque::new(),
            base: 0,
            emit_after: 0,
            unattributed: 0,
            typical_len: 0,
        };
        s.emit_after = s.complete_time(0);
        s
    }

    pub(super) fn complete_time(&self, k: i64) -> i64 {
        let end = self.timing.pulse_start(k) + self.timing.window_offset_us + self.timing.period_us;
        end.ceil() as i64 + REORDER_MARGIN_US
    }

    pub(super) fn emit_front(
        &mut self,
        on_pulse: &mut dyn FnMut(PulseEvents) -> Result<()>,
    ) -> Result<()> {
        let events = self.pending.pop_front().unwrap_or_default();
        self.typical_len = events.len();
        on_pulse(PulseEvents {
            index: self.base,
            start_us: self.timing.pulse_start(self.base),
            events,
        })?;
        self.base += 1;
        self.emit_after = self.complete_time(self.base);
        Ok(())
    }

    /// Assign the events of `ev` to pulses and hand each
    /// completed pulse to `on_pulse`. Fails when an event lies implausibly many
    /// pulses ahead (a clock jump) or when `on_pulse` fails.
    #[ebptv_macros::testkit]
    pub(crate) fn push(
        &mut self,
        ev: &EventChunk,
        on_pulse: &mut dyn FnMut(PulseEvents) -> Result<()>,
    ) -> Result<()> {
        let p = self.timing.period_us;
        let origin = self.timing.first_pulse_us + self.timing.window_offset_us;
        // The pulse of the last time looked up (`None`: before the first
        // pulse): tens of events share each µs timestamp, so most events
        // skip the division.
        let mut last: (i64, Option<i64>) = (i64::MIN, None);
        let mut pulse_of = |t: i64| {
            if t != last.0 || t == i64::MIN {
                let rel = (t as f64 - origin) / p;
                last = (t, (!(rel < 0.0)).then_some(rel as i64));
            }
            last.1
        };
        let n = ev.len();
        let mut i = 0;
        while i < n {
            let t = ev.t[i];
            if t >= self.emit_after {
                let gap = (t as f64 - origin) / p - self.base as f64;
                if gap > (MAX_EMPTY_PULSES + self.pending.len() as i64) as f64 {
                    return Err(Error::analysis(format!(
                        "event time {t} µs lies {gap:.0} pulses after pulse {}: the clock jumped (a damaged recording?)",
                        self.base
                    )));
                }
            }
            while t >= self.emit_after {
                self.emit_front(on_pulse)?;
            }
            let Some(k) = pulse_of(t).filter(|&k| k >= self.base) else {
                self.unattributed += 1;
                i += 1;
                continue;
            };
            // The run of following events of the same pulse that hand no
            // pulse over first: copied in one go (exactly what one event
            // at a time would do, as nothing changes within the run).
            let mut j = i + 1;
            while j < n && ev.t[j] < self.emit_after && pulse_of(ev.t[j]) == Some(k) {
                j += 1;
            }
            let idx = (k - self.base) as usize;
            while self.pending.len() <= idx {
                self.pending.push_back(EventChunk::default());
            }
            let chunk = &mut self.pending[idx];
            if chunk.t.capacity() == 0 {
                // Only pulses that get events are given room (a time jump
                // leaves many empty ones pending).
                *chunk = EventChunk::with_capacity(self.typical_len + self.typical_len / 8);
            }
            chunk.t.extend_from_slice(&ev.t[i..j]);
            chunk.x.extend_from_slice(&ev.x[i..j]);
            chunk.y.extend_from_slice(&ev.y[i..j]);
            chunk.p.extend_from_slice(&ev.p[i..j]);
            i = j;
        }
        Ok(())
    }

    /// Hand over the pulses still pending; returns the unattributed count.
    #[ebptv_macros::testkit]
    pub(crate) fn finish(
        mut self,
        on_pulse: &mut dyn FnMut(PulseEvents) -> Result<()>,
    ) -> Result<u64> {
        while !self.pending.is_empty() {
            self.emit_front(on_pulse)?;
        }
        Ok(self.unattributed)
    }
}
