"""Simulate a vortex, track it, plot the tracks and the binned grid.

    pip install ./python matplotlib && python examples/python/quickstart.py
"""
import matplotlib.pyplot as plt
import numpy as np

import ebptv

sim = ebptv.simulate("demo", seconds=0.05, seed=1)     # recording + truth
particles, tracks = ebptv.track(sim["recording"])      # as `ebptv track`
print(tracks.attrs["summary"]["tracks"], "tracks,", len(tracks), "points")
g = ebptv.grid(tracks, bin=16, as_xarray=False)        # as `ebptv grid`

fig, (a, b) = plt.subplots(1, 2, figsize=(12, 4))
for _, t in tracks[tracks.pulse < 40].groupby("track_id"):
    a.plot(t.x, t.y, lw=0.6)
a.set(title="tracks, first 40 pulses", aspect="equal")
nx, ny = g.attrs["nx"], g.attrs["ny"]
speed = np.hypot(g.u, g.v).to_numpy().reshape(ny, nx)
im = b.pcolormesh(g.x.to_numpy().reshape(ny, nx), g.y.to_numpy().reshape(ny, nx), speed)
b.quiver(g.x, g.y, g.u, -g.v)
b.set(title="mean velocity (px/s)", aspect="equal")
fig.colorbar(im, ax=b)
for ax in (a, b):
    ax.invert_yaxis()
plt.savefig("quickstart.png", dpi=120)
