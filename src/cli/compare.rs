use std::path::PathBuf;

use clap::Args;
use ebptv::compare::{compare, read_table};
use ebptv::io::atomic::AtomicFile;
use ebptv::plot::{heatmap, line_plot, Heatmap, LinePlot, Series, SeriesStyle};

#[derive(Args, Debug)]
pub struct CompareArgs {
    /// PTV grid statistics (`grid.csv`: x,y,count,u,v,uu,vv,uv).
    #[arg(long)]
    pub ptv: PathBuf,
    /// PIV statistics (`piv_mean.csv`: x,y,u,v,uu,vv,uv,valid).
    #[arg(long)]
    pub piv: PathBuf,
    /// Ignore PTV bins with fewer samples.
    #[arg(long, default_value_t = 1.0)]
    pub min_count: f64,
    /// A `calib.toml`: compare.json gains the differences in m/s and
    /// m²/s² (`physical`), and the figures are in mm and m/s.
    #[arg(long)]
    pub calibration: Option<PathBuf>,
    /// Output folder: compare.json (differences per component) and
    /// profiles.png.
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(a: CompareArgs) -> anyhow::Result<()> {
    let calib = a
        .calibration
        .as_deref()
        .map(ebptv::calib::Calibration::from_file)
        .transpose()?;
    let ptv = read_table(&a.ptv, &["x", "y", "count", "u", "v", "uu", "vv", "uv"])?;
    let piv = read_table(&a.piv, &["x", "y", "u", "v", "uu", "vv", "uv", "valid"])?;
    let c = compare(&ptv, &piv, a.min_count)?;
    ebptv::io::atomic::create_output_dir(&a.out)?;
    let mut json = serde_json::json!({
        "ptv": a.ptv.display().to_string(),
        "piv": a.piv.display().to_string(),
        "resampling": c.resampling,
        "ptv_bins": c.ptv_bins,
        "compared_bins": c.compared_bins,
    });
    for (q, s) in &c.quantities {
        json[q] = serde_json::to_value(s)?;
    }
    // Factor of a quantity from px/s or (px/s)² to m/s or m²/s² (signed:
    // v and uv change sign with an upward y axis).
    let factor = |q: &str| -> f64 {
        match &calib {
            None => 1.0,
            Some(cal) => {
                let (k, ky) = cal.velocity_px_s_to_m_s(1.0, 1.0);
                match q {
                    "u" => k,
                    "v" => ky,
                    "uv" => k * ky,
                    _ => k * k,
                }
            }
        }
    };
    if let Some(cal) = &calib {
        let mut phys = serde_json::json!({ "px_per_mm": cal.px_per_mm });
        for (q, s) in &c.quantities {
            let k = factor(q);
            let unit = if q.len() == 1 { "m_s" } else { "m2_s2" };
            phys[q] = serde_json::json!({
                "n": s.n,
                format!("mean_diff_{unit}"): s.mean_diff * k,
                format!("rms_diff_{unit}"): s.rms_diff * k.abs(),
                format!("ptv_rms_{unit}"): s.ptv_rms * k.abs(),
                format!("piv_rms_{unit}"): s.piv_rms * k.abs(),
            });
        }
        json["physical"] = phys;
    }
    let (lv, ls) = if calib.is_some() {
        ("m/s", "(m/s)^2")
    } else {
        ("px/s", "(px/s)^2")
    };
    AtomicFile::write_all_to(
        a.out.join("compare.json"),
        serde_json::to_string_pretty(&json)?.as_bytes(),
    )?;
    let (nx, ny) = (c.grid.xs.len(), c.grid.ys.len());
    let xr = (c.grid.xs[0], *c.grid.xs.last().unwrap());
    let yr = (c.grid.ys[0], *c.grid.ys.last().unwrap());
    for (q, map) in &c.diff_maps {
        let title = format!("PTV - PIV: {q}");
        let k = factor(q);
        let map: Vec<f64> = map.iter().map(|v| v * k).collect();
        heatmap(
            &a.out.join(format!("diff_{q}.png")),
            &Heatmap {
                title: &title,
                values: &map,
                nx,
                ny,
                x_range: xr,
                y_range: yr,
                colorbar_label: if q.len() == 1 { lv } else { ls },
                diverging: true,
                axes_mm: calib.as_ref(),
            },
        )?;
    }
    let ys: Vec<f64> = c
        .profiles
        .iter()
        .map(|p| calib.as_ref().map_or(p.0, |cal| cal.px_to_mm(0.0, p.0).1))
        .collect();
    let ks = [factor("u"), factor("u"), factor("v"), factor("v")];
    let cols: Vec<Vec<f64>> = (1..5)
        .map(|i| {
            c.profiles
                .iter()
                .map(|p| [p.1, p.2, p.3, p.4][i - 1] * ks[i - 1])
                .collect()
        })
        .collect();
    let (y_label, v_label) = if calib.is_some() {
        ("y (mm)", "velocity (m/s)")
    } else {
        ("y (px)", "velocity (px/s)")
    };
    line_plot(
        &a.out.join("profiles.png"),
        &LinePlot {
            title: "Column-averaged profiles",
            x_label: y_label,
            y_label: v_label,
            series: vec![
                Series {
                    label: "PTV u",
                    x: &ys,
                    y: &cols[0],
                    style: SeriesStyle::Points,
                },
                Series {
                    label: "PIV u",
                    x: &ys,
                    y: &cols[1],
                    style: SeriesStyle::Line,
                },
                Series {
                    label: "PTV v",
                    x: &ys,
                    y: &cols[2],
                    style: SeriesStyle::Points,
                },
                Series {
                    label: "PIV v",
                    x: &ys,
                    y: &cols[3],
                    style: SeriesStyle::Line,
                },
            ],
            log_x: false,
            log_y: false,
            vlines: vec![],
        },
    )?;
    for (q, s) in &c.quantities {
        println!(
            "{q:>3}: n {:6}  mean(PTV-PIV) {:+.4e}  rms {:.4e}  (PTV rms {:.4e}, PIV rms {:.4e})",
            s.n, s.mean_diff, s.rms_diff, s.ptv_rms, s.piv_rms
        );
    }
    Ok(())
}
