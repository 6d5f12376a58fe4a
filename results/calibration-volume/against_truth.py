#!/usr/bin/env python3
"""A calibration's parameters against the as-built truth (issue 18).

    PYTHONPATH=build/python /usr/bin/python3 results/calibration-volume/against_truth.py \\
        PARAMS.csv [TRUTH_SCENE]

PARAMS.csv: `prism calibrate --csv`'s table (parameter, start, fitted, sigma,
change_over_sigma, at_bound, and since the model's cells' check
sigma_residuals, sigma_cells). TRUTH_SCENE: a built-in name or JSON file (default
prototype-as-built). Prints, per kind of parameter, how many of those inside
their range lie within 3 of their reported sigmas of the truth (and, where
the table has it, within 3 of the residuals' sigma alone), how many
ended on a bound (no sigma), the RMS of (fitted - truth) / sigma, the
median and largest |fitted - truth| and the median sigma; then the lenslets
with a parameter beyond 3 sigma, with their focal lengths.
"""
import csv
import json
import math
import re
import statistics
import sys

from prism import _core


def value(scene, name):
    m = re.match(r"lenslets\[(\d+)\]\.(\w+)$", name)
    if m:
        return scene["lenslets"][int(m.group(1))].get(m.group(2), 0.0)
    if name.startswith("sensor."):
        return scene["sensor"].get(name[len("sensor."):], 0.0)
    return scene[name]


def kind(name):
    return re.sub(r"\[\d+\]", "[i]", name)


def main(args):
    if not 1 <= len(args) <= 2:
        sys.exit(__doc__)
    truth = json.loads(_core.load_scene(args[1] if len(args) > 1 else "prototype-as-built").json_text())
    rows = list(csv.DictReader(open(args[0])))
    by_kind = {}
    beyond = {}
    for r in rows:
        t, f, s = value(truth, r["parameter"]), float(r["fitted"]), float(r["sigma"])
        bound = r.get("at_bound") == "1"  # no sigma: the fit ended on the edge of its range
        z = (f - t) / s if s > 0 else math.inf
        s_res = float(r.get("sigma_residuals") or s)
        z_res = (f - t) / s_res if s_res > 0 else math.inf
        by_kind.setdefault(kind(r["parameter"]), []).append((abs(f - t), s, z, bound, z_res))
        m = re.match(r"lenslets\[(\d+)\]", r["parameter"])
        if m and (bound or abs(z) > 3):
            what = "at its bound" if bound else f"{z:+.1f}"
            beyond.setdefault(int(m.group(1)), []).append(f"{r['parameter'].split('.')[-1]} {what}")
    print("| parameter | within 3 sigma | within 3 sigma_residuals | at a bound | RMS error / sigma | median error "
          "| largest error | median sigma |")
    print("|---|---|---|---|---|---|---|---|")
    for k, v in by_kind.items():
        unit_um = k.endswith("_mm")
        scale, unit = (1e3, "um") if unit_um else (1.0, "deg")
        inside = [(e, s, z) for e, s, z, bound, _ in v if not bound]
        within = sum(abs(z) <= 3 for _, _, z in inside)
        within_res = sum(abs(z_res) <= 3 for _, _, _, bound, z_res in v if not bound)
        rms = math.sqrt(sum(z * z for _, _, z in inside) / len(inside)) if inside else math.nan
        median_sigma = statistics.median(s for _, s, _ in inside) * scale if inside else math.nan
        print(f"| {k} | {within} of {len(inside)} | {within_res} | {len(v) - len(inside)} | {rms:.1f} | "
              f"{statistics.median(e for e, *_ in v) * scale:.3g} {unit} | "
              f"{max(e for e, *_ in v) * scale:.3g} {unit} | {median_sigma:.3g} {unit} |")
    for lens in sorted(beyond):
        print(f"lenslet {lens} (f = {truth['lenslets'][lens]['focal_mm']:.2f} mm): {', '.join(beyond[lens])}")


if __name__ == "__main__":
    main(sys.argv[1:])
