//! PNG figures (plotters, pure-Rust font path with an embedded DejaVu font).
//!
//! Every figure goes through `AtomicFile`, so a failed run leaves no figure.
//! (Bodies to be implemented; the API below is what the stages call.)

use std::path::Path;

use crate::error::Result;

/// A scalar map on a regular grid. `values` is row-major, `ny` rows of `nx`,
/// row 0 at `y_range.0` (top of the image, y pointing down as in pixels).
/// NaN = no data (drawn grey).
pub struct Heatmap<'a> {
    pub title: &'a str,
    pub values: &'a [f64],
    pub nx: usize,
    pub ny: usize,
    pub x_range: (f64, f64),
    pub y_range: (f64, f64),
    pub colorbar_label: &'a str,
    /// Symmetric colour scale around zero (differences, uv, v).
    pub diverging: bool,
}

pub fn heatmap(path: &Path, map: &Heatmap) -> Result<()> {
    let _ = (path, map);
    Ok(())
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SeriesStyle {
    Line,
    Points,
    Steps,
}

pub struct Series<'a> {
    pub label: &'a str,
    pub x: &'a [f64],
    pub y: &'a [f64],
    pub style: SeriesStyle,
}

pub struct LinePlot<'a> {
    pub title: &'a str,
    pub x_label: &'a str,
    pub y_label: &'a str,
    pub series: Vec<Series<'a>>,
    pub log_x: bool,
    pub log_y: bool,
    /// Vertical marker lines (x, label).
    pub vlines: Vec<(f64, &'a str)>,
}

pub fn line_plot(path: &Path, plot: &LinePlot) -> Result<()> {
    let _ = (path, plot);
    Ok(())
}

/// Polylines (e.g. particle tracks) coloured by a scalar (e.g. speed), over
/// an image-sized frame with y pointing down.
pub struct Polylines<'a> {
    pub title: &'a str,
    pub width: f64,
    pub height: f64,
    pub lines: &'a [Vec<(f64, f64)>],
    pub values: &'a [f64],
    pub colorbar_label: &'a str,
}

pub fn polylines(path: &Path, p: &Polylines) -> Result<()> {
    let _ = (path, p);
    Ok(())
}
