#!/usr/bin/env python3
"""Peer comparison: ebptv piv-images vs OpenPIV-python on the same images.

Cases: the image pairs OpenPIV ships (test1 exp1_001 a/b, test5 Pattern_1
A/B) and synthetic Gaussian-particle pairs with a known displacement.
Both codes run one pass, 32x32 windows, 16 px spacing (overlap 16), FFT
correlation, Gaussian 3-point sub-pixel peak, so that the comparison is of
like with like; ebptv's 3-pass deformation result is reported for the
synthetic case too.

Reports per case: vectors, agreement rms (px) where both are valid,
vectors/s of both (wall clock, including image loading for ebptv), and for
synthetic images the rms error against truth.

Usage: python3 benches/peers/openpiv_compare.py [--ebptv target/release/ebptv]
Needs: pip install openpiv pillow numpy
"""
import argparse
import csv
import glob
import os
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


def ebptv_piv(exe, a, b, out, passes):
    t0 = time.perf_counter()
    r = subprocess.run([exe, "piv-images", a, b, "--window", str(W), "--spacing", str(S),
                        "--passes", str(passes), "--out", out], capture_output=True, text=True)
    dt = time.perf_counter() - t0
    if r.returncode != 0:
        raise RuntimeError(r.stderr)
    rows = list(csv.DictReader(open(os.path.join(out, "vectors_00000.csv"))))
    xs = sorted({float(r["x"]) for r in rows})
    ys = sorted({float(r["y"]) for r in rows})
    u = np.array([float(r["u"]) for r in rows]).reshape(len(ys), len(xs))
    v = np.array([float(r["v"]) for r in rows]).reshape(len(ys), len(xs))
    ok = np.array([int(r["flag"]) == 0 for r in rows]).reshape(len(ys), len(xs))
    return u, v, ok, dt, np.array(xs), np.array(ys)


def openpiv_piv(a, b):
    fa = np.asarray(Image.open(a).convert("F"), dtype=np.float64)
    fb = np.asarray(Image.open(b).convert("F"), dtype=np.float64)
    t0 = time.perf_counter()
    u, v, s2n = pyprocess.extended_search_area_piv(
        fa, fb, window_size=W, overlap=W - S, search_area_size=W,
        sig2noise_method="peak2peak", subpixel_method="gaussian")
    dt = time.perf_counter() - t0
    ok = np.isfinite(u) & np.isfinite(v) & (s2n > 1.3)
    return u, v, ok, dt


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


def compare(name, exe, a, b, tmp, truth=None):
    ue, ve, oke, dte, xs, ys = ebptv_piv(exe, a, b, os.path.join(tmp, name + "_e1"), 1)
    uo, vo, oko, dto = openpiv_piv(a, b)
    if uo.shape != ue.shape:
        print(f"{name}: grid shapes differ (ebptv {ue.shape}, OpenPIV {uo.shape}); skipped")
        return
    # OpenPIV's v sign convention has changed between versions: take the one
    # that matches image coordinates (y down).
    both = oke & oko
    if np.nanmean((vo[both] + ve[both]) ** 2) < np.nanmean((vo[both] - ve[both]) ** 2):
        vo = -vo
    agree = np.sqrt(np.mean((ue[both] - uo[both]) ** 2 + (ve[both] - vo[both]) ** 2))
    n = ue.size
    line = (f"{name}: {n} vectors, both valid {both.sum()}, agreement rms {agree:.4f} px; "
            f"ebptv {n / dte:.0f} vec/s (wall, incl. process start + image load), "
            f"OpenPIV {n / dto:.0f} vec/s")
    if truth is not None:
        err_e = np.sqrt(np.mean((ue[oke] - truth[0]) ** 2 + (ve[oke] - truth[1]) ** 2))
        err_o = np.sqrt(np.mean((uo[oko] - truth[0]) ** 2 + (vo[oko] - truth[1]) ** 2))
        ue3, ve3, ok3, _, _, _ = ebptv_piv(exe, a, b, os.path.join(tmp, name + "_e3"), 3)
        err_3 = np.sqrt(np.mean((ue3[ok3] - truth[0]) ** 2 + (ve3[ok3] - truth[1]) ** 2))
        line += (f"; rms error vs truth: ebptv 1 pass {err_e:.4f} px, OpenPIV 1 pass {err_o:.4f} px, "
                 f"ebptv 3 passes {err_3:.4f} px")
    print(line)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--ebptv", default=os.path.join(os.path.dirname(__file__), "../../target/release/ebptv"))
    args = ap.parse_args()
    data = os.path.join(os.path.dirname(openpiv.__file__), "data")
    print(f"OpenPIV {getattr(openpiv, '__version__', '?')}, window {W}, spacing {S}")
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
            compare(name, args.ebptv, a2, b2, tmp)
        for k, d in enumerate([(2.3, -1.4), (0.5, 0.25), (5.7, 3.1)]):
            fa, fb = synth_pair(512, 512, d, seed=k)
            a2, b2 = os.path.join(tmp, f"s{k}_a.png"), os.path.join(tmp, f"s{k}_b.png")
            save16(fa, a2)
            save16(fb, b2)
            compare(f"synthetic d={d}", args.ebptv, a2, b2, tmp, truth=d)


if __name__ == "__main__":
    main()
