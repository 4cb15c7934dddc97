//! `ebptv track`: recording (or particles.csv) → particles → tracks.

use std::io::BufRead;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use anyhow::Context;
use clap::Args;
use indicatif::ProgressBar;

use ebptv::cluster::Particle;
use ebptv::pulses::PulseOptions;
use ebptv::track::{
    track_recording, Linker, ParticlesCsvWriter, PtvSink, PtvStream, SummaryAcc, Track,
    TrackConfig, TrackerStats, TracksCsvWriter, TracksNpyWriter,
};

#[derive(Args, Debug)]
pub struct TrackArgs {
    /// A recording (any supported event format) or a `particles.csv`
    /// (`pulse,t_us,x,y,n_events`: linking only).
    pub input: PathBuf,
    /// Output directory (created if missing). It also receives
    /// `params.toml`, every option of the run, for --params.
    #[arg(long)]
    pub out: PathBuf,
    /// Largest distance (px) a particle moves between two pulses: new
    /// tracks look this far for their second position, and no track looks
    /// further. Set it a little above the fastest motion [default: 10].
    #[arg(long)]
    pub max_disp: Option<f64>,
    /// Pulses in a row a track may miss and still go on; the missed
    /// positions are filled in and marked `interpolated` [default: 1].
    #[arg(long)]
    pub gap: Option<u32>,
    /// Shortest track kept, in detections (at least 4); shorter ones that
    /// move with their neighbours are kept too [default: 5].
    #[arg(long)]
    pub min_length: Option<usize>,
    /// Events on pixels at most this far apart (px) make one particle
    /// image [default: 1.5].
    #[arg(long)]
    pub radius: Option<f64>,
    /// Mean flow `U,V` (px/s): new tracks look for their second position
    /// where this flow carries the first, which helps in fast flows.
    #[arg(long, value_delimiter = ',', num_args = 2)]
    pub prior: Option<Vec<f64>>,
    /// Pulse frequency (Hz), needed when the recording has no trigger
    /// channel and the pulse times are found from the events.
    #[arg(long)]
    pub pulse_hz: Option<f64>,
    /// Find the pulse times from the events even when the recording has
    /// trigger events.
    #[arg(long)]
    pub ignore_triggers: bool,
    /// Track even when the events show no bursts locked to pulses (see
    /// `ebptv pulses`).
    #[arg(long)]
    pub force_pulses: bool,
    /// Use OFF events too (default: ON events only).
    #[arg(long)]
    pub all_polarities: bool,
    /// File of pixels to ignore (hot or stuck pixels), one `x,y` per line.
    #[arg(long)]
    pub hot_pixels: Option<PathBuf>,
    /// Also bin the tracks onto a grid in one go, into OUT/grid: the options
    /// of `ebptv grid` as one string, e.g. --grid "--bin 16 --fit linear"
    /// (an empty string takes grid's defaults).
    #[arg(long, allow_hyphen_values = true)]
    pub grid: Option<String>,
    /// Read every option of the run from a TOML file: the tracker's parts
    /// ([track.gates], [track.init], [track.stitch], [track.fit]), the
    /// clustering ([cluster]) and run options such as tracks.npy output,
    /// the plot window, batching and the sliced linker ([run]). Keys left
    /// out take their defaults; options given here override the file. A
    /// run's OUT/params.toml is such a file.
    #[arg(long)]
    pub params: Option<PathBuf>,
}

/// What the tracking thread hands to the writer thread.
enum Output {
    /// A pulse's index and particles.
    Particles(i64, Vec<Particle>),
    Tracks(Vec<Track>),
}

/// The outputs of one run, on their own thread ([`Pipeline`] feeds it):
/// the CSV/NPY writers, the summary and the figure's polylines. Formatting
/// ~10⁶ rows per second of recording is about a fifth of the work of a
/// full-frame run; on a second core it overlaps tracking.
struct Writer {
    particles_out: ParticlesCsvWriter,
    tracks_out: TracksCsvWriter,
    npy_out: Option<TracksNpyWriter>,
    summary: SummaryAcc,
    first_pulse: Option<i64>,
    plot_pulses: i64,
    plot_lines: Vec<Vec<(f64, f64)>>,
    plot_speeds: Vec<f64>,
    width: f64,
    height: f64,
}

impl Writer {
    fn create(out: &Path, npy: bool, plot_pulses: i64) -> ebptv::Result<Self> {
        Ok(Writer {
            particles_out: ParticlesCsvWriter::create(&out.join("particles.csv"))?,
            tracks_out: TracksCsvWriter::create(&out.join("tracks.csv"))?,
            npy_out: npy
                .then(|| TracksNpyWriter::create(&out.join("tracks.npy")))
                .transpose()?,
            summary: SummaryAcc::default(),
            first_pulse: None,
            plot_pulses,
            plot_lines: Vec::new(),
            plot_speeds: Vec::new(),
            width: 0.0,
            height: 0.0,
        })
    }

    /// Write everything that arrives until the channel closes.
    fn run(mut self, rx: std::sync::mpsc::Receiver<Output>) -> ebptv::Result<Self> {
        for msg in rx {
            match msg {
                Output::Particles(pulse, ps) => self.particles(pulse, &ps)?,
                Output::Tracks(ts) => self.tracks(&ts)?,
            }
        }
        Ok(self)
    }

    fn particles(&mut self, pulse: i64, ps: &[Particle]) -> ebptv::Result<()> {
        self.first_pulse.get_or_insert(pulse);
        for p in ps {
            self.width = self.width.max(p.x + 1.0);
            self.height = self.height.max(p.y + 1.0);
        }
        self.particles_out.write(ps)
    }

    fn tracks(&mut self, tracks: &[Track]) -> ebptv::Result<()> {
        self.tracks_out.write(tracks)?;
        if let Some(npy) = &mut self.npy_out {
            npy.write(tracks)?;
        }
        self.summary.add(tracks);
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
        self,
        stats: &TrackerStats,
        out: &Path,
        width: Option<f64>,
        height: Option<f64>,
    ) -> anyhow::Result<()> {
        let summary = self.summary.summary(stats);
        // Outputs appear together at the end (each atomically). The big
        // files' commits wait for the disk (their sync) and the figure is
        // CPU work: nothing else runs at this point, so they run side by
        // side instead of one after another (water jet, 0.25 s: syncs of
        // ~50 and ~80 ms and a ~50 ms figure, now overlapping).
        let Writer {
            particles_out,
            tracks_out,
            npy_out,
            first_pulse,
            plot_pulses,
            plot_lines,
            plot_speeds,
            width: seen_width,
            height: seen_height,
            ..
        } = self;
        std::thread::scope(|scope| -> anyhow::Result<()> {
            let particles = scope.spawn(move || particles_out.finish());
            let tracks = scope.spawn(move || tracks_out.finish());
            let npy = npy_out.map(|npy| scope.spawn(move || npy.finish()));
            let rest = ebptv::track::write_summary_json(&out.join("summary.json"), &summary)
                .and_then(|()| {
                    ebptv::plot::polylines(
                        &out.join("tracks.png"),
                        &ebptv::plot::Polylines {
                            title: &format!(
                                "tracks, pulses {}..{}",
                                first_pulse.unwrap_or(0),
                                first_pulse.unwrap_or(0) + plot_pulses
                            ),
                            width: width.unwrap_or(seen_width.max(1.0)),
                            height: height.unwrap_or(seen_height.max(1.0)),
                            lines: &plot_lines,
                            values: &plot_speeds,
                            colorbar_label: "speed (px/s)",
                        },
                    )
                });
            let join = |h: std::thread::ScopedJoinHandle<'_, ebptv::Result<()>>| {
                h.join().unwrap_or_else(|e| std::panic::resume_unwind(e))
            };
            // Every commit is waited for; the first error is reported.
            let particles = join(particles);
            let tracks = join(tracks);
            let npy = npy.map(join).unwrap_or(Ok(()));
            particles?;
            tracks?;
            npy?;
            rest?;
            Ok(())
        })?;
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

/// Track points per message to the writer (×128 messages in the channel:
/// ~40 MB at most waiting).
const MESSAGE_POINTS: usize = 4096;

/// The [`PtvSink`] of a run: hands results to the [`Writer`] thread (a
/// bounded channel, so a slow disk holds the tracker back instead of
/// filling memory) and moves the progress bar.
struct Pipeline {
    tx: Option<std::sync::mpsc::SyncSender<Output>>,
    writer: Option<std::thread::JoinHandle<ebptv::Result<Writer>>>,
    progress: ProgressBar,
}

impl Pipeline {
    fn start(writer: Writer, progress: ProgressBar) -> anyhow::Result<Self> {
        let (tx, rx) = std::sync::mpsc::sync_channel(128);
        let handle = std::thread::Builder::new()
            .name("ebptv-track-writer".into())
            .spawn(move || writer.run(rx))
            .context("starting the output writer thread")?;
        Ok(Pipeline {
            tx: Some(tx),
            writer: Some(handle),
            progress,
        })
    }

    fn send(&mut self, msg: Output) -> ebptv::Result<()> {
        let tx = self.tx.as_ref().expect("sending after finish");
        if tx.send(msg).is_ok() {
            return Ok(());
        }
        // The writer stopped: it failed; report its error.
        self.tx = None;
        match self.join() {
            Err(e) => Err(e),
            Ok(_) => Err(ebptv::Error::analysis("the output writer stopped early")),
        }
    }

    fn join(&mut self) -> ebptv::Result<Writer> {
        let handle = self.writer.take().expect("writer joined once");
        handle
            .join()
            .unwrap_or_else(|e| std::panic::resume_unwind(e))
    }

    fn finish(
        mut self,
        stats: &TrackerStats,
        out: &Path,
        width: Option<f64>,
        height: Option<f64>,
    ) -> anyhow::Result<()> {
        self.progress.finish_and_clear();
        self.tx = None; // closes the channel: the writer drains it and returns
        let writer = self.join()?;
        writer.finish(stats, out, width, height)
    }
}

/// On an error the run ends without `finish`: close the channel and wait
/// for the writer, whose uncommitted files then remove themselves before
/// the process exits (no temporary files left behind).
impl Drop for Pipeline {
    fn drop(&mut self) {
        self.tx = None;
        if let Some(handle) = self.writer.take() {
            let _ = handle.join();
        }
    }
}

impl PtvSink for Pipeline {
    fn particles(&mut self, pulse: i64, t_us: f64, ps: &[Particle]) -> ebptv::Result<()> {
        self.take_particles(pulse, t_us, ps.to_vec())
    }

    fn take_particles(&mut self, pulse: i64, _t_us: f64, ps: Vec<Particle>) -> ebptv::Result<()> {
        self.progress.inc(1);
        self.send(Output::Particles(pulse, ps))
    }

    fn tracks(&mut self, tracks: &[Track]) -> ebptv::Result<()> {
        self.take_tracks(tracks.to_vec())
    }

    /// Large hand-outs (the sliced linker's come a group of slices at a
    /// time) go in messages of at most [`MESSAGE_POINTS`] points, so the
    /// bounded channel bounds the memory waiting for the writer.
    fn take_tracks(&mut self, tracks: Vec<Track>) -> ebptv::Result<()> {
        let mut chunk = Vec::new();
        let mut points = 0;
        for t in tracks {
            points += t.points.len();
            chunk.push(t);
            if points >= MESSAGE_POINTS {
                self.send(Output::Tracks(std::mem::take(&mut chunk)))?;
                points = 0;
            }
        }
        if chunk.is_empty() {
            return Ok(());
        }
        self.send(Output::Tracks(chunk))
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

/// The run's full set of options: the --params file (or the defaults),
/// then the command-line options over it.
fn config_of(args: &TrackArgs) -> anyhow::Result<TrackConfig> {
    let mut c = match &args.params {
        Some(p) => TrackConfig::read(p)?,
        None => TrackConfig::default(),
    };
    if let Some(v) = args.max_disp {
        c.track.max_disp = v;
    }
    if let Some(v) = args.gap {
        c.track.max_gap = v;
    }
    if let Some(v) = args.min_length {
        c.track.min_length = v;
    }
    if let Some(v) = args.radius {
        c.cluster.radius = v;
    }
    if let Some(p) = &args.prior {
        c.run.prior = Some([p[0], p[1]]);
    }
    if args.pulse_hz.is_some() {
        c.run.pulse_hz = args.pulse_hz;
    }
    c.run.ignore_triggers |= args.ignore_triggers;
    c.run.force_pulses |= args.force_pulses;
    if args.all_polarities {
        c.cluster.on_only = false;
    }
    if args.hot_pixels.is_some() {
        c.run.hot_pixels = args.hot_pixels.clone();
    }
    // The hot pixels' file goes into the set (the written params.toml
    // then holds the pixels themselves).
    if let Some(p) = c.run.hot_pixels.take() {
        c.cluster.hot_pixels.extend(read_hot_pixels(&p)?);
    }
    // Without the ghost test there is no flow to check new chains against.
    if c.track.init.ghost_check_length == 0 {
        c.track.init.ghost_check_init = false;
        c.track.init.init_gap = false;
    }
    Ok(c)
}

fn run_tracking(args: TrackArgs) -> anyhow::Result<()> {
    let config = config_of(&args)?;
    let TrackConfig {
        run,
        cluster,
        track: mut tparams,
    } = config.clone();
    if let Some([u, v]) = run.prior {
        tparams.prior = Some(ebptv::track::FlowPrior::uniform(u, v));
    }
    let mut stream = match run.linker {
        Linker::Sequential => PtvStream::new(cluster, tparams, run.batch)?,
        Linker::Sliced => PtvStream::sliced(cluster, tparams, run.slicing(), run.batch)
            .context("run.slice_pulses / run.slice_overlap")?,
    };
    ebptv::io::atomic::create_output_dir(&args.out)?;
    // Written with the other outputs, once tracking succeeded.
    let params_toml = config.to_toml()?;
    let write_params = || {
        ebptv::io::atomic::AtomicFile::write_all_to(
            args.out.join("params.toml"),
            params_toml.as_bytes(),
        )
    };

    let size = std::fs::metadata(&args.input).ok().map(|m| m.len());
    let progress = super::progress::file_bar(size, "pulse timing");
    let writer = Writer::create(&args.out, run.npy, run.plot_pulses)?;
    let mut pipe = Pipeline::start(writer, progress)?;

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
        write_params()?;
        return pipe.finish(&stats, &args.out, None, None);
    }

    let opts = PulseOptions {
        pulse_hz: run.pulse_hz,
        ignore_triggers: run.ignore_triggers,
        require_pulsed: !run.force_pulses,
        ..Default::default()
    };
    let geometry = {
        let src = ebptv::io::open(&args.input)?;
        super::print_warnings(&src);
        src.info().geometry
    };
    // The recording is read twice: pulse timing, then tracking (with the
    // tracker's counts on the bar).
    let progress = pipe.progress.clone();
    let counts = Arc::new([AtomicU64::new(0), AtomicU64::new(0)]);
    let passes = AtomicU64::new(0);
    let open = || -> ebptv::Result<Box<dyn ebptv::io::EventSource>> {
        let src = ebptv::io::open_for_analysis(&args.input)?;
        let reading = super::progress::Reading::new(src, progress.clone());
        if passes.fetch_add(1, Ordering::Relaxed) == 0 {
            return Ok(Box::new(reading));
        }
        progress.reset();
        progress.set_prefix("tracking");
        let c = counts.clone();
        Ok(Box::new(reading.with_note(Arc::new(move || {
            format!(
                "{} particles, {} active tracks",
                c[0].load(Ordering::Relaxed),
                c[1].load(Ordering::Relaxed)
            )
        }))))
    };
    let (report, stats, unassigned) = track_recording(&open, &opts, stream, &mut pipe, &mut |s| {
        let (particles, active) = s.progress();
        counts[0].store(particles, Ordering::Relaxed);
        counts[1].store(active as u64, Ordering::Relaxed);
    })?;
    if unassigned > 0 {
        pipe.progress.println(format!(
            "{unassigned} events could not be attributed to a pulse"
        ));
    }
    // Written with the other outputs, once tracking succeeded.
    let json = serde_json::to_vec_pretty(&report)?;
    ebptv::io::atomic::AtomicFile::write_all_to(args.out.join("pulses.json"), &json)?;
    write_params()?;
    pipe.finish(
        &stats,
        &args.out,
        geometry.map(|g| g.width as f64),
        geometry.map(|g| g.height as f64),
    )
}
