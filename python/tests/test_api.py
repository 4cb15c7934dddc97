"""The Python package against the command line: the same runs give the
same results, and bad input the same error message."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

import ebptv

ROOT = Path(__file__).resolve().parents[2]
BIN = os.environ.get("EBPTV_BIN", str(ROOT / "target" / "release" / "ebptv"))
# Real camera files, present where the shared data is (as in the Rust tests).
REAL = ROOT.parent / "shared" / "data" / "real"
REAL_FILES = [
    "evt3_sample.raw",
    "evt2_sample.raw",
    "faery_evt2.raw",
    "ncars_sample.dat",
    "davis346_test.aedat4",
    "atis_dvs.es",
]


def real(name: str) -> Path:
    p = REAL / name
    if not p.is_file():
        pytest.skip(f"{p} not found")
    return p


def cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([BIN, *args], capture_output=True, text=True)


def cli_ok(*args: str) -> str:
    r = cli(*args)
    assert r.returncode == 0, r.stderr
    return r.stdout


def cli_error(*args: str) -> str:
    """The message `ebptv` prints after `error: ` (to the end of stderr)."""
    r = cli(*args)
    assert r.returncode != 0
    at = r.stderr.rfind("error: ")
    assert at >= 0, r.stderr
    return r.stderr[at + len("error: ") :].rstrip("\n")


@pytest.fixture(scope="module")
def sim(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A simulated recording (the demo scene, 0.05 s, 250 pulses)."""
    out = tmp_path_factory.mktemp("sim")
    # The truth as CSV: ebptv.simulate writes truth_particles.csv too.
    cli_ok("--table-format", "csv", "simulate", "--preset", "demo", "--seconds", "0.05", "--seed", "3",
           "--out", str(out))
    return out / "recording.raw"


@pytest.fixture(scope="module")
def sim_run(sim: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("track")
    # CSV tables: the comparisons below read them with pandas.read_csv.
    cli_ok("--table-format", "csv", "track", str(sim), "--out", str(out))
    return out


# Timing of the reading pass, not a property of the file.
VOLATILE = {"decode_rate_mev_per_s", "decode_seconds"}


def info_cli(path: Path) -> dict:
    d = json.loads(cli_ok("info", "--json", str(path)))
    return {k: v for k, v in d.items() if k not in VOLATILE}


@pytest.mark.parametrize("name", REAL_FILES)
def test_info_and_events_of_real_files_match_the_cli(name: str) -> None:
    path = real(name)
    got = {k: v for k, v in ebptv.info(path).items() if k not in VOLATILE}
    want = info_cli(path)
    assert got == want
    ev = ebptv.read_events(path)
    assert len(ev["t"]) == want["events"]
    assert int((ev["p"] == 1).sum()) == want["on_events"]
    if len(ev["t"]):
        assert int(ev["t"].min()) == want["min_t_us"]
        assert int(ev["t"].max()) == want["max_t_us"]


def test_info_of_a_simulated_recording_matches_the_cli(sim: Path) -> None:
    got = {k: v for k, v in ebptv.info(sim).items() if k not in VOLATILE}
    assert got == info_cli(sim)
    assert got["pulsed"]["pulsed"] is True


def read_csv_events(path: Path) -> pd.DataFrame:
    return pd.read_csv(path, comment="#")


@pytest.mark.parametrize(
    "name,t_range,roi,polarity",
    [
        ("evt3_sample.raw", (None, None), None, None),
        ("evt3_sample.raw", None, (100, 50, 300, 200), "off"),
        ("atis_dvs.es", None, "10,20,100,80", "on"),
    ],
)
def test_selections_equal_ebptv_convert(
    name: str, t_range, roi, polarity, tmp_path: Path
) -> None:
    path = real(name)
    full = ebptv.read_events(path)
    if t_range is None:
        # The middle third of the recording.
        t0, t1 = int(full["t"].min()), int(full["t"].max())
        t_range = (t0 + (t1 - t0) // 3, t0 + 2 * (t1 - t0) // 3)
    args = ["convert", str(path), str(tmp_path / "sel.csv")]
    if t_range[0] is not None:
        args += ["--from-us", str(t_range[0])]
    if t_range[1] is not None:
        args += ["--to-us", str(t_range[1])]
    if roi is not None:
        args += ["--roi", roi if isinstance(roi, str) else ",".join(map(str, roi))]
    if polarity is not None:
        args += ["--polarity", polarity]
    cli_ok(*args)
    want = read_csv_events(tmp_path / "sel.csv")
    got = ebptv.read_events(path, t_range=t_range, roi=roi, polarity=polarity)
    assert len(got["t"]) == len(want) > 0
    for col in ("t", "x", "y", "p"):
        np.testing.assert_array_equal(got[col], want[col].to_numpy())


def test_iter_events_streams_what_read_events_reads(sim: Path) -> None:
    whole = ebptv.read_events(sim)
    chunks = list(ebptv.iter_events(sim, chunk=100_000))
    assert len(chunks) >= 10
    for col in ("t", "x", "y", "p"):
        np.testing.assert_array_equal(np.concatenate([c[col] for c in chunks]), whole[col])
    trig = np.concatenate([c["triggers"]["t"] for c in chunks])
    np.testing.assert_array_equal(trig, whole["triggers"]["t"])
    assert len(trig) > 0, "the simulated recording has trigger words"


def assert_same_tables(got: pd.DataFrame, csv: Path, decimals: dict) -> None:
    want = pd.read_csv(csv)
    assert list(got.columns) == list(want.columns)
    assert len(got) == len(want)
    for col in want.columns:
        d = decimals.get(col)
        if d is None:
            np.testing.assert_array_equal(got[col].to_numpy(), want[col].to_numpy(), err_msg=col)
        else:
            np.testing.assert_allclose(
                got[col].to_numpy(), want[col].to_numpy(), rtol=0, atol=0.51 * 10.0**-d,
                err_msg=col,
            )


def same_params(a: str, b: str) -> bool:
    """params.toml texts equal but for the table format (the CLI runs here
    write CSV; the in-memory run has no files)."""
    keep = lambda t: [l for l in t.splitlines() if not l.startswith("table_format")]
    return keep(a) == keep(b)


PARTICLE_DECIMALS = {"x": 4, "y": 4, "t_us": 6}
TRACK_DECIMALS = {"x": 4, "y": 4, "u": 3, "v": 3, "t_us": 6}


def test_track_equals_the_cli_files(sim: Path, sim_run: Path) -> None:
    particles, tracks = ebptv.track(sim)
    assert_same_tables(particles, sim_run / "particles.csv", PARTICLE_DECIMALS)
    assert_same_tables(tracks, sim_run / "tracks.csv", TRACK_DECIMALS)
    summary = json.loads((sim_run / "summary.json").read_text())
    # The CLI's summary also records how the run was made.
    assert "track" in summary.pop("provenance")["command_line"]
    assert tracks.attrs["summary"] == summary
    assert tracks.attrs["summary"]["tracks"] == tracks["track_id"].nunique() > 100
    pulses = json.loads((sim_run / "pulses.json").read_text())
    assert tracks.attrs["pulses"] == pulses
    assert same_params(tracks.attrs["params"], (sim_run / "params.toml").read_text())


def test_track_options_equal_the_cli_options(sim: Path, tmp_path: Path) -> None:
    # OFF events too: a params-file key on the command line.
    params = tmp_path / "all_polarities.toml"
    params.write_text("[cluster]\non_only = false\n")
    cli_ok("--table-format", "csv", "track", str(sim), "--out", str(tmp_path), "--max-disp", "6",
           "--min-length", "8", "--gap", "0", "--params", str(params))
    _, tracks = ebptv.track(sim, max_disp=6, min_length=8, gap=0, all_polarities=True)
    assert_same_tables(tracks, tmp_path / "tracks.csv", TRACK_DECIMALS)
    assert same_params(tracks.attrs["params"], (tmp_path / "params.toml").read_text())


def test_track_from_particles_equals_the_cli_on_particles_csv(
    sim_run: Path, tmp_path: Path
) -> None:
    csv = sim_run / "particles.csv"
    cli_ok("--table-format", "csv", "track", str(csv), "--out", str(tmp_path))
    _, from_file = ebptv.track(csv)
    _, from_frame = ebptv.track(pd.read_csv(csv))
    assert_same_tables(from_file, tmp_path / "tracks.csv", TRACK_DECIMALS)
    pd.testing.assert_frame_equal(from_file, from_frame)
    assert from_frame.attrs["pulses"] is None


def test_to_trackpy_names_the_columns_as_trackpy(sim: Path) -> None:
    _, tracks = ebptv.track(sim)
    tp = ebptv.to_trackpy(tracks)
    assert list(tp.columns[:4]) == ["frame", "particle", "x", "y"]
    np.testing.assert_array_equal(tp["frame"], tracks["pulse"])
    np.testing.assert_array_equal(tp["particle"], tracks["track_id"])


def test_bad_input_raises_the_cli_message(tmp_path: Path) -> None:
    missing = tmp_path / "missing.raw"
    with pytest.raises(ebptv.EbptvError) as e:
        ebptv.read_events(missing)
    assert str(e.value) == cli_error("info", str(missing))
    with pytest.raises(ebptv.EbptvError) as e:
        ebptv.info(missing)
    assert str(e.value) == cli_error("info", str(missing))
    garbage = tmp_path / "garbage.raw"
    garbage.write_bytes(b"\x00\x01not an event file" * 10)
    with pytest.raises(ebptv.EbptvError) as e:
        ebptv.track(garbage)
    assert str(e.value) == cli_error("track", str(garbage), "--out", str(tmp_path / "o"))
    with pytest.raises(ebptv.EbptvError) as e:
        ebptv.read_events(missing, roi=(1, 2, 0, 4))
    assert str(e.value) == cli_error("convert", str(missing), str(tmp_path / "o.csv"), "--roi", "1,2,0,4")
    with pytest.raises(ebptv.EbptvError) as e:
        ebptv.read_events(missing, polarity="up")
    assert "expected on, off or both" in str(e.value)


def test_an_unpulsed_real_recording_is_refused_as_by_the_cli(tmp_path: Path) -> None:
    path = real("evt3_sample.raw")
    with pytest.raises(ebptv.EbptvError) as e:
        ebptv.track(path)
    assert str(e.value) == cli_error("track", str(path), "--out", str(tmp_path / "o"))


def test_bad_options_raise(sim: Path, tmp_path: Path) -> None:
    with pytest.raises(ebptv.EbptvError) as e:
        ebptv.track(sim, linker="parallel")
    assert "linker" in str(e.value)
    bad = tmp_path / "p.toml"
    bad.write_text("[track]\nmax_dsip = 3.0\n")
    with pytest.raises(ebptv.EbptvError) as e:
        ebptv.track(sim, params=bad)
    assert str(e.value) == cli_error("track", str(sim), "--out", str(tmp_path / "o"), "--params", str(bad))


def test_ctrl_c_stops_a_tracking_run(sim: Path) -> None:
    import _thread
    import signal
    import threading
    import time

    # Ctrl-C as the interactive Python prompt has it: a process started in the
    # background (`cmd &` in a script, nohup) inherits SIGINT ignored, and
    # then `interrupt_main` does nothing.
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        t0 = time.perf_counter()
        ebptv.track(sim)
        whole = time.perf_counter() - t0
        timer = threading.Timer(0.1 * whole, _thread.interrupt_main)
        t0 = time.perf_counter()
        timer.start()
        with pytest.raises(KeyboardInterrupt):
            ebptv.track(sim)
        stopped = time.perf_counter() - t0
        timer.join()
    finally:
        signal.signal(signal.SIGINT, previous)
    assert stopped < 0.7 * whole, (stopped, whole)


def test_simulate_equals_ebptv_simulate(sim: Path, tmp_path: Path) -> None:
    got = ebptv.simulate("demo", seconds=0.05, seed=3, out=tmp_path / "s")
    raw = Path(got["recording"])
    assert raw.read_bytes() == sim.read_bytes()
    want_truth = pd.read_csv(sim.parent / "truth_particles.csv")
    pd.testing.assert_frame_equal(got["truth"], want_truth)
    assert len(got["events"]["t"]) == got["summary"]["events"] > 100_000
    with pytest.raises(ebptv.EbptvError) as e:
        ebptv.simulate("no-such-preset", out=tmp_path / "x")
    assert str(e.value) == cli_error("simulate", "--preset", "no-such-preset", "--out", str(tmp_path / "y"))


def test_pulses_equal_ebptv_pulses(sim: Path, tmp_path: Path) -> None:
    cli_ok("pulses", str(sim), "--out", str(tmp_path / "p"))
    want = json.loads((tmp_path / "p" / "pulses.json").read_text())
    # The CLI's report also records how it was made.
    assert want.pop("provenance")["command_line"][1] == "pulses"
    got = ebptv.pulses(sim)
    starts = got.pop("starts_us")
    assert got == want
    assert len(starts) == want["pulses"] >= 250
    np.testing.assert_allclose(np.diff(starts), want["period_us"], rtol=1e-12)


def test_pulses_of_an_unpulsed_real_file_raise_as_the_cli(tmp_path: Path) -> None:
    path = real("ncars_sample.dat")
    with pytest.raises(ebptv.EbptvError) as e:
        ebptv.pulses(path, pulse_hz=5000)
    assert str(e.value) == cli_error("pulses", str(path), "--pulse-hz", "5000", "--out", str(tmp_path / "q"))


def without_provenance(path: Path) -> dict:
    d = json.loads(path.read_text())
    d.pop("provenance", None)
    return d


def test_spectra_equal_ebptv_spectra(sim_run: Path, tmp_path: Path) -> None:
    tracks = sim_run / "tracks.csv"
    out = tmp_path / "spectra"
    cli_ok(
        "spectra", str(tracks), "--point", "100,100", "--point", "200,150",
        "--line", "50,50,300,200", "--line-points", "6", "--component", "sum",
        "--nperseg", "64", "--no-plots", "--out", str(out),
    )
    got = ebptv.spectra(
        tracks, points=[(100, 100), (200, 150)], line=(50, 50, 300, 200),
        line_points=6, component="sum", nperseg=64,
    )
    spectra, line = got.pop("psd"), got.pop("premultiplied_line")
    assert got == without_provenance(out / "spectrum.json")
    assert got["frames"] > 0 and len(got["points"]) == 2 and len(got["line"]["points"]) == 6
    pd.testing.assert_frame_equal(spectra, pd.read_csv(out / "spectra.csv"))
    pd.testing.assert_frame_equal(line, pd.read_csv(out / "premultiplied_line.csv"))
    assert len(spectra) == 33 and len(line) == 6 * 33


def test_spectra_defaults_are_the_cli_defaults(sim_run: Path, tmp_path: Path) -> None:
    tracks = sim_run / "tracks.csv"
    out = tmp_path / "spectra"
    # 250 frames: the default segment (256 frames) is too long for it.
    message = cli_error("spectra", str(tracks), "--point", "150,120", "--out", str(out))
    with pytest.raises(ebptv.EbptvError) as e:
        ebptv.spectra(tracks, points=[(150, 120)])
    assert str(e.value) == message and "(256)" in message
    cli_ok("spectra", str(tracks), "--point", "150,120", "--nperseg", "128", "--no-plots",
           "--out", str(out))
    got = ebptv.spectra(tracks, points=[(150, 120)], nperseg=128)
    assert got.pop("premultiplied_line") is None
    pd.testing.assert_frame_equal(got.pop("psd"), pd.read_csv(out / "spectra.csv"))
    assert got == without_provenance(out / "spectrum.json")
    assert ebptv.SPECTRA_DEFAULTS["nperseg"] == 256 and ebptv.SPECTRA_DEFAULTS["bin"] == 16


def test_spectra_bad_input_raises_the_cli_message(sim_run: Path, tmp_path: Path) -> None:
    missing = tmp_path / "missing.parquet"
    for args, kwargs, path in [
        ([], {}, sim_run / "tracks.csv"),
        (["--point", "1,1"], {"points": [(1, 1)]}, missing),
        (["--line", "0,0,9,9", "--line-points", "1"], {"line": (0, 0, 9, 9), "line_points": 1},
         sim_run / "tracks.csv"),
        (["--point", "1,1", "--bin", "0"], {"points": [(1, 1)], "bin": 0},
         sim_run / "tracks.csv"),
    ]:
        message = cli_error("spectra", str(path), *args, "--out", str(tmp_path / "o"))
        with pytest.raises(ebptv.EbptvError) as e:
            ebptv.spectra(path, **kwargs)
        assert str(e.value) == message


MODEL_CHECK_SMALL = dict(replicates=2, evaluations=3, max_effects=1, block_pulses=20)


def test_model_check_equals_ebptv_model_check(sim: Path, tmp_path: Path) -> None:
    args = [f"--{k.replace('_', '-')}={v}" for k, v in MODEL_CHECK_SMALL.items()]
    cli_ok("model-check", str(sim), *args, "--out", str(tmp_path / "cli"))
    got = ebptv.model_check(sim, out=tmp_path / "py", **MODEL_CHECK_SMALL)
    assert got.pop("out") == str(tmp_path / "py")
    # The notes name the output folder (the flow baseline's file).
    want = json.loads(
        (tmp_path / "cli" / "model_check.json").read_text().replace(str(tmp_path / "cli"), "OUT")
    )
    want.pop("provenance", None)
    got = json.loads(json.dumps(got).replace(str(tmp_path / "py"), "OUT"))
    assert got == want
    assert got["verdict"] in ("consistent", "explained", "unexplained") and got["notes"]
    assert (tmp_path / "py" / "model.toml").is_file()


def test_model_check_ignoring_the_triggers_finds_the_pulses_from_the_events(
    sim: Path, tmp_path: Path
) -> None:
    hinted = ebptv.model_check(
        sim, out=tmp_path / "hz", ignore_triggers=True, pulse_hz=5000.0, **MODEL_CHECK_SMALL
    )
    assert any("found from the events around 5000" in n for n in hinted["notes"]), hinted["notes"]


def test_model_check_bad_input_raises_the_cli_message(sim: Path, tmp_path: Path) -> None:
    for path, kwargs, args in [
        (sim, {"block_pulses": 5}, ["--block-pulses", "5"]),
        (sim, {"pulse_hz": 0.0}, ["--pulse-hz", "0"]),
        (tmp_path / "missing.raw", {}, []),
    ]:
        message = cli_error("model-check", str(path), *args, "--out", str(tmp_path / "o"))
        with pytest.raises(ebptv.EbptvError) as e:
            ebptv.model_check(path, out=tmp_path / "p", **kwargs)
        assert str(e.value) == message
