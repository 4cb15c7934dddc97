"""ebptv's Parquet tables read by an independent reader (pyarrow), checked
against the CSV tables of the same run."""

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
