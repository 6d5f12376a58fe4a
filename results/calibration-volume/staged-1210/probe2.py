import json, sys, numpy as np, prism
s0 = json.load(open('s1.json')); src = (-25.0, -25.0, 5.0)
kw = dict(rays=1024, binning=1, splat="footprint", backend="cpu")
l = 7; t0 = s0["lenslets"][l]["tilt_x_deg"]
print("lenslet 7:", s0["lenslets"][l])
def at(dt, key="tilt_x_deg"):
    s = json.loads(json.dumps(s0)); s["lenslets"][l][key] = s0["lenslets"][l][key] + dt
    return prism.psf(s, src, **kw)
b0 = at(0.0)
for dt in [-1e-3, -1e-4, -1e-5, -1e-6, -1e-7, -1e-8, 0, 1e-8, 1e-7, 1e-6, 1e-5, 1e-4, 1e-3]:
    b = at(dt)
    print(f"{dt:+.0e}: pixel(216,178) {b[216,178]:.6e} sum {b.sum():.9f} lit {(b>0).sum()}  max|d| {np.abs(b-b0).max():.3e}")
