use std::path::PathBuf;

use clap::Args;
use ebptv::piv::images::{expand_inputs, load_frames};
use ebptv::piv::output::write_vectors_table;
use ebptv::piv::piv_frames;

use super::piv::CorrelationArgs;
use rayon::prelude::*;

#[derive(Args, Debug)]
pub struct PivImagesArgs {
    /// Images in time order: PNG, TIFF (8/16-bit grey, palette, RGB; every
    /// page of a multi-page stack is a frame) or BMP files, folders of
    /// such files, or quoted patterns such as 'run/frame*.tif'; folders
    /// and patterns are read in natural order (frame2, then frame10).
    #[arg(required = true, num_args = 1..)]
    pub images: Vec<PathBuf>,
    #[command(flatten)]
    pub correlation: CorrelationArgs,
    /// Frames per evaluation: 2 = independent pairs (A B), (C D)...;
    /// N > 2 = sum of correlation over N consecutive images.
    #[arg(long, default_value_t = 2)]
    pub frames: usize,
    /// Treat the list as a sequence (1-2, 2-3, ...) instead of pairs (1-2, 3-4, ...).
    #[arg(long)]
    pub sequence: bool,
    /// Output folder: one vectors_NNNNN table (x,y,u,v,flag; .parquet, or
    /// .csv / .npy with --table-format) per evaluation, NNNNN its first
    /// frame.
    #[arg(long)]
    pub out: PathBuf,
}

pub fn run(a: PivImagesArgs, tables: Option<ebptv::table::TableFormat>) -> anyhow::Result<()> {
    if a.frames < 2 {
        anyhow::bail!("invalid parameter `frames`: {} (need at least 2)", a.frames);
    }
    let o = a.correlation.options();
    let files = expand_inputs(&a.images)?;
    // Decoded in parallel (wall time; the CPU time is the same).
    let loaded = files
        .par_iter()
        .map(|p| load_frames(p))
        .collect::<Result<Vec<_>, _>>()?;
    // Each frame remembers its file (and page) for error messages.
    let mut imgs = Vec::new();
    let mut names = Vec::new();
    for (p, l) in files.iter().zip(loaded) {
        if l.colour {
            eprintln!(
                "note: {} is a colour image; its luminance is used",
                p.display()
            );
        }
        let pages = l.frames.len();
        for (k, im) in l.frames.into_iter().enumerate() {
            imgs.push(im);
            names.push(if pages > 1 {
                format!("{} (page {})", p.display(), k + 1)
            } else {
                p.display().to_string()
            });
        }
    }
    if imgs.len() < a.frames {
        anyhow::bail!(
            "{} frame(s) given, --frames {} needs at least that many",
            imgs.len(),
            a.frames
        );
    }
    let format = tables.unwrap_or_default();
    let step = if a.sequence { 1 } else { a.frames };
    let starts: Vec<usize> = (0..=imgs.len() - a.frames).step_by(step).collect();
    ebptv::io::atomic::create_output_dir(&a.out)?;
    let bar = indicatif::ProgressBar::new(starts.len() as u64);
    let t0 = std::time::Instant::now();
    let c0 = process_cpu_seconds();
    // The fields stay in memory until all are measured (a field is a few
    // kB; the images, already all loaded, are far larger), so that the
    // timing below is of the correlation alone — like a peer's call that
    // returns arrays — and the table writing is timed on its own.
    let fields: Vec<_> = starts
        .par_iter()
        .map(|&s| -> anyhow::Result<_> {
            let refs: Vec<_> = imgs[s..s + a.frames].iter().collect();
            let f = piv_frames(&refs, &o).map_err(|e| anyhow::anyhow!("{}: {e}", names[s]))?;
            bar.inc(1);
            Ok(f)
        })
        .collect::<anyhow::Result<_>>()?;
    let dt = t0.elapsed().as_secs_f64();
    let cpu = process_cpu_seconds() - c0;
    starts.par_iter().zip(&fields).try_for_each(|(&s, f)| {
        write_vectors_table(&a.out, &format!("vectors_{s:05}"), format, f).map(|_| ())
    })?;
    bar.finish_and_clear();
    let cpu_write = process_cpu_seconds() - c0 - cpu;
    let n: usize = fields.iter().map(|f| f.grid.len()).sum();
    eprintln!(
        "{} field(s), {} vectors in {:.3} s ({:.0} vectors/s), {:.4} CPU-s ({:.0} vectors per CPU-s); table writing {:.4} CPU-s",
        starts.len(),
        n,
        dt,
        n as f64 / dt,
        cpu,
        n as f64 / cpu,
        cpu_write
    );
    Ok(())
}

/// CPU time (user + system, all threads) of this process so far, in
/// seconds: correlation cost independent of the machine's load, comparable
/// with a peer's process CPU time around its calls (images in memory).
fn process_cpu_seconds() -> f64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime writes only into the timespec passed.
    let rc = unsafe { libc::clock_gettime(libc::CLOCK_PROCESS_CPUTIME_ID, &mut ts) };
    if rc != 0 {
        return f64::NAN;
    }
    ts.tv_sec as f64 + ts.tv_nsec as f64 * 1e-9
}
