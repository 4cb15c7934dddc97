//! PNG figures (plotters, pure-Rust font path with an embedded DejaVu font).
//!
//! Three figure kinds cover what the stages need: a `heatmap` of a scalar
//! field on a regular grid (with a colour bar), a `line_plot` of several
//! series (legend, optional log axes, vertical markers) and `polylines`
//! (tracks coloured by a scalar). `histogram_plot` is a convenience over
//! `line_plot` for binned counts.
//!
//! Design choices:
//! - Rendering happens into an in-memory RGB buffer
//!   (`BitMapBackend::with_buffer`), which is then PNG-encoded with the `png`
//!   crate through [`AtomicFile`]: a failed run never leaves a half-written
//!   figure, and no plotters image-encoder path touches the file system.
//! - Text uses DejaVu Sans embedded in the binary (the `dejavu` crate),
//!   registered once with plotters' `ab_glyph` font path, so figures render
//!   identically on a headless batch node with no font libraries installed.
//! - Image coordinates: heatmaps and polylines put `y` downwards like a
//!   camera frame (row 0 at the top). plotters' Cartesian axes grow upwards,
//!   so these charts use the negated `y` internally and print `-y` on the
//!   tick labels.
//! - Colour maps: viridis (perceptually uniform, colour-blind safe) for
//!   magnitudes, and a blue-white-red diverging map symmetric around zero for
//!   signed quantities. NaN (no data) is a mid grey that neither map contains.
//! - Bad input (length mismatch, no finite data, non-finite or empty ranges)
//!   is a [`Error::InvalidParameter`] naming the figure and what is wrong;
//!   nothing is written then.

use std::cell::Cell;
use std::io::Write;
use std::ops::Range;
use std::path::Path;
use std::sync::Once;

use plotters::coord::combinators::IntoLogRange;
use plotters::coord::ranged1d::{AsRangedCoord, ValueFormatter};
use plotters::prelude::*;
use plotters::style::FontStyle;

use crate::error::{Error, Result};
use crate::io::atomic::AtomicFile;

/// Grey used for NaN (no data) cells and lines without a finite value.
pub(crate) const NAN_GREY: (u8, u8, u8) = (150, 150, 150);

/// Default size of a line plot, px.
pub(crate) const LINE_PLOT_SIZE: (u32, u32) = (960, 640);

const FONT: &str = "sans-serif";

static FONT_INIT: Once = Once::new();

fn ensure_font() {
    FONT_INIT.call_once(|| {
        // The embedded fonts are valid TrueType files; a failure here would be
        // a broken build of the `dejavu` crate, and text then simply fails to
        // render with a plotters error (reported, not a panic).
        let _ = plotters::style::register_font(FONT, FontStyle::Normal, dejavu::sans::regular());
        let _ = plotters::style::register_font(FONT, FontStyle::Bold, dejavu::sans::bold());
    });
}

/// A scalar map on a regular grid. `values` is row-major, `ny` rows of `nx`,
/// row 0 at `y_range.0` (top of the image, y pointing down as in pixels).
/// NaN = no data (drawn grey).
#[ebptv_macros::testkit]
pub(crate) struct Heatmap<'a> {
    /// Title drawn above the map.
    pub title: &'a str,
    /// The map, row-major, `nx * ny` values.
    pub values: &'a [f64],
    /// Columns of the grid.
    pub nx: usize,
    /// Rows of the grid.
    pub ny: usize,
    /// Horizontal extent of the map (left, right), in axis units (px for sensor maps).
    pub x_range: (f64, f64),
    /// Vertical extent of the map (top, bottom), in axis units (px for sensor maps).
    pub y_range: (f64, f64),
    /// Label of the colour bar (quantity and unit).
    pub colorbar_label: &'a str,
    /// Symmetric colour scale around zero (differences, uv, v).
    pub diverging: bool,
    /// Label the axes in mm through this calibration (the ranges stay in
    /// px: the ticks sit at round pixel positions, labelled with their
    /// position in mm); `None`: in px.
    pub axes_mm: Option<&'a crate::calib::Calibration>,
}

/// Draw a heatmap, image size chosen from the aspect ratio of the ranges.
#[ebptv_macros::testkit]
pub(crate) fn heatmap(path: &Path, map: &Heatmap) -> Result<()> {
    let size = heatmap_default_size(map.x_range, map.y_range);
    heatmap_sized(path, map, size)
}

/// Draw a heatmap at a given image size (px).
pub(crate) fn heatmap_sized(path: &Path, map: &Heatmap, size: (u32, u32)) -> Result<()> {
    let (buf, _) = render_heatmap(map, size).map_err(|e| at_path(path, e))?;
    write_png(path, &buf, size)
}

#[cfg(feature = "testkit")]
/// Draw a heatmap with an explicit colour range (e.g. the same scale on
/// several figures to compare). `vmin < vmax`, both finite.
pub(crate) fn heatmap_with_range(
    path: &Path,
    map: &Heatmap,
    size: (u32, u32),
    vrange: (f64, f64),
) -> Result<()> {
    let (buf, _) = render_heatmap_impl(map, size, Some(vrange)).map_err(|e| at_path(path, e))?;
    write_png(path, &buf, size)
}

/// How a [`Series`] is drawn.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum SeriesStyle {
    /// Straight segments joining consecutive points.
    Line,
    /// A marker at each point.
    Points,
    /// Piecewise constant: `y[i]` holds from `x[i]` to `x[i+1]` (the last
    /// step as wide as the one before it), e.g. a histogram given left bin
    /// edges.
    Steps,
}

/// One curve of a [`LinePlot`].
pub(crate) struct Series<'a> {
    /// Legend entry.
    pub label: &'a str,
    /// Abscissae.
    pub x: &'a [f64],
    /// Ordinates, one per abscissa.
    pub y: &'a [f64],
    /// How the curve is drawn.
    pub style: SeriesStyle,
}

/// A plot of one or several curves on shared axes.
pub(crate) struct LinePlot<'a> {
    /// Title drawn above the plot.
    pub title: &'a str,
    /// Label of the x axis (quantity and unit).
    pub x_label: &'a str,
    /// Label of the y axis (quantity and unit).
    pub y_label: &'a str,
    /// The curves.
    pub series: Vec<Series<'a>>,
    /// Logarithmic x axis (points with x ≤ 0 are skipped).
    pub log_x: bool,
    /// Logarithmic y axis (points with y ≤ 0 are skipped).
    pub log_y: bool,
    /// Vertical marker lines (x, label).
    pub vlines: Vec<(f64, &'a str)>,
}

/// Draw a line plot at [`LINE_PLOT_SIZE`]. Points that cannot be shown
/// (non-finite, or ≤ 0 on a log axis) are skipped; a series with no
/// showable point is an error.
pub(crate) fn line_plot(path: &Path, plot: &LinePlot) -> Result<()> {
    line_plot_sized(path, plot, LINE_PLOT_SIZE)
}

/// Draw a line plot at a given image size (px).
pub(crate) fn line_plot_sized(path: &Path, plot: &LinePlot, size: (u32, u32)) -> Result<()> {
    let buf = render_line_plot(plot, size).map_err(|e| at_path(path, e))?;
    write_png(path, &buf, size)
}

/// A histogram from bin edges (`edges.len() == counts.len() + 1`) drawn as
/// steps, one or several (e.g. measured vs simulated) on the same bins.
pub(crate) struct HistogramPlot<'a> {
    /// Title drawn above the plot.
    pub title: &'a str,
    /// Label of the x axis (quantity and unit).
    pub x_label: &'a str,
    /// Label of the y axis.
    pub y_label: &'a str,
    /// Bin edges, finite and increasing.
    pub edges: &'a [f64],
    /// (label, counts) per histogram.
    pub histograms: Vec<(&'a str, &'a [f64])>,
    /// Logarithmic y axis (empty bins are skipped).
    pub log_y: bool,
}

/// Draw a histogram plot as a PNG at `path`. Fails when there are fewer
/// than two edges, the edges are not finite and increasing, no histogram is
/// given, a histogram's count does not match the bins, or the image cannot
/// be drawn or written.
pub(crate) fn histogram_plot(path: &Path, h: &HistogramPlot) -> Result<()> {
    let what = |why: String| Error::param(format!("histogram `{}`", h.title), why);
    if h.edges.len() < 2 {
        return Err(what("needs at least two bin edges".into()));
    }
    if h.edges
        .windows(2)
        .any(|w| w[1].partial_cmp(&w[0]) != Some(std::cmp::Ordering::Greater))
    {
        return Err(what("bin edges must be finite and increasing".into()));
    }
    if h.histograms.is_empty() {
        return Err(what("no histogram to draw".into()));
    }
    // Steps need one y per x; repeat the last count at the right edge so the
    // last bin closes at its edge.
    let padded: Vec<Vec<f64>> = h
        .histograms
        .iter()
        .map(|(label, c)| {
            if c.len() + 1 != h.edges.len() {
                Err(what(format!(
                    "`{label}` has {} counts for {} bins",
                    c.len(),
                    h.edges.len() - 1
                )))
            } else {
                let mut v = c.to_vec();
                v.push(*c.last().unwrap_or(&0.0));
                Ok(v)
            }
        })
        .collect::<Result<_>>()?;
    let series = h
        .histograms
        .iter()
        .zip(&padded)
        .map(|((label, _), y)| Series {
            label,
            x: h.edges,
            y,
            style: SeriesStyle::Steps,
        })
        .collect();
    line_plot(
        path,
        &LinePlot {
            title: h.title,
            x_label: h.x_label,
            y_label: h.y_label,
            series,
            log_x: false,
            log_y: h.log_y,
            vlines: vec![],
        },
    )
}

/// Polylines (e.g. particle tracks) coloured by a scalar (e.g. speed), over
/// an image-sized frame with y pointing down. One value per line.
pub(crate) struct Polylines<'a> {
    /// Title drawn above the plot.
    pub title: &'a str,
    /// Width of the frame (px).
    pub width: f64,
    /// Height of the frame (px).
    pub height: f64,
    /// The lines, each a sequence of (x, y) points (px).
    pub lines: &'a [Vec<(f64, f64)>],
    /// Value of each line, mapped to its colour.
    pub values: &'a [f64],
    /// Label of the colour bar (quantity and unit).
    pub colorbar_label: &'a str,
}

/// Draw polylines, image size chosen from the frame's aspect ratio.
pub(crate) fn polylines(path: &Path, p: &Polylines) -> Result<()> {
    let size = heatmap_default_size((0.0, p.width), (0.0, p.height));
    polylines_sized(path, p, size)
}

/// Draw polylines at a given image size (px).
pub(crate) fn polylines_sized(path: &Path, p: &Polylines, size: (u32, u32)) -> Result<()> {
    let buf = render_polylines(p, size).map_err(|e| at_path(path, e))?;
    write_png(path, &buf, size)
}

// ---------------------------------------------------------------------------
// Colour maps

/// matplotlib's viridis at 0, 0.1, …, 1 (linear interpolation in between is
/// visually indistinguishable from the 256-entry table at figure sizes).
const VIRIDIS: [(u8, u8, u8); 11] = [
    (68, 1, 84),
    (72, 36, 117),
    (65, 68, 135),
    (53, 95, 141),
    (42, 120, 142),
    (33, 145, 140),
    (34, 168, 132),
    (68, 191, 112),
    (122, 209, 81),
    (189, 223, 38),
    (253, 231, 37),
];

/// Blue-white-red (ColorBrewer RdBu, reversed) from -1 to +1.
const DIVERGING: [(u8, u8, u8); 7] = [
    (33, 102, 172),
    (103, 169, 207),
    (209, 229, 240),
    (247, 247, 247),
    (253, 219, 199),
    (239, 138, 98),
    (178, 24, 43),
];

fn interpolate(table: &[(u8, u8, u8)], t: f64) -> (u8, u8, u8) {
    let t = if t.is_finite() {
        t.clamp(0.0, 1.0)
    } else {
        0.0
    };
    let pos = t * (table.len() - 1) as f64;
    let i = (pos.floor() as usize).min(table.len() - 2);
    let f = pos - i as f64;
    let lerp = |a: u8, b: u8| (a as f64 + (b as f64 - a as f64) * f).round() as u8;
    let (a, b) = (table[i], table[i + 1]);
    (lerp(a.0, b.0), lerp(a.1, b.1), lerp(a.2, b.2))
}

/// Colour for `t` in [0, 1] on viridis.
pub(crate) fn viridis(t: f64) -> (u8, u8, u8) {
    interpolate(&VIRIDIS, t)
}

/// Colour for `t` in [0, 1] on the blue-white-red map (0.5 = white).
pub(crate) fn diverging(t: f64) -> (u8, u8, u8) {
    interpolate(&DIVERGING, t)
}

fn rgb(c: (u8, u8, u8)) -> RGBColor {
    RGBColor(c.0, c.1, c.2)
}

/// Qualitative series colours (Tableau 10), distinguishable and print-safe.
const SERIES_COLOURS: [(u8, u8, u8); 10] = [
    (31, 119, 180),
    (255, 127, 14),
    (44, 160, 44),
    (214, 39, 40),
    (148, 103, 189),
    (140, 86, 75),
    (227, 119, 194),
    (127, 127, 127),
    (188, 189, 34),
    (23, 190, 207),
];

// ---------------------------------------------------------------------------
// Shared helpers

fn render_err<E: std::fmt::Display>(e: E) -> Error {
    Error::analysis(format!("rendering failed: {e}"))
}

/// Attach the output path to render errors so the user knows which figure.
fn at_path(path: &Path, e: Error) -> Error {
    match e {
        Error::Analysis(why) => Error::analysis(format!("{}: {why}", path.display())),
        other => other,
    }
}

fn write_png(path: &Path, rgb_buf: &[u8], (w, h): (u32, u32)) -> Result<()> {
    let mut file = AtomicFile::create(path)?;
    {
        let mut enc = png::Encoder::new(&mut file, w, h);
        enc.set_color(png::ColorType::Rgb);
        enc.set_depth(png::BitDepth::Eight);
        let mut writer = enc
            .write_header()
            .map_err(|e| Error::io(path, std::io::Error::other(e.to_string())))?;
        writer
            .write_image_data(rgb_buf)
            .map_err(|e| Error::io(path, std::io::Error::other(e.to_string())))?;
        writer
            .finish()
            .map_err(|e| Error::io(path, std::io::Error::other(e.to_string())))?;
    }
    file.flush().map_err(|e| Error::io(path, e))?;
    file.commit()
}

fn check_size(what: &str, (w, h): (u32, u32)) -> Result<()> {
    if !(200..=10_000).contains(&w) || !(150..=10_000).contains(&h) {
        return Err(Error::param(
            format!("{what} size"),
            format!("{w}x{h} px: width must be 200..=10000 and height 150..=10000"),
        ));
    }
    Ok(())
}

fn check_range(what: &str, name: &str, r: (f64, f64)) -> Result<()> {
    let ordered = r.1.partial_cmp(&r.0) == Some(std::cmp::Ordering::Greater);
    if !(r.0.is_finite() && r.1.is_finite() && ordered) {
        return Err(Error::param(
            format!("{what} {name}"),
            format!("({}, {}) must be finite with start < end", r.0, r.1),
        ));
    }
    Ok(())
}

/// Image size for a map whose plotting area keeps the data aspect ratio
/// (bounded to a sensible range of shapes).
fn heatmap_default_size(x: (f64, f64), y: (f64, f64)) -> (u32, u32) {
    let (dx, dy) = ((x.1 - x.0).abs(), (y.1 - y.0).abs());
    let aspect = if dx > 0.0 && dy > 0.0 && (dy / dx).is_finite() {
        (dy / dx).clamp(0.1, 2.0)
    } else {
        0.75
    };
    let plot_w = 800.0;
    let plot_h = (plot_w * aspect).max(120.0);
    // Margins: axes, title, colour bar.
    (plot_w as u32 + 260, plot_h as u32 + 140)
}

/// Tick label text: compact, no float noise.
fn fmt_tick(v: f64) -> String {
    let a = v.abs();
    if v == 0.0 {
        "0".into()
    } else if !(1e-3..1e5).contains(&a) {
        format!("{v:.1e}")
    } else if a >= 100.0 {
        format!("{v:.0}")
    } else {
        let s = format!("{v:.3}");
        let s = s.trim_end_matches('0').trim_end_matches('.');
        s.to_string()
    }
}

/// Tick label of a line plot axis: [`fmt_tick`], except that a log axis
/// spanning more than a decade (`decades`) labels only the ticks at 1, 2
/// and 5 × 10^k (only 10^k beyond six decades). Labelling every multiple
/// makes the top of each decade (…, 800, 900, 1000) run together.
fn axis_tick(v: f64, decades: Option<f64>) -> String {
    match decades {
        Some(d) if d > 1.0 && !log_tick_labelled(v, d) => String::new(),
        _ => fmt_tick(v),
    }
}

/// Whether `v` (a tick of a log axis spanning `decades` > 1) is 1, 2 or 5
/// × 10^k (1 × 10^k only beyond six decades).
fn log_tick_labelled(v: f64, decades: f64) -> bool {
    if !(v > 0.0 && v.is_finite()) {
        return false;
    }
    let e = v.log10().floor();
    let m = v / 10f64.powf(e);
    // Rounding may put 10^k just below it (mantissa 9.999…).
    let d = if m.round() >= 10.0 { 1.0 } else { m.round() };
    if (m - m.round()).abs() > 1e-6 * m {
        return false;
    }
    if decades > 6.0 {
        d == 1.0
    } else {
        d == 1.0 || d == 2.0 || d == 5.0
    }
}

fn text_style(size: u32) -> TextStyle<'static> {
    (FONT, size).into_font().color(&BLACK)
}

/// Draw a vertical colour bar with its axis and label into `area`.
fn draw_colorbar<DB: DrawingBackend>(
    area: &DrawingArea<DB, plotters::coord::Shift>,
    vmin: f64,
    vmax: f64,
    colour: &dyn Fn(f64) -> (u8, u8, u8),
    label: &str,
) -> Result<()> {
    let mut chart = ChartBuilder::on(area)
        .margin_top(50)
        .margin_bottom(70)
        .margin_right(10)
        .y_label_area_size(70)
        .set_label_area_size(LabelAreaPosition::Left, 0)
        .set_label_area_size(LabelAreaPosition::Right, 70)
        .build_cartesian_2d(0.0..1.0, vmin..vmax)
        .map_err(render_err)?;
    chart
        .configure_mesh()
        .disable_x_mesh()
        .disable_y_mesh()
        .disable_x_axis()
        .y_labels(8)
        .y_label_formatter(&|v| fmt_tick(*v))
        .y_label_style(text_style(14))
        .y_desc(label)
        .axis_desc_style(text_style(16))
        .draw()
        .map_err(render_err)?;
    let steps = 256;
    let span = vmax - vmin;
    chart
        .draw_series((0..steps).map(|i| {
            let a = vmin + span * i as f64 / steps as f64;
            let b = vmin + span * (i + 1) as f64 / steps as f64;
            let t = (i as f64 + 0.5) / steps as f64;
            Rectangle::new([(0.0, a), (1.0, b)], rgb(colour(t)).filled())
        }))
        .map_err(render_err)?;
    Ok(())
}

/// The key for cells without data: a grey swatch labelled "no data" under
/// the colour bar (in the bar's bottom margin).
fn draw_no_data_key<DB: DrawingBackend>(
    area: &DrawingArea<DB, plotters::coord::Shift>,
) -> Result<()> {
    let (_, h) = area.dim_in_pixel();
    let top = h as i32 - NO_DATA_KEY_FROM_BOTTOM;
    area.draw(&Rectangle::new(
        [(10, top), (30, top + 14)],
        rgb(NAN_GREY).filled(),
    ))
    .map_err(render_err)?;
    area.draw(&Rectangle::new(
        [(10, top), (30, top + 14)],
        RGBColor(90, 90, 90).stroke_width(1),
    ))
    .map_err(render_err)?;
    area.draw(&Text::new("no data", (36, top), text_style(14)))
        .map_err(render_err)?;
    Ok(())
}

/// Distance of the "no data" swatch's top edge from the image bottom, px.
const NO_DATA_KEY_FROM_BOTTOM: i32 = 50;

/// Pixel rectangle of a chart's plotting area: (x range, y range).
pub(crate) type PixelRect = (Range<i32>, Range<i32>);

// ---------------------------------------------------------------------------
// Heatmap

pub(crate) fn render_heatmap(map: &Heatmap, size: (u32, u32)) -> Result<(Vec<u8>, PixelRect)> {
    render_heatmap_impl(map, size, None)
}

fn render_heatmap_impl(
    map: &Heatmap,
    size: (u32, u32),
    vrange: Option<(f64, f64)>,
) -> Result<(Vec<u8>, PixelRect)> {
    let what = format!("heatmap `{}`", map.title);
    check_size(&what, size)?;
    if map.nx == 0 || map.ny == 0 {
        return Err(Error::param(
            format!("{what} grid"),
            format!("{}x{} cells: needs at least one", map.nx, map.ny),
        ));
    }
    if map.nx.checked_mul(map.ny) != Some(map.values.len()) {
        return Err(Error::param(
            format!("{what} values"),
            format!(
                "{} values for a grid of nx={} by ny={} ({} cells)",
                map.values.len(),
                map.nx,
                map.ny,
                map.nx.saturating_mul(map.ny)
            ),
        ));
    }
    check_range(&what, "x_range", map.x_range)?;
    check_range(&what, "y_range", map.y_range)?;
    if map.values.iter().any(|v| v.is_infinite()) {
        return Err(Error::param(
            format!("{what} values"),
            "contain ±infinity (use NaN for cells without data)",
        ));
    }

    // Colour range: explicit, else from the data; an all-NaN map is drawn grey
    // with a nominal scale rather than failing the whole run.
    let (vmin, vmax) = match vrange {
        Some(r) => {
            check_range(&what, "colour range", r)?;
            r
        }
        None => {
            let (lo, hi) = map
                .values
                .iter()
                .filter(|v| v.is_finite())
                .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &v| {
                    (lo.min(v), hi.max(v))
                });
            if map.diverging {
                let m = lo.abs().max(hi.abs());
                if m.is_finite() && m > 0.0 {
                    (-m, m)
                } else {
                    (-1.0, 1.0)
                }
            } else if !lo.is_finite() {
                (0.0, 1.0)
            } else if hi > lo {
                (lo, hi)
            } else {
                // A constant map: centre it in a unit-wide scale.
                let pad = if lo == 0.0 { 1.0 } else { lo.abs() * 0.5 };
                (lo - pad, lo + pad)
            }
        }
    };
    let cmap: fn(f64) -> (u8, u8, u8) = if map.diverging { diverging } else { viridis };

    ensure_font();
    let (w, h) = size;
    let mut buf = vec![255u8; (w * h * 3) as usize];
    let rect;
    {
        let root = BitMapBackend::with_buffer(&mut buf, size).into_drawing_area();
        root.fill(&WHITE).map_err(render_err)?;
        let (main, bar) = root.split_horizontally(w.saturating_sub(170));
        let (x0, x1) = map.x_range;
        let (y0, y1) = map.y_range;
        let mut chart = ChartBuilder::on(&main)
            .caption(map.title, text_style(22))
            .margin(15)
            .x_label_area_size(50)
            .y_label_area_size(70)
            .build_cartesian_2d(x0..x1, -y1..-y0)
            .map_err(render_err)?;
        chart
            .configure_mesh()
            .disable_x_mesh()
            .disable_y_mesh()
            .x_labels(10)
            .y_labels(8)
            .x_label_formatter(&|v| match map.axes_mm {
                Some(c) => fmt_tick(c.px_to_mm(*v, 0.0).0),
                None => fmt_tick(*v),
            })
            .y_label_formatter(&|v| match map.axes_mm {
                Some(c) => fmt_tick(c.px_to_mm(0.0, -*v).1),
                None => fmt_tick(-*v),
            })
            .label_style(text_style(14))
            .x_desc(if map.axes_mm.is_some() {
                "x (mm)"
            } else {
                "x (px)"
            })
            .y_desc(if map.axes_mm.is_some() {
                "y (mm)"
            } else {
                "y (px)"
            })
            .axis_desc_style(text_style(16))
            .draw()
            .map_err(render_err)?;

        // Fill the plotting area pixel by pixel with the cell under each
        // pixel centre: cost set by the figure size, not the grid size, and
        // no gaps or overdraw between cells.
        let area = chart.plotting_area();
        let (px, py) = area.get_pixel_range();
        let (pw, ph) = ((px.end - px.start).max(1), (py.end - py.start).max(1));
        for j in py.clone() {
            let fy = (j - py.start) as f64 + 0.5;
            let row = ((fy / ph as f64) * map.ny as f64) as usize;
            let row = row.min(map.ny - 1);
            for i in px.clone() {
                let fx = (i - px.start) as f64 + 0.5;
                let col = (((fx / pw as f64) * map.nx as f64) as usize).min(map.nx - 1);
                let v = map.values[row * map.nx + col];
                let c = if v.is_nan() {
                    NAN_GREY
                } else {
                    cmap((v - vmin) / (vmax - vmin))
                };
                root.draw_pixel((i, j), &rgb(c)).map_err(render_err)?;
            }
        }
        rect = (px, py);
        draw_colorbar(&bar, vmin, vmax, &cmap, map.colorbar_label)?;
        if map.values.iter().any(|v| v.is_nan()) {
            draw_no_data_key(&bar)?;
        }
        root.present().map_err(render_err)?;
    }
    Ok((buf, rect))
}

// ---------------------------------------------------------------------------
// Line plot

/// One series after validation: the points that can be drawn.
struct Prepared<'a> {
    label: &'a str,
    points: Vec<(f64, f64)>,
    style: SeriesStyle,
}

fn prepare_series<'a>(plot: &LinePlot<'a>, what: &str) -> Result<Vec<Prepared<'a>>> {
    if plot.series.is_empty() {
        return Err(Error::param(format!("{what} series"), "no series to draw"));
    }
    let ok_x = |x: f64| x.is_finite() && (!plot.log_x || x > 0.0);
    let ok_y = |y: f64| y.is_finite() && (!plot.log_y || y > 0.0);
    let mut out = Vec::with_capacity(plot.series.len());
    for s in &plot.series {
        if s.x.len() != s.y.len() {
            return Err(Error::param(
                format!("{what} series `{}`", s.label),
                format!("{} x values but {} y values", s.x.len(), s.y.len()),
            ));
        }
        let mut points: Vec<(f64, f64)> = Vec::with_capacity(s.x.len() * 2);
        if s.style == SeriesStyle::Steps {
            for i in 0..s.x.len() {
                let x_next = if i + 1 < s.x.len() {
                    s.x[i + 1]
                } else if i >= 1 {
                    s.x[i] + (s.x[i] - s.x[i - 1])
                } else {
                    s.x[i]
                };
                if ok_y(s.y[i]) && ok_x(s.x[i]) && ok_x(x_next) {
                    points.push((s.x[i], s.y[i]));
                    points.push((x_next, s.y[i]));
                }
            }
        } else {
            points.extend(
                s.x.iter()
                    .zip(s.y)
                    .filter(|(x, y)| ok_x(**x) && ok_y(**y))
                    .map(|(x, y)| (*x, *y)),
            );
        }
        if points.is_empty() {
            return Err(Error::param(
                format!("{what} series `{}`", s.label),
                if s.x.is_empty() {
                    "is empty".to_string()
                } else {
                    format!(
                        "has no drawable point (all non-finite{})",
                        if plot.log_x || plot.log_y {
                            " or ≤ 0 on a log axis"
                        } else {
                            ""
                        }
                    )
                },
            ));
        }
        out.push(Prepared {
            label: s.label,
            points,
            style: s.style,
        });
    }
    Ok(out)
}

/// Axis range covering `lo..hi` with some padding (multiplicative on logs).
fn padded(lo: f64, hi: f64, log: bool) -> (f64, f64) {
    if log {
        if hi > lo {
            let f = (hi / lo).powf(0.04);
            (lo / f, hi * f)
        } else {
            (lo / 2.0, hi * 2.0)
        }
    } else if hi > lo {
        let pad = (hi - lo) * 0.04;
        (lo - pad, hi + pad)
    } else {
        let pad = if lo == 0.0 { 1.0 } else { lo.abs() * 0.1 };
        (lo - pad, hi + pad)
    }
}

fn render_line_plot(plot: &LinePlot, size: (u32, u32)) -> Result<Vec<u8>> {
    let what = format!("line plot `{}`", plot.title);
    check_size(&what, size)?;
    let series = prepare_series(plot, &what)?;
    for (x, label) in &plot.vlines {
        if !x.is_finite() || (plot.log_x && *x <= 0.0) {
            return Err(Error::param(
                format!("{what} marker `{label}`"),
                format!("x = {x} cannot be shown on this axis"),
            ));
        }
    }
    let mut xr = (f64::INFINITY, f64::NEG_INFINITY);
    let mut yr = (f64::INFINITY, f64::NEG_INFINITY);
    for s in &series {
        for &(x, y) in &s.points {
            xr = (xr.0.min(x), xr.1.max(x));
            yr = (yr.0.min(y), yr.1.max(y));
        }
    }
    for (x, _) in &plot.vlines {
        xr = (xr.0.min(*x), xr.1.max(*x));
    }
    let xr = padded(xr.0, xr.1, plot.log_x);
    let yr = padded(yr.0, yr.1, plot.log_y);

    ensure_font();
    let mut buf = vec![255u8; (size.0 * size.1 * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, size).into_drawing_area();
        root.fill(&WHITE).map_err(render_err)?;
        match (plot.log_x, plot.log_y) {
            (false, false) => draw_lines(&root, plot, &series, xr.0..xr.1, yr.0..yr.1, xr, yr)?,
            (true, false) => draw_lines(
                &root,
                plot,
                &series,
                (xr.0..xr.1).log_scale(),
                yr.0..yr.1,
                xr,
                yr,
            )?,
            (false, true) => draw_lines(
                &root,
                plot,
                &series,
                xr.0..xr.1,
                (yr.0..yr.1).log_scale(),
                xr,
                yr,
            )?,
            (true, true) => draw_lines(
                &root,
                plot,
                &series,
                (xr.0..xr.1).log_scale(),
                (yr.0..yr.1).log_scale(),
                xr,
                yr,
            )?,
        }
        root.present().map_err(render_err)?;
    }
    Ok(buf)
}

fn draw_lines<DB, X, Y>(
    root: &DrawingArea<DB, plotters::coord::Shift>,
    plot: &LinePlot,
    series: &[Prepared],
    xr: X,
    yr: Y,
    x_bounds: (f64, f64),
    y_bounds: (f64, f64),
) -> Result<()>
where
    DB: DrawingBackend,
    X: AsRangedCoord<Value = f64>,
    Y: AsRangedCoord<Value = f64>,
    X::CoordDescType: ValueFormatter<f64>,
    Y::CoordDescType: ValueFormatter<f64>,
{
    // Decades spanned by a log axis (None on a linear one): how many of
    // its tick labels fit.
    let decades = |log: bool, (lo, hi): (f64, f64)| log.then(|| (hi / lo).log10());
    let (x_decades, y_decades) = (decades(plot.log_x, x_bounds), decades(plot.log_y, y_bounds));
    // plotters' log axes give 10^k twice (end of one decade, start of the
    // next): a repeated tick gets no second label (it would print bold).
    let (last_x, last_y) = (Cell::new(f64::NAN), Cell::new(f64::NAN));
    let once = |last: &Cell<f64>, v: f64, label: String| {
        let repeated = (v - last.get()).abs() <= 1e-9 * v.abs();
        last.set(v);
        if repeated {
            String::new()
        } else {
            label
        }
    };
    let mut chart = ChartBuilder::on(root)
        .caption(plot.title, text_style(22))
        .margin(15)
        .x_label_area_size(50)
        .y_label_area_size(80)
        .build_cartesian_2d(xr, yr)
        .map_err(render_err)?;
    chart
        .configure_mesh()
        .light_line_style(RGBColor(235, 235, 235))
        .bold_line_style(RGBColor(210, 210, 210))
        .x_labels(10)
        .y_labels(8)
        .x_label_formatter(&|v| once(&last_x, *v, axis_tick(*v, x_decades)))
        .y_label_formatter(&|v| once(&last_y, *v, axis_tick(*v, y_decades)))
        .label_style(text_style(14))
        .x_desc(plot.x_label)
        .y_desc(plot.y_label)
        .axis_desc_style(text_style(16))
        .draw()
        .map_err(render_err)?;

    for (k, s) in series.iter().enumerate() {
        let colour = rgb(SERIES_COLOURS[k % SERIES_COLOURS.len()]);
        let style = colour.stroke_width(2);
        let anno = match s.style {
            SeriesStyle::Line | SeriesStyle::Steps => chart
                .draw_series(LineSeries::new(s.points.iter().copied(), style))
                .map_err(render_err)?,
            SeriesStyle::Points => chart
                .draw_series(s.points.iter().map(|&p| Circle::new(p, 3, colour.filled())))
                .map_err(render_err)?,
        };
        if !s.label.is_empty() {
            anno.label(s.label).legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 20, y)], colour.stroke_width(3))
            });
        }
    }
    for (x, label) in &plot.vlines {
        let grey = RGBColor(90, 90, 90);
        chart
            .draw_series(DashedLineSeries::new(
                vec![(*x, y_bounds.0), (*x, y_bounds.1)],
                6,
                4,
                grey.stroke_width(1),
            ))
            .map_err(render_err)?;
        if !label.is_empty() {
            // Label next to the top of the marker, inside the plot.
            let (px, py) = chart.backend_coord(&(*x, y_bounds.1));
            root.draw(&Text::new(
                label.to_string(),
                (px + 4, py + 4),
                text_style(13).color(&grey),
            ))
            .map_err(render_err)?;
        }
    }
    if series.iter().any(|s| !s.label.is_empty()) {
        chart
            .configure_series_labels()
            .position(SeriesLabelPosition::UpperRight)
            .background_style(WHITE.mix(0.85))
            .border_style(RGBColor(160, 160, 160))
            .label_font(text_style(14))
            .draw()
            .map_err(render_err)?;
    }
    Ok(())
}

// ---------------------------------------------------------------------------
// Polylines

fn render_polylines(p: &Polylines, size: (u32, u32)) -> Result<Vec<u8>> {
    let what = format!("polylines `{}`", p.title);
    check_size(&what, size)?;
    check_range(&what, "width", (0.0, p.width))?;
    check_range(&what, "height", (0.0, p.height))?;
    if p.values.len() != p.lines.len() {
        return Err(Error::param(
            format!("{what} values"),
            format!(
                "{} values for {} lines (one value per line)",
                p.values.len(),
                p.lines.len()
            ),
        ));
    }
    let (lo, hi) = p
        .values
        .iter()
        .filter(|v| v.is_finite())
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &v| {
            (lo.min(v), hi.max(v))
        });
    let (vmin, vmax) = if !lo.is_finite() {
        (0.0, 1.0)
    } else if hi > lo {
        (lo, hi)
    } else {
        let pad = if lo == 0.0 { 1.0 } else { lo.abs() * 0.5 };
        (lo - pad, lo + pad)
    };

    ensure_font();
    let (w, h) = size;
    let mut buf = vec![255u8; (w * h * 3) as usize];
    {
        let root = BitMapBackend::with_buffer(&mut buf, size).into_drawing_area();
        root.fill(&WHITE).map_err(render_err)?;
        let (main, bar) = root.split_horizontally(w.saturating_sub(170));
        let mut chart = ChartBuilder::on(&main)
            .caption(p.title, text_style(22))
            .margin(15)
            .x_label_area_size(50)
            .y_label_area_size(70)
            .build_cartesian_2d(0.0..p.width, -p.height..0.0)
            .map_err(render_err)?;
        chart
            .configure_mesh()
            .light_line_style(WHITE)
            .bold_line_style(RGBColor(225, 225, 225))
            .x_labels(10)
            .y_labels(8)
            .x_label_formatter(&|v| fmt_tick(*v))
            .y_label_formatter(&|v| fmt_tick(-*v))
            .label_style(text_style(14))
            .x_desc("x (px)")
            .y_desc("y (px)")
            .axis_desc_style(text_style(16))
            .draw()
            .map_err(render_err)?;
        for (line, &v) in p.lines.iter().zip(p.values) {
            let pts: Vec<(f64, f64)> = line
                .iter()
                .filter(|(x, y)| x.is_finite() && y.is_finite())
                .map(|&(x, y)| (x, -y))
                .collect();
            let c = if v.is_finite() {
                viridis((v - vmin) / (vmax - vmin))
            } else {
                NAN_GREY
            };
            if pts.len() == 1 {
                chart
                    .draw_series(std::iter::once(Circle::new(pts[0], 2, rgb(c).filled())))
                    .map_err(render_err)?;
            } else if pts.len() > 1 {
                chart
                    .draw_series(LineSeries::new(pts, rgb(c).stroke_width(2)))
                    .map_err(render_err)?;
            }
        }
        draw_colorbar(&bar, vmin, vmax, &viridis, p.colorbar_label)?;
        root.present().map_err(render_err)?;
    }
    Ok(buf)
}

#[cfg(feature = "testkit")]
pub(crate) mod tests {
    // The figure builders drawn into images (src/plot/tests/figures.rs).
    pub(crate) mod figures;

    use super::*;

    fn pixel(buf: &[u8], w: u32, x: i32, y: i32) -> (u8, u8, u8) {
        let i = ((y as u32 * w + x as u32) * 3) as usize;
        (buf[i], buf[i + 1], buf[i + 2])
    }

    #[ebptv_macros::unit_test]
    fn colormaps_hit_their_anchors() {
        assert_eq!(viridis(0.0), VIRIDIS[0]);
        assert_eq!(viridis(1.0), VIRIDIS[10]);
        assert_eq!(viridis(0.5), VIRIDIS[5]);
        assert_eq!(diverging(0.5), (247, 247, 247));
        assert_eq!(diverging(0.0), DIVERGING[0]);
        assert_eq!(diverging(1.0), DIVERGING[6]);
        assert_eq!(viridis(f64::NAN), VIRIDIS[0]);
        // Neither map contains the NaN grey.
        for k in 0..=1000 {
            let t = k as f64 / 1000.0;
            assert_ne!(viridis(t), NAN_GREY);
            assert_ne!(diverging(t), NAN_GREY);
        }
    }

    #[ebptv_macros::unit_test]
    fn heatmap_cells_land_where_the_grid_says() {
        // 4x2 grid: row 0 (top) = NaN in the left half, low values right;
        // row 1 (bottom) = high values everywhere.
        let nan = f64::NAN;
        let values = [nan, nan, 0.0, 0.0, 1.0, 1.0, 1.0, 1.0];
        let map = Heatmap {
            title: "t",
            values: &values,
            nx: 4,
            ny: 2,
            x_range: (0.0, 4.0),
            y_range: (0.0, 2.0),
            colorbar_label: "v",
            diverging: false,
            axes_mm: None,
        };
        let size = (800, 500);
        let (buf, (px, py)) = render_heatmap(&map, size).unwrap();
        let at = |fx: f64, fy: f64| {
            let x = px.start + ((px.end - px.start) as f64 * fx) as i32;
            let y = py.start + ((py.end - py.start) as f64 * fy) as i32;
            pixel(&buf, size.0, x, y)
        };
        assert_eq!(at(0.1, 0.25), NAN_GREY, "top-left is NaN");
        assert_eq!(at(0.9, 0.25), VIRIDIS[0], "top-right is the minimum");
        assert_eq!(at(0.1, 0.75), VIRIDIS[10], "bottom row is the maximum");
        assert_eq!(at(0.9, 0.75), VIRIDIS[10]);
    }

    #[ebptv_macros::unit_test]
    fn calibrated_axes_label_in_mm_and_leave_the_cells() {
        let values = [0.0, 1.0, 2.0, 3.0];
        let calib = crate::calib::Calibration::from_toml(
            "px_per_mm = 10.0\norigin_px = [50.0, 20.0]\ny_axis = \"up\"\n",
            std::path::Path::new("c.toml"),
        )
        .unwrap();
        let mut map = Heatmap {
            title: "t",
            values: &values,
            nx: 2,
            ny: 2,
            x_range: (0.0, 400.0),
            y_range: (0.0, 200.0),
            colorbar_label: "v",
            diverging: false,
            axes_mm: None,
        };
        let size = (800, 500);
        let (px_buf, rect) = render_heatmap(&map, size).unwrap();
        map.axes_mm = Some(&calib);
        let (mm_buf, mm_rect) = render_heatmap(&map, size).unwrap();
        // The same cells in the same place; the tick labels and axis titles
        // (outside the plotting area) differ.
        assert_eq!(rect, mm_rect);
        let inside = |buf: &[u8]| {
            let mut v = Vec::new();
            for y in rect.1.clone() {
                for x in rect.0.clone() {
                    v.push(pixel(buf, size.0, x, y));
                }
            }
            v
        };
        assert_eq!(inside(&px_buf), inside(&mm_buf));
        assert_ne!(px_buf, mm_buf);
    }

    #[ebptv_macros::unit_test]
    fn diverging_is_symmetric_around_zero() {
        let values = [-1.0, 0.0, 3.0];
        let map = Heatmap {
            title: "d",
            values: &values,
            nx: 3,
            ny: 1,
            x_range: (0.0, 3.0),
            y_range: (0.0, 1.0),
            colorbar_label: "dv",
            diverging: true,
            axes_mm: None,
        };
        let size = (800, 400);
        let (buf, (px, py)) = render_heatmap(&map, size).unwrap();
        let yc = (py.start + py.end) / 2;
        let w = px.end - px.start;
        let mid = pixel(&buf, size.0, px.start + w / 2, yc);
        assert_eq!(mid, diverging(0.5), "zero is white");
        let right = pixel(&buf, size.0, px.start + w * 5 / 6, yc);
        assert_eq!(
            right, DIVERGING[6],
            "the largest |v| is the end of the scale"
        );
        let left = pixel(&buf, size.0, px.start + w / 6, yc);
        assert_eq!(left, diverging(0.5 - 1.0 / 6.0), "-1 of ±3 sits at 1/3");
    }

    #[ebptv_macros::unit_test]
    fn crowded_log_axes_label_one_two_five() {
        // 70..2200 Hz: ticks at 100, 200, …, 900, 1000, 2000.
        let d = (2200.0f64 / 70.0).log10();
        let shown: Vec<String> = [100.0, 200.0, 300.0, 500.0, 800.0, 900.0, 1000.0, 2000.0]
            .iter()
            .map(|&v| axis_tick(v, Some(d)))
            .collect();
        assert_eq!(shown, ["100", "200", "", "500", "", "", "1000", "2000"]);
        // Rounding noise around a power of ten still counts as one.
        assert!(log_tick_labelled(999.999_999_9, d));
        // Within a decade every tick keeps its label; linear axes too.
        assert_eq!(axis_tick(900.0, Some(0.9)), "900");
        assert_eq!(axis_tick(900.0, None), "900");
        // Beyond six decades only powers of ten.
        assert_eq!(axis_tick(200.0, Some(7.0)), "");
        assert_eq!(axis_tick(100.0, Some(7.0)), "100");
    }

    #[ebptv_macros::unit_test]
    fn heatmap_with_empty_cells_has_a_no_data_key() {
        let key_pixel = |values: &[f64]| {
            let map = Heatmap {
                title: "k",
                values,
                nx: 2,
                ny: 1,
                x_range: (0.0, 2.0),
                y_range: (0.0, 1.0),
                colorbar_label: "v",
                diverging: false,
                axes_mm: None,
            };
            let size = (800u32, 400u32);
            let (buf, _) = render_heatmap(&map, size).unwrap();
            // Centre of the swatch in the colour-bar column.
            let x = (size.0 - 170 + 20) as i32;
            let y = size.1 as i32 - NO_DATA_KEY_FROM_BOTTOM + 7;
            pixel(&buf, size.0, x, y)
        };
        assert_eq!(key_pixel(&[f64::NAN, 1.0]), NAN_GREY);
        assert_eq!(
            key_pixel(&[0.0, 1.0]),
            (255, 255, 255),
            "no key without empty cells"
        );
    }

    #[ebptv_macros::unit_test]
    fn tick_format_is_compact() {
        assert_eq!(fmt_tick(0.0), "0");
        assert_eq!(fmt_tick(1.5), "1.5");
        assert_eq!(fmt_tick(2.0), "2");
        assert_eq!(fmt_tick(640.0), "640");
        assert_eq!(fmt_tick(1e6), "1.0e6");
    }
}
