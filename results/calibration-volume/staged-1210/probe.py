# Which scene parameter makes p0000's model (source -25, -25, 5 mm) jump: each perturbed by a vanishing amount.
import json, sys, time, numpy as np, prism
base_scene = json.load(open(sys.argv[1]))
src = (-25.0, -25.0, 5.0)
kw = dict(rays=1024, binning=1, splat="footprint", backend="cpu")
t = time.time(); b0 = prism.psf(base_scene, src, **kw); print("render", time.time() - t, "s, sum", b0.sum(), "lit", (b0 > 0).sum(), flush=True)
def probe(name, mutate, eps):
    s = json.loads(json.dumps(base_scene)); mutate(s, eps)
    b = prism.psf(s, src, **kw)
    d = b - b0
    new = ((b0 == 0) & (b != 0)).sum(); gone = ((b0 != 0) & (b == 0)).sum()
    i = np.unravel_index(np.abs(d).argmax(), d.shape)
    rel = np.abs(d).max() / b0.max()
    return rel, new, gone, i, b[i], b0[i]
rows = []
L = len(base_scene["lenslets"])
for l in range(L):
    for key, eps in [("x_mm", 1e-7), ("y_mm", 1e-7), ("focal_mm", 1e-7), ("tilt_x_deg", 1e-6), ("tilt_y_deg", 1e-6)]:
        def m(s, e, l=l, key=key): s["lenslets"][l][key] = s["lenslets"][l].get(key, 0.0) + e
        r = probe(f"lenslets[{l}].{key}", m, eps)
        rows.append((r[0], f"lenslets[{l}].{key}", r))
        if r[0] > 1e-4: print(f"lenslets[{l}].{key}", r, flush=True)
rows.sort(reverse=True)
for r in rows[:12]: print(r[1], r[2])
