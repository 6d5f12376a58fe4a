# Does the jump along lenslet 7's tilt_x (p0000, stage 1's end) go when the footprint never splits (SPLIT_DEPTH = 0)?
import json, subprocess, sys, os, numpy as np, prism
s0 = json.load(open('s1.json'))
def render(binary, dt, tag):
    s = json.loads(json.dumps(s0)); s["lenslets"][7]["tilt_x_deg"] += dt
    json.dump(s, open(f'/tmp/p4-{tag}.json', 'w'))
    out = f'/tmp/p4-{tag}.exr'
    subprocess.run([binary, 'psf', '--scene', f'/tmp/p4-{tag}.json', '--source-mm', '-25,-25,5', '--out', out,
                    '--binning', '1', '--rays', '1024', '--backend', 'cpu'], check=True, capture_output=True)
    return np.asarray(prism.read_exr(out))
for name, binary in [('as committed', '/work/main/build/host/prism'), ('variant', '/tmp/wt/build/host/prism')]:
    lo, hi = render(binary, 1e-7, 'lo'), render(binary, 1e-6, 'hi')
    d = hi - lo
    print(f"{name}: +1e-7 -> +1e-6 deg: largest pixel change {np.abs(d).max():.3e}, sum {d.sum():+.3e}, lit {(lo>0).sum()} -> {(hi>0).sum()}")
