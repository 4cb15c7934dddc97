#!/usr/bin/env python3
"""Link the same particles.csv with trackpy and with ebptv; score both
against the truth.

Usage:
    python3 benches/peers/trackpy_compare.py DIR [--ebptv PATH] [--search-range 10] [--memory 2]

DIR holds particles.csv (pulse,t_us,x,y,n_events) and truth_particles.csv
(pulse,t_us,particle_id,x,y,u,v), as written by the simulator or by
`PTV_SYNTH_OUT=DIR cargo run --release -p ebptv-benches --example ptv_synth_export`.

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


def found_links(tracks, truth, max_dist):
    """Truth-particle links (pulse k, id) that a track holds between k and k+1,
    and the attributed points."""
    t = tracks.sort_values(["track", "pulse"]).reset_index(drop=True)
    t["tid"] = attribute(t, truth, max_dist)
    tr, pu, ti = t.track.to_numpy(), t.pulse.to_numpy(), t.tid.to_numpy()
    same = (tr[1:] == tr[:-1]) & (pu[1:] == pu[:-1] + 1) & (ti[1:] == ti[:-1]) & (ti[:-1] >= 0)
    return set(zip(pu[:-1][same], ti[:-1][same])), t


def missed_breakdown(eb, tp, detections, truth, max_dist):
    """Why ebptv misses the truth links that trackpy finds: where the
    particle's points are on ebptv's tracks at pulses k and k+1."""
    det = detections.reset_index(drop=True)
    det["tid"] = attribute(det, truth, max_dist)
    detected = set(zip(det.pulse[det.tid >= 0], det.tid[det.tid >= 0]))
    truth_links = {(k, i) for (k, i) in detected if (k + 1, i) in detected}
    eb_found, ebt = found_links(eb, truth, max_dist)
    tp_found, _ = found_links(tp, truth, max_dist)
    eb_found &= truth_links
    tp_found &= truth_links
    # (pulse, tid) -> rows of ebptv's points attributed there.
    at = {}
    for r, (k, i) in enumerate(zip(ebt.pulse.to_numpy(), ebt.tid.to_numpy())):
        if i >= 0:
            at.setdefault((k, i), []).append(r)
    row_of = {(tr, k): r for r, (tr, k) in enumerate(zip(ebt.track.to_numpy(), ebt.pulse.to_numpy()))}
    length = ebt.groupby("track").pulse.count().to_dict()
    # Detected run of each truth particle around a pulse (life in detections).
    life = det[det.tid >= 0].groupby("tid").pulse.nunique().to_dict()

    def other(r, k2):
        tr = ebt.track[r]
        r2 = row_of.get((tr, k2))
        if r2 is None:
            return "track ends" if k2 > ebt.pulse[r] else "track starts"
        return "off truth" if ebt.tid[r2] < 0 else "other particle"

    def why(k, i):
        a, b = at.get((k, i), []), at.get((k + 1, i), [])
        if not a and not b:
            n = life.get(i, 0)
            return f"particle on no track at k, k+1 (life {'<5' if n < 5 else '5-9' if n < 10 else '>=10'} detections)"
        if a and not b:
            return f"on a track at k only: at k+1 its track's point is {other(a[0], k + 1)}"
        if b and not a:
            return f"on a track at k+1 only: at k its track's point is {other(b[0], k)}"
        ta, tb = {ebt.track[r] for r in a}, {ebt.track[r] for r in b}
        if ta & tb:
            return "same track (points not consecutive)"
        short = min(length[ebt.track[a[0]]], length[ebt.track[b[0]]])
        return f"on two tracks (shorter {'<10' if short < 10 else '>=10'} points)"

    for name, miss in [("trackpy finds, ebptv misses", tp_found - eb_found), ("ebptv finds, trackpy misses", eb_found - tp_found)]:
        print(f"{name}: {len(miss)} of {len(truth_links)} truth links")
        if name.startswith("trackpy"):
            counts = {}
            for k, i in miss:
                w = why(k, i)
                counts[w] = counts.get(w, 0) + 1
            for w, c in sorted(counts.items(), key=lambda x: -x[1]):
                print(f"  {c:6d}  {w}")


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
            [exe, "--table-format", "csv", "track", particles_csv, "--out", out, "--max-disp", str(search_range), "--gap", str(memory)],
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
    ap.add_argument(
        "--trackpy-cache",
        help="CSV of trackpy's linked output (with its timing in CSV.json): read it when it "
        "exists instead of linking again, write it otherwise (trackpy takes minutes)",
    )
    ap.add_argument(
        "--missed",
        action="store_true",
        help="break down the truth links trackpy finds and ebptv misses (and the reverse)",
    )
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
        if a.trackpy_cache and os.path.exists(a.trackpy_cache):
            tp_tracks = pd.read_csv(a.trackpy_cache)
            timing = json.load(open(a.trackpy_cache + ".json"))
            tp_dt, tp_cpu = timing["wall_s"], timing["cpu_s"]
        else:
            tp_tracks, tp_dt, tp_cpu = run_trackpy(particles, a.search_range, a.memory)
            if a.trackpy_cache:
                tp_tracks.to_csv(a.trackpy_cache, index=False)
                json.dump({"wall_s": tp_dt, "cpu_s": tp_cpu}, open(a.trackpy_cache + ".json", "w"))
        rows.append(("trackpy", score(tp_tracks, particles, truth, a.match), tp_dt, tp_cpu, float("nan")))
        if a.missed:
            missed_breakdown(tracks, tp_tracks, particles, truth, a.match)

    print(f"{n} particles, {particles.pulse.nunique()} pulses, search range {a.search_range} px, memory/gap {a.memory}")
    print(f"{'tracker':8} {'precision':>9} {'recall':>7} {'links':>8} {'wall s':>8} {'cpu s':>7} {'points/cpu-s':>13} {'vel rms px/pulse':>16}")
    for name, s, dt, cpu, vel in rows:
        print(f"{name:8} {s['precision']:9.4f} {s['recall']:7.4f} {s['links']:8d} {dt:8.3f} {cpu:7.3f} {n / cpu:13.0f} {vel:16.3f}")
    if len(rows) == 2:
        print(f"speed-up: {rows[1][3] / rows[0][3]:.1f}x in CPU time, {rows[1][2] / rows[0][2]:.1f}x in wall time")


if __name__ == "__main__":
    sys.exit(main())
