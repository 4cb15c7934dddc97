#!/usr/bin/env python3
"""Absurd values for every numeric option: no panic, no abort, no endless run.

    python3 benches/option_sweep.py [--bin target/release/ebptv] [--timeout 60]

Three sweeps, each value in turn with everything else at its default:
- the numeric command-line options of `pulses`, `grid`, `spectra` and
  `piv-images` (parsed from `--help`), on `speeddev_shedding`, the tracks
  `track` makes of it and four synthetic PNG frames (`piv`, a slow
  command, shares its correlation options with `piv-images`);
- every numeric key of `ebptv track`'s params.toml (`--params`), on
  `ptvdev_vortex`;
- every numeric key of a simulated scenario (`ebptv simulate --config`,
  the demo preset cut to 4 ms).

Values: 0, -1, 1e-12, 1e6, 1e12, nan (integers: 0, -1, 10^6, 10^12; on
the command line 10^8 too, where --help does not tell the type). Each
run is under `prlimit --as=4 GB`. A run is flagged (`!!`) when it ends
otherwise than with exit 0 (accepted), 1 (a clear error) or 2 (refused by
the argument parser): a panic (101), an abort (-6), a timeout. Accepted
runs slower than 10 s are listed too: an option that makes a run slow
should be bounded. Prints one line per run and a summary; exit 1 when
anything is flagged.
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DEV = ROOT.parent / "shared" / "data" / "dev"
FLOATS = ["0", "-1", "1e-12", "1e6", "1e12", "nan"]
INTS = ["0", "-1", "1000000", "1000000000000"]
# Command-line options: --help does not tell integers from floats.
CLI_VALUES = FLOATS + ["100000000"]


cmd_dir = tempfile.gettempdir()


def run(cmd: list[str], timeout: float) -> tuple[object, float, str]:
    t0 = time.perf_counter()
    try:
        # (In the scratch folder: options that name files, --write-mask
        # say, write them where the run is.)
        p = subprocess.run(["prlimit", "--as=4000000000", *cmd], capture_output=True, text=True,
                           timeout=timeout, cwd=cmd_dir)
        rc: object = p.returncode
        last = (p.stderr.strip().splitlines() or [""])[-1][:150]
    except subprocess.TimeoutExpired:
        rc, last = "timeout", ""
    return rc, time.perf_counter() - t0, last


def report(label: str, rc: object, dt: float, last: str, flagged: list[str]) -> None:
    bad = rc not in (0, 1, 2)
    slow = rc == 0 and dt > 10.0
    mark = "!!" if bad else ("slow" if slow else "  ")
    line = f"{mark} {label}: exit {rc}, {dt:.1f} s  {last}"
    print(line, flush=True)
    if bad:
        flagged.append(line)


def cli_sweep(ebptv: str, work: Path, timeout: float, flagged: list[str]) -> None:
    rec = DEV / "speeddev_shedding" / "events.raw"
    tracks_dir = work / "tracks"
    subprocess.run([ebptv, "track", str(rec), "--pulse-hz", "5000", "--out", str(tracks_dir)],
                   check=True, capture_output=True)
    tracks = str(tracks_dir / "tracks.parquet")
    base = {
        "pulses": [str(rec), "--pulse-hz", "5000"],
        "grid": [tracks],
        "spectra": [tracks, "--point", "320,180", "--line", "0,180,640,180"],
    }
    frames = synthetic_frames(work / "frames", 4)
    base["piv-images"] = [str(f) for f in frames]
    skip = {"--out", "--pulse-hz", "--point", "--line"}
    for cmd, args in base.items():
        help_text = subprocess.run([ebptv, cmd, "--help"], capture_output=True, text=True).stdout
        for opt, meta in re.findall(r"^\s+(?:-\w, )?(--[\w-]+) <([\w_]+)>", help_text, re.M):
            if opt in skip:
                continue
            for v in CLI_VALUES:
                out = work / "o"
                shutil.rmtree(out, ignore_errors=True)
                rc, dt, last = run([ebptv, cmd, *args, opt, v, "--out", str(out)], timeout)
                report(f"{cmd} {opt} {v}", rc, dt, last, flagged)


def synthetic_frames(folder: Path, n: int) -> list[Path]:
    """`n` 8-bit PNG frames of 256x256 px: 800 Gaussian particles moving
    (2.3, 1.1) px per frame (numpy and zlib only)."""
    import struct
    import zlib

    import numpy as np

    folder.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(1)
    xs, ys = rng.uniform(0, 256, 800), rng.uniform(0, 256, 800)
    yy, xx = np.mgrid[0:256, 0:256]

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (struct.pack(">I", len(data)) + kind + data
                + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF))

    paths = []
    for k in range(n):
        img = np.zeros((256, 256))
        for x, y in zip(xs + 2.3 * k, ys + 1.1 * k):
            img += 200 * np.exp(-((xx - x) ** 2 + (yy - y) ** 2) / 2.0)
        rows = np.clip(img, 0, 255).astype(np.uint8)
        raw = b"".join(b"\x00" + bytes(r) for r in rows)
        path = folder / f"f{k}.png"
        path.write_bytes(b"\x89PNG\r\n\x1a\n"
                         + chunk(b"IHDR", struct.pack(">IIBBBBB", 256, 256, 8, 0, 0, 0, 0))
                         + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))
        paths.append(path)
    return paths


def toml_sweep(name: str, text: str, command: list[str], work: Path, timeout: float,
               flagged: list[str]) -> None:
    lines = text.splitlines()
    section = ""
    for i, line in enumerate(lines):
        if line.startswith("["):
            section = line
        m = re.match(r"^(\w+) = (-?[0-9.e+-]+)$", line)
        if not m:
            continue
        key, value = m.groups()
        values = INTS if re.fullmatch(r"-?[0-9]+", value) else [
            v if "." in v or "e" in v or v == "nan" else v + ".0" for v in FLOATS]
        for v in values:
            path = work / f"{name}.toml"
            path.write_text("\n".join(lines[:i] + [f"{key} = {v}"] + lines[i + 1:]) + "\n")
            out = work / "o"
            shutil.rmtree(out, ignore_errors=True)
            rc, dt, last = run([*command, str(path), "--out", str(out)], timeout)
            report(f"{name} {section}{key} = {v}", rc, dt, last, flagged)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bin", default=str(ROOT / "target" / "release" / "ebptv"))
    ap.add_argument("--timeout", type=float, default=60.0)
    a = ap.parse_args()
    flagged: list[str] = []
    global cmd_dir
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        cmd_dir = tmp
        cli_sweep(a.bin, work, a.timeout, flagged)
        vortex = DEV / "ptvdev_vortex" / "events.raw"
        run_dir = work / "vortex"
        subprocess.run([a.bin, "track", str(vortex), "--out", str(run_dir)], check=True,
                       capture_output=True)
        toml_sweep("params", (run_dir / "params.toml").read_text(),
                   [a.bin, "track", str(vortex), "--params"], work, a.timeout, flagged)
        sim_dir = work / "sim"
        subprocess.run([a.bin, "simulate", "--preset", "demo", "--seconds", "0.004", "--out",
                        str(sim_dir)], check=True, capture_output=True)
        toml_sweep("scenario", (sim_dir / "scenario.toml").read_text(),
                   [a.bin, "simulate", "--config"], work, a.timeout, flagged)
    print(f"\n{len(flagged)} flagged")
    for line in flagged:
        print(line)
    return 1 if flagged else 0


if __name__ == "__main__":
    sys.exit(main())
