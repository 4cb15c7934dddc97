//! Pseudo-images: one grey image per light pulse, built from the events the
//! pulse caused.
//!
//! Each event adds to its pixel (binary: the pixel is 1 if it fired at all;
//! counts: the number of events), ON events only by default (the sensor is
//! biased for ON events; OFF events trail the particle and would smear it).
//! A separable Gaussian blur (σ 0.5–2 px, the paper's 1–2 px kernel) turns
//! the 1–2 px binary particle images into smooth blobs that give a
//! correlation peak the 3-point Gaussian fit can resolve below a pixel.
//!
//! [`FrameRing`] keeps only the last `N_f` pseudo-images while the recording
//! streams past, recycling their buffers: memory is `N_f` images whatever the
//! recording's length.

use std::collections::VecDeque;
use std::sync::Arc;

use super::Image;
use crate::error::{Error, Result};
use crate::events::{EventChunk, ON};

/// How an event contributes to its pixel.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PixelMode {
    /// 1 where at least one event fired.
    Binary,
    /// Number of events.
    Counts,
}

/// Options of pseudo-image construction.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PseudoOptions {
    /// How events contribute to their pixel.
    pub mode: PixelMode,
    /// Use OFF events too (default: ON only).
    pub both_polarities: bool,
    /// Gaussian blur σ (px); 0 = none.
    pub sigma: f64,
}

impl Default for PseudoOptions {
    fn default() -> Self {
        PseudoOptions {
            mode: PixelMode::Binary,
            both_polarities: false,
            sigma: 1.0,
        }
    }
}

impl PseudoOptions {
    pub(crate) fn check(&self) -> Result<()> {
        if !(self.sigma.is_finite() && (0.0..=10.0).contains(&self.sigma)) {
            return Err(Error::param(
                "sigma",
                format!(
                    "{} px: the blur must be between 0 and 10 px (typically 0.5-2)",
                    self.sigma
                ),
            ));
        }
        Ok(())
    }
}

/// Normalised, truncated (±3σ) Gaussian kernel.
pub(crate) fn gaussian_kernel(sigma: f64) -> Vec<f32> {
    if sigma <= 0.0 {
        return vec![1.0];
    }
    let r = (3.0 * sigma).ceil() as i64;
    let k: Vec<f64> = (-r..=r)
        .map(|i| (-(i * i) as f64 / (2.0 * sigma * sigma)).exp())
        .collect();
    let s: f64 = k.iter().sum();
    k.into_iter().map(|v| (v / s) as f32).collect()
}

/// Separable convolution with `kernel`, edges replicated. `tmp` is reused.
pub(crate) fn blur(img: &mut Image, kernel: &[f32], tmp: &mut Vec<f32>) {
    if kernel.len() <= 1 {
        return;
    }
    let (w, h) = (img.width, img.height);
    let r = (kernel.len() / 2) as i64;
    tmp.resize(w * h, 0.0);
    for y in 0..h {
        let row = &img.data[y * w..(y + 1) * w];
        let out = &mut tmp[y * w..(y + 1) * w];
        for x in 0..w {
            let mut acc = 0.0f32;
            for (m, &kv) in kernel.iter().enumerate() {
                let xx = (x as i64 + m as i64 - r).clamp(0, w as i64 - 1) as usize;
                acc += kv * row[xx];
            }
            out[x] = acc;
        }
    }
    for y in 0..h {
        for x in 0..w {
            let mut acc = 0.0f32;
            for (m, &kv) in kernel.iter().enumerate() {
                let yy = (y as i64 + m as i64 - r).clamp(0, h as i64 - 1) as usize;
                acc += kv * tmp[yy * w + x];
            }
            img.data[y * w + x] = acc;
        }
    }
}

/// The same convolution as [`blur`] (edges replicated) for a sparse image
/// given as its non-zero pixels `(index, value)`: each pixel adds the 2-D
/// kernel around it into `out` (zeroed here). Costs `(2r+1)²` per lit
/// pixel instead of `2(2r+1)` per image pixel: a pulse lights a few
/// thousand pixels of a megapixel sensor. Replicated edges are the
/// virtual pixels beyond the border carrying the edge value, so a lit
/// edge pixel spreads from all its virtual copies.
pub(crate) fn blur_sparse(lit: &[(usize, f32)], kernel: &[f32], out: &mut Image) {
    let (w, h) = (out.width as i64, out.height as i64);
    out.data.iter_mut().for_each(|v| *v = 0.0);
    let r = (kernel.len() / 2) as i64;
    for &(idx, val) in lit {
        let (px, py) = ((idx as i64) % w, (idx as i64) / w);
        let (x_lo, x_hi) = (
            if px == 0 { -r } else { px },
            if px == w - 1 { px + r } else { px },
        );
        let (y_lo, y_hi) = (
            if py == 0 { -r } else { py },
            if py == h - 1 { py + r } else { py },
        );
        for jy in y_lo..=y_hi {
            for jx in x_lo..=x_hi {
                for y in (jy - r).max(0)..=(jy + r).min(h - 1) {
                    let wy = val * kernel[(jy - y + r) as usize];
                    let row = &mut out.data[(y * w) as usize..((y + 1) * w) as usize];
                    for x in (jx - r).max(0)..=(jx + r).min(w - 1) {
                        row[x as usize] += wy * kernel[(jx - x + r) as usize];
                    }
                }
            }
        }
    }
}

/// Builds pseudo-images of a fixed size, reusing its kernel and scratch.
pub(crate) struct PseudoImager {
    pub width: usize,
    pub height: usize,
    opts: PseudoOptions,
    kernel: Vec<f32>,
    tmp: Vec<f32>,
    lit: Vec<(usize, f32)>,
}

impl PseudoImager {
    pub(crate) fn new(width: usize, height: usize, opts: PseudoOptions) -> Result<Self> {
        opts.check()?;
        if width == 0 || height == 0 {
            return Err(Error::param(
                "geometry",
                format!("{width}x{height} px image"),
            ));
        }
        Ok(PseudoImager {
            width,
            height,
            opts,
            kernel: gaussian_kernel(opts.sigma),
            tmp: Vec::new(),
            lit: Vec::new(),
        })
    }

    /// Render `events` into `out` (resized and overwritten). Events outside
    /// the image are ignored. Sparse frames are blurred by splatting the
    /// kernel around the lit pixels ([`blur_sparse`]), dense ones with the
    /// separable [`blur`]; both give the same image.
    pub(crate) fn render(&mut self, events: &EventChunk, out: &mut Image) {
        out.width = self.width;
        out.height = self.height;
        out.data.clear();
        out.data.resize(self.width * self.height, 0.0);
        self.lit.clear();
        for i in 0..events.len() {
            if !self.opts.both_polarities && events.p[i] != ON {
                continue;
            }
            let (x, y) = (events.x[i] as usize, events.y[i] as usize);
            if x >= self.width || y >= self.height {
                continue;
            }
            let idx = y * self.width + x;
            let px = &mut out.data[idx];
            if *px == 0.0 {
                self.lit.push((idx, 0.0));
            }
            match self.opts.mode {
                PixelMode::Binary => *px = 1.0,
                PixelMode::Counts => *px += 1.0,
            }
        }
        let taps = self.kernel.len();
        if taps <= 1 {
            return;
        }
        if self.lit.len() * taps < self.width * self.height {
            for l in self.lit.iter_mut() {
                l.1 = out.data[l.0];
            }
            // Index order: the sum order, hence the rounding, does not
            // depend on the event order within the pulse.
            self.lit.sort_unstable_by_key(|l| l.0);
            blur_sparse(&self.lit, &self.kernel, out);
        } else {
            blur(out, &self.kernel, &mut self.tmp);
        }
    }
}

/// The last `capacity` frames, oldest first, with recycled buffers.
///
/// Frames are reference-counted so that evaluations queued for parallel
/// processing ([`PivStream`](super::PivStream) with a batch) can hold on to
/// them after they left the ring without copying; a buffer is recycled
/// when the ring held its last reference.
pub(crate) struct FrameRing {
    capacity: usize,
    frames: VecDeque<(i64, Arc<Image>)>,
    spare: Vec<Image>,
}

impl FrameRing {
    pub(crate) fn new(capacity: usize) -> Self {
        FrameRing {
            capacity: capacity.max(1),
            frames: VecDeque::with_capacity(capacity),
            spare: Vec::new(),
        }
    }

    /// A buffer to render the next frame into (recycled when possible).
    pub(crate) fn take_buffer(&mut self) -> Image {
        self.spare.pop().unwrap_or_else(|| Image::zeros(0, 0))
    }

    /// Keep the buffer of a frame for reuse if `f` was its last reference.
    pub(crate) fn recycle(&mut self, f: Arc<Image>) {
        if let Ok(img) = Arc::try_unwrap(f) {
            self.spare.push(img);
        }
    }

    /// Append a frame with its pulse index, dropping the oldest when full.
    pub(crate) fn push(&mut self, index: i64, img: Image) {
        if self.frames.len() == self.capacity {
            if let Some((_, old)) = self.frames.pop_front() {
                self.recycle(old);
            }
        }
        self.frames.push_back((index, Arc::new(img)));
    }

    /// Forget all frames (e.g. after a gap in the pulse sequence).
    pub(crate) fn clear(&mut self) {
        while let Some((_, f)) = self.frames.pop_front() {
            self.recycle(f);
        }
    }

    pub(crate) fn is_full(&self) -> bool {
        self.frames.len() == self.capacity
    }

    #[cfg(feature = "testkit")]
    pub(crate) fn len(&self) -> usize {
        self.frames.len()
    }

    /// Pulse index of the newest frame.
    pub(crate) fn last_index(&self) -> Option<i64> {
        self.frames.back().map(|f| f.0)
    }

    /// Pulse index of the oldest frame.
    pub(crate) fn first_index(&self) -> Option<i64> {
        self.frames.front().map(|f| f.0)
    }

    #[cfg(feature = "testkit")]
    pub(crate) fn images(&self) -> Vec<&Image> {
        self.frames.iter().map(|f| &*f.1).collect()
    }

    /// The frames, shared (no copy): for evaluations run later.
    pub(crate) fn shared_images(&self) -> Vec<Arc<Image>> {
        self.frames.iter().map(|f| Arc::clone(&f.1)).collect()
    }
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;

    #[ebptv_macros::unit_test]
    fn kernel_sums_to_one_and_blur_keeps_mass() {
        let k = gaussian_kernel(1.3);
        assert!((k.iter().sum::<f32>() - 1.0).abs() < 1e-5);
        let mut img = Image::zeros(21, 17);
        img.data[8 * 21 + 10] = 1.0;
        let mut tmp = Vec::new();
        blur(&mut img, &k, &mut tmp);
        assert!((img.data.iter().sum::<f32>() - 1.0).abs() < 1e-4);
        // Centre of mass unchanged.
        let cx: f32 = img
            .data
            .iter()
            .enumerate()
            .map(|(i, v)| v * (i % 21) as f32)
            .sum();
        assert!((cx - 10.0).abs() < 1e-3);
    }

    #[ebptv_macros::unit_test]
    fn sparse_blur_equals_separable_blur_including_edges() {
        let (w, h) = (23usize, 17usize);
        let k = gaussian_kernel(1.2);
        let mut img = Image::zeros(w, h);
        // Corners, edges, interior, neighbours, a weighted pixel.
        let lit = [
            (0, 0, 1.0f32),
            (22, 16, 1.0),
            (0, 9, 2.0),
            (11, 0, 1.0),
            (22, 5, 1.0),
            (10, 8, 3.0),
            (11, 8, 1.0),
            (1, 1, 1.0),
            (21, 15, 1.0),
        ];
        for &(x, y, v) in &lit {
            img.data[y * w + x] = v;
        }
        let sparse: Vec<(usize, f32)> = lit.iter().map(|&(x, y, v)| (y * w + x, v)).collect();
        let mut a = img.clone();
        blur(&mut a, &k, &mut Vec::new());
        let mut b = Image::zeros(w, h);
        b.data.fill(7.0); // overwritten
        blur_sparse(&sparse, &k, &mut b);
        for i in 0..w * h {
            assert!(
                (a.data[i] - b.data[i]).abs() < 1e-5,
                "pixel {i}: {} vs {}",
                a.data[i],
                b.data[i]
            );
        }
    }

    #[ebptv_macros::unit_test]
    fn on_events_only_by_default_and_counts() {
        let mut ev = EventChunk::default();
        ev.push(0, 2, 1, 1);
        ev.push(1, 2, 1, 1);
        ev.push(2, 3, 1, 0);
        ev.push(3, 99, 1, 1); // outside: ignored
        let mut img = Image::zeros(0, 0);
        let mut b = PseudoImager::new(
            5,
            3,
            PseudoOptions {
                sigma: 0.0,
                ..Default::default()
            },
        )
        .unwrap();
        b.render(&ev, &mut img);
        assert_eq!(img.get(2, 1), 1.0);
        assert_eq!(img.get(3, 1), 0.0);
        let mut c = PseudoImager::new(
            5,
            3,
            PseudoOptions {
                sigma: 0.0,
                mode: PixelMode::Counts,
                both_polarities: true,
            },
        )
        .unwrap();
        c.render(&ev, &mut img);
        assert_eq!(img.get(2, 1), 2.0);
        assert_eq!(img.get(3, 1), 1.0);
    }

    #[ebptv_macros::unit_test]
    fn ring_keeps_last_n() {
        let mut r = FrameRing::new(3);
        for k in 0..7 {
            let mut b = r.take_buffer();
            b.width = 1;
            b.height = 1;
            b.data = vec![k as f32];
            r.push(k, b);
        }
        assert_eq!(r.len(), 3);
        assert_eq!(r.first_index(), Some(4));
        assert_eq!(r.images()[2].data[0], 6.0);
    }

    #[ebptv_macros::unit_test]
    fn absurd_sigma_is_rejected() {
        assert!(PseudoImager::new(
            4,
            4,
            PseudoOptions {
                sigma: -1.0,
                ..Default::default()
            }
        )
        .is_err());
    }
}
