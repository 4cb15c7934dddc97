//! Multi-frame, multi-pass correlation on one stack of `N_f` frames.
//!
//! One evaluation measures the displacement per frame step on a regular
//! node grid from frames `f_0 … f_{N_f−1}` (pairs `(k, k+1)`, sum of
//! correlation):
//!
//! 1. **Pass 1** — windows (twice the final size when `passes > 1` and it
//!    fits, for a robust start) at the same place in both frames.
//! 2. **Validate** — normalised median test, outliers replaced; the field is
//!    the predictor of the next pass.
//! 3. **Passes 2…** — final-size windows; each pixel of the window is
//!    sampled at `x − d(x)/2` in frame k and `x + d(x)/2` in frame k+1,
//!    `d` the bilinearly interpolated predictor (symmetric image
//!    deformation, second-order accurate in time; cubic B-spline image
//!    interpolation). The correlation then measures only the residual, near
//!    zero, where the circular correlation has no bias, and the node value
//!    becomes predictor + residual.
//!
//! Nodes sit at the centres of windows starting at `i·spacing`, so every
//! final window lies inside the image. Windows and nodes are independent:
//! rayon maps over nodes, each thread with its own FFT workspace.

use rayon::prelude::*;

use super::correlate::{find_peak, remove_mean, CorrelationPlan, Workspace};
use super::validate::{self, flag, MedianTest};
use super::Image;
use crate::error::{Error, Result};

/// Options of the correlation.
#[derive(Debug, Clone, PartialEq)]
pub struct PivOptions {
    /// Final interrogation window width (px).
    pub window_w: usize,
    /// Final interrogation window height (px).
    pub window_h: usize,
    /// Node spacing in x and y (px).
    pub spacing_x: usize,
    pub spacing_y: usize,
    /// Number of passes (1 = plain single pass, no deformation).
    pub passes: usize,
    /// Normalised median test.
    pub median: MedianTest,
    /// Optional mask (`true` = masked), `width*height`, row-major.
    pub mask: Option<Vec<bool>>,
}

impl PivOptions {
    pub fn new(window: usize, spacing: usize) -> Self {
        PivOptions {
            window_w: window,
            window_h: window,
            spacing_x: spacing,
            spacing_y: spacing,
            passes: 3,
            median: MedianTest::default(),
            mask: None,
        }
    }
}

/// The node grid: node (i, j) at `(x0 + i·dx, y0 + j·dy)`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct NodeGrid {
    pub nx: usize,
    pub ny: usize,
    pub x0: f64,
    pub y0: f64,
    pub dx: f64,
    pub dy: f64,
}

impl NodeGrid {
    #[inline]
    pub fn x(&self, i: usize) -> f64 {
        self.x0 + i as f64 * self.dx
    }
    #[inline]
    pub fn y(&self, j: usize) -> f64 {
        self.y0 + j as f64 * self.dy
    }
    pub fn len(&self) -> usize {
        self.nx * self.ny
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
}

/// Displacement per frame step on the node grid (px). `flags` from
/// [`validate::flag`]; replaced vectors keep their replacement value.
#[derive(Debug, Clone, PartialEq)]
pub struct VectorField {
    pub grid: NodeGrid,
    pub u: Vec<f64>,
    pub v: Vec<f64>,
    pub flags: Vec<u8>,
    /// Correlation peak height per node (0–1, mean over pairs).
    pub peak: Vec<f32>,
}

/// Check the options against an image size and build the node grid.
pub fn node_grid(width: usize, height: usize, o: &PivOptions) -> Result<NodeGrid> {
    if o.window_w < 2 || o.window_h < 2 {
        return Err(Error::param(
            "window",
            format!(
                "{}x{} px: windows need at least 2 px each way",
                o.window_w, o.window_h
            ),
        ));
    }
    if o.spacing_x == 0 || o.spacing_y == 0 {
        return Err(Error::param("spacing", "must be at least 1 px"));
    }
    if o.passes == 0 {
        return Err(Error::param("passes", "must be at least 1"));
    }
    if o.window_w > width || o.window_h > height {
        return Err(Error::param(
            "window",
            format!(
                "{}x{} px window larger than the {}x{} px image",
                o.window_w, o.window_h, width, height
            ),
        ));
    }
    if let Some(m) = &o.mask {
        if m.len() != width * height {
            return Err(Error::param(
                "mask",
                format!("{} values for a {}x{} image", m.len(), width, height),
            ));
        }
    }
    Ok(NodeGrid {
        nx: (width - o.window_w) / o.spacing_x + 1,
        ny: (height - o.window_h) / o.spacing_y + 1,
        x0: (o.window_w as f64 - 1.0) / 2.0,
        y0: (o.window_h as f64 - 1.0) / 2.0,
        dx: o.spacing_x as f64,
        dy: o.spacing_y as f64,
    })
}

/// Cubic B-spline coefficients of an image (Unser's recursive prefilter,
/// mirror boundaries), so that [`sample_bspline`] interpolates the pixel
/// values exactly. Image deformation needs this accuracy: a short kernel
/// such as Keys' cubic shifts the signal by an amount that depends on the
/// fractional sample position, antisymmetrically, and the symmetric
/// deformation (`−d/2`, `+d/2`) doubles instead of cancelling that error —
/// a peak-locking-like bias of several hundredths of a pixel for 3 px
/// particle images.
pub fn bspline_coefficients(img: &Image) -> Image {
    let mut c = img.clone();
    let (w, h) = (img.width, img.height);
    let mut line = Vec::new();
    for y in 0..h {
        line.clear();
        line.extend_from_slice(&c.data[y * w..(y + 1) * w]);
        prefilter_line(&mut line);
        c.data[y * w..(y + 1) * w].copy_from_slice(&line);
    }
    for x in 0..w {
        line.clear();
        line.extend((0..h).map(|y| c.data[y * w + x]));
        prefilter_line(&mut line);
        for (y, v) in line.iter().enumerate() {
            c.data[y * w + x] = *v;
        }
    }
    c
}

fn prefilter_line(s: &mut [f32]) {
    let n = s.len();
    if n < 2 {
        return;
    }
    let z = 3.0f64.sqrt() - 2.0;
    let lambda = (1.0 - z) * (1.0 - 1.0 / z);
    let mut c: Vec<f64> = s.iter().map(|&v| v as f64 * lambda).collect();
    // Causal initialisation (mirror boundary), truncated where z^k is negligible.
    let horizon = n.min(30);
    let mut zk = z;
    let mut sum = c[0];
    for v in c.iter().take(horizon).skip(1) {
        sum += zk * v;
        zk *= z;
    }
    c[0] = sum;
    for k in 1..n {
        c[k] += z * c[k - 1];
    }
    c[n - 1] = (z / (z * z - 1.0)) * (c[n - 1] + z * c[n - 2]);
    for k in (0..n - 1).rev() {
        c[k] = z * (c[k + 1] - c[k]);
    }
    for (d, v) in s.iter_mut().zip(c) {
        *d = v as f32;
    }
}

#[inline]
fn bspline3(t: f32) -> f32 {
    let t = t.abs();
    if t < 1.0 {
        2.0 / 3.0 - t * t + 0.5 * t * t * t
    } else if t < 2.0 {
        let u = 2.0 - t;
        u * u * u / 6.0
    } else {
        0.0
    }
}

/// Image value at a real position from B-spline coefficients
/// ([`bspline_coefficients`]); edge coefficients replicated outside.
#[inline]
pub fn sample_bspline(coef: &Image, x: f32, y: f32) -> f32 {
    let xf = x.floor();
    let yf = y.floor();
    let (fx, fy) = (x - xf, y - yf);
    let (xi, yi) = (xf as i64, yf as i64);
    let wmax = coef.width as i64 - 1;
    let hmax = coef.height as i64 - 1;
    let wx = [
        bspline3(fx + 1.0),
        bspline3(fx),
        bspline3(1.0 - fx),
        bspline3(2.0 - fx),
    ];
    let wy = [
        bspline3(fy + 1.0),
        bspline3(fy),
        bspline3(1.0 - fy),
        bspline3(2.0 - fy),
    ];
    let mut acc = 0.0f32;
    for (m, wyv) in wy.iter().enumerate() {
        let yy = (yi - 1 + m as i64).clamp(0, hmax) as usize;
        let row = &coef.data[yy * coef.width..(yy + 1) * coef.width];
        let mut r = 0.0f32;
        for (n, wxv) in wx.iter().enumerate() {
            let xx = (xi - 1 + n as i64).clamp(0, wmax) as usize;
            r += wxv * row[xx];
        }
        acc += wyv * r;
    }
    acc
}

/// Bilinear interpolation of a node field at pixel position (x, y),
/// constant extrapolation beyond the outer nodes.
#[inline]
pub fn interp_field(g: &NodeGrid, f: &[f64], x: f64, y: f64) -> f64 {
    let fi = ((x - g.x0) / g.dx).clamp(0.0, (g.nx - 1) as f64);
    let fj = ((y - g.y0) / g.dy).clamp(0.0, (g.ny - 1) as f64);
    let i0 = (fi.floor() as usize).min(g.nx.saturating_sub(2));
    let j0 = (fj.floor() as usize).min(g.ny.saturating_sub(2));
    let i1 = (i0 + 1).min(g.nx - 1);
    let j1 = (j0 + 1).min(g.ny - 1);
    let (tx, ty) = (fi - i0 as f64, fj - j0 as f64);
    let a = f[j0 * g.nx + i0] * (1.0 - tx) + f[j0 * g.nx + i1] * tx;
    let b = f[j1 * g.nx + i0] * (1.0 - tx) + f[j1 * g.nx + i1] * tx;
    a * (1.0 - ty) + b * ty
}

/// A predictor: displacement per frame step on the node grid.
struct Predictor<'a> {
    grid: &'a NodeGrid,
    u: &'a [f64],
    v: &'a [f64],
    /// B-spline coefficients of every frame, for deformation.
    coefs: &'a [Image],
}

/// Per-thread state.
struct Thread {
    ws: Workspace,
    a: Vec<f32>,
    b: Vec<f32>,
    plane: Vec<f32>,
    disp: Vec<(f32, f32)>,
    inside: Vec<bool>,
}

/// Mean removal over the pixels marked `inside`; the others become 0.
/// Returns the energies of `a` and `b`.
fn remove_mean_where(a: &mut [f32], b: &mut [f32], inside: &[bool]) -> (f64, f64) {
    let cnt = inside.iter().filter(|&&k| k).count();
    if cnt == 0 {
        return (0.0, 0.0);
    }
    let (mut sa, mut sb) = (0.0f64, 0.0f64);
    for i in 0..a.len() {
        if inside[i] {
            sa += a[i] as f64;
            sb += b[i] as f64;
        }
    }
    let (ma, mb) = ((sa / cnt as f64) as f32, (sb / cnt as f64) as f32);
    let (mut ea, mut eb) = (0.0f64, 0.0f64);
    for i in 0..a.len() {
        if inside[i] {
            a[i] -= ma;
            b[i] -= mb;
            ea += (a[i] as f64).powi(2);
            eb += (b[i] as f64).powi(2);
        } else {
            a[i] = 0.0;
            b[i] = 0.0;
        }
    }
    (ea, eb)
}

/// Measure one node: returns (dx, dy, peak height, ok).
#[allow(clippy::too_many_arguments)]
fn measure_node(
    t: &mut Thread,
    frames: &[&Image],
    x_start: usize,
    y_start: usize,
    ww: usize,
    wh: usize,
    pred: Option<&Predictor>,
    node_pred: (f64, f64),
) -> (f64, f64, f32, bool) {
    let n = ww * wh;
    t.ws.reset();
    // Per-pixel predictor displacement (same for every pair).
    if let Some(p) = pred {
        t.disp.clear();
        for y in 0..wh {
            for x in 0..ww {
                let (px, py) = ((x_start + x) as f64, (y_start + y) as f64);
                t.disp.push((
                    interp_field(p.grid, p.u, px, py) as f32,
                    interp_field(p.grid, p.v, px, py) as f32,
                ));
            }
        }
    }
    for k in 0..frames.len() - 1 {
        let (fa, fb) = (frames[k], frames[k + 1]);
        match pred {
            None => {
                for y in 0..wh {
                    let ra = &fa.data[(y_start + y) * fa.width + x_start..][..ww];
                    let rb = &fb.data[(y_start + y) * fb.width + x_start..][..ww];
                    t.a[y * ww..(y + 1) * ww].copy_from_slice(ra);
                    t.b[y * ww..(y + 1) * ww].copy_from_slice(rb);
                }
            }
            Some(p) => {
                let (ca, cb) = (&p.coefs[k], &p.coefs[k + 1]);
                // Pixels whose sample in either frame falls outside the image
                // are left out of both windows (zero after mean removal):
                // edge-replicated values would correlate with nothing.
                let (wmax, hmax) = ((fa.width - 1) as f32, (fa.height - 1) as f32);
                let inside = |x: f32, y: f32| x >= 0.0 && y >= 0.0 && x <= wmax && y <= hmax;
                let mut any_out = false;
                for y in 0..wh {
                    for x in 0..ww {
                        let i = y * ww + x;
                        let (du, dv) = t.disp[i];
                        let (px, py) = ((x_start + x) as f32, (y_start + y) as f32);
                        let (ax, ay) = (px - 0.5 * du, py - 0.5 * dv);
                        let (bx, by) = (px + 0.5 * du, py + 0.5 * dv);
                        let ok = inside(ax, ay) && inside(bx, by);
                        t.inside[i] = ok;
                        any_out |= !ok;
                        if ok {
                            t.a[i] = sample_bspline(ca, ax, ay);
                            t.b[i] = sample_bspline(cb, bx, by);
                        }
                    }
                }
                if any_out {
                    let (ea, eb) = remove_mean_where(&mut t.a[..n], &mut t.b[..n], &t.inside[..n]);
                    t.ws.add_pair(&t.a[..n], &t.b[..n], ea, eb);
                    continue;
                }
            }
        }
        let ea = remove_mean(&mut t.a[..n]);
        let eb = remove_mean(&mut t.b[..n]);
        t.ws.add_pair(&t.a[..n], &t.b[..n], ea, eb);
    }
    if t.ws.pairs() == 0 {
        return (f64::NAN, f64::NAN, 0.0, false);
    }
    t.ws.finish(&mut t.plane[..n]);
    let p = find_peak(&t.plane[..n], ww, wh);
    if p.at_border || !(p.height > 0.0) {
        return (f64::NAN, f64::NAN, p.height, false);
    }
    (node_pred.0 + p.dx, node_pred.1 + p.dy, p.height, true)
}

/// One correlation pass over all nodes.
fn run_pass(
    frames: &[&Image],
    grid: &NodeGrid,
    ww: usize,
    wh: usize,
    pred: Option<&Predictor>,
    masked: &[bool],
) -> VectorField {
    let (width, height) = (frames[0].width, frames[0].height);
    let plan = CorrelationPlan::new(ww, wh);
    let n = ww * wh;
    let results: Vec<(f64, f64, f32, u8)> = (0..grid.len())
        .into_par_iter()
        .map_init(
            || Thread {
                ws: plan.workspace(),
                a: vec![0.0; n],
                b: vec![0.0; n],
                plane: vec![0.0; n],
                disp: Vec::with_capacity(n),
                inside: vec![true; n],
            },
            |t, k| {
                if masked[k] {
                    return (f64::NAN, f64::NAN, 0.0, flag::MASKED);
                }
                let (i, j) = (k % grid.nx, k / grid.nx);
                let (cx, cy) = (grid.x(i), grid.y(j));
                // Window centred on the node, moved inside the image if it
                // would stick out (only possible for enlarged first-pass windows).
                let xs = (cx - (ww as f64 - 1.0) / 2.0)
                    .round()
                    .clamp(0.0, (width - ww) as f64) as usize;
                let ys = (cy - (wh as f64 - 1.0) / 2.0)
                    .round()
                    .clamp(0.0, (height - wh) as f64) as usize;
                let node_pred = match pred {
                    Some(p) => (p.u[k], p.v[k]),
                    None => (0.0, 0.0),
                };
                let (u, v, h, ok) = measure_node(t, frames, xs, ys, ww, wh, pred, node_pred);
                (u, v, h, if ok { flag::VALID } else { flag::NO_PEAK })
            },
        )
        .collect();
    VectorField {
        grid: *grid,
        u: results.iter().map(|r| r.0).collect(),
        v: results.iter().map(|r| r.1).collect(),
        peak: results.iter().map(|r| r.2).collect(),
        flags: results.iter().map(|r| r.3).collect(),
    }
}

fn check_frames(frames: &[&Image]) -> Result<()> {
    if frames.len() < 2 {
        return Err(Error::param(
            "frames",
            format!(
                "{} frame(s) given; correlation needs at least 2",
                frames.len()
            ),
        ));
    }
    let (w, h) = (frames[0].width, frames[0].height);
    for (k, f) in frames.iter().enumerate() {
        if f.width != w || f.height != h || f.data.len() != w * h {
            return Err(Error::param(
                "frames",
                format!(
                    "frame {} is {}x{} px but frame 0 is {}x{} px: all frames must have the same size",
                    k, f.width, f.height, w, h
                ),
            ));
        }
    }
    Ok(())
}

/// Multi-frame, multi-pass PIV on `frames` (≥ 2, same size): displacement
/// per frame step (px) at every node, validated, outliers replaced.
pub fn piv_frames(frames: &[&Image], o: &PivOptions) -> Result<VectorField> {
    check_frames(frames)?;
    let (width, height) = (frames[0].width, frames[0].height);
    let grid = node_grid(width, height, o)?;
    let masked: Vec<bool> = (0..grid.len())
        .map(|k| match &o.mask {
            Some(m) => {
                let x = grid.x(k % grid.nx).round() as usize;
                let y = grid.y(k / grid.nx).round() as usize;
                m[y.min(height - 1) * width + x.min(width - 1)]
            }
            None => false,
        })
        .collect();
    // Masked pixels carry no signal.
    let masked_frames: Vec<Image>;
    let frames: Vec<&Image> = match &o.mask {
        Some(m) => {
            masked_frames = frames
                .iter()
                .map(|f| {
                    let mut g = (*f).clone();
                    for (d, &mm) in g.data.iter_mut().zip(m) {
                        if mm {
                            *d = 0.0;
                        }
                    }
                    g
                })
                .collect();
            masked_frames.iter().collect()
        }
        None => frames.to_vec(),
    };

    let mut field: Option<VectorField> = None;
    let mut coefs: Vec<Image> = Vec::new();
    for pass in 0..o.passes {
        let (mut ww, mut wh) = (o.window_w, o.window_h);
        if pass == 0 && o.passes > 1 && 2 * ww <= width && 2 * wh <= height {
            ww *= 2;
            wh *= 2;
        }
        if pass == 1 {
            coefs = frames.par_iter().map(|f| bspline_coefficients(f)).collect();
        }
        let pred = field.as_ref().map(|f| Predictor {
            grid: &f.grid,
            u: &f.u,
            v: &f.v,
            coefs: &coefs,
        });
        let mut next = run_pass(&frames, &grid, ww, wh, pred.as_ref(), &masked);
        validate::normalized_median_test(
            &next.u,
            &next.v,
            &mut next.flags,
            grid.nx,
            grid.ny,
            o.median,
        );
        validate::replace_invalid(&mut next.u, &mut next.v, &mut next.flags, grid.nx, grid.ny);
        // A predictor needs values everywhere; nodes nothing could fill
        // (masked, or no valid vector at all) predict zero.
        if pass + 1 < o.passes && next.u.iter().any(|x| !x.is_finite()) {
            let mut p = next.clone();
            for k in 0..p.u.len() {
                if !p.u[k].is_finite() || !p.v[k].is_finite() {
                    p.u[k] = 0.0;
                    p.v[k] = 0.0;
                }
            }
            field = Some(p);
        } else {
            field = Some(next);
        }
    }
    let mut f = field.expect("passes >= 1");
    // Restore NaN where the last pass has no value (masked / unfillable).
    for k in 0..f.u.len() {
        if f.flags[k] & flag::MASKED != 0 {
            f.u[k] = f64::NAN;
            f.v[k] = f64::NAN;
        }
    }
    Ok(f)
}
