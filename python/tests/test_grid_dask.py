"""Grids: the package against `ebptv grid`, and a Dask graph of per-slice
binning against one binning of the whole table."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import ebptv
from test_api import cli_error, cli_ok, sim, sim_run  # noqa: F401 (fixtures)

STATS = ["u", "v", "uu", "vv", "uv"]


def test_grid_equals_ebptv_grid(sim_run: Path, tmp_path: Path) -> None:  # noqa: F811
    tracks = pd.read_csv(sim_run / "tracks.csv")
    for args, kw in [([], {}), (["--bin", "24", "--min-count", "5", "--fit", "linear"],
                                 dict(bin=24, min_count=5, fit="linear"))]:
        out = tmp_path / ("g" + "".join(args))
        cli_ok("grid", str(sim_run / "tracks.csv"), "--out", str(out), "--no-plots", *args)
        # The command's grid table is Parquet by default.
        assert not (out / "grid.csv").exists()
        want = pd.read_parquet(out / "grid.parquet")
        got = ebptv.grid(tracks, **kw, as_xarray=False)
        assert list(got.columns[:8]) == list(want.columns)
        assert len(got) == len(want)
        np.testing.assert_array_equal(got[["x", "y", "count"]], want[["x", "y", "count"]])
        np.testing.assert_allclose(got[STATS], want[STATS], rtol=1e-9, atol=1e-9)
        assert np.isfinite(got["u"]).sum() > 10


def test_grid_defaults_are_the_cli_defaults() -> None:
    help_text = cli_ok("grid", "--help")
    assert f"[default: {ebptv.GRID_DEFAULTS['bin']:g}]" in help_text
    assert f"[default: {ebptv.GRID_DEFAULTS['min_count']}]" in help_text


def test_bad_grid_options_raise_the_cli_message(sim_run: Path, tmp_path: Path) -> None:  # noqa: F811
    tracks = pd.read_csv(sim_run / "tracks.csv")
    with pytest.raises(ebptv.EbptvError) as e:
        ebptv.grid(tracks, bin=0)
    assert str(e.value) == cli_error(
        "grid", str(sim_run / "tracks.csv"), "--out", str(tmp_path / "o"), "--bin", "0"
    )


@pytest.mark.filterwarnings("ignore:Sending large graph")
def test_dask_slices_merge_to_the_grid_of_the_whole(sim: Path) -> None:  # noqa: F811
    dd = pytest.importorskip("dask.dataframe")
    distributed = pytest.importorskip("distributed")
    import ebptv.dask as edask

    _, tracks = ebptv.track(sim)
    tracks.attrs = {}
    whole = ebptv.grid(tracks, as_xarray=False)
    parts = dd.from_pandas(tracks, npartitions=5, sort=False)
    assert parts.npartitions == 5
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as cluster:
        with distributed.Client(cluster) as client:
            merged = client.compute(edask.grid(parts)).result()
    assert len(merged) == len(whole)
    np.testing.assert_array_equal(merged[["x", "y", "count", "n_tracks"]],
                                  whole[["x", "y", "count", "n_tracks"]])
    np.testing.assert_allclose(merged[STATS], whole[STATS], rtol=1e-9, atol=1e-6)
    # A slice alone is not the whole: the test can tell them apart.
    one = ebptv.grid(parts.get_partition(0).compute(), as_xarray=False)
    assert one["count"].sum() < whole["count"].sum()
