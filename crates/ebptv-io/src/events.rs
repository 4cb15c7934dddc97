//! The event model shared by every stage.
//!
//! Events travel as struct-of-arrays chunks ([`EventChunk`]): one vector per
//! field, so that the hot loops (pulse folding, clustering, pseudo-images)
//! touch only the fields they need and the decoders can append without
//! per-event allocation. Triggers (external-trigger events, one per laser
//! pulse edge) travel beside the events in the same [`Chunk`], never mixed
//! into them.
//!
//! Time is the raw sensor time in microseconds (`i64`): readers never clamp,
//! sort or shift it (EVT3's TIME_LOW may step backwards; that is data).
//! Pixel coordinates: x = column (rightwards), y = row (downwards).

use serde::{Deserialize, Serialize};

/// Sensor geometry in pixels.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Geometry {
    /// Sensor width, pixels.
    pub width: u16,
    /// Sensor height, pixels.
    pub height: u16,
}

impl Geometry {
    /// A sensor of `width` × `height` pixels.
    pub fn new(width: u16, height: u16) -> Self {
        Geometry { width, height }
    }
    /// Number of pixels.
    pub fn pixels(&self) -> usize {
        self.width as usize * self.height as usize
    }
    /// True when pixel (`x`, `y`) lies on the sensor.
    pub fn contains(&self, x: u16, y: u16) -> bool {
        x < self.width && y < self.height
    }
}

/// Polarity of a contrast-detection event: 1 = ON (brighter), 0 = OFF.
pub const ON: u8 = 1;
/// Polarity of an OFF (darker) event.
pub const OFF: u8 = 0;

/// A block of contrast-detection events, struct-of-arrays.
///
/// All four vectors always have the same length. Reuse one chunk across
/// [`crate::EventSource::next_chunk`] calls: `clear` keeps the capacity.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct EventChunk {
    /// Raw sensor time, µs.
    pub t: Vec<i64>,
    /// Columns, pixels.
    pub x: Vec<u16>,
    /// Rows, pixels.
    pub y: Vec<u16>,
    /// 1 = ON, 0 = OFF.
    pub p: Vec<u8>,
}

impl EventChunk {
    /// An empty chunk with room for `n` events.
    pub fn with_capacity(n: usize) -> Self {
        EventChunk {
            t: Vec::with_capacity(n),
            x: Vec::with_capacity(n),
            y: Vec::with_capacity(n),
            p: Vec::with_capacity(n),
        }
    }
    /// Appends one event.
    #[inline]
    pub fn push(&mut self, t: i64, x: u16, y: u16, p: u8) {
        self.t.push(t);
        self.x.push(x);
        self.y.push(y);
        self.p.push(p);
    }
    /// Number of events.
    #[inline]
    pub fn len(&self) -> usize {
        self.t.len()
    }
    /// True when the chunk holds no events.
    #[inline]
    pub fn is_empty(&self) -> bool {
        self.t.is_empty()
    }
    /// Empties the chunk, keeping its allocations.
    pub fn clear(&mut self) {
        self.t.clear();
        self.x.clear();
        self.y.clear();
        self.p.clear();
    }
    /// Append all events of `other`.
    pub fn extend_from(&mut self, other: &EventChunk) {
        self.t.extend_from_slice(&other.t);
        self.x.extend_from_slice(&other.x);
        self.y.extend_from_slice(&other.y);
        self.p.extend_from_slice(&other.p);
    }
    /// Keep only the events for which `keep(t, x, y, p)` is true, in order,
    /// compacting in place.
    pub fn retain(&mut self, mut keep: impl FnMut(i64, u16, u16, u8) -> bool) {
        let mut w = 0;
        for r in 0..self.len() {
            if keep(self.t[r], self.x[r], self.y[r], self.p[r]) {
                self.t[w] = self.t[r];
                self.x[w] = self.x[r];
                self.y[w] = self.y[r];
                self.p[w] = self.p[r];
                w += 1;
            }
        }
        self.t.truncate(w);
        self.x.truncate(w);
        self.y.truncate(w);
        self.p.truncate(w);
    }
    /// Iterate as `Event` values (convenient, not the fast path).
    pub fn iter(&self) -> impl Iterator<Item = Event> + '_ {
        (0..self.len()).map(move |i| Event {
            t: self.t[i],
            x: self.x[i],
            y: self.y[i],
            p: self.p[i],
        })
    }
}

/// One event, array-of-structs form (tests, writers, small tools).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct Event {
    /// Time, µs.
    pub t: i64,
    /// Column, pixels.
    pub x: u16,
    /// Row, pixels.
    pub y: u16,
    /// Polarity: [`ON`] or [`OFF`].
    pub p: u8,
}

/// Edge of an external-trigger signal.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Edge {
    /// Low-to-high transition.
    Rising,
    /// High-to-low transition.
    Falling,
}

/// An external-trigger event (a laser pulse edge when the laser's TTL is
/// wired to the camera's trigger input).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct Trigger {
    /// Raw sensor time, µs.
    pub t: i64,
    /// Trigger channel id (EVK2: main input 1; EVK4: 0).
    pub channel: u8,
    /// Which transition the trigger input saw.
    pub edge: Edge,
}

/// What one call to `next_chunk` delivers: events and the triggers decoded
/// from the same stretch of the file, each in file order.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Chunk {
    /// The contrast events, in stream order.
    pub events: EventChunk,
    /// The external trigger events, in stream order.
    pub triggers: Vec<Trigger>,
}

impl Chunk {
    /// Empties the chunk, keeping its allocations.
    pub fn clear(&mut self) {
        self.events.clear();
        self.triggers.clear();
    }
    /// True when the chunk holds neither events nor triggers.
    pub fn is_empty(&self) -> bool {
        self.events.is_empty() && self.triggers.is_empty()
    }
}
