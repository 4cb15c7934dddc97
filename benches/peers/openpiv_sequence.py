#!/usr/bin/env python3
"""Peer comparison on an image sequence: `ebptv piv-images` vs OpenPIV's loop.

Generates PAIRS synthetic 512x512 image pairs (Gaussian particles, sigma
0.8 px, 0.02 ppp, 16-bit PNG) moved by a known, smooth displacement field
(a uniform shift plus a sine in each component), then evaluates all of them
with both tools, one pass each, 32x32 windows, 16 px spacing, Gaussian
3-point sub-pixel peak:

- OpenPIV: the loop of its tutorials in a fresh Python process
  (`openpiv.tools.imread` of each frame, then
  `pyprocess.extended_search_area_piv`), with the Rust backend when
  `openpiv-rust` is installed, else its numpy/scipy one;
- ebptv: one `ebptv piv-images A1 B1 A2 B2 ... --passes 1` process.

Reported for each: vectors per second of wall time of the whole process
(interpreter or program start-up and image reading included), CPU seconds
(user + sys) of that process, the share of valid vectors and the rms error
of the valid vectors against the true field at the nodes. Both run in the
same invocation, one after the other.

With --samples the script also checks that `ebptv piv-images` reads
OpenPIV's own sample images as shipped (test1 BMP pair, test5 palette TIFF
pair) and agrees with OpenPIV on them. Those images are GPL: they are read
from the installed openpiv package and never copied into this repository.

Usage: python3 benches/peers/openpiv_sequence.py [--ebptv target/release/ebptv] [--pairs 60] [--samples]
Needs: pip install openpiv openpiv-rust pillow numpy
"""
import argparse
import csv
import glob
import os
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
    sys.exit("openpiv is not installed: pip install openpiv openpiv-rust")

W, S = 32, 16
SIZE = 512

# OpenPIV's tutorial loop, run as its own process so that its start-up and
# image reading are timed like ebptv's.
OPENPIV_LOOP = r"""
import sys
import numpy as np
from openpiv import pyprocess, tools
out, backend, files = sys.argv[1], sys.argv[2], sys.argv[3:]
us, vs, s2ns = [], [], []
for a, b in zip(files[0::2], files[1::2]):
    fa = tools.imread(a).astype(np.float64)
    fb = tools.imread(b).astype(np.float64)
    u, v, s2n = pyprocess.extended_search_area_piv(
        fa, fb, window_size=%(W)d, overlap=%(W)d - %(S)d, search_area_size=%(W)d,
        sig2noise_method="peak2peak", subpixel_method="gaussian", backend=backend)
    us.append(u); vs.append(v); s2ns.append(s2n)
x, y = pyprocess.get_coordinates(fa.shape, search_area_size=%(W)d, overlap=%(W)d - %(S)d)
np.savez(out, u=np.array(us), v=np.array(vs), s2n=np.array(s2ns), x=x, y=y)
""" % {"W": W, "S": S}


def field(x, y):
    """The true displacement (px per pair) at image position (x, y)."""
    u = 2.3 + 0.5 * np.sin(2 * np.pi * y / SIZE)
    v = -1.4 + 0.5 * np.sin(2 * np.pi * x / SIZE)
    return u, v


def render(px, py, sigma=0.8):
    img = np.zeros((SIZE, SIZE))
    for cx, cy in zip(px, py):
        x0, x1 = int(max(cx - 4, 0)), int(min(cx + 5, SIZE))
        y0, y1 = int(max(cy - 4, 0)), int(min(cy + 5, SIZE))
        if x0 >= x1 or y0 >= y1:
            continue
        gx = np.exp(-((np.arange(x0, x1) - cx) ** 2) / (2 * sigma ** 2))
        gy = np.exp(-((np.arange(y0, y1) - cy) ** 2) / (2 * sigma ** 2))
        img[y0:y1, x0:x1] += np.outer(gy, gx)
    return img


def synth_pair(seed, ppp=0.02):
    """Particles at p - d(p)/2 in the first image and p + d(p)/2 in the
    second: the displacement at p is exactly the field there."""
    rng = np.random.default_rng(seed)
    m = 10
    n = int(ppp * (SIZE + 2 * m) ** 2)
    x = rng.uniform(-m, SIZE + m, n)
    y = rng.uniform(-m, SIZE + m, n)
    u, v = field(x, y)
    return render(x - u / 2, y - v / 2), render(x + u / 2, y + v / 2)


def save16(arr, path):
    Image.fromarray(np.clip(arr * 20000, 0, 65535).astype(np.uint16)).save(path)


def timed(cmd):
    """Run `cmd`; wall seconds and CPU seconds (user + sys) of the child."""
    r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    r = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
    if r.returncode != 0:
        raise RuntimeError(f"{cmd[0]} failed:\n{r.stderr}")
    cpu = (r1.ru_utime - r0.ru_utime) + (r1.ru_stime - r0.ru_stime)
    return wall, cpu


def read_ebptv(out, first_frame):
    rows = list(csv.DictReader(open(os.path.join(out, f"vectors_{first_frame:05d}.csv"))))
    x = np.array([float(r["x"]) for r in rows])
    y = np.array([float(r["y"]) for r in rows])
    u = np.array([float(r["u"]) for r in rows])
    v = np.array([float(r["v"]) for r in rows])
    ok = np.array([int(r["flag"]) == 0 for r in rows])
    return x, y, u, v, ok


def rms(a):
    return float(np.sqrt(np.mean(a))) if a.size else float("nan")


def run_ebptv(exe, files, out):
    wall, cpu = timed([exe, "--table-format", "csv", "piv-images", *files, "--window", str(W), "--spacing", str(S),
                       "--passes", "1", "--out", out])
    sq, valid, total = [], 0, 0
    for k in range(len(files) // 2):
        x, y, u, v, ok = read_ebptv(out, 2 * k)
        tu, tv = field(x, y)
        sq.append(((u - tu) ** 2 + (v - tv) ** 2)[ok])
        valid += int(ok.sum())
        total += ok.size
    return wall, cpu, total, valid, rms(np.concatenate(sq))


def run_openpiv(files, out, backend):
    script = os.path.join(os.path.dirname(out), "openpiv_loop.py")
    with open(script, "w") as f:
        f.write(OPENPIV_LOOP)
    wall, cpu = timed([sys.executable, script, out, backend, *files])
    d = np.load(out)
    u, v, s2n, x, y = d["u"], d["v"], d["s2n"], d["x"], d["y"]
    # OpenPIV's coordinates put y upwards from the bottom edge: the node
    # in image rows is SIZE - y; its v sign has changed between versions,
    # so take the one that matches image coordinates (y down).
    y_img = SIZE - y if np.mean(y[0]) > np.mean(y[-1]) else y
    tu, tv = field(x, y_img)
    ok = np.isfinite(u) & np.isfinite(v) & (s2n > 1.3)
    if np.mean((v[ok] + tv[None].repeat(len(u), 0)[ok]) ** 2) < np.mean((v[ok] - tv[None].repeat(len(u), 0)[ok]) ** 2):
        v = -v
    tu, tv = tu[None].repeat(len(u), 0), tv[None].repeat(len(u), 0)
    err = rms(((u - tu) ** 2 + (v - tv) ** 2)[ok])
    return wall, cpu, u.size, int(ok.sum()), err


def check_samples(exe, tmp):
    """`ebptv piv-images` on OpenPIV's sample pairs as shipped."""
    data = os.path.join(os.path.dirname(openpiv.__file__), "data")
    for name, pa, pb in [("test1 (BMP)", "test1/exp1_001_a.bmp", "test1/exp1_001_b.bmp"),
                         ("test5 (palette TIFF)", "test5/Pattern_1_A.tif", "test5/Pattern_1_B.tif")]:
        a, b = os.path.join(data, pa), os.path.join(data, pb)
        if not (os.path.exists(a) and os.path.exists(b)):
            print(f"sample {name}: not shipped with this OpenPIV version; skipped")
            continue
        out = os.path.join(tmp, "sample_" + pa.split("/")[0])
        r = subprocess.run([exe, "--table-format", "csv", "piv-images", a, b, "--window", str(W), "--spacing", str(S),
                            "--passes", "1", "--out", out], capture_output=True, text=True)
        if r.returncode != 0:
            print(f"sample {name}: ebptv FAILED: {r.stderr.strip()}")
            continue
        _, _, ue, ve, oke = read_ebptv(out, 0)
        from openpiv import tools
        fa = tools.imread(a).astype(np.float64)
        fb = tools.imread(b).astype(np.float64)
        uo, vo, s2n = pyprocess.extended_search_area_piv(
            fa, fb, window_size=W, overlap=W - S, search_area_size=W,
            sig2noise_method="peak2peak", subpixel_method="gaussian")
        uo, vo, oko = uo.ravel(), vo.ravel(), (np.isfinite(uo) & (s2n > 1.3)).ravel()
        if uo.size != ue.size:
            print(f"sample {name}: read, {ue.size} vectors (OpenPIV grid {uo.size}: not compared)")
            continue
        both = oke & oko
        if np.mean((vo[both] + ve[both]) ** 2) < np.mean((vo[both] - ve[both]) ** 2):
            vo = -vo
        agree = rms(((ue - uo) ** 2 + (ve - vo) ** 2)[both])
        print(f"sample {name}: read, {ue.size} vectors, {int(oke.sum())} valid; "
              f"agreement with OpenPIV {agree:.3f} px rms over {int(both.sum())} vectors")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--ebptv", default=os.path.join(os.path.dirname(__file__), "../../target/release/ebptv"))
    ap.add_argument("--pairs", type=int, default=60)
    ap.add_argument("--samples", action="store_true",
                    help="also check ebptv on OpenPIV's sample images (BMP, palette TIFF)")
    args = ap.parse_args()
    backend = "rust" if getattr(pyprocess, "HAS_RUST", False) else "numpy"
    print(f"OpenPIV {getattr(openpiv, '__version__', '?')} ({backend} backend), "
          f"{args.pairs} pairs {SIZE}x{SIZE}, window {W}, spacing {S}, one pass", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        files = []
        for k in range(args.pairs):
            fa, fb = synth_pair(seed=k)
            for tag, img in (("a", fa), ("b", fb)):
                path = os.path.join(tmp, f"pair{k:03d}_{tag}.png")
                save16(img, path)
                files.append(path)
        e = run_ebptv(args.ebptv, files, os.path.join(tmp, "ebptv"))
        o = run_openpiv(files, os.path.join(tmp, "openpiv.npz"), backend)
        for name, (wall, cpu, n, valid, err) in (("ebptv piv-images", e), (f"OpenPIV ({backend})", o)):
            print(f"{name:18s} {n} vectors in {wall:.2f} s wall ({cpu:.2f} CPU-s): "
                  f"{n / wall / 1e3:.1f} k vectors/s, {100 * valid / n:.1f} % valid, "
                  f"rms error {err:.4f} px", flush=True)
        print(f"ebptv / OpenPIV: {o[0] / e[0]:.1f}x vectors/s (wall), {o[1] / e[1]:.1f}x per CPU-s")
        if args.samples:
            check_samples(args.ebptv, tmp)


if __name__ == "__main__":
    main()
