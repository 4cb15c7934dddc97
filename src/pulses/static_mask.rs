//! An automatic mask of the sensor regions that are not flow: pixels that
//! fire out of step with the particles. Particles cross a pixel now and
//! then; a wall, a model edge or a reflection lit by every pulse fires at
//! nearly every pulse, and a hot pixel fires between the pulses too.

use super::{split_pulses, PulseReport};
use crate::calib::PixelMask;
use crate::error::Result;
use crate::io::EventSource;

/// Options of [`static_mask`].
#[derive(Debug, Clone, Copy)]
pub(crate) struct StaticMaskOptions {
    /// A pixel with events in more than this fraction of the pulses is
    /// static (a particle image stays on a pixel for a few pulses only).
    pub max_pulse_fraction: f64,
    /// Also mask the hot pixels of the report (event rate above its
    /// `hot_threshold_hz`, events between the pulses included).
    pub hot_pixels: bool,
}

impl Default for StaticMaskOptions {
    fn default() -> Self {
        StaticMaskOptions {
            max_pulse_fraction: 0.5,
            hot_pixels: true,
        }
    }
}

/// The static pixels of a recording (`source`, read from its start) whose
/// pulses `report` found ([`super::analyze`]): pixels with events in more
/// than `max_pulse_fraction` of the pulses, and the hot pixels.
pub(crate) fn static_mask(
    source: &mut dyn EventSource,
    report: &PulseReport,
    opts: &StaticMaskOptions,
) -> Result<PixelMask> {
    let (w, h) = (report.rate_map.width as u32, report.rate_map.height as u32);
    let n = w as usize * h as usize;
    // Pulses with an event per pixel, and the last pulse counted.
    let mut pulses_with = vec![0u32; n];
    let mut last = vec![i64::MIN; n];
    let mut n_pulses = 0u64;
    split_pulses(source, &report.timing, &mut |pe| {
        n_pulses += 1;
        let ev = &pe.events;
        for i in 0..ev.len() {
            let (x, y) = (ev.x[i] as usize, ev.y[i] as usize);
            if x < w as usize && y < h as usize {
                let k = y * w as usize + x;
                if last[k] != pe.index {
                    last[k] = pe.index;
                    pulses_with[k] += 1;
                }
            }
        }
        Ok(())
    })?;
    let mut m = PixelMask::new(w, h);
    let limit = opts.max_pulse_fraction * n_pulses as f64;
    for k in 0..n {
        let hot = opts.hot_pixels
            && report.rate_map.rate.len() == n
            && report.rate_map.rate[k] as f64 > report.rate_map.hot_threshold_hz;
        if (n_pulses > 0 && pulses_with[k] as f64 > limit) || hot {
            m.set((k % w as usize) as u32, (k / w as usize) as u32);
        }
    }
    Ok(m)
}
