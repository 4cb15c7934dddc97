"""PIV from Python against `ebptv piv`, grids as xarray Datasets, tracks
in physical units against `ebptv track --calibration --mask`, and Ctrl-C
during the long calls."""

from __future__ import annotations

import inspect
import json
import os
import re
import signal
import struct
import subprocess
import sys
import time
import zlib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import ebptv
from test_api import (  # noqa: F401 (fixtures)
    ROOT,
    TRACK_DECIMALS,
    cli_error,
    cli_ok,
    real,
    sim,
    sim_run,
)

VORTEX = ROOT.parent / "shared" / "data" / "dev" / "ptvdev_vortex" / "events.raw"


def vortex() -> Path:
    if not VORTEX.is_file():
        pytest.skip(f"{VORTEX} not found")
    return VORTEX


def write_png(path: Path, mask: np.ndarray) -> None:
    """An 8-bit grey PNG of `mask` (non-zero = masked)."""
    h, w = mask.shape
    raw = b"".join(b"\x00" + bytes(row) for row in (mask != 0).astype(np.uint8) * 255)

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(
            ">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
                     + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))


CALIB = """px_per_mm = 12.5
origin_px = [240.0, 160.0]
y_axis = "up"

[mask]
polygons = [[[0, 0], [480, 0], [480, 40], [0, 40]]]
"""


def read_table(out: Path, stem: str) -> pd.DataFrame:
    """The table `stem` of a run: Parquet (the default) or CSV."""
    pq = out / f"{stem}.parquet"
    return pd.read_parquet(pq) if pq.exists() else pd.read_csv(out / f"{stem}.csv")


def assert_piv_equals_cli_files(got: dict, out: Path) -> None:
    pd.testing.assert_frame_equal(got["mean"], read_table(out, "piv_mean"))
    # (t_us is float; the CSV's whole microseconds read back as integers.)
    pd.testing.assert_frame_equal(got["steps"], read_table(out, "piv_steps"),
                                  check_dtype=False)
    for name in ("u", "v", "flag"):
        want = np.load(out / f"piv_{name}.npy")
        assert got[name].dtype == want.dtype and got[name].shape == want.shape, name
        np.testing.assert_array_equal(got[name], want, err_msg=name)
    n, ny, nx = got["u"].shape
    assert got["report"]["fields"] == n == len(got["steps"])
    assert (ny, nx) == (got["report"]["ny"], got["report"]["nx"]) == (len(got["y"]), len(got["x"]))
    np.testing.assert_array_equal(got["mean"]["x"].to_numpy()[:nx], got["x"])
    np.testing.assert_array_equal(got["mean"]["y"].to_numpy()[::nx], got["y"])


def test_piv_equals_ebptv_piv(sim: Path, tmp_path: Path) -> None:  # noqa: F811
    out = tmp_path / "piv"
    r = subprocess.run([os.environ.get("EBPTV_BIN", str(ROOT / "target/release/ebptv")), "piv",
                        str(sim), "--out", str(out)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    got = ebptv.piv(sim)
    assert_piv_equals_cli_files(got, out)
    assert list(got["mean"].columns) == ebptv.PIV_MEAN_COLUMNS
    rep = got["report"]
    assert f"{rep['fields']} PIV fields, {rep['nodes']} nodes each" in r.stderr
    assert rep["fields"] > 40 and rep["nodes_without_vector"] is None
    pulses = ebptv.pulses(sim)
    pulses.pop("starts_us")
    assert rep["pulses"] == pulses
    assert rep["pulse_hz"] == pytest.approx(1e6 / pulses["period_us"])
    # A measured flow: most vectors valid, the vortex turning.
    assert (got["flag"] == 0).mean() > 0.8
    assert np.nanmax(np.abs(got["mean"]["u"])) > 1000


def test_piv_options_calibration_and_mask_equal_the_cli(tmp_path: Path) -> None:
    rec = vortex()
    calib = tmp_path / "calib.toml"
    calib.write_text(CALIB)
    strut = np.zeros((320, 480), np.uint8)
    strut[:, 200:232] = 1
    mask = tmp_path / "strut.png"
    write_png(mask, strut)
    out = tmp_path / "piv"
    cli_ok("--table-format", "csv", "piv", str(rec), "--window", "24", "--frames", "4", "--step", "5", "--passes", "2",
           "--sigma", "0.8", "--calibration", str(calib), "--mask", str(mask), "--out", str(out))
    got = ebptv.piv(rec, window=24, frames=4, step=5, passes=2, sigma=0.8, calibration=calib,
                    mask=mask)
    assert_piv_equals_cli_files(got, out)
    assert list(got["mean"].columns[8:]) == [
        "X_mm", "Y_mm", "U_m_s", "V_m_s", "uu_m2_s2", "vv_m2_s2", "uv_m2_s2"]
    # The wall band and the strut give no vector.
    assert got["report"]["nodes_without_vector"] > 0
    assert np.all(got["mean"]["valid"][got["mean"]["y"] < 30] == 0)


def test_piv_defaults_are_the_cli_defaults() -> None:
    help_text = cli_ok("piv", "--help")
    sig = inspect.signature(ebptv.piv).parameters
    d = ebptv.PIV_DEFAULTS
    for name in ("window", "frames", "passes", "pyramid", "sigma"):
        assert sig[name].default == d[name], name
        assert re.search(rf"--{name.replace('_', '-')} <[A-Z_]+>.*?\[default: {d[name]:g}\]",
                         help_text, re.S), name
    for name in ("no_clip", "counts", "both_polarities", "force_pulses"):
        assert sig[name].default is d[name] is False, name
    assert d["step"] == d["frames"] - 1 and d["window_h"] == d["window"]
    assert d["spacing"] == d["window"] // 2


def test_piv_bad_input_raises_the_cli_message(sim: Path, tmp_path: Path) -> None:  # noqa: F811
    small = tmp_path / "small.png"
    write_png(small, np.zeros((10, 10), np.uint8))
    for path, kwargs, args in [
        (tmp_path / "missing.raw", {}, []),
        (sim, {"frames": 1}, ["--frames", "1"]),
        (sim, {"pyramid": 3, "frames": 3}, ["--pyramid", "3", "--frames", "3"]),
        (sim, {"mask": small}, ["--mask", str(small)]),
        (real("evt3_sample.raw"), {}, []),
    ]:
        message = cli_error("piv", str(path), *args, "--out", str(tmp_path / "o"))
        with pytest.raises(ebptv.EbptvError) as e:
            ebptv.piv(path, **kwargs)
        assert str(e.value) == message


def test_grid_is_an_xarray_dataset_of_the_dataframe_values(sim_run: Path) -> None:  # noqa: F811
    xr = pytest.importorskip("xarray")
    tracks = pd.read_csv(sim_run / "tracks.csv")
    ds = ebptv.grid(tracks, bin=24)
    assert isinstance(ds, xr.Dataset)
    df = ebptv.grid(tracks, bin=24, as_xarray=False)
    assert isinstance(df, pd.DataFrame)
    ny, nx = df.attrs["ny"], df.attrs["nx"]
    assert ds.sizes == {"y": ny, "x": nx} and nx > 5 and ny > 5
    for c in ("count", "u", "v", "uu", "vv", "uv", "n_tracks"):
        np.testing.assert_array_equal(ds[c].values.ravel(), df[c].to_numpy(), err_msg=c)
    # The coordinates: value at (y, x) is the row with that x and y.
    row = df.dropna().iloc[len(df.dropna()) // 2]
    assert float(ds["u"].sel(x=row["x"], y=row["y"])) == row["u"]
    assert ds["u"].attrs["units"] == "px/s"
    assert isinstance(ebptv.grid(tracks, as_xarray=True), xr.Dataset)


def test_track_in_physical_units_equals_the_cli(sim: Path, tmp_path: Path) -> None:  # noqa: F811
    calib = tmp_path / "calib.toml"
    calib.write_text(CALIB.replace("480", "640"))
    strut = np.zeros((360, 640), np.uint8)
    strut[:, 300:320] = 1
    mask = tmp_path / "strut.png"
    write_png(mask, strut)
    out = tmp_path / "t"
    cli_ok("--table-format", "csv", "track", str(sim), "--calibration", str(calib), "--mask",
           str(mask), "--out", str(out))
    _, tracks = ebptv.track(sim, calibration=calib, mask=mask)
    assert list(tracks.columns[7:]) == ebptv.TRACKS_PHYSICAL_COLUMNS
    want = pd.read_csv(out / "tracks.csv")
    assert list(tracks.columns) == list(want.columns) and len(tracks) == len(want) > 1000
    for c in ebptv.TRACKS_COLUMNS:
        d = TRACK_DECIMALS.get(c)
        atol = 0 if d is None else 0.51 * 10.0**-d
        np.testing.assert_allclose(tracks[c], want[c], rtol=0, atol=atol, err_msg=c)
    for c in ebptv.TRACKS_PHYSICAL_COLUMNS:  # 7 significant digits in the file
        np.testing.assert_allclose(tracks[c], want[c], rtol=1e-6, atol=1e-12, err_msg=c)
    # 12.5 px/mm, y up: mm from px, m/s from px/s.
    np.testing.assert_allclose(tracks["X_mm"], (tracks["x"] - 240) / 12.5)
    np.testing.assert_allclose(tracks["V_m_s"], -tracks["v"] / 12.5e3)
    assert not ((tracks["x"] > 301) & (tracks["x"] < 318)).any(), "points in the strut"
    _, plain = ebptv.track(sim)
    assert list(plain.columns) == ebptv.TRACKS_COLUMNS and len(plain) > len(tracks)
    missing = tmp_path / "missing.toml"
    with pytest.raises(ebptv.EbptvError) as e:
        ebptv.track(sim, calibration=missing)
    assert str(e.value) == cli_error("track", str(sim), "--calibration", str(missing),
                                     "--out", str(tmp_path / "o"))


@pytest.fixture(scope="module")
def long_sim(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A simulated recording long enough that every call below runs for
    seconds (the demo scene, 1 s, 5000 pulses)."""
    out = tmp_path_factory.mktemp("long")
    cli_ok("simulate", "--preset", "demo", "--seconds", "1", "--seed", "2", "--out", str(out))
    return out / "recording.raw"


# The child handles Ctrl-C as the interactive Python prompt does, even when the
# tests run in the background (which starts processes with SIGINT ignored).
CHILD = """
import signal, sys, time, ebptv
signal.signal(signal.SIGINT, signal.default_int_handler)
call = {call}
print("started", flush=True)
t0 = time.perf_counter()
try:
    call()
except KeyboardInterrupt:
    print("interrupted", time.perf_counter() - t0, flush=True)
else:
    print("finished", time.perf_counter() - t0, flush=True)
"""


@pytest.mark.parametrize("call, delay", [
    ("lambda: ebptv.pulses(sys.argv[1])", 0.1),
    ("lambda: ebptv.track(sys.argv[1])", 1.0),
    ("lambda: ebptv.piv(sys.argv[1])", 1.0),
    ("lambda: ebptv.model_check(sys.argv[2])", 1.0),
])
def test_ctrl_c_interrupts_a_long_call(call: str, delay: float, long_sim: Path,
                                       sim: Path) -> None:  # noqa: F811
    child = subprocess.Popen([sys.executable, "-c", CHILD.format(call=call), str(long_sim),
                              str(sim)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert child.stdout is not None
    assert child.stdout.readline().strip() == "started"
    time.sleep(delay)
    sent = time.perf_counter()
    child.send_signal(signal.SIGINT)
    out, err = child.communicate(timeout=60)
    stopped = time.perf_counter() - sent
    assert out.startswith("interrupted"), (out, err)
    assert child.returncode == 0, err
    # Within a few checks (50 ms, one chunk, one pair of PIV fields).
    assert stopped < 5.0, stopped
