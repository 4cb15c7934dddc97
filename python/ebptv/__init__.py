"""ebptv from Python: event-based particle tracking velocimetry.

Each function is one call into the Rust library behind the ``ebptv``
command line; results come back as numpy arrays and pandas DataFrames with
the columns of the command's files (README: file contracts). Errors raise
:class:`EbptvError` with the message ``ebptv`` prints after ``error:``.
Long calls release the GIL and stop on Ctrl-C (``KeyboardInterrupt``).

>>> import ebptv
>>> particles, tracks = ebptv.track("events.raw")          # doctest: +SKIP
>>> ebptv.to_trackpy(tracks).head()                          # doctest: +SKIP
"""

from __future__ import annotations

import io
import json
import os
from typing import Any, Dict, Iterator, Optional, Sequence, Tuple, Union

import numpy as np
import pandas as pd

from . import _ebptv
from ._ebptv import EbptvError

__all__ = [
    "EbptvError",
    "read_events",
    "iter_events",
    "info",
    "track",
    "to_trackpy",
    "simulate",
    "pulses",
    "grid",
    "grid_state",
    "grid_merge",
    "grid_estimate",
    "grid_to_xarray",
    "GRID_DEFAULTS",
    "spectra",
    "SPECTRA_DEFAULTS",
    "model_check",
    "piv",
    "PIV_DEFAULTS",
    "PIV_MEAN_COLUMNS",
    "PIV_STEPS_COLUMNS",
    "GRID_COLUMNS",
    "PARTICLES_COLUMNS",
    "TRACKS_COLUMNS",
    "TRACKS_PHYSICAL_COLUMNS",
]

PathLike = Union[str, "os.PathLike[str]"]
Events = Dict[str, Any]

#: Columns of ``particles.csv`` (µs, px).
PARTICLES_COLUMNS = ["pulse", "t_us", "x", "y", "n_events"]
#: Columns of ``tracks.csv`` (µs, px, px/s).
TRACKS_COLUMNS = ["track_id", "pulse", "t_us", "x", "y", "u", "v"]
#: Columns a calibration adds to the tracks (mm, m/s).
TRACKS_PHYSICAL_COLUMNS = ["X_mm", "Y_mm", "U_m_s", "V_m_s"]

#: Columns of the ``grid`` table (``grid.parquet``, ``.csv`` or ``.npy``):
#: px, px/s, (px/s)²; rows ordered by y then x.
GRID_COLUMNS = ["x", "y", "count", "u", "v", "uu", "vv", "uv"]
#: The defaults of ``ebptv grid`` (read from the library): ``bin``,
#: ``overlap``, ``origin``, ``weighting``, ``fit``, ``min_count``,
#: ``noise_rms``.
GRID_DEFAULTS: Dict[str, Any] = dict(_ebptv.GRID_DEFAULTS)

#: Events per chunk of :func:`iter_events` (the library's reading chunk).
DEFAULT_CHUNK = 1 << 20


def _selection(
    t_range: Optional[Tuple[Optional[int], Optional[int]]],
    roi: Union[None, str, Sequence[int]],
    polarity: Optional[str],
) -> Dict[str, Any]:
    from_us, to_us = t_range if t_range is not None else (None, None)
    if roi is not None and not isinstance(roi, str):
        roi = ",".join(str(int(v)) for v in roi)
    return {"from_us": from_us, "to_us": to_us, "roi": roi, "polarity": polarity}


def read_events(
    path: PathLike,
    t_range: Optional[Tuple[Optional[int], Optional[int]]] = None,
    roi: Union[None, str, Sequence[int]] = None,
    polarity: Optional[str] = None,
) -> Events:
    """All events of a recording, as numpy columns.

    Any format ``ebptv`` reads (RAW EVT 2.0/2.1/3.0, DAT, CSV, AEDAT4, ES).
    The selection is that of ``ebptv convert``:

    - ``t_range=(from_us, to_us)``: events with ``from_us <= t < to_us``
      (µs of raw sensor time; either end may be ``None``);
    - ``roi=(x0, y0, width, height)`` (or the string ``"x0,y0,w,h"``);
    - ``polarity="on" | "off" | "both"`` (default both).

    Returns ``{"t": int64 µs, "x": uint16, "y": uint16, "p": uint8 (1 = ON),
    "triggers": {"t": int64, "channel": uint8, "rising": bool}}``; triggers
    are kept inside the time range (region and polarity do not apply).
    """
    return _ebptv.read_events(os.fspath(path), **_selection(t_range, roi, polarity))


def iter_events(
    path: PathLike,
    chunk: int = DEFAULT_CHUNK,
    t_range: Optional[Tuple[Optional[int], Optional[int]]] = None,
    roi: Union[None, str, Sequence[int]] = None,
    polarity: Optional[str] = None,
) -> Iterator[Events]:
    """The events of :func:`read_events`, streamed: dicts of the same
    columns holding about ``chunk`` events each (fewer after a selection),
    so a recording larger than memory can be processed piece by piece."""
    if chunk < 1:
        raise ValueError(f"chunk = {chunk}: must be at least 1")
    return iter(_ebptv.EventChunks(os.fspath(path), chunk, **_selection(t_range, roi, polarity)))


def info(path: PathLike) -> Dict[str, Any]:
    """What ``ebptv info --json`` prints for the recording: format,
    geometry, counts, time span, rates, anomalies and the pulsed-light
    verdict (``"pulsed"``)."""
    return json.loads(_ebptv.info(os.fspath(path)))


def track(
    path_or_particles: Union[PathLike, pd.DataFrame],
    *,
    params: Optional[PathLike] = None,
    max_disp: Optional[float] = None,
    gap: Optional[int] = None,
    min_length: Optional[int] = None,
    radius: Optional[float] = None,
    prior: Optional[Tuple[float, float]] = None,
    pulse_hz: Optional[float] = None,
    ignore_triggers: bool = False,
    force_pulses: bool = False,
    all_polarities: bool = False,
    hot_pixels: Optional[PathLike] = None,
    linker: Optional[str] = None,
    calibration: Optional[PathLike] = None,
    mask: Optional[PathLike] = None,
) -> Tuple[pd.DataFrame, pd.DataFrame]:
    """The run of ``ebptv track`` in memory: ``(particles, tracks)``.

    ``path_or_particles`` is a recording, a ``particles.csv`` (linking
    only) or a DataFrame with the particles columns
    (``pulse, t_us, x, y, n_events``). The options are those of
    ``ebptv track`` with the same defaults (``None``: the library's
    default; ``params``: a ``params.toml`` as for ``--params``, the other
    options over it; ``linker``: ``"sequential"`` or ``"sliced"``).

    ``calibration``: a ``calib.toml`` as for ``--calibration``: ``tracks``
    gains the physical columns ``X_mm, Y_mm, U_m_s, V_m_s`` after the pixel
    ones, and the file's ``[mask]`` applies. ``mask``: as ``--mask``, a PNG
    of the sensor's size (non-zero = not flow: its events are ignored, no
    track is stitched across it) or a list of hot pixels (``x,y`` lines).

    ``particles`` has the ``particles.csv`` columns and ``tracks`` the
    ``tracks.csv`` columns, row for row what ``ebptv track`` writes
    (values unrounded: the files round x, y to 4 and u, v to 3 decimals).
    ``tracks.attrs`` holds ``summary`` (summary.json), ``pulses``
    (pulses.json; ``None`` for particles) and ``params`` (params.toml).
    """
    options = dict(
        max_disp=max_disp,
        gap=gap,
        min_length=min_length,
        radius=radius,
        prior=tuple(prior) if prior is not None else None,
        pulse_hz=pulse_hz,
        ignore_triggers=ignore_triggers,
        force_pulses=force_pulses,
        all_polarities=all_polarities,
        hot_pixels=os.fspath(hot_pixels) if hot_pixels is not None else None,
        linker=linker,
        calibration=os.fspath(calibration) if calibration is not None else None,
        mask=os.fspath(mask) if mask is not None else None,
    )
    params_path = os.fspath(params) if params is not None else None
    if isinstance(path_or_particles, pd.DataFrame):
        df = path_or_particles
        missing = [c for c in PARTICLES_COLUMNS if c not in df.columns]
        if missing:
            raise EbptvError(f"particles: missing column(s) {', '.join(missing)}")
        cols = (
            np.ascontiguousarray(df["pulse"], dtype=np.int64),
            np.ascontiguousarray(df["t_us"], dtype=np.float64),
            np.ascontiguousarray(df["x"], dtype=np.float64),
            np.ascontiguousarray(df["y"], dtype=np.float64),
            np.ascontiguousarray(df["n_events"], dtype=np.uint32),
        )
        result = _ebptv.track(particles=cols, params=params_path, options=options)
    else:
        result = _ebptv.track(
            path=os.fspath(path_or_particles), params=params_path, options=options
        )
    pcols, tcols, summary, pulses, toml, physical = result
    particles = pd.DataFrame(pcols, columns=PARTICLES_COLUMNS)
    tracks = pd.DataFrame(tcols, columns=TRACKS_COLUMNS)
    if physical is not None:
        for c in TRACKS_PHYSICAL_COLUMNS:
            tracks[c] = physical[c]
    tracks.attrs["summary"] = json.loads(summary)
    tracks.attrs["pulses"] = json.loads(pulses) if pulses is not None else None
    tracks.attrs["params"] = toml
    return particles, tracks


def to_trackpy(tracks: pd.DataFrame) -> pd.DataFrame:
    """Tracks with trackpy's column names: ``frame`` (the pulse),
    ``particle`` (the track id), ``x``, ``y``, plus ``t_us``, ``u``, ``v``."""
    out = tracks.rename(columns={"pulse": "frame", "track_id": "particle"})
    cols = ["frame", "particle", "x", "y"] + [
        c for c in ("t_us", "u", "v") if c in out.columns
    ]
    return out[cols].reset_index(drop=True)


def grid_state(
    tracks: pd.DataFrame,
    bin: Optional[float] = None,
    bin_h: Optional[float] = None,
    overlap: Optional[float] = None,
    origin: Optional[Tuple[float, float]] = None,
    weighting: Optional[str] = None,
    what: str = "tracks",
) -> str:
    """The grid accumulator of a tracks table (columns of ``tracks.csv``),
    binned as ``ebptv grid`` bins a tracks file, as the text of a
    ``grid_state.json`` (what ``ebptv grid --merge`` reads).

    States of parts of a table (contiguous rows, or time slices) merge
    with :func:`grid_merge` into the state of the whole, to rounding.
    ``None`` takes the default of ``ebptv grid`` (:data:`GRID_DEFAULTS`):
    16 px square bins, no overlap, origin at pixel corners, top-hat
    weighting.
    """
    d = GRID_DEFAULTS
    return _ebptv.grid_state(
        np.ascontiguousarray(tracks["track_id"], dtype=np.uint64),
        np.ascontiguousarray(tracks["t_us"], dtype=np.float64),
        np.ascontiguousarray(tracks["x"], dtype=np.float64),
        np.ascontiguousarray(tracks["y"], dtype=np.float64),
        np.ascontiguousarray(tracks["u"], dtype=np.float64),
        np.ascontiguousarray(tracks["v"], dtype=np.float64),
        float(d["bin"] if bin is None else bin),
        None if bin_h is None else float(bin_h),
        float(d["overlap"] if overlap is None else overlap),
        tuple(d["origin"] if origin is None else origin),
        d["weighting"] if weighting is None else weighting,
        what,
    )


def grid_merge(states: Sequence[str]) -> str:
    """Grid states (:func:`grid_state`) merged in order, as
    ``ebptv grid --merge`` merges ``grid_state.json`` files: bins must share
    size, overlap, origin and weighting; the window grows to hold all."""
    return _ebptv.grid_merge(list(states))


def grid_estimate(
    state: str,
    fit: Optional[str] = None,
    min_count: Optional[int] = None,
    noise_rms: Optional[float] = None,
) -> pd.DataFrame:
    """The statistics of a grid state: the ``grid`` table's columns
    (``x, y, count, u, v, uu, vv, uv``; empty bins NaN) plus ``n_tracks``.
    ``fit``: ``"none"`` (bin mean), ``"linear"`` or ``"quadratic"``; the
    defaults are those of ``ebptv grid``. ``attrs`` holds ``nx`` and ``ny``."""
    d = GRID_DEFAULTS
    cols = _ebptv.grid_estimate(
        state,
        d["fit"] if fit is None else fit,
        int(d["min_count"] if min_count is None else min_count),
        float(d["noise_rms"] if noise_rms is None else noise_rms),
    )
    nx, ny = cols.pop("nx"), cols.pop("ny")
    out = pd.DataFrame(cols, columns=GRID_COLUMNS + ["n_tracks"])
    out.attrs["nx"], out.attrs["ny"] = nx, ny
    return out


def grid(
    tracks: pd.DataFrame,
    bin: Optional[float] = None,
    bin_h: Optional[float] = None,
    overlap: Optional[float] = None,
    origin: Optional[Tuple[float, float]] = None,
    weighting: Optional[str] = None,
    fit: Optional[str] = None,
    min_count: Optional[int] = None,
    noise_rms: Optional[float] = None,
    as_xarray: Optional[bool] = None,
) -> Any:
    """Tracks binned onto an Eulerian grid, the same options and defaults
    as ``ebptv grid`` (``None``: the CLI's default, :data:`GRID_DEFAULTS`).
    ``tracks`` has the ``tracks.csv`` columns (from :func:`track`).

    ``as_xarray``: ``None`` (the default) gives an ``xarray.Dataset`` when
    xarray is installed and a DataFrame otherwise; ``True`` always a
    Dataset (``ImportError`` without xarray); ``False`` always a DataFrame.

    The DataFrame is ``ebptv grid``'s ``grid`` table (see
    :func:`grid_estimate`): rows by y then x, ``attrs`` ``nx`` and ``ny``.
    The Dataset holds the same values on dimensions ``(y, x)`` (bin
    centres, px, as coordinates): ``count``, ``u``, ``v`` (px/s), ``uu``,
    ``vv``, ``uv`` ((px/s)²) and ``n_tracks``; empty bins NaN.
    """
    state = grid_state(tracks, bin, bin_h, overlap, origin, weighting)
    frame = grid_estimate(state, fit, min_count, noise_rms)
    if as_xarray is False:
        return frame
    try:
        import xarray  # noqa: F401
    except ImportError:
        if as_xarray:
            raise
        return frame
    return grid_to_xarray(frame)


def grid_to_xarray(frame: pd.DataFrame) -> Any:
    """A grid DataFrame (:func:`grid_estimate`, rows by y then x) as an
    ``xarray.Dataset`` on dimensions ``(y, x)``."""
    import xarray as xr

    nx, ny = int(frame.attrs["nx"]), int(frame.attrs["ny"])
    x = frame["x"].to_numpy()[:nx]
    y = frame["y"].to_numpy()[::nx] if nx else frame["y"].to_numpy()
    units = {"count": "1", "u": "px/s", "v": "px/s", "uu": "(px/s)^2", "vv": "(px/s)^2",
             "uv": "(px/s)^2", "n_tracks": "1"}
    data = {
        c: (("y", "x"), frame[c].to_numpy().reshape(ny, nx), {"units": u})
        for c, u in units.items()
        if c in frame.columns
    }
    return xr.Dataset(
        data,
        coords={"x": ("x", x, {"units": "px"}), "y": ("y", y, {"units": "px"})},
        attrs={"nx": nx, "ny": ny},
    )


def simulate(
    preset: str = "demo",
    seconds: Optional[float] = None,
    seed: int = 1,
    out: Optional[PathLike] = None,
) -> Dict[str, Any]:
    """``ebptv simulate --preset PRESET [--seconds S] --seed SEED --out OUT``:
    a simulated recording with its ground truth (``seconds``: ``None`` keeps
    the preset's duration; ``out``: a new temporary directory when
    ``None``).

    Returns ``{"recording": path of the EVT 3.0 file, "events": its events
    (:func:`read_events`), "truth": the true particle images per pulse
    (``truth_particles.csv``) as a DataFrame, "summary": summary.json}``.
    """
    if out is None:
        import tempfile

        out = tempfile.mkdtemp(prefix=f"ebptv-{preset}-")
    out = os.fspath(out)
    summary = json.loads(_ebptv.simulate(out, preset, seconds, int(seed)))
    recording = os.path.join(out, summary["recording"])
    return {
        "recording": recording,
        "events": read_events(recording),
        "truth": pd.read_csv(os.path.join(out, "truth_particles.csv")),
        "summary": summary,
    }


def pulses(
    path: PathLike,
    pulse_hz: Optional[float] = None,
    pulse_hz_range: Optional[Tuple[float, float]] = None,
    trigger_channel: Optional[int] = None,
    ignore_triggers: bool = False,
    onset_latency_us: Optional[float] = None,
    force_pulses: bool = False,
) -> Dict[str, Any]:
    """``ebptv pulses``: the pulse timing and diagnostics of a recording.

    Returns ``pulses.json`` as a dict, plus ``"starts_us"``: the start time
    (µs) of every pulse, a numpy array. The options are those of
    ``ebptv pulses`` (``pulse_hz``: nominal frequency when estimating from
    the events, ±2 % searched; ``pulse_hz_range=(a, b)``; ``force_pulses``:
    go on when the events show no bursts locked to pulses).
    """
    text, starts = _ebptv.pulses(
        os.fspath(path),
        pulse_hz,
        tuple(pulse_hz_range) if pulse_hz_range is not None else None,
        trigger_channel,
        ignore_triggers,
        onset_latency_us,
        force_pulses,
    )
    report = json.loads(text)
    report["starts_us"] = starts
    return report


#: The defaults of ``ebptv spectra`` (read from the library):
#: ``line_points``, ``component``, ``bin``, ``every``, ``nperseg``,
#: ``seg_overlap``, ``f_min``, ``f_max`` (infinite: the Nyquist
#: frequency), ``min_count``.
SPECTRA_DEFAULTS: Dict[str, Any] = dict(_ebptv.SPECTRA_DEFAULTS)


def spectra(
    tracks: PathLike,
    points: Sequence[Tuple[float, float]] = (),
    line: Optional[Tuple[float, float, float, float]] = None,
    line_points: Optional[int] = None,
    component: Optional[str] = None,
    bin: Optional[float] = None,
    bin_h: Optional[float] = None,
    every: Optional[int] = None,
    nperseg: Optional[int] = None,
    seg_overlap: Optional[float] = None,
    f_min: Optional[float] = None,
    f_max: Optional[float] = None,
    moving_average: Optional[int] = None,
    min_count: Optional[int] = None,
    calibration: Optional[PathLike] = None,
) -> Dict[str, Any]:
    """``ebptv spectra``: velocity spectra (Welch PSD, significant peak,
    noise floor) at points and along a line, from a tracks table
    (``tracks.parquet``, ``.csv`` or ``.npy`` of :func:`track`'s run).

    ``points``: ``[(x, y), ...]`` (px; the first gives ``peak_hz``);
    ``line=(x0, y0, x1, y1)`` (px) with ``line_points`` points for the
    pre-multiplied spectra of ``component`` (``"u"``, ``"v"``, ``"sum"``).
    The other options are those of ``ebptv spectra``; ``None`` takes its
    default (:data:`SPECTRA_DEFAULTS`); ``calibration``: a ``calib.toml``.

    Returns ``spectrum.json`` as a dict, plus ``"psd"`` (the
    ``spectra.csv`` table, ``None`` without points) and
    ``"premultiplied_line"`` (the ``premultiplied_line.csv`` table,
    ``None`` without a line) as DataFrames.
    """
    text, spectra_csv, line_csv = _ebptv.spectra(
        os.fspath(tracks),
        [(float(x), float(y)) for x, y in points],
        tuple(float(v) for v in line) if line is not None else None,
        line_points,
        component,
        bin,
        bin_h,
        every,
        nperseg,
        seg_overlap,
        f_min,
        f_max,
        moving_average,
        min_count,
        os.fspath(calibration) if calibration is not None else None,
    )
    report = json.loads(text)
    report["psd"] = pd.read_csv(io.StringIO(spectra_csv)) if spectra_csv is not None else None
    report["premultiplied_line"] = (
        pd.read_csv(io.StringIO(line_csv)) if line_csv is not None else None
    )
    return report


def model_check(
    path: PathLike,
    out: Optional[PathLike] = None,
    model: Optional[PathLike] = None,
    seed: Optional[int] = None,
    replicates: Optional[int] = None,
    evaluations: Optional[int] = None,
    max_effects: Optional[int] = None,
    block_pulses: Optional[int] = None,
    pulse_hz: Optional[float] = None,
    ignore_triggers: Optional[bool] = None,
) -> Dict[str, Any]:
    """``ebptv model-check PATH --out OUT``: the measured recording against
    the simulator; the missing effects, fitted, with the gap before and
    after (docs/readme/modelcheck.md).

    ``model``: a starting scenario TOML (default: a standard sensor
    calibrated to the measurement). The other options are those of
    ``ebptv model-check``; ``None`` takes its default (seed 1, 5
    replicates, 12 evaluations, 3 effects, 100 block pulses). Without a trigger channel the pulses are
    found from the events, around ``pulse_hz`` when given;
    ``ignore_triggers``: find them from the events even when there are
    triggers. ``out``: the folder of ``model_check.json``,
    ``model.toml``, ``report.md`` and the figures (a new temporary
    directory when ``None``).

    Returns ``model_check.json`` as a dict, plus ``"out"``: the folder.
    """
    if out is None:
        import tempfile

        out = tempfile.mkdtemp(prefix="ebptv-model-check-")
    out = os.fspath(out)
    report = json.loads(
        _ebptv.model_check(
            os.fspath(path),
            out,
            os.fspath(model) if model is not None else None,
            seed,
            replicates,
            evaluations,
            max_effects,
            block_pulses,
            pulse_hz,
            ignore_triggers,
        )
    )
    report["out"] = out
    return report


#: The defaults of ``ebptv piv`` (read from the library): ``window``,
#: ``window_h``, ``spacing``, ``passes``, ``pyramid``, ``no_clip``,
#: ``frames``, ``step``, ``sigma``, ``counts``, ``both_polarities``,
#: ``force_pulses``.
PIV_DEFAULTS: Dict[str, Any] = dict(_ebptv.PIV_DEFAULTS)

#: Columns of the ``piv_mean`` table (px, px/s, (px/s)², fraction of valid steps).
PIV_MEAN_COLUMNS = ["x", "y", "u", "v", "uu", "vv", "uv", "valid"]
#: Columns of the ``piv_steps`` table.
PIV_STEPS_COLUMNS = ["step", "first_pulse", "t_us"]


def piv(
    path: PathLike,
    window: int = 32,
    frames: int = 5,
    *,
    window_h: Optional[int] = None,
    spacing: Optional[int] = None,
    passes: int = 3,
    pyramid: int = 1,
    no_clip: bool = False,
    step: Optional[int] = None,
    sigma: float = 1.0,
    counts: bool = False,
    both_polarities: bool = False,
    pulse_hz: Optional[float] = None,
    batch: Optional[int] = None,
    force_pulses: bool = False,
    calibration: Optional[PathLike] = None,
    mask: Optional[PathLike] = None,
) -> Dict[str, Any]:
    """``ebptv piv PATH``: multi-frame correlation PIV on the pulsed
    pseudo-images of a recording, in memory. The options are those of
    ``ebptv piv`` with the same defaults (:data:`PIV_DEFAULTS`):
    ``window`` px (``window_h``: its height, default the width), nodes
    ``spacing`` px apart (default half the window), ``passes``,
    ``pyramid``, ``frames`` pulses per evaluation and one every ``step``
    pulses (default ``frames - 1``), blur ``sigma`` px, ``counts``
    instead of binary pseudo-images, ``both_polarities``, ``pulse_hz``
    when the recording has no triggers, ``batch`` steps evaluated in
    parallel (the fields do not depend on it), ``force_pulses``,
    ``calibration`` (``calib.toml``: physical columns in ``mean``, its
    ``[mask]`` applied) and ``mask`` (PNG of the sensor's size).

    Returns a dict:

    - ``"mean"``: the ``piv_mean`` table as a DataFrame (:data:`PIV_MEAN_COLUMNS`,
      then ``X_mm, Y_mm, U_m_s, V_m_s, uu_m2_s2, vv_m2_s2, uv_m2_s2`` with a
      calibration);
    - ``"steps"``: the ``piv_steps`` table (:data:`PIV_STEPS_COLUMNS`);
    - ``"u"``, ``"v"`` (float32, px/s) and ``"flag"`` (uint8, 0 = valid):
      the fields of every step, shape ``(steps, ny, nx)``, as
      ``piv_u.npy``, ``piv_v.npy``, ``piv_flag.npy``; ``"x"`` (nx) and
      ``"y"`` (ny): the node coordinates (px);
    - ``"report"``: ``fields``, ``nodes``, ``nx``, ``ny``, ``pulse_hz``,
      ``nodes_without_vector`` (with a mask, else ``None``) and
      ``pulses`` (pulses.json).

    Every field is held in memory; for long recordings use the command
    line, which streams them to disk.
    """
    r = _ebptv.piv(
        os.fspath(path),
        window=int(window),
        window_h=window_h,
        spacing=spacing,
        passes=int(passes),
        pyramid=int(pyramid),
        no_clip=bool(no_clip),
        frames=int(frames),
        step=step,
        sigma=float(sigma),
        counts=bool(counts),
        both_polarities=bool(both_polarities),
        pulse_hz=pulse_hz,
        batch=batch,
        force_pulses=bool(force_pulses),
        calibration=os.fspath(calibration) if calibration is not None else None,
        mask=os.fspath(mask) if mask is not None else None,
    )
    first_pulse, t_us = r["first_pulse"], r["t_us"]
    steps = pd.DataFrame(
        {"step": np.arange(len(first_pulse)), "first_pulse": first_pulse, "t_us": t_us},
        columns=PIV_STEPS_COLUMNS,
    )
    ny, nx = len(r["y"]), len(r["x"])
    return {
        "mean": pd.read_csv(io.StringIO(r["mean_csv"])),
        "steps": steps,
        "u": r["u"],
        "v": r["v"],
        "flag": r["flag"],
        "x": r["x"],
        "y": r["y"],
        "report": {
            "fields": len(first_pulse),
            "nodes": r["nodes"],
            "nx": nx,
            "ny": ny,
            "pulse_hz": r["pulse_hz"],
            "nodes_without_vector": r["nodes_without_vector"],
            "pulses": json.loads(r["pulses"]),
        },
    }
