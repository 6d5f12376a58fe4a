import prism, numpy as np, json, time, sys
BACKEND = sys.argv[2] if len(sys.argv) > 2 else "cpu"
d = prism.scene('prototype-as-built').to_dict()
# one f = 3 mm lenslet near the middle (x 9, y 1.7), source under it near the face
f3 = [l for l in d['lenslets'] if abs(l['focal_mm'] - 3) < 0.2]
l = min(f3, key=lambda l: abs(l['x_mm'] - 9) + abs(l['y_mm'] - 1.7))
d['lenslets'] = [l]
src = (l['x_mm'] + 2.0, l['y_mm'] - 3.0, float(sys.argv[1]) if len(sys.argv) > 1 else 6.0)
print('lenslet', l, 'source', src)
def render(cells, strat, backend=BACKEND):
    t = time.time()
    b = prism.psf(d, src, rays=cells, binning=16, splat='footprint', stratification=strat, backend=backend).astype(np.float64)
    print(f'  rendered {cells} cells strat {strat} ({backend}) in {time.time()-t:.1f} s, sum {b.sum():.4f}')
    return b
ref = render(65536, 0)
peak = ref.max()
rows = {}
for cells, strat in [(1024, 0), (4096, 1), (16384, 0), (16384, 1), (65536, 1)]:
    b = render(cells, strat)
    rows[(cells, strat)] = b
for (cells, strat), b in rows.items():
    diff = (b - ref) / peak
    out = []
    for lo, hi in [(7e-5, 2e-4), (2e-4, 7e-4), (7e-4, 1e-2), (1e-2, 2)]:
        m = (ref >= lo * peak) & (ref < hi * peak)
        rel = (b[m] - ref[m]) / ref[m]
        out.append(f'[{lo:.0e},{hi:.0e}) n {m.sum():4d} mean rel {rel.mean():+.3f} rms {np.sqrt((rel**2).mean()):.3f}')
    dark = (ref == 0) & (b > 7e-5 * peak)
    print(f'{cells:6d} strat {strat}: ' + ' | '.join(out) + f' | lit where ref dark (>7e-5): {dark.sum()}, total light there {b[ref == 0].sum()/b.sum():.2e}')
import matplotlib; matplotlib.use('Agg'); import matplotlib.pyplot as plt
ys, xs = np.nonzero(ref > 1e-6 * peak)
sl = (slice(ys.min(), ys.max() + 1), slice(xs.min(), xs.max() + 1))
fig, ax = plt.subplots(1, 3, figsize=(16, 5))
ax[0].imshow(np.log10(ref[sl] / peak + 1e-7), vmin=-6, vmax=0); ax[0].set_title('65536 cells, log10 of peak')
for a, key in zip(ax[1:], [(1024, 0), (16384, 1)]):
    r = (rows[key] - ref)[sl] / np.maximum(ref[sl], 1e-4 * peak)
    im = a.imshow(np.clip(r, -3, 3), cmap='RdBu', vmin=-3, vmax=3); a.set_title(f'{key[0]} cells strat {key[1]}: (b - ref) / max(ref, 1e-4 peak)')
plt.colorbar(im); plt.savefig('footprint-rim.png', dpi=70)
