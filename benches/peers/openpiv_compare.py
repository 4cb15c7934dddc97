#!/usr/bin/env python3
"""Peer comparison: ebptv piv-images vs OpenPIV-python on the same images.

Cases: the image pairs OpenPIV ships (test1 exp1_001 a/b, test5 Pattern_1
A/B) and synthetic Gaussian-particle pairs with a known displacement.
Both codes run one pass, 32x32 windows, 16 px spacing (overlap 16), FFT
correlation, Gaussian 3-point sub-pixel peak, so that the comparison is of
like with like; ebptv's 3-pass deformation result is reported for the
synthetic case too.

OpenPIV runs with both of its backends when available: the numpy/scipy
path and the Rust extension (`pip install openpiv-rust`, module
`openpiv_rust`). Reports per case: vectors, agreement rms (px) where both
are valid, vectors per second of each code over REPEAT runs of the pair
(wall clock of the correlation only: ebptv's own timing line, OpenPIV's
call; and per CPU-second: ebptv's process CPU time of the correlation as
`piv-images` reports it, and of its whole process incl. start-up and PNG
decoding, against OpenPIV's process CPU time of the calls), and for synthetic
images the rms error against truth.

Usage: python3 benches/peers/openpiv_compare.py [--ebptv target/release/ebptv]
Needs: pip install openpiv openpiv-rust pillow numpy
"""
import argparse
import csv
import glob
import json
import os
import re
import resource
import subprocess
import sys
import tempfile
import time

import numpy as np
from PIL import Image

try:
    import openpiv
    from openpiv import pyprocess
except ImportError:
    sys.exit("openpiv is not installed: pip install openpiv")

W, S = 32, 16


REPEAT = 20  # pairs per timing run: ~19 k vectors for 512x512 images


def ebptv_piv(exe, a, b, out, passes, repeat=1):
    """Run `ebptv piv-images` on `repeat` copies of the pair (a, b).

    Returns the first field and timings: ebptv's own wall time of the
    correlation (printed on stderr, image loading excluded) and the CPU time
    (user + sys) of the whole child process (includes start-up and PNG
    decoding, so it favours OpenPIV)."""
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    r = subprocess.run([exe, "--table-format", "csv", "piv-images", *([a, b] * repeat), "--window", str(W), "--spacing", str(S),
                        "--passes", str(passes), "--out", out], capture_output=True, text=True)
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    if r.returncode != 0:
        raise RuntimeError(r.stderr)
    m = re.search(r"(\d+) vectors in ([0-9.]+) s", r.stderr)
    wall = float(m.group(2)) if m else float("nan")
    # ebptv's own process CPU time of the correlation (images already
    # loaded), the like-for-like counterpart of OpenPIV's timing.
    m = re.search(r"([0-9.]+) CPU-s", r.stderr)
    cpu_corr = float(m.group(1)) if m else float("nan")
    rows = list(csv.DictReader(open(os.path.join(out, "vectors_00000.csv"))))
    xs = sorted({float(r["x"]) for r in rows})
    ys = sorted({float(r["y"]) for r in rows})
    u = np.array([float(r["u"]) for r in rows]).reshape(len(ys), len(xs))
    v = np.array([float(r["v"]) for r in rows]).reshape(len(ys), len(xs))
    ok = np.array([int(r["flag"]) == 0 for r in rows]).reshape(len(ys), len(xs))
    return u, v, ok, wall, (cpu, cpu_corr)


def openpiv_piv(a, b, backend, repeat=1):
    """OpenPIV one pass on the loaded images, `repeat` times; wall and
    process CPU time (all threads) of the correlation calls only."""
    fa = np.asarray(Image.open(a).convert("F"), dtype=np.float64)
    fb = np.asarray(Image.open(b).convert("F"), dtype=np.float64)
    t0, c0 = time.perf_counter(), time.process_time()
    for _ in range(repeat):
        u, v, s2n = pyprocess.extended_search_area_piv(
            fa, fb, window_size=W, overlap=W - S, search_area_size=W,
            sig2noise_method="peak2peak", subpixel_method="gaussian", backend=backend)
    dt, dc = time.perf_counter() - t0, time.process_time() - c0
    ok = np.isfinite(u) & np.isfinite(v) & (s2n > 1.3)
    return u, v, ok, dt, dc


def to_png(src, dst):
    im = Image.open(src).convert("F")
    arr = np.asarray(im)
    arr = np.clip(arr / max(arr.max(), 1) * 65535, 0, 65535).astype(np.uint16)
    Image.fromarray(arr).save(dst)


def synth_pair(w, h, d, seed, ppp=0.02, sigma=0.8):
    rng = np.random.default_rng(seed)
    m = 10
    n = int(ppp * (w + 2 * m) * (h + 2 * m))
    x = rng.uniform(-m, w + m, n)
    y = rng.uniform(-m, h + m, n)
    yy, xx = np.mgrid[0:h, 0:w]
    def render(px, py):
        img = np.zeros((h, w))
        for cx, cy in zip(px, py):
            x0, x1 = int(max(cx - 4, 0)), int(min(cx + 5, w))
            y0, y1 = int(max(cy - 4, 0)), int(min(cy + 5, h))
            if x0 >= x1 or y0 >= y1:
                continue
            img[y0:y1, x0:x1] += np.exp(-((xx[y0:y1, x0:x1] - cx) ** 2 + (yy[y0:y1, x0:x1] - cy) ** 2) / (2 * sigma ** 2))
        return img
    return render(x, y), render(x + d[0], y + d[1])


def save16(arr, path):
    Image.fromarray(np.clip(arr * 20000, 0, 65535).astype(np.uint16)).save(path)


def rms(du, dv):
    return float(np.sqrt(np.mean(du ** 2 + dv ** 2)))


def compare(name, exe, a, b, tmp, backends, truth=None):
    ue, ve, oke, _, _ = ebptv_piv(exe, a, b, os.path.join(tmp, name + "_e1"), 1)
    n = ue.size
    _, _, _, wall_e, (cpu_e, cpu_c) = ebptv_piv(exe, a, b, os.path.join(tmp, name + "_t1"), 1, REPEAT)
    line = [f"{name}: {n} vectors; ebptv 1 pass {n * REPEAT / wall_e:.0f} vec/s wall, "
            f"{n * REPEAT / cpu_c:.0f} vec/CPU-s (correlation), "
            f"{n * REPEAT / cpu_e:.0f} vec/CPU-s (whole process)"]
    res = {"case": name, "vectors": n, "ebptv_vps_wall": n * REPEAT / wall_e, "ebptv_vps_cpu": n * REPEAT / cpu_e,
           "ebptv_vps_cpu_corr": n * REPEAT / cpu_c}
    if truth is not None:
        res["err_ebptv1"] = rms(ue[oke] - truth[0], ve[oke] - truth[1])
        ue3, ve3, ok3, _, _ = ebptv_piv(exe, a, b, os.path.join(tmp, name + "_e3"), 3)
        res["err_ebptv3"] = rms(ue3[ok3] - truth[0], ve3[ok3] - truth[1])
        line.append(f"error vs truth ebptv 1 pass {res['err_ebptv1']:.4f} px, 3 passes {res['err_ebptv3']:.4f} px")
    for be in backends:
        uo, vo, oko, _, _ = openpiv_piv(a, b, be)
        _, _, _, dto, dco = openpiv_piv(a, b, be, REPEAT)
        if uo.shape != ue.shape:
            line.append(f"OpenPIV {be}: grid shape {uo.shape} differs from ebptv {ue.shape}; skipped")
            continue
        # OpenPIV's v sign convention has changed between versions: take the
        # one that matches image coordinates (y down).
        both = oke & oko
        if np.nanmean((vo[both] + ve[both]) ** 2) < np.nanmean((vo[both] - ve[both]) ** 2):
            vo = -vo
        agree = rms(ue[both] - uo[both], ve[both] - vo[both])
        res[f"{be}_both_valid"] = int(both.sum())
        res[f"{be}_agree"] = agree
        res[f"{be}_vps_wall"] = n * REPEAT / dto
        res[f"{be}_vps_cpu"] = n * REPEAT / dco
        msg = (f"OpenPIV {be}: both valid {both.sum()}, agreement rms {agree:.4f} px, "
               f"{n * REPEAT / dto:.0f} vec/s wall, {n * REPEAT / dco:.0f} vec/CPU-s "
               f"(ebptv/OpenPIV: {dto / wall_e:.1f}x wall, {dco / cpu_c:.1f}x CPU correlation, "
               f"{dco / cpu_e:.1f}x CPU whole process)")
        if truth is not None:
            res[f"err_{be}"] = rms(uo[oko] - truth[0], vo[oko] - truth[1])
            msg += f", error vs truth {res[f'err_{be}']:.4f} px"
        line.append(msg)
    print("\n    ".join(line), flush=True)
    return res


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--ebptv", default=os.path.join(os.path.dirname(__file__), "../../target/release/ebptv"))
    ap.add_argument("--json", help="write the results here")
    args = ap.parse_args()
    data = os.path.join(os.path.dirname(openpiv.__file__), "data")
    backends = ["scipy"] + (["rust"] if pyprocess.HAS_RUST else [])
    print(f"OpenPIV {getattr(openpiv, '__version__', '?')}, window {W}, spacing {S}, "
          f"backends {backends}" + ("" if pyprocess.HAS_RUST else
                                    " (Rust backend not installed: pip install openpiv-rust)"))
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, pa, pb in [("openpiv-test1", "test1/exp1_001_a.bmp", "test1/exp1_001_b.bmp"),
                             ("openpiv-test5", "test5/Pattern_1_A.tif", "test5/Pattern_1_B.tif")]:
            a, b = os.path.join(data, pa), os.path.join(data, pb)
            if not (os.path.exists(a) and os.path.exists(b)):
                print(f"{name}: images not shipped with this OpenPIV version; skipped")
                continue
            a2, b2 = os.path.join(tmp, name + "_a.png"), os.path.join(tmp, name + "_b.png")
            to_png(a, a2)
            to_png(b, b2)
            results.append(compare(name, args.ebptv, a2, b2, tmp, backends))
        for k, d in enumerate([(2.3, -1.4), (0.5, 0.25), (5.7, 3.1)]):
            fa, fb = synth_pair(512, 512, d, seed=k)
            a2, b2 = os.path.join(tmp, f"s{k}_a.png"), os.path.join(tmp, f"s{k}_b.png")
            save16(fa, a2)
            save16(fb, b2)
            results.append(compare(f"synthetic d={d}", args.ebptv, a2, b2, tmp, backends, truth=d))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)


if __name__ == "__main__":
    main()
