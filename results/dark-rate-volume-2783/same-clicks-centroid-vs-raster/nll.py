# Event 21 of run.sh (truth 4.0 mm deep): the binary-sensor NLL (alpha profiled, dark rate 1e-6) of its clicks at the truth and at
# the two models' estimates, under each model at 1024 (the refinement's) and 4096 cells (the truth's). Run in run.sh's folder with
# PYTHONPATH=build/python; the binaries before and after a122f0c as run.sh names them.
import prism, numpy as np, subprocess, sys
from scipy.optimize import minimize_scalar
ev = next(iter(prism.EventFile('ev21.events')))
f = prism.EventFile('ev21.events'); W = f.header['grid_width']
clicks = np.asarray(ev.clicks)
def render(binary, pos, cells=1024):
    out = '/tmp/nll.exr'
    subprocess.run([binary, 'psf', '--scene', 'prototype', '--source-mm', ','.join(map(str, pos)), '--rays', str(cells),
                    '--binning', '16', '--out', out], check=True, capture_output=True)
    return prism.read_exr(out).astype(float).ravel()
def nll(b, dark=1e-6):
    b = b / b.sum()
    def f(a):
        lam = a * b + dark
        lc = lam[clicks]
        return lam.sum() - (lc + np.log(-np.expm1(-lc))).sum()
    r = minimize_scalar(f, bounds=(1, 1000), method='bounded')
    return r.fun, r.x
pts = {'truth': (-7.873081556932682, -19.27667068260296, 3.978375973283066),
       'new est': (-8.572708442, -20.13157025, 5.944974879), 'old est': (-7.890648961, -19.18292701, 4.030680366)}
print('clicks', len(clicks), 'grid width', W)
for name, binary in [('new model', '/work/exp/fd/prism-head'), ('old model', '/work/exp/fd/prism-old')]:
    for cells in [1024, 4096]:
        print(name, cells, {k: '%.2f (alpha %.1f)' % nll(render(binary, p, cells)) for k, p in pts.items()})
