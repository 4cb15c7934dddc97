"""ebptv's Parquet tables read by an independent reader (pyarrow), checked
against the CSV tables of the same run."""

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pyarrow.parquet as pq
import pytest

BIN = os.environ.get("EBPTV_BIN", "target/release/ebptv")
DEV_VORTEX = Path("/work/shared/data/dev/ptvdev_vortex/events.raw")

# Column → (dtype, decimals the CSV keeps; None: written exactly).
COLUMNS = {
    "particles": {
        "pulse": ("int64", None),
        "t_us": ("float64", None),
        "x": ("float64", 4),
        "y": ("float64", 4),
        "n_events": ("int64", None),
    },
    "tracks": {
        "track_id": ("int64", None),
        "pulse": ("int64", None),
        "t_us": ("float64", None),
        "x": ("float64", 4),
        "y": ("float64", 4),
        "u": ("float64", 3),
        "v": ("float64", 3),
    },
}


def run(*args: str) -> None:
    subprocess.run([BIN, *args], check=True, capture_output=True)


@pytest.fixture(scope="module")
def simulated(tmp_path_factory: pytest.TempPathFactory) -> Path:
    sim = tmp_path_factory.mktemp("sim")
    run("simulate", "--preset", "demo", "--seconds", "0.1", "--out", str(sim))
    return sim / "recording.raw"


def recordings() -> list:
    cases = [pytest.param("simulated", id="simulated")]
    cases.append(
        pytest.param(
            DEV_VORTEX,
            id="ptvdev_vortex",
            marks=pytest.mark.skipif(
                not DEV_VORTEX.is_file(), reason="dev recording not on this machine"
            ),
        )
    )
    return cases


def track_both(rec: Path, tmp: Path) -> tuple:
    pq_dir, csv_dir = tmp / "parquet", tmp / "csv"
    run("track", str(rec), "--out", str(pq_dir))
    run("--table-format", "csv", "track", str(rec), "--out", str(csv_dir))
    return pq_dir, csv_dir


@pytest.mark.parametrize("recording", recordings())
def test_parquet_tables_equal_the_csv_tables(
    recording, simulated: Path, tmp_path: Path
) -> None:
    rec = simulated if recording == "simulated" else recording
    pq_dir, csv_dir = track_both(rec, tmp_path)
    assert not (pq_dir / "tracks.csv").exists()
    assert not (csv_dir / "tracks.parquet").exists()
    for table, cols in COLUMNS.items():
        pf = pq.ParquetFile(pq_dir / f"{table}.parquet")
        # The file's own schema: required INT64/DOUBLE columns, in order.
        schema = pf.schema_arrow
        assert schema.names == list(cols), table
        for name, (dtype, _) in cols.items():
            assert str(schema.field(name).type) == {"int64": "int64", "float64": "double"}[dtype]
        got = pf.read().to_pandas()
        # The CSV read with the contract's dtypes (a float column whose
        # values happen to be whole would be guessed int64 from the text).
        want = pd.read_csv(
            csv_dir / f"{table}.csv", dtype={n: d for n, (d, _) in cols.items()}
        )
        assert list(got.columns) == list(want.columns) == list(cols), table
        assert len(got) == len(want) > 100, (table, len(got), len(want))
        # Integer columns are integers in the CSV text too.
        guessed = pd.read_csv(csv_dir / f"{table}.csv", nrows=1000)
        for name, (dtype, decimals) in cols.items():
            assert str(got[name].dtype) == dtype, (table, name, got[name].dtype)
            if dtype == "int64":
                assert str(guessed[name].dtype) == "int64", (table, name)
            if decimals is None:
                np.testing.assert_array_equal(got[name].to_numpy(), want[name].to_numpy())
            else:
                # CSV rounds to `decimals`; Parquet keeps every bit.
                np.testing.assert_allclose(
                    got[name].to_numpy(),
                    want[name].to_numpy(),
                    rtol=0,
                    atol=0.5 * 10.0**-decimals * (1 + 1e-9),
                )
                assert not np.array_equal(got[name].to_numpy(), want[name].to_numpy())


def test_npy_tables_and_relinking(simulated: Path, tmp_path: Path) -> None:
    run("--table-format", "npy", "track", str(simulated), "--out", str(tmp_path / "npy"))
    run("track", str(simulated), "--out", str(tmp_path / "pq"))
    tracks_npy = np.load(tmp_path / "npy" / "tracks.npy")
    tracks_pq = pq.read_table(tmp_path / "pq" / "tracks.parquet").to_pandas()
    assert list(tracks_npy.dtype.names) == list(COLUMNS["tracks"])
    for name in COLUMNS["tracks"]:
        np.testing.assert_array_equal(tracks_npy[name], tracks_pq[name].to_numpy())
    # The particles table of a run, in any format, is an input of `track`:
    # the same particles link to the same tracks.
    relinked = []
    for src in ("npy/particles.npy", "pq/particles.parquet"):
        out = tmp_path / ("relinked_" + src.split("/")[0])
        run("track", str(tmp_path / src), "--out", str(out))
        relinked.append(pq.read_table(out / "tracks.parquet").to_pandas())
    assert len(relinked[0]) > 100
    pd.testing.assert_frame_equal(relinked[0], relinked[1])


# The other row tables: column → dtype. Their CSV writes every float in
# shortest round-trip form (equal values), except the simulator's truth,
# whose CSV keeps `decimals`.
F, I = "float64", "int64"
STATS = {"u": F, "v": F, "uu": F, "vv": F, "uv": F}
PHYSICAL = {c: F for c in ("X_mm", "Y_mm", "U_m_s", "V_m_s", "uu_m2_s2", "vv_m2_s2", "uv_m2_s2")}
GRID = {"x": F, "y": F, "count": I, **STATS}
GRID_EXTRA = {"x": F, "y": F, "n_tracks": I, "se_u": F, "se_v": F, "se_uu": F, "se_vv": F,
              "se_uv": F, "dudx": F, "dudy": F, "dvdx": F, "dvdy": F, "fit_params": I}
PIV_MEAN = {"x": F, "y": F, **STATS, "valid": F}
PIV_STEPS = {"step": I, "first_pulse": I, "t_us": F}
VECTORS = {"x": F, "y": F, "u": F, "v": F, "flag": I}
TRUTH = {"pulse": I, "t_us": F, "particle_id": I, "x": F, "y": F, "u": F, "v": F}
TRUTH_DECIMALS = {"t_us": 3, "x": 4, "y": 4, "u": 3, "v": 3}
CALIB = 'px_per_mm = 10.0\norigin_px = [0.0, 80.0]\ny_axis = "up"\n'


def assert_table_equals_csv(pq_path: Path, csv_path: Path, cols: dict, decimals=None) -> None:
    """The Parquet table `pq_path`, read by pyarrow, has the columns,
    dtypes and values of the CSV table `csv_path` of the same run."""
    decimals = decimals or {}
    assert pq_path.suffix == ".parquet" and csv_path.suffix == ".csv"
    assert not pq_path.with_suffix(".csv").exists(), pq_path
    assert not csv_path.with_suffix(".parquet").exists(), csv_path
    table = pq.read_table(pq_path)
    assert table.schema.names == list(cols), pq_path.name
    for name, dtype in cols.items():
        want_type = {"int64": "int64", "float64": "double"}[dtype]
        assert str(table.schema.field(name).type) == want_type, (pq_path.name, name)
        assert not table.schema.field(name).nullable or table.column(name).null_count == 0
    got = table.to_pandas()
    want = pd.read_csv(csv_path, dtype=cols)
    assert list(want.columns) == list(cols), csv_path.name
    assert len(got) == len(want) > 0, (pq_path.name, len(got), len(want))
    for name, dtype in cols.items():
        assert str(got[name].dtype) == dtype, (pq_path.name, name)
        g, w = got[name].to_numpy(), want[name].to_numpy()
        if name in decimals:
            np.testing.assert_array_equal(np.isnan(g), np.isnan(w))
            np.testing.assert_allclose(g, w, rtol=0, atol=0.5 * 10.0 ** -decimals[name] * (1 + 1e-9),
                                       equal_nan=True)
        else:
            # NaN (empty bins, nodes without a vector) equals NaN.
            np.testing.assert_array_equal(g, w, err_msg=f"{pq_path.name} {name}")


def write_png(path: Path, img: np.ndarray) -> None:
    """An 8-bit grey PNG."""
    import struct
    import zlib

    h, w = img.shape
    raw = b"".join(b"\x00" + img[r].astype(np.uint8).tobytes() for r in range(h))

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(
            ">I", zlib.crc32(kind + data) & 0xFFFFFFFF)

    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
                     + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))


@pytest.fixture(scope="module")
def runs(tmp_path_factory: pytest.TempPathFactory) -> dict:
    """The same simulation, grid, PIV and image PIV with Parquet, CSV and
    .npy tables: {format: {stage: folder}}."""
    d = tmp_path_factory.mktemp("formats")
    calib = d / "calib.toml"
    calib.write_text(CALIB)
    # Particle images and the same shifted by (3, -2) px.
    rng = np.random.default_rng(5)
    yy, xx = np.mgrid[0:96, 0:128]
    px, py = rng.uniform(0, 128, 300), rng.uniform(0, 96, 300)

    def frame(dx: float, dy: float) -> np.ndarray:
        img = np.zeros((96, 128))
        for x, y in zip(px + dx, py + dy):
            img += 200 * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / 2.0)
        return np.clip(img, 0, 255)

    images = []
    for k in range(3):
        images.append(d / f"f{k}.png")
        write_png(images[-1], frame(3 * k, -2 * k))
    out = {}
    for fmt in ("parquet", "csv", "npy"):
        o = {s: d / fmt / s for s in ("sim", "ptv", "grid", "grid_cal", "piv", "images")}
        flag = ["--table-format", fmt]
        run(*flag, "simulate", "--preset", "demo", "--seconds", "0.05", "--out", str(o["sim"]))
        if fmt == "parquet":
            run("track", str(o["sim"] / "recording.raw"), "--out", str(o["ptv"]))
        tracks = d / "parquet" / "ptv" / "tracks.parquet"
        run(*flag, "grid", str(tracks), "--bin", "16", "--no-plots", "--out", str(o["grid"]))
        run(*flag, "grid", str(tracks), "--bin", "16", "--no-plots", "--calibration", str(calib),
            "--out", str(o["grid_cal"]))
        run(*flag, "piv", str(o["sim"] / "recording.raw"), "--window", "32", "--frames", "5",
            "--out", str(o["piv"]))
        run(*flag, "piv-images", *map(str, images), "--sequence", "--window", "32", "--spacing", "16",
            "--out", str(o["images"]))
        out[fmt] = o
    return out


TABLES = [
    ("sim", "truth_particles", TRUTH),
    ("grid", "grid", GRID),
    ("grid", "grid_extra", GRID_EXTRA),
    ("grid_cal", "grid", {**GRID, **PHYSICAL}),
    ("piv", "piv_mean", PIV_MEAN),
    ("piv", "piv_steps", PIV_STEPS),
    ("images", "vectors_00000", VECTORS),
    ("images", "vectors_00001", VECTORS),
]


@pytest.mark.parametrize("stage,table,cols", TABLES, ids=[f"{s}/{t}" for s, t, _ in TABLES])
def test_row_tables_in_parquet_equal_the_csv(runs: dict, stage: str, table: str, cols: dict) -> None:
    decimals = TRUTH_DECIMALS if table == "truth_particles" else None
    pq_path = runs["parquet"][stage] / f"{table}.parquet"
    csv_path = runs["csv"][stage] / f"{table}.csv"
    assert_table_equals_csv(pq_path, csv_path, cols, decimals)
    # The .npy table: the same fields, dtypes and values as the Parquet one.
    arr = np.load(runs["npy"][stage] / f"{table}.npy")
    assert list(arr.dtype.names) == list(cols)
    got = pq.read_table(pq_path).to_pandas()
    for name, dtype in cols.items():
        assert str(arr.dtype[name]) == dtype, (table, name)
        np.testing.assert_array_equal(arr[name], got[name].to_numpy())


def test_empty_bins_and_nodes_are_nan_in_parquet(runs: dict) -> None:
    grid = pq.read_table(runs["parquet"]["grid"] / "grid.parquet").to_pandas()
    assert grid["u"].isna().any() and grid["u"].notna().sum() > 50
    assert (grid["count"][grid["u"].isna()] < 10).all()


def test_every_reader_takes_every_format(runs: dict, tmp_path: Path) -> None:
    """`compare` reads grid and PIV tables of any format: the same numbers
    from Parquet, CSV and .npy."""
    reports = []
    for fmt in ("parquet", "csv", "npy"):
        o = runs[fmt]
        run("compare", "--ptv", str(o["grid"] / f"grid.{fmt}"), "--piv", str(o["piv"] / f"piv_mean.{fmt}"),
            "--out", str(tmp_path / fmt))
        rep = json.loads((tmp_path / fmt / "compare.json").read_text())
        reports.append({k: v for k, v in rep.items() if k not in ("ptv", "piv", "provenance")})
    assert reports[0] == reports[1] == reports[2]
