#!/usr/bin/env python3
"""chi2 (the calibration's, profiled scales, the model's pixels) along the
straight line between two fits' parameters: A = a params.csv's fitted
column, B = a fitted scene. Each point: a scene written, `prism calibrate
--max-steps 1` and the start chi2 it prints. Run in a folder holding the
prism binary as ./prism, the merged PSFs and a line/ folder:
    python3 line.py BASE_SCENE.json A.csv B.json MERGED RELIABLE T1,T2,...
(as run here: camera-nominal.json ../footprint-rim/prototype-reliable-2-stretched-params.csv
 fitted-from-truth.json merged 2 0,1,0.5,0.25,0.75,0.1,0.9)"""
import csv, json, re, subprocess, sys
base, a_csv, b_json, merged, rel = sys.argv[1:6]
ts = [float(t) for t in sys.argv[6].split(",")]
def setp(scene, name, v):
    m = re.match(r"lenslets\[(\d+)\]\.(\w+)$", name)
    if m: scene["lenslets"][int(m.group(1))][m.group(2)] = v
    elif name.startswith("sensor."): scene["sensor"][name[7:]] = v
    else: scene[name] = v
def getp(scene, name):
    m = re.match(r"lenslets\[(\d+)\]\.(\w+)$", name)
    if m: return scene["lenslets"][int(m.group(1))].get(m.group(2), 0.0)
    if name.startswith("sensor."): return scene["sensor"].get(name[7:], 0.0)
    return scene[name]
A = {r["parameter"]: float(r["fitted"]) for r in csv.DictReader(open(a_csv))}
B = json.load(open(b_json))
for t in ts:
    s = json.load(open(base))
    for n, va in A.items():
        setp(s, n, va + t * (getp(B, n) - va))
    json.dump(s, open("line/point.json", "w"))
    out = subprocess.run(["./prism", "calibrate", "--merged", merged, "--scene", "line/point.json", "--reliable", rel,
                          "--fit", "sensor_offset", "--max-steps", "1", "--cells-check", "1", "--out", "line/out.json",
                          "--threads", "1"], capture_output=True, text=True)
    m = re.search(r"chi2 ([0-9.e+-]+) ->", out.stdout + out.stderr)
    print(t, m.group(1) if m else (out.stdout + out.stderr)[-300:], flush=True)
