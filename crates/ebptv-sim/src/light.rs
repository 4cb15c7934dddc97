//! The pulsed light sheet: pulse envelope with rise/fall and the laser's
//! saw-tooth power modulation.
//!
//! Pulse k starts (rising trigger edge) at `first_pulse_us + k·period`.
//! Power ramps linearly up over `rise_us`, holds, and ramps down over
//! `fall_us`, so that the width between the half-power points is
//! `pulse_width_us`; the falling trigger edge is at start + width. The
//! photoreceptor is slow compared to the pulse (latency tens of µs vs. a
//! pulse of a few µs), so a pixel responds to the pulse's mean power: the
//! envelope enters the signal through `PulseShape::mean_level` and, for
//! moving particles, as the weights of the image positions along the streak.

use super::scenario::Light;

/// Quadrature of one pulse's envelope.
#[derive(Debug, Clone)]
#[ebptv_macros::testkit]
pub(crate) struct PulseShape {
    /// Sample times after the pulse start (µs) and their normalised weights.
    pub nodes: Vec<(f64, f64)>,
    /// Mean power over the nominal width, relative to the plateau.
    pub mean_level: f64,
    /// Power-weighted mean time after the pulse start (µs).
    pub centroid_us: f64,
    /// End of the fall (µs after start).
    pub end_us: f64,
}

impl PulseShape {
    /// The shape of the pulses of `l`.
    #[ebptv_macros::testkit]
    pub(crate) fn new(l: &Light) -> PulseShape {
        let end = 0.5 * l.rise_us + l.pulse_width_us + 0.5 * l.fall_us;
        let n = 64;
        let mut nodes = Vec::with_capacity(n);
        let mut total = 0.0;
        let mut tw = 0.0;
        for i in 0..n {
            let t = (i as f64 + 0.5) / n as f64 * end;
            let w = envelope(l, t) * (end / n as f64);
            nodes.push((t, w));
            total += w;
            tw += t * w;
        }
        for nd in &mut nodes {
            nd.1 /= total;
        }
        PulseShape {
            nodes,
            mean_level: total / l.pulse_width_us,
            centroid_us: tw / total,
            end_us: end,
        }
    }
}

/// Relative laser power at `t` µs after the pulse start.
pub(crate) fn envelope(l: &Light, t: f64) -> f64 {
    let end = 0.5 * l.rise_us + l.pulse_width_us + 0.5 * l.fall_us;
    if t < 0.0 || t > end {
        return 0.0;
    }
    let up = if l.rise_us > 0.0 {
        (t / l.rise_us).min(1.0)
    } else {
        1.0
    };
    let down = if l.fall_us > 0.0 {
        ((end - t) / l.fall_us).min(1.0)
    } else {
        1.0
    };
    let saw = (t * 1e-6 * l.sawtooth_hz).fract() - 0.5;
    up.min(down) * (1.0 + l.sawtooth_depth * saw)
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;

    #[ebptv_macros::unit_test]
    fn rectangular_pulse_has_unit_level() {
        let l = Light {
            rise_us: 0.0,
            fall_us: 0.0,
            sawtooth_depth: 0.0,
            ..Light::default()
        };
        let s = PulseShape::new(&l);
        assert!((s.mean_level - 1.0).abs() < 1e-9);
        assert!((s.centroid_us - l.pulse_width_us / 2.0).abs() < 1e-9);
        let w: f64 = s.nodes.iter().map(|n| n.1).sum();
        assert!((w - 1.0).abs() < 1e-12);
    }

    #[ebptv_macros::unit_test]
    fn trapezoid_keeps_half_power_width() {
        let l = Light {
            rise_us: 4.0,
            fall_us: 4.0,
            sawtooth_depth: 0.0,
            ..Light::default()
        };
        let s = PulseShape::new(&l);
        // Linear ramps symmetric about the half-power points: area = width.
        assert!((s.mean_level - 1.0).abs() < 1e-3, "{}", s.mean_level);
        assert!((envelope(&l, 2.0) - 0.5).abs() < 1e-12);
    }

    #[ebptv_macros::unit_test]
    fn sawtooth_modulates_power() {
        let l = Light {
            rise_us: 0.0,
            fall_us: 0.0,
            pulse_width_us: 30.0,
            sawtooth_depth: 0.15,
            sawtooth_hz: 50_000.0,
            ..Light::default()
        };
        let lo = envelope(&l, 0.01);
        let hi = envelope(&l, 19.99);
        assert!((hi - lo - 0.15).abs() < 0.01, "{lo} {hi}");
    }
}
