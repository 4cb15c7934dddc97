//! The Python bindings (feature `python`), registered as `ebptv._ebptv`
//! by the `ebptv-python` crate: the library's stages for Python. Each function is one
//! call into the `ebptv` crate; results come back as numpy arrays, JSON
//! text and TOML text, which the `ebptv` package (python/ebptv) turns into
//! dicts and pandas DataFrames. Long calls run without the GIL and look
//! for Ctrl-C between pulses / chunks.

use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::time::Duration;

use numpy::{IntoPyArray, PyArrayMethods, PyReadonlyArray1};
use pyo3::create_exception;
use pyo3::exceptions::PyException;
use pyo3::prelude::*;
use pyo3::types::PyDict;

use ebptv::cluster::Particle;
use ebptv::io::filter::{Filtered, PolaritySelect, Roi, Selection};
use ebptv::io::{self, EventSource};
use ebptv::track::{self as ptv, PtvSink, Track, TrackConfig, TrackInput};
use ebptv::{grid, Cancel, Chunk};

create_exception!(
    _ebptv,
    EbptvError,
    PyException,
    "An error of the ebptv library; the message is the one `ebptv` prints after `error:`."
);

/// The library's error as a Python exception with the same message.
fn err(e: ebptv::Error) -> PyErr {
    EbptvError::new_err(e.to_string())
}

/// How often a long call looks for Ctrl-C.
const SIGNAL_CHECK: Duration = Duration::from_millis(50);

/// Stack of the thread a long call runs on (the size of a main thread's).
const WORKER_STACK: usize = 8 << 20;

/// Runs `f` without the GIL on a thread of its own while this (the
/// calling) thread looks for Ctrl-C every [`SIGNAL_CHECK`]: when a signal
/// handler raises, `f`'s [`Cancel`] is set, the library stops at its next
/// check, and the handler's exception (`KeyboardInterrupt`) is raised in
/// place of `f`'s result. Signals are only seen on Python's main thread,
/// and the library's parallel parts run on other threads: hence the
/// watching thread.
fn interruptible<T, F>(py: Python<'_>, f: F) -> PyResult<T>
where
    T: Send,
    F: FnOnce(&Cancel) -> ebptv::Result<T> + Send,
{
    let cancel = Cancel::new();
    let (result, raised) = py.allow_threads(|| {
        std::thread::scope(|s| {
            let (done, finished) = mpsc::channel::<()>();
            let c = &cancel;
            let worker = std::thread::Builder::new()
                .name("ebptv-call".into())
                .stack_size(WORKER_STACK)
                .spawn_scoped(s, move || {
                    let r = f(c);
                    let _ = done.send(());
                    r
                });
            let worker = match worker {
                Ok(w) => w,
                Err(e) => {
                    return (
                        Err(ebptv::Error::analysis(format!(
                            "cannot start a thread: {e}"
                        ))),
                        None,
                    )
                }
            };
            let mut raised = None;
            while let Err(mpsc::RecvTimeoutError::Timeout) = finished.recv_timeout(SIGNAL_CHECK) {
                if raised.is_none() {
                    if let Err(e) = Python::with_gil(|py| py.check_signals()) {
                        raised = Some(e);
                        cancel.cancel();
                    }
                }
            }
            match worker.join() {
                Ok(r) => (r, raised),
                Err(panic) => std::panic::resume_unwind(panic),
            }
        })
    });
    match raised {
        Some(e) => Err(e),
        None => result.map_err(err),
    }
}

fn selection(
    from_us: Option<i64>,
    to_us: Option<i64>,
    roi: Option<&str>,
    polarity: Option<&str>,
) -> ebptv::Result<Selection> {
    Ok(Selection {
        from_us,
        to_us,
        roi: roi.map(str::parse::<Roi>).transpose()?,
        polarity: polarity
            .map(str::parse::<PolaritySelect>)
            .transpose()?
            .unwrap_or_default(),
    })
}

/// Columns of events and triggers, filled chunk by chunk.
#[derive(Default)]
struct Columns {
    t: Vec<i64>,
    x: Vec<u16>,
    y: Vec<u16>,
    p: Vec<u8>,
    trigger_t: Vec<i64>,
    trigger_channel: Vec<u8>,
    trigger_rising: Vec<bool>,
}

impl Columns {
    fn extend(&mut self, c: &Chunk) {
        self.t.extend_from_slice(&c.events.t);
        self.x.extend_from_slice(&c.events.x);
        self.y.extend_from_slice(&c.events.y);
        self.p.extend_from_slice(&c.events.p);
        for tr in &c.triggers {
            self.trigger_t.push(tr.t);
            self.trigger_channel.push(tr.channel);
            self.trigger_rising.push(tr.edge == ebptv::Edge::Rising);
        }
    }

    fn into_dict(self, py: Python<'_>) -> PyResult<Bound<'_, PyDict>> {
        let d = PyDict::new(py);
        d.set_item("t", self.t.into_pyarray(py))?;
        d.set_item("x", self.x.into_pyarray(py))?;
        d.set_item("y", self.y.into_pyarray(py))?;
        d.set_item("p", self.p.into_pyarray(py))?;
        let tr = PyDict::new(py);
        tr.set_item("t", self.trigger_t.into_pyarray(py))?;
        tr.set_item("channel", self.trigger_channel.into_pyarray(py))?;
        tr.set_item("rising", self.trigger_rising.into_pyarray(py))?;
        d.set_item("triggers", tr)?;
        Ok(d)
    }
}

fn open_selected(
    path: &Path,
    chunk_events: Option<usize>,
    sel: Selection,
) -> ebptv::Result<Filtered<Box<dyn EventSource>>> {
    let opts = io::OpenOptions {
        chunk_events,
        ..Default::default()
    };
    Filtered::new(io::open_with(path, &opts)?, sel)
}

/// All events of a recording (optionally a time range, region and
/// polarity) as columns.
#[pyfunction]
#[pyo3(signature = (path, from_us=None, to_us=None, roi=None, polarity=None))]
fn read_events<'py>(
    py: Python<'py>,
    path: PathBuf,
    from_us: Option<i64>,
    to_us: Option<i64>,
    roi: Option<&str>,
    polarity: Option<&str>,
) -> PyResult<Bound<'py, PyDict>> {
    let sel = selection(from_us, to_us, roi, polarity).map_err(err)?;
    interruptible(py, |cancel| -> ebptv::Result<Columns> {
        let mut src = open_selected(&path, None, sel)?;
        let mut cols = Columns::default();
        let mut chunk = Chunk::default();
        while src.next_chunk(&mut chunk)? {
            cols.extend(&chunk);
            cancel.check()?;
        }
        Ok(cols)
    })?
    .into_dict(py)
}

/// A recording read chunk by chunk (`ebptv.iter_events`).
#[pyclass(unsendable)]
struct EventChunks {
    src: Filtered<Box<dyn EventSource>>,
    chunk: Chunk,
}

#[pymethods]
impl EventChunks {
    #[new]
    #[pyo3(signature = (path, chunk, from_us=None, to_us=None, roi=None, polarity=None))]
    fn new(
        path: PathBuf,
        chunk: usize,
        from_us: Option<i64>,
        to_us: Option<i64>,
        roi: Option<&str>,
        polarity: Option<&str>,
    ) -> PyResult<Self> {
        let sel = selection(from_us, to_us, roi, polarity).map_err(err)?;
        Ok(EventChunks {
            src: open_selected(&path, Some(chunk), sel).map_err(err)?,
            chunk: Chunk::default(),
        })
    }

    fn __iter__(slf: PyRef<'_, Self>) -> PyRef<'_, Self> {
        slf
    }

    fn __next__<'py>(&mut self, py: Python<'py>) -> PyResult<Option<Bound<'py, PyDict>>> {
        loop {
            let EventChunks { src, chunk } = self;
            let more = py.allow_threads(|| src.next_chunk(chunk)).map_err(err)?;
            if !more {
                return Ok(None);
            }
            // A filter can leave a chunk empty: go on to the next.
            if chunk.events.t.is_empty() && chunk.triggers.is_empty() {
                py.check_signals()?;
                continue;
            }
            let mut cols = Columns::default();
            cols.extend(chunk);
            return cols.into_dict(py).map(Some);
        }
    }
}

/// `ebptv info --json` as JSON text.
#[pyfunction]
fn info(py: Python<'_>, path: PathBuf) -> PyResult<String> {
    interruptible(py, |cancel| -> ebptv::Result<String> {
        let info = ebptv::pulses::file_info(
            &path,
            &io::OpenOptions::default(),
            io::summary::DEFAULT_PEAK_BIN_US,
            &mut |_| {},
        )?;
        let v = info.to_json()?;
        cancel.check()?;
        serde_json::to_string(&v).map_err(|e| ebptv::Error::analysis(e.to_string()))
    })
}

/// Collects a run's particles and tracks, looking at the cancel flag
/// after each pulse.
struct Collect {
    particles: Vec<Particle>,
    tracks: Vec<Track>,
    cancel: Cancel,
}

impl PtvSink for Collect {
    fn particles(&mut self, _pulse: i64, _t_us: f64, ps: &[Particle]) -> ebptv::Result<()> {
        self.particles.extend_from_slice(ps);
        self.cancel.check()
    }
    fn tracks(&mut self, tracks: &[Track]) -> ebptv::Result<()> {
        self.tracks.extend_from_slice(tracks);
        Ok(())
    }
    fn take_tracks(&mut self, tracks: Vec<Track>) -> ebptv::Result<()> {
        self.tracks.extend(tracks);
        Ok(())
    }
}

/// The options of `ebptv track`: a --params file, then the command-line
/// options over it (the names of `ebptv track`'s options).
fn track_config(
    params: Option<&Path>,
    options: Option<&Bound<'_, PyDict>>,
) -> PyResult<TrackConfig> {
    let mut c = match params {
        Some(p) => TrackConfig::read(p).map_err(err)?,
        None => TrackConfig::default(),
    };
    let Some(options) = options else {
        return Ok(c);
    };
    for (k, v) in options.iter() {
        let key: String = k.extract()?;
        if v.is_none() {
            continue;
        }
        match key.as_str() {
            "max_disp" => c.track.max_disp = v.extract()?,
            "gap" => c.track.max_gap = v.extract()?,
            "min_length" => c.track.min_length = v.extract()?,
            "radius" => c.cluster.radius = v.extract()?,
            "prior" => c.run.prior = Some(v.extract::<[f64; 2]>()?),
            "pulse_hz" => c.run.pulse_hz = Some(v.extract()?),
            "ignore_triggers" => c.run.ignore_triggers |= v.extract::<bool>()?,
            "force_pulses" => c.run.force_pulses |= v.extract::<bool>()?,
            "all_polarities" => {
                if v.extract::<bool>()? {
                    c.cluster.on_only = false;
                }
            }
            "hot_pixels" => c.run.hot_pixels = Some(v.extract::<PathBuf>()?),
            "calibration" => c.run.calibration = Some(v.extract::<PathBuf>()?),
            "mask" => c.run.set_mask_file(&v.extract::<PathBuf>()?).map_err(err)?,
            "linker" => {
                c.run.linker = match v.extract::<String>()?.as_str() {
                    "sequential" => ptv::Linker::Sequential,
                    "sliced" => ptv::Linker::Sliced,
                    other => {
                        return Err(EbptvError::new_err(format!(
                            "linker: `{other}`: expected sequential or sliced"
                        )))
                    }
                }
            }
            _ => {
                return Err(pyo3::exceptions::PyTypeError::new_err(format!(
                    "track() got an unexpected option `{key}`"
                )))
            }
        }
    }
    Ok(c)
}

/// Particles as columns (`particles.csv`).
fn particle_columns<'py>(py: Python<'py>, ps: &[Particle]) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item(
        "pulse",
        ps.iter()
            .map(|p| p.pulse)
            .collect::<Vec<_>>()
            .into_pyarray(py),
    )?;
    d.set_item(
        "t_us",
        ps.iter()
            .map(|p| p.t_us)
            .collect::<Vec<_>>()
            .into_pyarray(py),
    )?;
    d.set_item(
        "x",
        ps.iter().map(|p| p.x).collect::<Vec<_>>().into_pyarray(py),
    )?;
    d.set_item(
        "y",
        ps.iter().map(|p| p.y).collect::<Vec<_>>().into_pyarray(py),
    )?;
    d.set_item(
        "n_events",
        ps.iter()
            .map(|p| p.n_events)
            .collect::<Vec<_>>()
            .into_pyarray(py),
    )?;
    Ok(d)
}

/// Track points as columns (`tracks.csv`).
fn track_columns<'py>(py: Python<'py>, tracks: &[Track]) -> PyResult<Bound<'py, PyDict>> {
    let n: usize = tracks.iter().map(|t| t.points.len()).sum();
    let mut id = Vec::with_capacity(n);
    let mut pulse = Vec::with_capacity(n);
    let (mut t, mut x, mut y, mut u, mut v) = (
        Vec::with_capacity(n),
        Vec::with_capacity(n),
        Vec::with_capacity(n),
        Vec::with_capacity(n),
        Vec::with_capacity(n),
    );
    for tr in tracks {
        for p in &tr.points {
            id.push(tr.id);
            pulse.push(p.pulse);
            t.push(p.t_us);
            x.push(p.x);
            y.push(p.y);
            u.push(p.u);
            v.push(p.v);
        }
    }
    let d = PyDict::new(py);
    d.set_item("track_id", id.into_pyarray(py))?;
    d.set_item("pulse", pulse.into_pyarray(py))?;
    d.set_item("t_us", t.into_pyarray(py))?;
    d.set_item("x", x.into_pyarray(py))?;
    d.set_item("y", y.into_pyarray(py))?;
    d.set_item("u", u.into_pyarray(py))?;
    d.set_item("v", v.into_pyarray(py))?;
    Ok(d)
}

/// What [`track`] hands back: particles, tracks, summary.json,
/// pulses.json (recordings only), params.toml and, with a calibration,
/// the physical columns of the tracks.
type TrackResult<'py> = (
    Bound<'py, PyDict>,
    Bound<'py, PyDict>,
    String,
    Option<String>,
    String,
    Option<Bound<'py, PyDict>>,
);

/// Particle columns `pulse, t_us, x, y, n_events`.
type ParticleArrays<'py> = (
    PyReadonlyArray1<'py, i64>,
    PyReadonlyArray1<'py, f64>,
    PyReadonlyArray1<'py, f64>,
    PyReadonlyArray1<'py, f64>,
    PyReadonlyArray1<'py, u32>,
);

/// The run of `ebptv track` on a file (recording or particles.csv) or on
/// particle columns, its results in memory.
#[pyfunction]
#[pyo3(signature = (path=None, particles=None, params=None, options=None))]
fn track<'py>(
    py: Python<'py>,
    path: Option<PathBuf>,
    particles: Option<ParticleArrays<'py>>,
    params: Option<PathBuf>,
    options: Option<&Bound<'py, PyDict>>,
) -> PyResult<TrackResult<'py>> {
    let config = track_config(params.as_deref(), options)?;
    let input = match (&path, particles) {
        (Some(p), None) => TrackInput::of_path(p),
        (None, Some((pulse, t, x, y, n))) => {
            let (pulse, t, x, y, n) = (
                pulse.as_slice()?,
                t.as_slice()?,
                x.as_slice()?,
                y.as_slice()?,
                n.as_slice()?,
            );
            let len = pulse.len();
            if [t.len(), x.len(), y.len(), n.len()]
                .iter()
                .any(|&l| l != len)
            {
                return Err(EbptvError::new_err(
                    "particles: the columns pulse, t_us, x, y, n_events differ in length",
                ));
            }
            TrackInput::Particles(
                (0..len)
                    .map(|i| Particle {
                        pulse: pulse[i],
                        t_us: t[i],
                        x: x[i],
                        y: y[i],
                        n_events: n[i],
                        n_pixels: 0,
                        extent_x: 0.0,
                        extent_y: 0.0,
                        first_latency_us: 0.0,
                    })
                    .collect(),
            )
        }
        _ => {
            return Err(pyo3::exceptions::PyTypeError::new_err(
                "track() takes a path or particle columns",
            ))
        }
    };
    let (particles, tracks, summary, pulses, toml, calib) = interruptible(py, |cancel| {
        let config = ptv::resolve_config(&config)?;
        let calib = config
            .run
            .calibration
            .as_deref()
            .map(ebptv::calib::Calibration::from_file)
            .transpose()?;
        let stream = ptv::stream_of(&config)?;
        let mut sink = Collect {
            particles: Vec::new(),
            tracks: Vec::new(),
            cancel: cancel.clone(),
        };
        let run = ptv::track_into(input, &config, stream, &mut sink, &|_| {}, cancel)?;
        let summary = ptv::Summary::new(&sink.tracks, &run.stats);
        let json = |e: serde_json::Error| ebptv::Error::analysis(e.to_string());
        let summary = serde_json::to_string(&summary).map_err(json)?;
        let pulses = run
            .pulses
            .as_ref()
            .map(|p| serde_json::to_string(p).map_err(json))
            .transpose()?;
        let toml = config.to_toml()?;
        Ok((sink.particles, sink.tracks, summary, pulses, toml, calib))
    })?;
    let physical = calib
        .map(|c| physical_columns(py, &c, &tracks))
        .transpose()?;
    Ok((
        particle_columns(py, &particles)?,
        track_columns(py, &tracks)?,
        summary,
        pulses,
        toml,
        physical,
    ))
}

/// The physical columns of a calibrated run's track points
/// (`X_mm, Y_mm, U_m_s, V_m_s`), in the order of [`track_columns`].
fn physical_columns<'py>(
    py: Python<'py>,
    calib: &ebptv::calib::Calibration,
    tracks: &[Track],
) -> PyResult<Bound<'py, PyDict>> {
    let names = ebptv::calib::Calibration::point_columns();
    let mut cols: Vec<Vec<f64>> = vec![Vec::new(); names.len()];
    for p in tracks.iter().flat_map(|t| &t.points) {
        for (c, v) in cols.iter_mut().zip(calib.point_values(p.x, p.y, p.u, p.v)) {
            c.push(v);
        }
    }
    let d = PyDict::new(py);
    for (name, c) in names.iter().zip(cols) {
        d.set_item(*name, c.into_pyarray(py))?;
    }
    Ok(d)
}

fn from_name<T: serde::de::DeserializeOwned>(
    what: &str,
    name: &str,
    expected: &str,
) -> PyResult<T> {
    serde_json::from_value(serde_json::Value::String(name.to_string()))
        .map_err(|_| EbptvError::new_err(format!("{what}: `{name}`: expected {expected}")))
}

/// The defaults of `ebptv grid`, from the library.
fn grid_defaults(py: Python<'_>) -> PyResult<Bound<'_, PyDict>> {
    let b = grid::BinOptions::default();
    let e = grid::EstimateOptions::default();
    let d = PyDict::new(py);
    d.set_item("bin", b.bin)?;
    d.set_item("overlap", b.overlap)?;
    d.set_item("origin", b.origin)?;
    d.set_item("weighting", to_name(&b.weighting))?;
    d.set_item("fit", to_name(&e.fit))?;
    d.set_item("min_count", grid::DEFAULT_MIN_COUNT)?;
    d.set_item("noise_rms", e.noise_rms)?;
    Ok(d)
}

fn to_name<T: serde::Serialize>(v: &T) -> String {
    match serde_json::to_value(v) {
        Ok(serde_json::Value::String(s)) => s,
        _ => String::new(),
    }
}

/// The grid accumulator (`grid_state.json` text) of track points, binned
/// as `ebptv grid` bins a tracks file.
#[pyfunction]
#[pyo3(signature = (track_id, t_us, x, y, u, v, bin, bin_h, overlap, origin, weighting, what))]
#[allow(clippy::too_many_arguments)]
fn grid_state(
    py: Python<'_>,
    track_id: PyReadonlyArray1<'_, u64>,
    t_us: PyReadonlyArray1<'_, f64>,
    x: PyReadonlyArray1<'_, f64>,
    y: PyReadonlyArray1<'_, f64>,
    u: PyReadonlyArray1<'_, f64>,
    v: PyReadonlyArray1<'_, f64>,
    bin: f64,
    bin_h: Option<f64>,
    overlap: f64,
    origin: (f64, f64),
    weighting: &str,
    what: &str,
) -> PyResult<String> {
    let opts = grid::BinOptions {
        bin,
        bin_h,
        overlap,
        origin,
        weighting: from_name("weighting", weighting, "tophat or gaussian")?,
    };
    let (id, t, x, y, u, v) = (
        track_id.as_slice()?,
        t_us.as_slice()?,
        x.as_slice()?,
        y.as_slice()?,
        u.as_slice()?,
        v.as_slice()?,
    );
    let n = id.len();
    if [t.len(), x.len(), y.len(), u.len(), v.len()]
        .iter()
        .any(|&l| l != n)
    {
        return Err(EbptvError::new_err(format!(
            "{what}: the columns differ in length"
        )));
    }
    let samples: Vec<grid::Sample> = (0..n)
        .map(|i| grid::Sample {
            x: x[i],
            y: y[i],
            u: u[i],
            v: v[i],
            t_us: t[i],
            track_id: id[i],
        })
        .collect();
    interruptible(py, |cancel| -> ebptv::Result<String> {
        let mut cancelled = Ok(());
        let acc = grid::accumulate(&samples, &opts, what, &mut |_| {
            if cancelled.is_ok() {
                cancelled = cancel.check();
            }
        })?;
        cancelled?;
        grid::io::state_json(&acc).map_err(|e| ebptv::Error::analysis(e.to_string()))
    })
}

fn load(text: &str, k: usize) -> ebptv::Result<grid::GridAccumulator> {
    grid::io::state_from_json(text.as_bytes(), Path::new(&format!("state {k}")))
}

/// Grid states merged in order (`ebptv grid --merge`).
#[pyfunction]
fn grid_merge(py: Python<'_>, states: Vec<String>) -> PyResult<String> {
    py.allow_threads(|| -> ebptv::Result<String> {
        let mut acc: Option<grid::GridAccumulator> = None;
        for (k, s) in states.iter().enumerate() {
            let part = load(s, k)?;
            match acc.as_mut() {
                None => acc = Some(part),
                Some(m) => m.merge(&part)?,
            }
        }
        let acc = acc.ok_or_else(|| ebptv::Error::param("merge", "no grid states to merge"))?;
        grid::io::state_json(&acc).map_err(|e| ebptv::Error::analysis(e.to_string()))
    })
    .map_err(err)
}

/// The statistics of a grid state as the columns of the `grid` table.
#[pyfunction]
fn grid_estimate<'py>(
    py: Python<'py>,
    state: &str,
    fit: &str,
    min_count: u64,
    noise_rms: f64,
) -> PyResult<Bound<'py, PyDict>> {
    let opt = grid::EstimateOptions {
        fit: from_name("fit", fit, "none, linear or quadratic")?,
        min_count,
        noise_rms,
    };
    let g = py
        .allow_threads(|| -> ebptv::Result<grid::GridStats> {
            opt.validate()?;
            grid::estimate(&load(state, 0)?, &opt)
        })
        .map_err(err)?;
    let mut cols: [Vec<f64>; 7] = Default::default();
    let mut count = Vec::with_capacity(g.bins.len());
    let mut n_tracks = Vec::with_capacity(g.bins.len());
    // Rows ordered by y then x, as in grid.csv.
    for (iy, &y) in g.ys.iter().enumerate() {
        for (ix, &x) in g.xs.iter().enumerate() {
            let b = g.at(ix, iy);
            for (c, val) in cols.iter_mut().zip([x, y, b.u, b.v, b.uu, b.vv, b.uv]) {
                c.push(val);
            }
            count.push(b.count);
            n_tracks.push(b.n_tracks);
        }
    }
    let d = PyDict::new(py);
    let [x, y, u, v, uu, vv, uv] = cols;
    d.set_item("x", x.into_pyarray(py))?;
    d.set_item("y", y.into_pyarray(py))?;
    d.set_item("count", count.into_pyarray(py))?;
    d.set_item("u", u.into_pyarray(py))?;
    d.set_item("v", v.into_pyarray(py))?;
    d.set_item("uu", uu.into_pyarray(py))?;
    d.set_item("vv", vv.into_pyarray(py))?;
    d.set_item("uv", uv.into_pyarray(py))?;
    d.set_item("n_tracks", n_tracks.into_pyarray(py))?;
    d.set_item("nx", g.spec.nx)?;
    d.set_item("ny", g.spec.ny)?;
    Ok(d)
}

/// `ebptv simulate --preset NAME --out OUT [--seconds S] --seed SEED`:
/// writes the recording (EVT 3.0), the truth and the summary into `out`;
/// returns the summary as JSON text.
#[pyfunction]
#[pyo3(signature = (out, preset, seconds=None, seed=1))]
fn simulate(
    py: Python<'_>,
    out: PathBuf,
    preset: &str,
    seconds: Option<f64>,
    seed: u64,
) -> PyResult<String> {
    let mut sc = ebptv::sim::presets::preset(preset).map_err(err)?;
    if let Some(s) = seconds {
        sc.duration_s = s;
    }
    interruptible(py, |cancel| -> ebptv::Result<String> {
        sc.validate()?;
        let mut cancelled = Ok(());
        let summary = ebptv::sim::write_recording(&sc, seed, &out, io::Format::Evt3, |_, _| {
            if cancelled.is_ok() {
                cancelled = cancel.check();
            }
        })?;
        cancelled?;
        serde_json::to_string(&summary).map_err(|e| ebptv::Error::analysis(e.to_string()))
    })
}

/// `ebptv pulses`: the pulse analysis (pulses.json as JSON text) and the
/// start time (µs) of every pulse.
#[pyfunction]
#[pyo3(signature = (path, pulse_hz=None, pulse_hz_range=None, trigger_channel=None, ignore_triggers=false, onset_latency_us=None, force_pulses=false))]
#[allow(clippy::too_many_arguments)]
fn pulses<'py>(
    py: Python<'py>,
    path: PathBuf,
    pulse_hz: Option<f64>,
    pulse_hz_range: Option<(f64, f64)>,
    trigger_channel: Option<u8>,
    ignore_triggers: bool,
    onset_latency_us: Option<f64>,
    force_pulses: bool,
) -> PyResult<(String, Bound<'py, numpy::PyArray1<f64>>)> {
    let opts = ebptv::pulses::PulseOptions {
        pulse_hz,
        pulse_hz_range,
        trigger_channel,
        ignore_triggers,
        onset_latency_us,
        require_pulsed: !force_pulses,
    };
    let (json, starts) = interruptible(py, |cancel| -> ebptv::Result<(String, Vec<f64>)> {
        let mut src = io::guard::TimeGuard::new(io::open(&path)?);
        let mut an = ebptv::pulses::Analyzer::new(opts, src.info().geometry)?;
        let mut chunk = Chunk::default();
        while src.next_chunk(&mut chunk)? {
            an.push(&chunk)?;
            cancel.check()?;
        }
        let mut report = an.finish().map_err(|e| {
            ebptv::Error::analysis(format!("{}: pulse analysis: {e}", path.display()))
        })?;
        (report.time_jumps, report.time_jump_events) = src.jumps();
        let starts = (0..report.pulses as i64)
            .map(|k| report.timing.pulse_start(k))
            .collect();
        let json =
            serde_json::to_string(&report).map_err(|e| ebptv::Error::analysis(e.to_string()))?;
        Ok((json, starts))
    })?;
    Ok((json, starts.into_pyarray(py)))
}

/// The defaults of `ebptv spectra`, from the library.
fn spectra_defaults(py: Python<'_>) -> PyResult<Bound<'_, PyDict>> {
    let o = ebptv::spectra::RunOptions::default();
    let d = PyDict::new(py);
    d.set_item("line_points", o.line_points)?;
    d.set_item("component", o.component.name())?;
    d.set_item("bin", o.bin)?;
    d.set_item("every", o.every)?;
    d.set_item("nperseg", o.nperseg)?;
    d.set_item("seg_overlap", o.seg_overlap)?;
    d.set_item("f_min", o.f_min)?;
    d.set_item("f_max", o.f_max)?;
    d.set_item("min_count", o.min_count)?;
    Ok(d)
}

/// `ebptv spectra` on a tracks table: spectrum.json (JSON text),
/// spectra.csv and premultiplied_line.csv (text; `None` without points /
/// line). `None` options take the CLI's defaults.
#[pyfunction]
#[pyo3(signature = (tracks, points, line=None, line_points=None, component=None, bin=None, bin_h=None, every=None, nperseg=None, seg_overlap=None, f_min=None, f_max=None, moving_average=None, min_count=None, calibration=None))]
#[allow(clippy::too_many_arguments)]
fn spectra(
    py: Python<'_>,
    tracks: PathBuf,
    points: Vec<(f64, f64)>,
    line: Option<(f64, f64, f64, f64)>,
    line_points: Option<usize>,
    component: Option<String>,
    bin: Option<f64>,
    bin_h: Option<f64>,
    every: Option<usize>,
    nperseg: Option<usize>,
    seg_overlap: Option<f64>,
    f_min: Option<f64>,
    f_max: Option<f64>,
    moving_average: Option<usize>,
    min_count: Option<u64>,
    calibration: Option<PathBuf>,
) -> PyResult<(String, Option<String>, Option<String>)> {
    let d = ebptv::spectra::RunOptions::default();
    let r = py.allow_threads(|| -> ebptv::Result<_> {
        let mut opt = ebptv::spectra::RunOptions {
            points,
            line,
            line_points: line_points.unwrap_or(d.line_points),
            component: component
                .as_deref()
                .map(str::parse)
                .transpose()?
                .unwrap_or(d.component),
            bin: bin.unwrap_or(d.bin),
            bin_h,
            every: every.unwrap_or(d.every),
            nperseg: nperseg.unwrap_or(d.nperseg),
            seg_overlap: seg_overlap.unwrap_or(d.seg_overlap),
            f_min: f_min.unwrap_or(d.f_min),
            f_max: f_max.unwrap_or(d.f_max),
            moving_average,
            min_count: min_count.unwrap_or(d.min_count),
            calibration: None,
        };
        opt.validate()?;
        opt.calibration = calibration
            .as_deref()
            .map(ebptv::calib::Calibration::from_file)
            .transpose()?;
        let run = ebptv::spectra::run_on_tracks(&tracks, &opt)?;
        let json = serde_json::to_string(&run.summary)
            .map_err(|e| ebptv::Error::analysis(e.to_string()))?;
        Ok((json, run.spectra_csv, run.line_csv))
    });
    r.map_err(err)
}

/// `ebptv model-check`: the check of a measured recording against the
/// simulator, outputs written into `out`; model_check.json as JSON text.
/// `None` options take the CLI's defaults.
#[pyfunction]
#[pyo3(signature = (path, out, model=None, seed=None, replicates=None, evaluations=None, max_effects=None, block_pulses=None, pulse_hz=None, ignore_triggers=None))]
#[allow(clippy::too_many_arguments)]
fn model_check(
    py: Python<'_>,
    path: PathBuf,
    out: PathBuf,
    model: Option<PathBuf>,
    seed: Option<u64>,
    replicates: Option<usize>,
    evaluations: Option<usize>,
    max_effects: Option<usize>,
    block_pulses: Option<u64>,
    pulse_hz: Option<f64>,
    ignore_triggers: Option<bool>,
) -> PyResult<String> {
    use ebptv::modelcheck::check::{check_recording_with, ModelCheckOptions};
    let d = ModelCheckOptions::default();
    let opts = ModelCheckOptions {
        model,
        seed: seed.unwrap_or(d.seed),
        replicates: replicates.unwrap_or(d.replicates),
        evaluations: evaluations.unwrap_or(d.evaluations),
        max_effects: max_effects.unwrap_or(d.max_effects),
        block_pulses: block_pulses.unwrap_or(d.block_pulses),
        pulse_hz,
        ignore_triggers: ignore_triggers.unwrap_or(d.ignore_triggers),
    };
    interruptible(py, |cancel| -> ebptv::Result<String> {
        check_recording_with(&path, &out, &opts, cancel)?;
        let json = out.join("model_check.json");
        std::fs::read_to_string(&json).map_err(|e| ebptv::Error::io(&json, e))
    })
}

/// The defaults of `ebptv piv`, from the library.
fn piv_defaults(py: Python<'_>) -> PyResult<Bound<'_, PyDict>> {
    let o = ebptv::piv::PivRunOptions::default();
    let c = &o.correlation;
    let d = PyDict::new(py);
    d.set_item("window", c.window_w)?;
    d.set_item("window_h", c.window_h)?;
    d.set_item("spacing", c.spacing_x)?;
    d.set_item("passes", c.passes)?;
    d.set_item("pyramid", c.pyramid)?;
    d.set_item("no_clip", !c.clip_background)?;
    d.set_item("frames", o.frames)?;
    d.set_item("step", o.step())?;
    d.set_item("sigma", o.pseudo.sigma)?;
    d.set_item("counts", o.counts())?;
    d.set_item("both_polarities", o.pseudo.both_polarities)?;
    d.set_item("force_pulses", o.force_pulses)?;
    Ok(d)
}

/// The fields of a PIV run, collected in memory (px/s, as `piv_u.npy`).
#[derive(Default)]
struct Fields {
    pulse_hz: f64,
    u: Vec<f32>,
    v: Vec<f32>,
    flags: Vec<u8>,
}

impl ebptv::piv::PivSink for Fields {
    fn start(&mut self, _grid: &ebptv::piv::NodeGrid, pulse_hz: f64) -> ebptv::Result<()> {
        self.pulse_hz = pulse_hz;
        Ok(())
    }

    fn field(&mut self, f: &ebptv::piv::StepField) -> ebptv::Result<()> {
        let hz = self.pulse_hz;
        self.u.extend(f.field.u.iter().map(|&x| (x * hz) as f32));
        self.v.extend(f.field.v.iter().map(|&x| (x * hz) as f32));
        self.flags.extend_from_slice(&f.field.flags);
        Ok(())
    }
}

/// `ebptv piv` on a recording, in memory: the fields of every step
/// (`u`, `v` in px/s and `flag`, `(steps, ny, nx)` as `piv_u.npy` …), the
/// node coordinates, the steps (`piv_steps.csv` columns), `piv_mean.csv`
/// as text, pulses.json as JSON text and the run's counts. `None` options
/// take the CLI's defaults.
#[pyfunction]
#[pyo3(signature = (path, window=None, window_h=None, spacing=None, passes=None, pyramid=None, no_clip=None, frames=None, step=None, sigma=None, counts=None, both_polarities=None, pulse_hz=None, batch=None, force_pulses=None, calibration=None, mask=None))]
#[allow(clippy::too_many_arguments)]
fn piv<'py>(
    py: Python<'py>,
    path: PathBuf,
    window: Option<usize>,
    window_h: Option<usize>,
    spacing: Option<usize>,
    passes: Option<usize>,
    pyramid: Option<usize>,
    no_clip: Option<bool>,
    frames: Option<usize>,
    step: Option<usize>,
    sigma: Option<f64>,
    counts: Option<bool>,
    both_polarities: Option<bool>,
    pulse_hz: Option<f64>,
    batch: Option<usize>,
    force_pulses: Option<bool>,
    calibration: Option<PathBuf>,
    mask: Option<PathBuf>,
) -> PyResult<Bound<'py, PyDict>> {
    use ebptv::piv::{PivOptions, PivRunOptions, PixelMode};
    let d = PivRunOptions::default();
    let mut correlation =
        PivOptions::sized(window.unwrap_or(d.correlation.window_w), window_h, spacing);
    correlation.passes = passes.unwrap_or(d.correlation.passes);
    correlation.pyramid = pyramid.unwrap_or(d.correlation.pyramid);
    correlation.clip_background = !no_clip.unwrap_or(!d.correlation.clip_background);
    let mut pseudo = d.pseudo;
    if let Some(c) = counts {
        pseudo.mode = if c {
            PixelMode::Counts
        } else {
            PixelMode::Binary
        };
    }
    pseudo.both_polarities = both_polarities.unwrap_or(pseudo.both_polarities);
    pseudo.sigma = sigma.unwrap_or(pseudo.sigma);
    let opts = PivRunOptions {
        correlation,
        frames: frames.unwrap_or(d.frames),
        step,
        pseudo,
        pulse_hz,
        batch,
        force_pulses: force_pulses.unwrap_or(d.force_pulses),
        calibration,
        mask,
    };
    let (fields, run) = interruptible(py, |cancel| {
        let mut fields = Fields::default();
        let run = ebptv::piv::run_recording(&path, &opts, &mut fields, &|_| {}, cancel)?;
        Ok((fields, run))
    })?;
    let g = run.grid;
    let n = run.steps.len();
    let shape = [n, g.ny, g.nx];
    let out = PyDict::new(py);
    out.set_item("u", fields.u.into_pyarray(py).reshape(shape)?)?;
    out.set_item("v", fields.v.into_pyarray(py).reshape(shape)?)?;
    out.set_item("flag", fields.flags.into_pyarray(py).reshape(shape)?)?;
    out.set_item(
        "x",
        (0..g.nx)
            .map(|i| g.x(i))
            .collect::<Vec<_>>()
            .into_pyarray(py),
    )?;
    out.set_item(
        "y",
        (0..g.ny)
            .map(|j| g.y(j))
            .collect::<Vec<_>>()
            .into_pyarray(py),
    )?;
    let (first, t): (Vec<i64>, Vec<f64>) = run.steps.iter().copied().unzip();
    out.set_item("first_pulse", first.into_pyarray(py))?;
    out.set_item("t_us", t.into_pyarray(py))?;
    out.set_item(
        "mean_csv",
        ebptv::piv::output::mean_csv(&run.mean, run.calibration.as_ref()),
    )?;
    out.set_item(
        "pulses",
        serde_json::to_string(&run.pulses).map_err(|e| EbptvError::new_err(e.to_string()))?,
    )?;
    out.set_item("pulse_hz", run.pulse_hz)?;
    out.set_item("nodes", g.len())?;
    out.set_item(
        "nodes_without_vector",
        run.masked.then(|| run.nodes_without_vector()),
    )?;
    Ok(out)
}

/// Adds the functions, classes and constants of `ebptv._ebptv` to the
/// extension module `m` (the `#[pymodule]` of the `ebptv-python` crate).
pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("EbptvError", m.py().get_type::<EbptvError>())?;
    m.add_function(wrap_pyfunction!(read_events, m)?)?;
    m.add_class::<EventChunks>()?;
    m.add_function(wrap_pyfunction!(info, m)?)?;
    m.add_function(wrap_pyfunction!(track, m)?)?;
    m.add_function(wrap_pyfunction!(simulate, m)?)?;
    m.add_function(wrap_pyfunction!(pulses, m)?)?;
    m.add_function(wrap_pyfunction!(grid_state, m)?)?;
    m.add_function(wrap_pyfunction!(grid_merge, m)?)?;
    m.add_function(wrap_pyfunction!(grid_estimate, m)?)?;
    m.add("GRID_DEFAULTS", grid_defaults(m.py())?)?;
    m.add_function(wrap_pyfunction!(spectra, m)?)?;
    m.add_function(wrap_pyfunction!(model_check, m)?)?;
    m.add("SPECTRA_DEFAULTS", spectra_defaults(m.py())?)?;
    m.add_function(wrap_pyfunction!(piv, m)?)?;
    m.add("PIV_DEFAULTS", piv_defaults(m.py())?)?;
    Ok(())
}
