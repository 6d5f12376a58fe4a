#!/usr/bin/env python3
"""A fit's path, lenslet by lenslet, against the truth: each scene that
`prism calibrate --checkpoint DIR/reached.json` wrote, copied after every
step to DIR/traj/step-N.json, and per step the chosen lenslets' errors
(x, y, focal in um; tilts in degrees) and the lenslet farthest off in position.
    python3 trajectory.py TRUTH.json DIR [LENSLETS, e.g. 11,30]"""
import json, sys, glob, re, math
truth = json.load(open(sys.argv[1]))
d = sys.argv[2]
lens = [int(a) for a in sys.argv[3].split(',')] if len(sys.argv) > 3 else [11]
def lenses(j): return j["lenslets"]
files = sorted(glob.glob(d + "/traj/step-*.json"), key=lambda f: int(re.findall(r"step-(\d+)", f)[0]))
T = lenses(truth)
for f in files:
    j = json.load(open(f)); L = lenses(j)
    n = re.findall(r"step-(\d+)", f)[0]
    row = []
    for l in lens:
        a, t = L[l], T[l]
        row.append("L%d dx %+6.1f dy %+6.1f df %+6.1f um dtx %+5.2f dty %+5.2f" % (l, 1e3*(a["x_mm"]-t["x_mm"]), 1e3*(a["y_mm"]-t["y_mm"]), 1e3*(a["focal_mm"]-t["focal_mm"]), a.get("tilt_x_deg",0)-t.get("tilt_x_deg",0), a.get("tilt_y_deg",0)-t.get("tilt_y_deg",0)))
    # worst lenslet by position error
    worst = max(range(len(L)), key=lambda l: math.hypot(L[l]["x_mm"]-T[l]["x_mm"], L[l]["y_mm"]-T[l]["y_mm"]))
    w = 1e3*math.hypot(L[worst]["x_mm"]-T[worst]["x_mm"], L[worst]["y_mm"]-T[worst]["y_mm"])
    print(n, " | ".join(row), "| worst pos L%d %.1f um" % (worst, w))
