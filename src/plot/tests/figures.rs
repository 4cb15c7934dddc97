//! Figures: the PNGs decode, have the requested size, show the data, and
//! bad input is a clear error with nothing written. (`ebptv demo` writes
//! the same kinds of figure, for a visual check.)

use std::collections::HashSet;
use std::path::{Path, PathBuf};

use crate::plot::{self, Heatmap, HistogramPlot, LinePlot, Polylines, Series, SeriesStyle};
use crate::Error;

struct Out {
    _tmp: tempfile::TempDir,
    dir: PathBuf,
}

fn out_dir() -> Out {
    let tmp = tempfile::tempdir().unwrap();
    let dir = tmp.path().to_path_buf();
    Out { _tmp: tmp, dir }
}

/// Decode an RGB PNG: (width, height, pixels).
fn decode(path: &Path) -> (u32, u32, Vec<(u8, u8, u8)>) {
    let dec = png::Decoder::new(std::fs::File::open(path).unwrap());
    let mut reader = dec.read_info().unwrap();
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).unwrap();
    assert_eq!(info.color_type, png::ColorType::Rgb);
    let px = buf[..info.buffer_size()]
        .chunks_exact(3)
        .map(|c| (c[0], c[1], c[2]))
        .collect();
    (info.width, info.height, px)
}

fn distinct_colours(px: &[(u8, u8, u8)]) -> usize {
    px.iter().collect::<HashSet<_>>().len()
}

fn no_stray_files(dir: &Path) {
    for e in std::fs::read_dir(dir).unwrap() {
        let name = e.unwrap().file_name().to_string_lossy().into_owned();
        assert!(!name.ends_with(".partial"), "temporary left behind: {name}");
    }
}

fn gaussian_bump(nx: usize, ny: usize) -> Vec<f64> {
    let mut v = Vec::with_capacity(nx * ny);
    for j in 0..ny {
        for i in 0..nx {
            let (x, y) = (i as f64 - nx as f64 * 0.3, j as f64 - ny as f64 * 0.6);
            v.push((-(x * x + y * y) / (0.05 * (nx * nx) as f64)).exp());
        }
    }
    v
}

#[ebptv_macros::unit_test]
fn heatmap_png_decodes_with_requested_size_and_many_colours() {
    let out = out_dir();
    let (nx, ny) = (64, 36);
    let mut values = gaussian_bump(nx, ny);
    // A block of missing data in the top-left corner.
    for j in 0..6 {
        for i in 0..10 {
            values[j * nx + i] = f64::NAN;
        }
    }
    let path = out.dir.join("heatmap.png");
    let map = Heatmap {
        title: "Event count per pixel",
        values: &values,
        nx,
        ny,
        x_range: (0.0, 640.0),
        y_range: (0.0, 360.0),
        colorbar_label: "events",
        diverging: false,
        axes_mm: None,
    };
    plot::heatmap_sized(&path, &map, (1000, 600)).unwrap();
    let (w, h, px) = decode(&path);
    assert_eq!((w, h), (1000, 600));
    assert!(
        distinct_colours(&px) > 200,
        "a smooth field shows many colours"
    );
    let grey = px.iter().filter(|&&c| c == plot::NAN_GREY).count();
    // 60 of 2304 cells are NaN: ~2.6 % of a plot area of roughly 0.5 of the image.
    let frac = grey as f64 / px.len() as f64;
    assert!(frac > 0.005 && frac < 0.03, "NaN grey fraction {frac}");
    no_stray_files(&out.dir);

    // The default-size entry point writes a readable figure too.
    let path2 = out.dir.join("heatmap_default.png");
    plot::heatmap(&path2, &map).unwrap();
    let (w2, h2, _) = decode(&path2);
    assert!(w2 > h2, "640x360 frame gives a landscape figure");
}

#[ebptv_macros::unit_test]
fn diverging_heatmap_and_all_nan_map_render() {
    let out = out_dir();
    let (nx, ny) = (40, 30);
    let values: Vec<f64> = (0..nx * ny)
        .map(|k| ((k % nx) as f64 / nx as f64 - 0.5) * ((k / nx) as f64 / ny as f64))
        .collect();
    let path = out.dir.join("diverging.png");
    plot::heatmap(
        &path,
        &Heatmap {
            title: "u - u_PIV",
            values: &values,
            nx,
            ny,
            x_range: (0.0, 400.0),
            y_range: (0.0, 300.0),
            colorbar_label: "du (px/s)",
            diverging: true,
            axes_mm: None,
        },
    )
    .unwrap();
    let (_, _, px) = decode(&path);
    assert!(distinct_colours(&px) > 100);
    // Reds and blues both present.
    assert!(px.iter().any(|c| c.0 > 150 && c.2 < 80));
    assert!(px.iter().any(|c| c.2 > 150 && c.0 < 80));

    let nan = vec![f64::NAN; 12];
    let path = out.dir.join("all_nan.png");
    plot::heatmap(
        &path,
        &Heatmap {
            title: "empty",
            values: &nan,
            nx: 4,
            ny: 3,
            x_range: (0.0, 4.0),
            y_range: (0.0, 3.0),
            colorbar_label: "",
            diverging: false,
            axes_mm: None,
        },
    )
    .unwrap();
    let (_, _, px) = decode(&path);
    let grey = px.iter().filter(|&&c| c == plot::NAN_GREY).count();
    assert!(
        grey as f64 > 0.3 * px.len() as f64,
        "an all-NaN map is grey"
    );
}

#[ebptv_macros::unit_test]
fn heatmap_rejects_bad_input_without_writing() {
    let out = out_dir();
    let path = out.dir.join("bad.png");
    let v = vec![1.0; 10];
    let base = |values: &'static [f64]| Heatmap {
        title: "bad",
        values,
        nx: 4,
        ny: 3,
        x_range: (0.0, 1.0),
        y_range: (0.0, 1.0),
        colorbar_label: "",
        diverging: false,
        axes_mm: None,
    };
    let leak: &'static [f64] = Box::leak(v.into_boxed_slice());
    let e = plot::heatmap(&path, &base(leak)).unwrap_err();
    assert!(matches!(e, Error::InvalidParameter { .. }), "{e}");
    assert!(e.to_string().contains("10 values"), "{e}");

    let twelve: &'static [f64] = Box::leak(vec![1.0; 12].into_boxed_slice());
    let mut m = base(twelve);
    m.x_range = (0.0, f64::NAN);
    let e = plot::heatmap(&path, &m).unwrap_err();
    assert!(e.to_string().contains("x_range"), "{e}");
    let mut m = base(twelve);
    m.y_range = (5.0, 5.0);
    assert!(plot::heatmap(&path, &m).is_err());
    let inf: &'static [f64] = Box::leak(
        [1.0, f64::INFINITY]
            .iter()
            .copied()
            .chain(std::iter::repeat_n(0.0, 10))
            .collect::<Vec<_>>()
            .into_boxed_slice(),
    );
    let e = plot::heatmap(&path, &base(inf)).unwrap_err();
    assert!(e.to_string().contains("infinity"), "{e}");
    let mut m = base(twelve);
    m.nx = 0;
    assert!(plot::heatmap(&path, &m).is_err());
    assert!(plot::heatmap_sized(&path, &base(twelve), (10, 10)).is_err());
    assert!(plot::heatmap_with_range(&path, &base(twelve), (400, 300), (1.0, 0.0)).is_err());
    assert!(!path.exists());
    no_stray_files(&out.dir);
}

#[ebptv_macros::unit_test]
fn line_plot_with_legend_log_axes_and_markers() {
    let out = out_dir();
    let f: Vec<f64> = (1..400).map(|k| k as f64 * 0.5).collect();
    let spectrum: Vec<f64> = f
        .iter()
        .map(|&f| 1.0 / (1.0 + (f / 20.0).powi(2)) + 3.0 * (-((f - 35.4) / 1.5).powi(2)).exp())
        .collect();
    let noise: Vec<f64> = f
        .iter()
        .map(|&f| 1e-3 * (1.0 + 0.1 * (f * 7.0).sin()))
        .collect();
    let path = out.dir.join("spectrum.png");
    plot::line_plot(
        &path,
        &LinePlot {
            title: "Power spectrum",
            x_label: "f (Hz)",
            y_label: "PSD ((px/s)^2/Hz)",
            series: vec![
                Series {
                    label: "u",
                    x: &f,
                    y: &spectrum,
                    style: SeriesStyle::Line,
                },
                Series {
                    label: "noise floor",
                    x: &f,
                    y: &noise,
                    style: SeriesStyle::Points,
                },
            ],
            log_x: true,
            log_y: true,
            vlines: vec![(35.4, "shedding 35.4 Hz")],
        },
    )
    .unwrap();
    let (w, h, px) = decode(&path);
    assert_eq!((w, h), plot::LINE_PLOT_SIZE);
    // The first two series colours both appear (lines and legend).
    assert!(px.contains(&(31, 119, 180)), "series 1 colour drawn");
    assert!(px.contains(&(255, 127, 14)), "series 2 colour drawn");

    // Linear axes, steps, custom size.
    let x: Vec<f64> = (0..50).map(|k| k as f64 * 4.0).collect();
    let y: Vec<f64> = x
        .iter()
        .map(|&x| (-(x - 100.0).powi(2) / 800.0).exp())
        .collect();
    let path = out.dir.join("latency.png");
    plot::line_plot_sized(
        &path,
        &LinePlot {
            title: "Folded latency",
            x_label: "t mod T (us)",
            y_label: "fraction",
            series: vec![Series {
                label: "",
                x: &x,
                y: &y,
                style: SeriesStyle::Steps,
            }],
            log_x: false,
            log_y: false,
            vlines: vec![(100.0, "peak")],
        },
        (640, 400),
    )
    .unwrap();
    let (w, h, px) = decode(&path);
    assert_eq!((w, h), (640, 400));
    assert!(px.contains(&(31, 119, 180)));
}

#[ebptv_macros::unit_test]
fn line_plot_rejects_bad_series() {
    let out = out_dir();
    let path = out.dir.join("bad_line.png");
    let mk = |series: Vec<Series<'static>>, log_y: bool| LinePlot {
        title: "bad",
        x_label: "x",
        y_label: "y",
        series,
        log_x: false,
        log_y,
        vlines: vec![],
    };
    let e = plot::line_plot(&path, &mk(vec![], false)).unwrap_err();
    assert!(e.to_string().contains("no series"), "{e}");
    let s = |x: &'static [f64], y: &'static [f64]| Series {
        label: "s",
        x,
        y,
        style: SeriesStyle::Line,
    };
    let e = plot::line_plot(&path, &mk(vec![s(&[], &[])], false)).unwrap_err();
    assert!(e.to_string().contains("empty"), "{e}");
    let e = plot::line_plot(&path, &mk(vec![s(&[1.0, 2.0], &[1.0])], false)).unwrap_err();
    assert!(e.to_string().contains("2 x values but 1 y values"), "{e}");
    let e = plot::line_plot(
        &path,
        &mk(vec![s(&[1.0, 2.0], &[f64::NAN, f64::INFINITY])], false),
    )
    .unwrap_err();
    assert!(e.to_string().contains("no drawable point"), "{e}");
    let e = plot::line_plot(&path, &mk(vec![s(&[1.0, 2.0], &[0.0, -1.0])], true)).unwrap_err();
    assert!(e.to_string().contains("log axis"), "{e}");
    // A constant series is fine (the range is widened).
    plot::line_plot(&path, &mk(vec![s(&[1.0, 2.0], &[3.0, 3.0])], false)).unwrap();
    assert!(path.exists());
    no_stray_files(&out.dir);
}

#[ebptv_macros::unit_test]
fn histogram_plot_overlays_measured_and_simulated() {
    let out = out_dir();
    let edges: Vec<f64> = (0..=20).map(|k| k as f64 * 10.0).collect();
    let a: Vec<f64> = (0..20)
        .map(|k| (-(k as f64 - 9.0).powi(2) / 8.0).exp())
        .collect();
    let b: Vec<f64> = (0..20)
        .map(|k| (-(k as f64 - 11.0).powi(2) / 12.0).exp())
        .collect();
    let path = out.dir.join("hist.png");
    plot::histogram_plot(
        &path,
        &HistogramPlot {
            title: "Events per cluster",
            x_label: "events",
            y_label: "fraction",
            edges: &edges,
            histograms: vec![("measured", &a), ("simulated", &b)],
            log_y: false,
        },
    )
    .unwrap();
    let (_, _, px) = decode(&path);
    assert!(px.contains(&(31, 119, 180)) && px.contains(&(255, 127, 14)));
    let e = plot::histogram_plot(
        &path,
        &HistogramPlot {
            title: "bad",
            x_label: "",
            y_label: "",
            edges: &edges,
            histograms: vec![("short", &a[..5])],
            log_y: false,
        },
    )
    .unwrap_err();
    assert!(e.to_string().contains("5 counts for 20 bins"), "{e}");
}

#[ebptv_macros::unit_test]
fn polylines_coloured_by_value() {
    let out = out_dir();
    let lines: Vec<Vec<(f64, f64)>> = (0..30)
        .map(|k| {
            let y0 = 10.0 + k as f64 * 10.0;
            (0..20)
                .map(|i| (20.0 + i as f64 * 25.0, y0 + 8.0 * (i as f64 * 0.4).sin()))
                .collect()
        })
        .collect();
    let speeds: Vec<f64> = (0..30).map(|k| 100.0 + k as f64 * 10.0).collect();
    let path = out.dir.join("tracks.png");
    plot::polylines_sized(
        &path,
        &Polylines {
            title: "Tracks",
            width: 640.0,
            height: 360.0,
            lines: &lines,
            values: &speeds,
            colorbar_label: "speed (px/s)",
        },
        (900, 560),
    )
    .unwrap();
    let (w, h, px) = decode(&path);
    assert_eq!((w, h), (900, 560));
    // Both ends of viridis appear: lowest and highest speed lines (and bar).
    assert!(px.contains(&plot::viridis(0.0)) && px.contains(&plot::viridis(1.0)));
    assert!(distinct_colours(&px) > 100);

    let e = plot::polylines(
        &path,
        &Polylines {
            title: "bad",
            width: 640.0,
            height: 360.0,
            lines: &lines,
            values: &speeds[..3],
            colorbar_label: "",
        },
    )
    .unwrap_err();
    assert!(e.to_string().contains("3 values for 30 lines"), "{e}");
    let e = plot::polylines(
        &path,
        &Polylines {
            title: "bad",
            width: f64::INFINITY,
            height: 360.0,
            lines: &lines,
            values: &speeds,
            colorbar_label: "",
        },
    )
    .unwrap_err();
    assert!(e.to_string().contains("width"), "{e}");
}
