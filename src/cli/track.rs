//! `ebptv track`: recording (or particles.csv) → particles → tracks.

use std::io::BufRead;
use std::path::{Path, PathBuf};

use anyhow::Context;
use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};

use ebptv::cluster::{ClusterParams, Particle};
use ebptv::pulses::PulseOptions;
use ebptv::track::{
    track_recording, ParticlesCsvWriter, PtvSink, PtvStream, SummaryAcc, Track, TrackParams,
    TrackerStats, TracksCsvWriter,
};

#[derive(Args, Debug)]
pub struct TrackArgs {
    /// A recording (any supported event format) or a `particles.csv`
    /// (`pulse,t_us,x,y,n_events`: linking only).
    pub input: PathBuf,
    /// Output directory (created if missing).
    #[arg(long)]
    pub out: PathBuf,
    /// Also bin the tracks onto a grid in one go, into OUT/grid: the options
    /// of `ebptv grid` as one string, e.g. --grid "--bin 16 --fit linear"
    /// (an empty string takes grid's defaults).
    #[arg(long, allow_hyphen_values = true)]
    pub grid: Option<String>,
    /// Clustering radius (px): events on pixels at most this far apart join.
    #[arg(long, default_value_t = 1.5)]
    pub radius: f64,
    /// Largest particle displacement between pulses (px).
    #[arg(long, default_value_t = 10.0)]
    pub max_disp: f64,
    /// Fewest detections of a kept track.
    #[arg(long, default_value_t = 5)]
    pub min_length: usize,
    /// Missed pulses a track may bridge.
    #[arg(long, default_value_t = 2)]
    pub gap: u32,
    /// Nominal pulse frequency (Hz) when pulse times are estimated from the
    /// events (no trigger channel).
    #[arg(long)]
    pub pulse_hz: Option<f64>,
    /// Ignore the trigger channel and estimate pulse times from the events.
    #[arg(long)]
    pub ignore_triggers: bool,
    /// Cluster OFF events too (default: ON events only).
    #[arg(long)]
    pub all_polarities: bool,
    /// Smallest cluster kept (events).
    #[arg(long, default_value_t = 1)]
    pub min_events: u32,
    /// Largest cluster kept (events).
    #[arg(long, default_value_t = 64)]
    pub max_events: u32,
    /// File of pixels to ignore, one `x,y` per line.
    #[arg(long)]
    pub hot_pixels: Option<PathBuf>,
    /// Uniform mean-flow prior `U,V` (px/s) for track initialisation.
    #[arg(long, value_delimiter = ',', num_args = 2)]
    pub prior: Option<Vec<f64>>,
    /// Pulses shown in tracks.png (from the first pulse); a short window
    /// keeps individual tracks visible at paper seeding densities.
    #[arg(long, default_value_t = 20)]
    pub plot_pulses: i64,
    /// Also write tracks.npy (a structured array with the tracks.csv
    /// columns). Holds every track point in memory until the end.
    #[arg(long)]
    pub npy: bool,
    /// Pulses clustered per parallel batch.
    #[arg(long, default_value_t = 512)]
    pub batch: usize,
}

/// The outputs of one run: a [`PtvSink`] that writes files, keeps the
/// summary, the figure's polylines and the progress bar.
struct Pipeline {
    particles_out: ParticlesCsvWriter,
    tracks_out: TracksCsvWriter,
    summary: SummaryAcc,
    first_pulse: Option<i64>,
    plot_pulses: i64,
    plot_lines: Vec<Vec<(f64, f64)>>,
    plot_speeds: Vec<f64>,
    /// Columns of tracks.npy when requested.
    npy: Option<[Vec<f64>; 7]>,
    width: f64,
    height: f64,
    progress: ProgressBar,
}

impl PtvSink for Pipeline {
    fn particles(&mut self, pulse: i64, _t_us: f64, ps: &[Particle]) -> ebptv::Result<()> {
        self.first_pulse.get_or_insert(pulse);
        for p in ps {
            self.width = self.width.max(p.x + 1.0);
            self.height = self.height.max(p.y + 1.0);
        }
        self.particles_out.write(ps)?;
        self.progress.inc(1);
        Ok(())
    }

    fn tracks(&mut self, tracks: &[Track]) -> ebptv::Result<()> {
        self.emit(tracks)
    }
}

impl Pipeline {
    fn emit(&mut self, tracks: &[Track]) -> ebptv::Result<()> {
        self.tracks_out.write(tracks)?;
        self.summary.add(tracks);
        if let Some(cols) = &mut self.npy {
            for t in tracks {
                for p in &t.points {
                    for (c, v) in cols.iter_mut().zip([
                        t.id as f64,
                        p.pulse as f64,
                        p.t_us,
                        p.x,
                        p.y,
                        p.u,
                        p.v,
                    ]) {
                        c.push(v);
                    }
                }
            }
        }
        let end = self.first_pulse.unwrap_or(0) + self.plot_pulses;
        for t in tracks {
            let pts: Vec<(f64, f64)> = t
                .points
                .iter()
                .filter(|p| p.pulse < end)
                .map(|p| (p.x, p.y))
                .collect();
            if pts.len() >= 2 {
                let speed =
                    t.points.iter().map(|p| p.u.hypot(p.v)).sum::<f64>() / t.points.len() as f64;
                self.plot_lines.push(pts);
                self.plot_speeds.push(speed);
            }
        }
        Ok(())
    }

    fn finish(
        mut self,
        stats: &TrackerStats,
        out: &Path,
        width: Option<f64>,
        height: Option<f64>,
    ) -> anyhow::Result<()> {
        self.progress.finish_and_clear();
        let summary = self.summary.summary(stats);
        // Outputs appear together at the end (each atomically).
        self.particles_out.finish()?;
        self.tracks_out.finish()?;
        ebptv::track::write_summary_json(&out.join("summary.json"), &summary)?;
        if let Some(cols) = self.npy.take() {
            let [id, pulse, t, x, y, u, v] = cols;
            use ebptv::io::npy::NpyColumn;
            let id: Vec<u64> = id.iter().map(|&a| a as u64).collect();
            let pulse: Vec<i64> = pulse.iter().map(|&a| a as i64).collect();
            ebptv::io::npy::write_npy_table(
                out.join("tracks.npy"),
                &[
                    ("track_id", NpyColumn::U64(&id)),
                    ("pulse", NpyColumn::I64(&pulse)),
                    ("t_us", NpyColumn::F64(&t)),
                    ("x", NpyColumn::F64(&x)),
                    ("y", NpyColumn::F64(&y)),
                    ("u", NpyColumn::F64(&u)),
                    ("v", NpyColumn::F64(&v)),
                ],
            )?;
        }
        ebptv::plot::polylines(
            &out.join("tracks.png"),
            &ebptv::plot::Polylines {
                title: &format!(
                    "tracks, pulses {}..{}",
                    self.first_pulse.unwrap_or(0),
                    self.first_pulse.unwrap_or(0) + self.plot_pulses
                ),
                width: width.unwrap_or(self.width.max(1.0)),
                height: height.unwrap_or(self.height.max(1.0)),
                lines: &self.plot_lines,
                values: &self.plot_speeds,
                colorbar_label: "speed (px/s)",
            },
        )?;
        eprintln!(
            "{} pulses, {} particles, {} tracks ({:.1} % of particles on tracks, mean length {:.1}) → {}",
            summary.pulses,
            summary.particles,
            summary.tracks,
            100.0 * summary.fraction_on_tracks,
            summary.mean_track_length,
            out.display()
        );
        Ok(())
    }
}

/// True when the file's first line looks like a particles.csv header (has
/// a `pulse` column; event CSVs do not). Missing columns are then reported
/// by the particles.csv reader.
fn is_particles_csv(path: &Path) -> bool {
    let Ok(f) = std::fs::File::open(path) else {
        return false;
    };
    let mut line = String::new();
    if std::io::BufReader::new(f).read_line(&mut line).is_err() {
        return false;
    }
    let cols: Vec<&str> = line.trim().split(',').map(|c| c.trim()).collect();
    cols.contains(&"pulse")
}

fn read_hot_pixels(path: &Path) -> anyhow::Result<std::collections::HashSet<(u16, u16)>> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    let mut set = std::collections::HashSet::new();
    for (i, line) in text.lines().enumerate() {
        let f: Vec<&str> = line.split(',').map(|s| s.trim()).collect();
        if f.len() < 2 || line.trim().is_empty() {
            continue;
        }
        match (f[0].parse::<u16>(), f[1].parse::<u16>()) {
            (Ok(x), Ok(y)) => {
                set.insert((x, y));
            }
            _ if i == 0 => {} // header
            _ => anyhow::bail!(
                "{}: line {}: expected `x,y` pixel coordinates, got `{line}`",
                path.display(),
                i + 1
            ),
        }
    }
    Ok(set)
}

pub fn run(args: TrackArgs) -> anyhow::Result<()> {
    let grid = args.grid.clone();
    let out = args.out.clone();
    // Check the grid options before the (long) tracking run.
    let grid_cli = grid
        .map(|g| {
            let mut argv = vec!["ebptv".to_string(), "grid".into()];
            argv.push(out.join("tracks.csv").display().to_string());
            argv.extend(["--out".into(), out.join("grid").display().to_string()]);
            argv.extend(g.split_whitespace().map(String::from));
            <super::Cli as clap::Parser>::try_parse_from(&argv)
                .map_err(|e| anyhow::anyhow!("--grid \"{g}\": {e}"))
        })
        .transpose()?;
    run_tracking(args)?;
    match grid_cli {
        Some(cli) => super::run(cli),
        None => Ok(()),
    }
}

fn run_tracking(args: TrackArgs) -> anyhow::Result<()> {
    let cluster = ClusterParams {
        radius: args.radius,
        on_only: !args.all_polarities,
        min_events: args.min_events,
        max_events: args.max_events,
        hot_pixels: match &args.hot_pixels {
            Some(p) => read_hot_pixels(p)?,
            None => Default::default(),
        },
    };
    let mut tparams = TrackParams {
        max_disp: args.max_disp,
        min_length: args.min_length,
        max_gap: args.gap,
        ..Default::default()
    };
    if let Some(p) = &args.prior {
        tparams.prior = Some(ebptv::track::FlowPrior::uniform(p[0], p[1]));
    }
    let mut stream = PtvStream::new(cluster, tparams, args.batch)?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("creating {}", args.out.display()))?;

    let progress = ProgressBar::new_spinner();
    progress.set_style(
        ProgressStyle::with_template("{spinner} {elapsed} {pos} pulses  {msg}")
            .expect("valid template"),
    );
    progress.enable_steady_tick(std::time::Duration::from_millis(200));
    let mut pipe = Pipeline {
        particles_out: ParticlesCsvWriter::create(&args.out.join("particles.csv"))?,
        tracks_out: TracksCsvWriter::create(&args.out.join("tracks.csv"))?,
        summary: SummaryAcc::default(),
        first_pulse: None,
        plot_pulses: args.plot_pulses,
        plot_lines: Vec::new(),
        plot_speeds: Vec::new(),
        npy: args.npy.then(Default::default),
        width: 0.0,
        height: 0.0,
        progress,
    };

    if is_particles_csv(&args.input) {
        let particles = ebptv::track::read_particles_csv(&args.input)?;
        let mut order: Vec<usize> = (0..particles.len()).collect();
        order.sort_by_key(|&i| particles[i].pulse);
        let sorted: Vec<Particle> = order.iter().map(|&i| particles[i]).collect();
        let mut s = 0;
        while s < sorted.len() {
            let mut e = s;
            while e < sorted.len() && sorted[e].pulse == sorted[s].pulse {
                e += 1;
            }
            stream.push_particles(sorted[s].pulse, sorted[s].t_us, &sorted[s..e], &mut pipe)?;
            s = e;
        }
        let stats = stream.finish(&mut pipe)?;
        return pipe.finish(&stats, &args.out, None, None);
    }

    let opts = PulseOptions {
        pulse_hz: args.pulse_hz,
        ignore_triggers: args.ignore_triggers,
        ..Default::default()
    };
    let geometry = ebptv::io::open(&args.input)?.info().geometry;
    let progress = pipe.progress.clone();
    let (report, stats, unassigned) = track_recording(
        &|| ebptv::io::open(&args.input),
        &opts,
        stream,
        &mut pipe,
        &mut |s| {
            let (particles, active) = s.progress();
            progress.set_message(format!(
                "{} events, {particles} particles, {active} active tracks",
                s.events()
            ));
        },
    )?;
    if unassigned > 0 {
        pipe.progress.println(format!(
            "{unassigned} events could not be attributed to a pulse"
        ));
    }
    // Written with the other outputs, once tracking succeeded.
    let json = serde_json::to_vec_pretty(&report)?;
    ebptv::io::atomic::AtomicFile::write_all_to(args.out.join("pulses.json"), &json)?;
    pipe.finish(
        &stats,
        &args.out,
        geometry.map(|g| g.width as f64),
        geometry.map(|g| g.height as f64),
    )
}
