#!/usr/bin/env python3
"""Link the same particles.csv with trackpy and with ebptv; score both
against the truth.

Usage:
    python3 benches/peers/trackpy_compare.py DIR [--ebptv PATH] [--search-range 10] [--memory 2]

DIR holds particles.csv (pulse,t_us,x,y,n_events) and truth_particles.csv
(pulse,t_us,particle_id,x,y,u,v), as written by the simulator or by
`PTV_SYNTH_OUT=DIR cargo test --release --test ptv_synth_export -- --ignored`.

Scoring (identical for both trackers): every output point is attributed to
the nearest truth particle of its pulse within --match px (none if
farther). A link is a pair of consecutive points of one track; it is
correct when both belong to the same truth particle. precision = correct /
all links. A truth link is a truth particle detected (some detection
within --match px) at pulses k and k+1; recall = truth links that appear
as a link between consecutive pulses of one output track / truth links.
ebptv's tracks.csv holds fitted positions and bridged gap points, trackpy's
output the raw detections; both are attributed the same way.

Speed: trackpy is timed around link_df (plus its predictor); ebptv is timed
as a whole process (reading the CSV, linking, fitting, writing every output
file with fsync), so the comparison is conservative for ebptv; its CPU time
(user+sys) is reported too.
"""
import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree


def attribute(points, truth, max_dist):
    """Truth particle id of each (pulse, x, y) point, -1 when none is near."""
    ids = np.full(len(points), -1, dtype=np.int64)
    for pulse, grp in points.groupby("pulse"):
        tr = truth[truth.pulse == pulse]
        if tr.empty:
            continue
        tree = cKDTree(tr[["x", "y"]].to_numpy())
        d, i = tree.query(grp[["x", "y"]].to_numpy(), distance_upper_bound=max_dist)
        ok = np.isfinite(d)
        sel = np.full(len(grp), -1, dtype=np.int64)
        sel[ok] = tr.particle_id.to_numpy()[i[ok]]
        ids[points.index.get_indexer(grp.index)] = sel
    return ids


def score(tracks, detections, truth, max_dist):
    """tracks: DataFrame with track, pulse, x, y. detections: particles."""
    tracks = tracks.sort_values(["track", "pulse"]).reset_index(drop=True)
    tracks["tid"] = attribute(tracks, truth, max_dist)
    det = detections.reset_index(drop=True)
    det["tid"] = attribute(det, truth, max_dist)
    detected = set(zip(det.pulse[det.tid >= 0], det.tid[det.tid >= 0]))
    truth_links = {(k, i) for (k, i) in detected if (k + 1, i) in detected}
    same_track = tracks.track.to_numpy()[1:] == tracks.track.to_numpy()[:-1]
    a, b = tracks.tid.to_numpy()[:-1][same_track], tracks.tid.to_numpy()[1:][same_track]
    pa, pb = tracks.pulse.to_numpy()[:-1][same_track], tracks.pulse.to_numpy()[1:][same_track]
    correct = (a == b) & (a >= 0)
    found = {(k, i) for k, i, c, k2 in zip(pa, a, correct, pb) if c and k2 == k + 1} & truth_links
    links = int(same_track.sum())
    return {
        "links": links,
        "precision": float(correct.sum() / max(links, 1)),
        "recall": float(len(found) / max(len(truth_links), 1)),
        "truth_links": len(truth_links),
    }


def run_trackpy(particles, search_range, memory):
    import trackpy as tp

    tp.quiet()
    df = particles.rename(columns={"pulse": "frame"})[["frame", "x", "y"]].copy()
    pred = tp.predict.NearestVelocityPredict()
    t0 = time.perf_counter()
    c0 = time.process_time()
    # Dense seeding makes oversize subnetworks at this search range;
    # adaptive search is trackpy's documented remedy.
    linked = pred.link_df(df, search_range, memory=memory, adaptive_stop=1.0, adaptive_step=0.9)
    dt = time.perf_counter() - t0
    cpu = time.process_time() - c0
    out = linked.rename(columns={"frame": "pulse", "particle": "track"})[["track", "pulse", "x", "y"]]
    return out, dt, cpu


def run_ebptv(exe, particles_csv, search_range, memory):
    with tempfile.TemporaryDirectory() as out:
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        subprocess.run(
            [exe, "track", particles_csv, "--out", out, "--max-disp", str(search_range), "--gap", str(memory)],
            check=True,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        dt = time.perf_counter() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
        tracks = pd.read_csv(os.path.join(out, "tracks.csv")).rename(columns={"track_id": "track"})
        summary = json.load(open(os.path.join(out, "summary.json")))
    return tracks[["track", "pulse", "x", "y", "u", "v"]], dt, cpu, summary


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dir")
    ap.add_argument("--ebptv", default=os.path.join(os.path.dirname(__file__), "../../target/release/ebptv"))
    ap.add_argument("--search-range", type=float, default=10.0)
    ap.add_argument("--memory", type=int, default=2)
    ap.add_argument("--match", type=float, default=1.5, help="px: point-to-truth attribution distance")
    ap.add_argument("--skip-trackpy", action="store_true")
    a = ap.parse_args()

    pcsv = os.path.join(a.dir, "particles.csv")
    particles = pd.read_csv(pcsv)
    truth = pd.read_csv(os.path.join(a.dir, "truth_particles.csv"))
    n = len(particles)
    period_s = float(np.median(np.diff(np.unique(truth.t_us)))) * 1e-6
    rows = []

    tracks, dt, cpu, summary = run_ebptv(a.ebptv, pcsv, a.search_range, a.memory)
    s = score(tracks, particles, truth, a.match)
    # Velocity error of ebptv's fitted velocities at attributed points.
    tracks = tracks.copy()
    tracks["tid"] = attribute(tracks, truth, a.match)
    m = tracks[tracks.tid >= 0].merge(truth, left_on=["pulse", "tid"], right_on=["pulse", "particle_id"], suffixes=("", "_t"))
    vel = float(np.sqrt(np.mean(((m.u - m.u_t) * period_s) ** 2 + ((m.v - m.v_t) * period_s) ** 2) / 2))
    rows.append(("ebptv", s, dt, cpu, vel))

    if not a.skip_trackpy:
        tp_tracks, tp_dt, tp_cpu = run_trackpy(particles, a.search_range, a.memory)
        rows.append(("trackpy", score(tp_tracks, particles, truth, a.match), tp_dt, tp_cpu, float("nan")))

    print(f"{n} particles, {particles.pulse.nunique()} pulses, search range {a.search_range} px, memory/gap {a.memory}")
    print(f"{'tracker':8} {'precision':>9} {'recall':>7} {'links':>8} {'wall s':>8} {'cpu s':>7} {'points/cpu-s':>13} {'vel rms px/pulse':>16}")
    for name, s, dt, cpu, vel in rows:
        print(f"{name:8} {s['precision']:9.4f} {s['recall']:7.4f} {s['links']:8d} {dt:8.3f} {cpu:7.3f} {n / cpu:13.0f} {vel:16.3f}")
    if len(rows) == 2:
        print(f"speed-up: {rows[1][3] / rows[0][3]:.1f}x in CPU time, {rows[1][2] / rows[0][2]:.1f}x in wall time")


if __name__ == "__main__":
    sys.exit(main())
