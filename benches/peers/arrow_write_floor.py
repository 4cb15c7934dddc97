#!/usr/bin/env python3
"""Peer comparison: the cost of writing `ebptv track`'s tables with Apache
Arrow's C++ Parquet writer (pyarrow), as a floor for ebptv's writing stage.

`ebptv track REC --out DIR` writes `particles.parquet` and `tracks.parquet`
on its writer thread while the recording streams. This script reads both
tables back into memory (columnar, so the writer gets them at no cost: a
stricter floor than ebptv's writer, which also assembles the columns from
rows) and writes them again with pyarrow, with the settings ebptv uses
(Snappy, no dictionaries) and with no compression and Zstandard, best of
REPEAT, in CPU time of this process. It prints the bytes and the CPU ns per
event of the recording (`--events`, e.g. from `ebptv info --json`), to set
beside the writing row of `benches/stage_budget.sh`.

Usage: python3 benches/peers/arrow_write_floor.py DIR --events N [--repeat 3]
Needs: pip install pyarrow
"""
import argparse
import os
import tempfile
import time

import pyarrow.parquet as pq


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("dir", help="an `ebptv track` output directory (Parquet tables)")
    ap.add_argument("--events", type=int, required=True, help="events of the recording")
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args()
    tables = {}
    for name in ("particles", "tracks"):
        path = os.path.join(a.dir, name + ".parquet")
        tables[name] = pq.read_table(path)
        print(f"{name}: {tables[name].num_rows} rows, columns {tables[name].schema.names}, "
              f"ebptv's file {os.path.getsize(path)} B")
    print("| compression | bytes (both tables) | CPU s (best of %d) | CPU ns per event |" % a.repeat)
    print("|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for comp in ("NONE", "SNAPPY", "ZSTD"):
            best, size = float("inf"), 0
            for _ in range(a.repeat):
                t0 = time.process_time()
                size = 0
                for name, t in tables.items():
                    out = os.path.join(tmp, name + ".parquet")
                    pq.write_table(t, out, compression=comp, use_dictionary=False)
                    size += os.path.getsize(out)
                best = min(best, time.process_time() - t0)
            print(f"| {comp.lower()} | {size} | {best:.3f} | {1e9 * best / a.events:.0f} |")


if __name__ == "__main__":
    main()
