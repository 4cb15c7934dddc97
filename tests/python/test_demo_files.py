"""ebptv's output files read by an independent reader (numpy)."""

import json
import os
import subprocess
from pathlib import Path

import numpy as np

BIN = os.environ.get("EBPTV_BIN", "target/release/ebptv")


def test_demo_tracks_csv_is_read_by_numpy(tmp_path: Path) -> None:
    out = tmp_path / "demo"
    subprocess.run(
        [BIN, "--table-format", "csv", "demo", "--out", str(out)],
        check=True,
        capture_output=True,
    )
    assert not (out / "ptv" / "tracks.parquet").exists()
    tracks = np.genfromtxt(out / "ptv" / "tracks.csv", delimiter=",", names=True)
    for col in ("track_id", "pulse", "t_us", "x", "y", "u", "v"):
        assert col in tracks.dtype.names, col
    summary = json.loads((out / "ptv" / "summary.json").read_text())
    assert len(np.unique(tracks["track_id"])) == summary["tracks"]
    assert np.all(np.isfinite(tracks["u"]))
