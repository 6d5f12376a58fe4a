#!/usr/bin/env python3
"""Per-point figures from a journal of `prism evaluate` on the paper's
protocol, finished or not (evaluate writes its CSVs only at the end of a run).

    python3 results/protocol_summary.py JOURNAL [--trials N]

The points are those of evaluate's protocol (host/reconstruct/evaluate.cpp,
`plan`), in the journal's order of experiments: the photon series at (1, 1, 31), the x, y and
depth lines through it at 2.5 mm steps, the double-vertex line with a fixed
vertex at (1, 1, 7.5). Per point and vertex: the trials' 3D errors, the mean
of all but the best and the worst (the paper's protocol; evaluate's own
figure), and the median of the estimates' own CRLBs (the binary sensor's at
the fitted photons: the journal keeps no truth CRLB), and their ratio. Each
estimate is matched to the nearest true vertex.
"""
import argparse
import json
import math
import statistics


def line(lo, hi, through, step):
    out, x = [], through
    while x >= lo - 1e-9:
        out.append(x)
        x -= step
    x = through + step
    while x <= hi + 1e-9:
        out.append(x)
        x += step
    return sorted(out)


def points(experiments):
    """The protocol's points in the order of --experiments, for the default
    dictionary grid (x, y in -25..25 mm, depth 0..50 mm)."""
    centre = (1.0, 1.0, 31.0)
    out = []
    for e in experiments:
        if e == "photons":
            out += [("photons", [(centre, n)]) for n in (50, 100, 200, 400)]
        elif e == "single-lines":
            out += [("x", [((x, 1.0, 31.0), 100)]) for x in line(-25, 25, 1, 2.5)]
            out += [("y", [((1.0, y, 31.0), 100)]) for y in line(-25, 25, 1, 2.5)]
            out += [("depth", [((1.0, 1.0, z), 100)]) for z in line(0, 50, 31, 2.5)]
        elif e == "double":
            out += [("double", [((1.0, 1.0, z), 125), ((1.0, 1.0, 7.5), 125)]) for z in line(0, 50, 31, 2.5)]
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("journal")
    args = ap.parse_args()
    lines = open(args.journal).read().splitlines()
    header = json.loads(lines[0])
    rows = [json.loads(l) for l in lines[1:] if l.strip()]
    by_point = {}
    for r in rows:
        by_point.setdefault(r["point"], []).append(r["estimate"])
    print(f"# {args.journal}: {len(rows)} events, experiments {','.join(header['experiments'])}")
    print("point experiment truth_mm photons trials mean3d_mm crlb3d_mm ratio beyond_3mm")
    for i, (name, verts) in enumerate(points(header["experiments"])):
        if i not in by_point:
            continue
        for truth, photons in verts:
            errs, crlb = [], []
            for est in by_point[i]:
                e = min(est, key=lambda v: math.dist((v["x_mm"], v["y_mm"], v["depth_mm"]), truth))
                errs.append(math.dist((e["x_mm"], e["y_mm"], e["depth_mm"]), truth))
                crlb.append(e["crlb_mm"][3])
            kept = sorted(errs)[1:-1] if len(errs) >= 3 else errs
            mean, c = statistics.mean(kept), statistics.median(crlb)
            far = sum(x > 3 for x in errs)
            t = ",".join(f"{v:g}" for v in truth)
            print(f"{i} {name} {t} {photons} {len(errs)} {mean:.3f} {c:.3f} {mean / c:.2f} {far}")


if __name__ == "__main__":
    main()
