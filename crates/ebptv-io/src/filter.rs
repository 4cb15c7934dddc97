//! Selection of a time range, a region of interest and a polarity, as a
//! wrapper around any [`EventSource`].

use crate::error::{Error, Result};
use crate::events::{Chunk, OFF, ON};
use crate::{Anomalies, EventSource, StreamInfo};

/// Which polarities to keep.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum PolaritySelect {
    /// ON events only.
    On,
    /// OFF events only.
    Off,
    /// Both polarities.
    #[default]
    Both,
}

impl std::str::FromStr for PolaritySelect {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self> {
        match s {
            "on" | "ON" | "pos" | "positive" => Ok(PolaritySelect::On),
            "off" | "OFF" | "neg" | "negative" => Ok(PolaritySelect::Off),
            "both" | "all" => Ok(PolaritySelect::Both),
            _ => Err(Error::param(
                "polarity",
                format!("`{s}`: expected on, off or both"),
            )),
        }
    }
}

/// Rectangular region of interest, pixel coordinates, half-open.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Roi {
    /// Left column, pixels.
    pub x0: u16,
    /// Top row, pixels.
    pub y0: u16,
    /// Width, pixels.
    pub width: u16,
    /// Height, pixels.
    pub height: u16,
}

impl Roi {
    /// True when pixel (`x`, `y`) lies inside the region.
    #[inline]
    pub(crate) fn contains(&self, x: u16, y: u16) -> bool {
        x >= self.x0 && y >= self.y0 && (x - self.x0) < self.width && (y - self.y0) < self.height
    }
}

impl std::str::FromStr for Roi {
    type Err = Error;
    /// `x0,y0,w,h`
    fn from_str(s: &str) -> Result<Self> {
        let parts: Vec<&str> = s.split(',').map(|p| p.trim()).collect();
        let bad = || {
            Error::param(
                "roi",
                format!("`{s}`: expected x0,y0,width,height (pixels)"),
            )
        };
        if parts.len() != 4 {
            return Err(bad());
        }
        let v: Vec<u16> = parts
            .iter()
            .map(|p| p.parse::<u16>().map_err(|_| bad()))
            .collect::<Result<_>>()?;
        if v[2] == 0 || v[3] == 0 {
            return Err(Error::param(
                "roi",
                format!("`{s}`: width and height must be positive"),
            ));
        }
        Ok(Roi {
            x0: v[0],
            y0: v[1],
            width: v[2],
            height: v[3],
        })
    }
}

/// The selection applied by [`Filtered`].
#[derive(Debug, Clone, Default)]
pub struct Selection {
    /// Keep events with `t >= from_us`.
    pub from_us: Option<i64>,
    /// Keep events with `t < to_us`.
    pub to_us: Option<i64>,
    /// Keep only events inside this region.
    pub roi: Option<Roi>,
    /// Keep only events of this polarity.
    pub polarity: PolaritySelect,
}

impl Selection {
    /// Checks that the time window and region are well formed.
    pub(crate) fn validate(&self) -> Result<()> {
        if let (Some(a), Some(b)) = (self.from_us, self.to_us) {
            if b <= a {
                return Err(Error::param(
                    "to-us",
                    format!("end {b} µs is not after start {a} µs"),
                ));
            }
        }
        Ok(())
    }
}

/// A source restricted to a [`Selection`]. Triggers are kept when inside the
/// time range (an ROI or polarity does not apply to them).
pub struct Filtered<S: EventSource> {
    inner: S,
    sel: Selection,
}

impl<S: EventSource> Filtered<S> {
    /// Wraps `inner` so that it yields only the events `sel` selects; errors when `sel` is invalid.
    pub fn new(inner: S, sel: Selection) -> Result<Self> {
        sel.validate()?;
        Ok(Filtered { inner, sel })
    }
}

impl<S: EventSource> EventSource for Filtered<S> {
    fn info(&self) -> &StreamInfo {
        self.inner.info()
    }

    fn next_chunk(&mut self, chunk: &mut Chunk) -> Result<bool> {
        loop {
            if !self.inner.next_chunk(chunk)? {
                return Ok(false);
            }
            let from = self.sel.from_us.unwrap_or(i64::MIN);
            let to = self.sel.to_us.unwrap_or(i64::MAX);
            let roi = self.sel.roi;
            let pol = self.sel.polarity;
            chunk.events.retain(|t, x, y, p| {
                t >= from
                    && t < to
                    && roi.is_none_or(|r| r.contains(x, y))
                    && match pol {
                        PolaritySelect::Both => true,
                        PolaritySelect::On => p == ON,
                        PolaritySelect::Off => p == OFF,
                    }
            });
            chunk.triggers.retain(|tr| tr.t >= from && tr.t < to);
            if !chunk.is_empty() {
                return Ok(true);
            }
        }
    }

    fn anomalies(&self) -> Anomalies {
        self.inner.anomalies()
    }
    fn bytes_read(&self) -> u64 {
        self.inner.bytes_read()
    }
}
