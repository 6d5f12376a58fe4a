# Where exactly p0000's model jumps along lenslet 7's tilt_x, and by how much, at 1024 and 4096 cells.
import json, numpy as np, prism
s0 = json.load(open('s1.json')); src = (-25.0, -25.0, 5.0)
def at(dt, rays):
    s = json.loads(json.dumps(s0)); s["lenslets"][7]["tilt_x_deg"] += dt
    return prism.psf(s, src, rays=rays, binning=1, splat="footprint", backend="cpu")
for rays in (1024, 4096):
    lo, hi = 1e-7, 1e-6
    blo, bhi = at(lo, rays), at(hi, rays)
    if np.abs(bhi - blo).max() < 1e-8:
        print(rays, "cells: no jump between +1e-7 and +1e-6 deg"); 
    else:
        for _ in range(30):
            mid = 0.5 * (lo + hi); bm = at(mid, rays)
            if np.abs(bm - blo).max() > np.abs(bhi - bm).max(): hi, bhi = mid, bm
            else: lo, blo = mid, bm
        d = bhi - blo
        print(f"{rays} cells: jump at tilt_x + {lo:.9e} deg: sum {d.sum():+.3e} of {blo.sum():.6f}, {int((np.abs(d) > 1e-9).sum())} pixels move, largest {np.abs(d).max():.3e} (the pixel's own {blo.flat[np.abs(d).argmax()]:.3e})")
    # how many jumps over a 0.01 degree range, in 2000 steps
    ts = np.linspace(-0.005, 0.005, 401); prev = at(ts[0], rays); jumps = 0
    for t in ts[1:]:
        b = at(t, rays)
        if np.abs(b - prev).max() > 20 * 5e-9 * 25: jumps += 1
        prev = b
    print(f"{rays} cells: steps of 2.5e-5 deg over +-0.005 deg with a pixel moving > 2.5e-6: {jumps} of 400")
