//! Physical units and masks: a [`Calibration`] (scale, origin, direction
//! of the y axis, read from a `calib.toml`) turns pixels and px/s into mm
//! and m/s on output, and a [`PixelMask`] (a PNG image, polygons of the
//! calibration file, or both) marks the sensor regions that are not flow:
//! walls, the model, reflections.
//!
//! ```toml
//! # the scale: px_per_mm, or [reference] (two points and their distance)
//! px_per_mm = 12.5
//! origin_px = [320.0, 240.0]   # pixel of X = Y = 0 (default [0, 0])
//! y_axis = "up"                # "up" or "down" (default: down, as pixel rows)
//!
//! [mask]                       # optional
//! image = "walls.png"          # relative to this file; non-zero = masked
//! polygons = [[[0, 0], [640, 0], [640, 20], [0, 20]]]
//! ```
//!
//! Pixel coordinates are those of the outputs: pixel `(i, j)` has its
//! centre at `x = i, y = j`. A calibration never changes the pixel columns;
//! it adds physical ones after them (`Calibration::point_columns`,
//! `Calibration::field_columns`).

use std::path::{Path, PathBuf};
use std::sync::Arc;

use serde::Deserialize;

use crate::error::{Error, Result};

/// The contents of a `calib.toml`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct CalibFile {
    px_per_mm: Option<f64>,
    reference: Option<ReferenceFile>,
    origin_px: Option<[f64; 2]>,
    y_axis: Option<YAxis>,
    mask: Option<MaskFile>,
}

/// Two points on the image a known distance apart.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct ReferenceFile {
    a_px: [f64; 2],
    b_px: [f64; 2],
    distance_mm: f64,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct MaskFile {
    image: Option<PathBuf>,
    #[serde(default)]
    polygons: Vec<Vec<[f64; 2]>>,
}

/// Direction of the physical y axis on the image.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum YAxis {
    /// Y grows towards the top of the image (against pixel rows).
    Up,
    /// Y grows with the pixel rows (towards the bottom of the image).
    Down,
}

/// Pixels to physical units: `X = (x − x0) / s`, `Y = ±(y − y0) / s` with
/// `s` in px/mm, velocities in m/s and stresses in m²/s².
#[derive(Debug, Clone)]
pub struct Calibration {
    /// Scale (px per mm).
    pub px_per_mm: f64,
    /// Pixel position of the physical origin.
    pub origin_px: [f64; 2],
    /// Direction of the physical y axis.
    pub y_axis: YAxis,
    /// The mask of the file's `[mask]` table, if any.
    pub mask: Option<Arc<PixelMask>>,
}

fn config_err(path: &Path, why: impl Into<String>) -> Error {
    Error::Config {
        path: path.to_path_buf(),
        why: why.into(),
    }
}

impl Calibration {
    /// The scale of two points `a`, `b` (px) that are `distance_mm` apart.
    pub(crate) fn scale_from_points(a: [f64; 2], b: [f64; 2], distance_mm: f64) -> f64 {
        (a[0] - b[0]).hypot(a[1] - b[1]) / distance_mm
    }

    /// Reads a `calib.toml`; errors name the file and the key. A mask
    /// image is read relative to the file's directory.
    pub fn from_file(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        Self::from_toml(&text, path)
    }

    /// Parses the text of a `calib.toml`; `path` names it in errors and
    /// anchors a relative mask image.
    pub(crate) fn from_toml(text: &str, path: &Path) -> Result<Self> {
        let f: CalibFile =
            toml::from_str(text).map_err(|e| config_err(path, e.to_string().trim_end()))?;
        let px_per_mm =
            match (f.px_per_mm, &f.reference) {
                (Some(_), Some(_)) => {
                    return Err(config_err(
                        path,
                        "give the scale once: either `px_per_mm` or `[reference]`, not both",
                    ))
                }
                (None, None) => return Err(config_err(
                    path,
                    "no scale: give `px_per_mm` or a `[reference]` table (a_px, b_px, distance_mm)",
                )),
                (Some(s), None) => {
                    if !(s.is_finite() && s > 0.0) {
                        return Err(config_err(
                            path,
                            format!("key `px_per_mm`: must be a positive number, got {s}"),
                        ));
                    }
                    s
                }
                (None, Some(r)) => {
                    for (k, p) in [("a_px", r.a_px), ("b_px", r.b_px)] {
                        if !p.iter().all(|v| v.is_finite()) {
                            return Err(config_err(
                                path,
                                format!("key `reference.{k}`: coordinates must be finite"),
                            ));
                        }
                    }
                    if !(r.distance_mm.is_finite() && r.distance_mm > 0.0) {
                        return Err(config_err(
                            path,
                            format!(
                                "key `reference.distance_mm`: must be a positive number, got {}",
                                r.distance_mm
                            ),
                        ));
                    }
                    let s = Self::scale_from_points(r.a_px, r.b_px, r.distance_mm);
                    if !(s.is_finite() && s > 0.0) {
                        return Err(config_err(
                            path,
                            "keys `reference.a_px`, `reference.b_px`: the two points coincide",
                        ));
                    }
                    s
                }
            };
        let origin_px = f.origin_px.unwrap_or([0.0, 0.0]);
        if !origin_px.iter().all(|v| v.is_finite()) {
            return Err(config_err(
                path,
                "key `origin_px`: coordinates must be finite",
            ));
        }
        let mask = match f.mask {
            None => None,
            Some(m) => {
                let mut mask = match &m.image {
                    Some(img) => {
                        let img = match path.parent() {
                            Some(dir) if img.is_relative() => dir.join(img),
                            _ => img.clone(),
                        };
                        Some(
                            PixelMask::from_png(&img)
                                .map_err(|e| config_err(path, format!("key `mask.image`: {e}")))?,
                        )
                    }
                    None => None,
                };
                if !m.polygons.is_empty() {
                    let p = PixelMask::from_polygons(&m.polygons)
                        .map_err(|why| config_err(path, format!("key `mask.polygons`: {why}")))?;
                    mask = Some(match mask {
                        Some(a) => a.union(&p),
                        None => p,
                    });
                }
                match mask {
                    Some(m) => Some(Arc::new(m)),
                    None => {
                        return Err(config_err(path, "table `mask`: give `image` or `polygons`"))
                    }
                }
            }
        };
        Ok(Calibration {
            px_per_mm,
            origin_px,
            y_axis: f.y_axis.unwrap_or(YAxis::Down),
            mask,
        })
    }

    fn y_sign(&self) -> f64 {
        match self.y_axis {
            YAxis::Up => -1.0,
            YAxis::Down => 1.0,
        }
    }

    /// A position (px) in mm.
    pub fn px_to_mm(&self, x: f64, y: f64) -> (f64, f64) {
        (
            (x - self.origin_px[0]) / self.px_per_mm,
            self.y_sign() * (y - self.origin_px[1]) / self.px_per_mm,
        )
    }

    /// A velocity (px/s) in m/s.
    pub fn velocity_px_s_to_m_s(&self, u: f64, v: f64) -> (f64, f64) {
        let k = 1.0 / (self.px_per_mm * 1000.0);
        (u * k, self.y_sign() * v * k)
    }

    /// Reynolds stresses `uu, vv, uv` ((px/s)²) in m²/s².
    pub fn stress_px2_s2_to_m2_s2(&self, uu: f64, vv: f64, uv: f64) -> (f64, f64, f64) {
        let k = 1.0 / (self.px_per_mm * 1000.0).powi(2);
        (uu * k, vv * k, self.y_sign() * uv * k)
    }

    /// The physical columns of a point with a velocity (tracks).
    pub(crate) fn point_columns() -> &'static [&'static str] {
        &["X_mm", "Y_mm", "U_m_s", "V_m_s"]
    }

    /// Values of [`Self::point_columns`] for a point at `(x, y)` px moving
    /// at `(u, v)` px/s.
    pub(crate) fn point_values(&self, x: f64, y: f64, u: f64, v: f64) -> [f64; 4] {
        let (xm, ym) = self.px_to_mm(x, y);
        let (um, vm) = self.velocity_px_s_to_m_s(u, v);
        [xm, ym, um, vm]
    }

    /// The physical columns of a field of mean velocities and stresses
    /// (grids, PIV means).
    pub(crate) fn field_columns() -> &'static [&'static str] {
        &[
            "X_mm", "Y_mm", "U_m_s", "V_m_s", "uu_m2_s2", "vv_m2_s2", "uv_m2_s2",
        ]
    }

    /// Values of [`Self::field_columns`].
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn field_values(
        &self,
        x: f64,
        y: f64,
        u: f64,
        v: f64,
        uu: f64,
        vv: f64,
        uv: f64,
    ) -> [f64; 7] {
        let [xm, ym, um, vm] = self.point_values(x, y, u, v);
        let (a, b, c) = self.stress_px2_s2_to_m2_s2(uu, vv, uv);
        [xm, ym, um, vm, a, b, c]
    }
}

/// `,A,B,…`: physical columns appended to a CSV header.
pub(crate) fn header_suffix(columns: &[&str]) -> String {
    columns.iter().map(|c| format!(",{c}")).collect()
}

/// A physical value as CSV text: 7 significant digits (`nan` when not
/// finite).
pub(crate) fn format_value(v: f64) -> String {
    if !v.is_finite() {
        return "nan".into();
    }
    let rounded: f64 = format!("{v:.6e}").parse().unwrap_or(v);
    // + 0.0: a flipped zero is written `0`, not `-0`.
    format!("{}", rounded + 0.0)
}

/// Appends `,v` for each value ([`format_value`]).
pub(crate) fn push_values(out: &mut Vec<u8>, values: &[f64]) {
    for &v in values {
        out.push(b',');
        out.extend_from_slice(format_value(v).as_bytes());
    }
}

/// Reads the optional calibration and mask of a command: the mask of
/// `mask_file` (a PNG) joined with the calibration file's `[mask]`.
pub(crate) fn load(
    calibration: Option<&Path>,
    mask_file: Option<&Path>,
) -> Result<(Option<Calibration>, Option<Arc<PixelMask>>)> {
    let calib = calibration.map(Calibration::from_file).transpose()?;
    let file_mask = mask_file.map(PixelMask::from_png).transpose()?;
    let mask = match (calib.as_ref().and_then(|c| c.mask.clone()), file_mask) {
        (Some(a), Some(b)) => Some(Arc::new(a.union(&b))),
        (Some(a), None) => Some(a),
        (None, Some(b)) => Some(Arc::new(b)),
        (None, None) => None,
    };
    Ok((calib, mask))
}

/// A mask over the sensor: pixel `(i, j)` (centre at `x = i, y = j`) is
/// either masked (not flow) or not. Pixels beyond its size are not masked.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PixelMask {
    width: u32,
    height: u32,
    bits: Vec<bool>,
}

impl PixelMask {
    /// An empty (nothing masked) mask of `width × height` pixels.
    #[ebptv_macros::testkit]
    pub(crate) fn new(width: u32, height: u32) -> Self {
        PixelMask {
            width,
            height,
            bits: vec![false; width as usize * height as usize],
        }
    }

    /// Width and height (px).
    #[ebptv_macros::testkit]
    pub(crate) fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }

    /// Mask pixel `(x, y)` (ignored beyond the size).
    #[ebptv_macros::testkit]
    pub(crate) fn set(&mut self, x: u32, y: u32) {
        if x < self.width && y < self.height {
            self.bits[y as usize * self.width as usize + x as usize] = true;
        }
    }

    /// Number of masked pixels.
    #[ebptv_macros::testkit]
    pub(crate) fn count(&self) -> usize {
        self.bits.iter().filter(|&&b| b).count()
    }

    /// Reads a PNG: a pixel whose colour (grey level or any of R, G, B;
    /// not alpha) is non-zero is masked.
    #[ebptv_macros::testkit]
    pub(crate) fn from_png(path: &Path) -> Result<Self> {
        let bad = |why: String| Error::Config {
            path: path.to_path_buf(),
            why,
        };
        let f = std::fs::File::open(path).map_err(|e| Error::io(path, e))?;
        let mut dec = png::Decoder::new(std::io::BufReader::new(f));
        dec.set_transformations(png::Transformations::EXPAND);
        let mut reader = dec
            .read_info()
            .map_err(|e| bad(format!("not a readable PNG mask: {e}")))?;
        let mut buf = vec![0; reader.output_buffer_size()];
        let info = reader
            .next_frame(&mut buf)
            .map_err(|e| bad(format!("not a readable PNG mask: {e}")))?;
        let (w, h) = (info.width, info.height);
        if w > 65536 || h > 65536 {
            return Err(bad(format!(
                "mask of {w} x {h} pixels: larger than any sensor"
            )));
        }
        let bytes = match info.bit_depth {
            png::BitDepth::Sixteen => 2,
            _ => 1,
        };
        let (channels, colour) = match info.color_type {
            png::ColorType::Grayscale => (1, 1),
            png::ColorType::GrayscaleAlpha => (2, 1),
            png::ColorType::Rgb => (3, 3),
            png::ColorType::Rgba => (4, 3),
            png::ColorType::Indexed => (3, 3), // expanded to RGB
        };
        let mut m = PixelMask::new(w, h);
        for y in 0..h as usize {
            let row = &buf[y * info.line_size..(y + 1) * info.line_size];
            for x in 0..w as usize {
                let px = &row[x * channels * bytes..(x * channels + colour) * bytes];
                m.bits[y * w as usize + x] = px.iter().any(|&b| b != 0);
            }
        }
        Ok(m)
    }

    /// Writes the mask as an 8-bit grey PNG (255 = masked), atomically.
    #[ebptv_macros::testkit]
    pub(crate) fn write_png(&self, path: &Path) -> Result<()> {
        let mut file = crate::io::atomic::AtomicFile::create(path)?;
        {
            let mut enc = png::Encoder::new(&mut file, self.width.max(1), self.height.max(1));
            enc.set_color(png::ColorType::Grayscale);
            enc.set_depth(png::BitDepth::Eight);
            let werr =
                |e: png::EncodingError| Error::io(path, std::io::Error::other(e.to_string()));
            let mut w = enc.write_header().map_err(werr)?;
            let mut data: Vec<u8> = self.bits.iter().map(|&b| if b { 255 } else { 0 }).collect();
            if data.is_empty() {
                data.push(0);
            }
            w.write_image_data(&data).map_err(werr)?;
            w.finish().map_err(werr)?;
        }
        file.commit()
    }

    /// The pixels whose centres lie inside any of `polygons` (px, even-odd
    /// rule); an error text when a polygon has fewer than 3 vertices or
    /// coordinates that are not finite or beyond any sensor.
    pub(crate) fn from_polygons(polygons: &[Vec<[f64; 2]>]) -> std::result::Result<Self, String> {
        let (mut w, mut h) = (0u32, 0u32);
        for (i, p) in polygons.iter().enumerate() {
            if p.len() < 3 {
                return Err(format!("polygon {}: fewer than 3 vertices", i + 1));
            }
            for v in p {
                if !(v[0].is_finite() && v[1].is_finite())
                    || v[0].abs() > 65536.0
                    || v[1].abs() > 65536.0
                {
                    return Err(format!(
                        "polygon {}: vertex [{}, {}] is not a pixel position",
                        i + 1,
                        v[0],
                        v[1]
                    ));
                }
                w = w.max((v[0].max(0.0).ceil() as u32 + 1).min(65536));
                h = h.max((v[1].max(0.0).ceil() as u32 + 1).min(65536));
            }
        }
        let mut m = PixelMask::new(w, h);
        for p in polygons {
            let x_lo = p
                .iter()
                .map(|v| v[0])
                .fold(f64::INFINITY, f64::min)
                .max(0.0)
                .floor() as u32;
            let y_lo = p
                .iter()
                .map(|v| v[1])
                .fold(f64::INFINITY, f64::min)
                .max(0.0)
                .floor() as u32;
            for y in y_lo..h {
                for x in x_lo..w {
                    if inside(p, x as f64, y as f64) {
                        m.bits[y as usize * w as usize + x as usize] = true;
                    }
                }
            }
        }
        Ok(m)
    }

    /// Pixels masked in either mask (the size of the larger).
    pub(crate) fn union(&self, other: &PixelMask) -> PixelMask {
        let mut m = PixelMask::new(self.width.max(other.width), self.height.max(other.height));
        for src in [self, other] {
            for y in 0..src.height {
                for x in 0..src.width {
                    if src.is_masked_px(x, y) {
                        m.set(x, y);
                    }
                }
            }
        }
        m
    }

    /// Whether pixel `(x, y)` is masked.
    #[inline]
    #[ebptv_macros::testkit]
    pub(crate) fn is_masked_px(&self, x: u32, y: u32) -> bool {
        x < self.width
            && y < self.height
            && self.bits[y as usize * self.width as usize + x as usize]
    }

    /// Whether the pixel holding position `(x, y)` (px) is masked.
    #[inline]
    pub(crate) fn is_masked(&self, x: f64, y: f64) -> bool {
        let (i, j) = ((x + 0.5).floor(), (y + 0.5).floor());
        i >= 0.0 && j >= 0.0 && i < u32::MAX as f64 && j < u32::MAX as f64 && {
            self.is_masked_px(i as u32, j as u32)
        }
    }

    /// Fraction of the pixels with centres in `[x0, x1) × [y0, y1)` that
    /// are masked (0 when the rectangle holds no pixel centre).
    pub(crate) fn masked_fraction(&self, x0: f64, x1: f64, y0: f64, y1: f64) -> f64 {
        let lo = |v: f64| v.ceil().max(0.0);
        let hi = |v: f64| (v.ceil() - 1.0).max(-1.0);
        let (i0, i1, j0, j1) = (lo(x0), hi(x1), lo(y0), hi(y1));
        if i1 < i0 || j1 < j0 {
            return 0.0;
        }
        let (i0, i1, j0, j1) = (i0 as u64, i1 as u64, j0 as u64, j1 as u64);
        let total = (i1 - i0 + 1) * (j1 - j0 + 1);
        let mut masked = 0u64;
        for j in j0..=j1.min(self.height as u64) {
            for i in i0..=i1.min(self.width as u64) {
                if self.is_masked_px(i as u32, j as u32) {
                    masked += 1;
                }
            }
        }
        masked as f64 / total as f64
    }

    /// Whether the straight segment from `a` to `b` (px) passes over a
    /// masked pixel (sampled every quarter pixel, ends included).
    pub(crate) fn crosses(&self, a: (f64, f64), b: (f64, f64)) -> bool {
        let len = (b.0 - a.0).hypot(b.1 - a.1);
        if !len.is_finite() {
            return false;
        }
        let n = (len * 4.0).ceil().max(1.0) as usize;
        (0..=n).any(|k| {
            let s = k as f64 / n as f64;
            self.is_masked(a.0 + s * (b.0 - a.0), a.1 + s * (b.1 - a.1))
        })
    }
}

/// Even-odd test of point `(x, y)` against polygon `p`.
fn inside(p: &[[f64; 2]], x: f64, y: f64) -> bool {
    let mut c = false;
    let mut j = p.len() - 1;
    for i in 0..p.len() {
        let (xi, yi, xj, yj) = (p[i][0], p[i][1], p[j][0], p[j][1]);
        if (yi > y) != (yj > y) && x < (xj - xi) * (y - yi) / (yj - yi) + xi {
            c = !c;
        }
        j = i;
    }
    c
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    use super::*;

    fn parse(text: &str) -> Result<Calibration> {
        Calibration::from_toml(text, Path::new("c.toml"))
    }

    #[ebptv_macros::unit_test]
    fn two_points_equal_the_equivalent_scale() {
        let a =
            parse("[reference]\na_px = [100, 50]\nb_px = [400, 450]\ndistance_mm = 50\n").unwrap();
        // 500 px over 50 mm.
        let b = parse("px_per_mm = 10.0\n").unwrap();
        assert!((a.px_per_mm - b.px_per_mm).abs() < 1e-12, "{}", a.px_per_mm);
        assert_eq!(
            a.point_values(7.0, 9.0, 3.0, -4.0),
            b.point_values(7.0, 9.0, 3.0, -4.0)
        );
    }

    #[ebptv_macros::unit_test]
    fn origin_and_y_up_place_and_orient_the_axes() {
        let c = parse("px_per_mm = 4\norigin_px = [100, 200]\ny_axis = \"up\"\n").unwrap();
        assert_eq!(c.px_to_mm(104.0, 192.0), (1.0, 2.0));
        // 4000 px/s = 1 mm/ms = 1 m/s … at 4 px/mm: 4000 px/s = 1000 mm/s.
        assert_eq!(c.velocity_px_s_to_m_s(4000.0, 8000.0), (1.0, -2.0));
        assert_eq!(c.stress_px2_s2_to_m2_s2(16e6, 16e6, 16e6), (1.0, 1.0, -1.0));
    }

    #[ebptv_macros::unit_test]
    fn bad_files_name_the_file_and_the_key() {
        for (text, key) in [
            ("px_per_mm = -2\n", "px_per_mm"),
            ("px_per_mm = 2\norigin = [0, 0]\n", "origin"),
            ("", "px_per_mm"),
            (
                "px_per_mm = 2\n[reference]\na_px=[0,0]\nb_px=[1,0]\ndistance_mm=1\n",
                "reference",
            ),
            (
                "[reference]\na_px=[3,3]\nb_px=[3,3]\ndistance_mm=1\n",
                "a_px",
            ),
            (
                "[reference]\na_px=[0,0]\nb_px=[1,0]\ndistance_mm=0\n",
                "distance_mm",
            ),
            ("px_per_mm = 2\ny_axis = \"left\"\n", "y_axis"),
            (
                "px_per_mm = 2\n[mask]\npolygons = [[[0,0],[1,1]]]\n",
                "mask.polygons",
            ),
            (
                "px_per_mm = 2\n[mask]\nimage = \"nowhere.png\"\n",
                "mask.image",
            ),
        ] {
            let e = parse(text).unwrap_err().to_string();
            assert!(
                e.starts_with("c.toml: ") && e.contains(key),
                "{text:?} → {e}"
            );
        }
    }

    #[ebptv_macros::unit_test]
    fn polygons_mask_the_pixel_centres_inside() {
        let c = parse(
            "px_per_mm = 2\n[mask]\npolygons = [[[-0.5,-0.5],[9.5,-0.5],[9.5,2.5],[-0.5,2.5]]]\n",
        )
        .unwrap();
        let m = c.mask.unwrap();
        assert_eq!(m.count(), 30);
        assert!(m.is_masked(0.0, 0.0) && m.is_masked(9.2, 2.4) && !m.is_masked(3.0, 3.0));
        assert!(m.crosses((5.0, -1.0), (5.0, 8.0)));
        assert!(!m.crosses((0.0, 3.0), (9.0, 3.0)));
        assert_eq!(m.masked_fraction(-0.5, 9.5, -0.5, 5.5), 0.5);
    }

    #[ebptv_macros::unit_test]
    fn a_mask_survives_its_png() {
        let mut m = PixelMask::new(7, 5);
        m.set(1, 2);
        m.set(6, 4);
        let dir = std::env::temp_dir().join(format!("ebptv-mask-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let p = dir.join("m.png");
        m.write_png(&p).unwrap();
        assert_eq!(PixelMask::from_png(&p).unwrap(), m);
        std::fs::write(&p, b"not a png").unwrap();
        let e = PixelMask::from_png(&p).unwrap_err().to_string();
        assert!(e.contains("m.png") && e.contains("PNG"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
