#!/usr/bin/env python3
"""The HDR merge's error against the truth, by brightness.

usage: merge_bias.py MERGED TRUTH

MERGED: a `prism dictionary merge-hdr` output (pNNNN.exr + pNNNN.json);
TRUTH: a `prism dictionary build` of the same positions without noise (its
manifest's grid names the file of each position). Per PSF the merged PSF is
scaled to the truth over the pixels 30..3000 times its faintest kept value;
per band of truth (in units of that faintest value, log-spaced) the printed
figure is the band's summed error over its summed truth, averaged over the
PSFs (and their spread). Needs the prism module (PYTHONPATH=build/python).
"""
import glob
import json
import sys

import numpy as np
import prism

merged, truth_dir = sys.argv[1], sys.argv[2]
grid = json.load(open(truth_dir + '/manifest.json'))['grid']
xs, ys, ds = grid['x_mm'], grid['y_mm'], grid['depth_mm']
edges = np.exp(np.linspace(np.log(0.3), np.log(3000), 34))
per_band = [[] for _ in edges[:-1]]
for f in sorted(glob.glob(merged + '/*.exr')):
    src = json.load(open(f[:-4] + '.json'))['source']
    n = xs.index(src['x_mm']) + len(xs) * (ys.index(src['y_mm']) + len(ys) * ds.index(src['depth_mm']))
    t = prism.read_exr('%s/psf/%05d.exr' % (truth_dir, n), 'Y').astype(float).ravel()
    p = prism.read_exr(f, 'Y').astype(float).ravel()
    faintest = p[p > 0].min()
    s = p.sum() / t.sum()
    for _ in range(3):
        sel = (s * t > 30 * faintest) & (s * t < 3000 * faintest)
        s = p[sel].sum() / t[sel].sum()
    mu = s * t / faintest
    for i in range(len(edges) - 1):
        b = (mu >= edges[i]) & (mu < edges[i + 1])
        if b.any():
            per_band[i].append((p[b] / faintest - mu[b]).sum() / mu[b].sum())
print('| truth / faintest kept | mean relative error | spread over PSFs | PSFs |')
print('|---|---|---|---|')
for i in range(len(edges) - 1):
    if per_band[i]:
        print('| %.2f - %.2f | %+.4f | %.4f | %d |' % (edges[i], edges[i + 1], np.mean(per_band[i]),
                                                      np.std(per_band[i]), len(per_band[i])))
