use std::path::PathBuf;

use clap::Args;
use ebptv::compare::{compare_to_dir, CompareOptions};

#[derive(Args, Debug)]
pub struct CompareArgs {
    /// PTV grid statistics (the `grid` table of `ebptv grid`, any format:
    /// x,y,count,u,v,uu,vv,uv).
    #[arg(long)]
    pub ptv: PathBuf,
    /// PIV statistics (the `piv_mean` table of `ebptv piv`, any format:
    /// x,y,u,v,uu,vv,uv,valid).
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
    let c = compare_to_dir(
        &CompareOptions {
            ptv: a.ptv,
            piv: a.piv,
            min_count: a.min_count,
            calibration: a.calibration,
        },
        &a.out,
    )?;
    for (q, s) in &c.quantities {
        println!(
            "{q:>3}: n {:6}  mean(PTV-PIV) {:+.4e}  rms {:.4e}  (PTV rms {:.4e}, PIV rms {:.4e})",
            s.n, s.mean_diff, s.rms_diff, s.ptv_rms, s.piv_rms
        );
    }
    Ok(())
}
