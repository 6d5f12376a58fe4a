#!/usr/bin/env python3
"""Issue 18: a bootstrap over the PSFs against the sandwich's sigmas.

    python3 results/calibration-volume/bootstrap/bootstrap.py [--max] BASE_PARAMS.csv REPLICATE_PARAMS.csv... > OUT.csv

BASE_PARAMS.csv: `prism calibrate --csv` of the fit on all PSFs. Each
REPLICATE_PARAMS.csv: the same fit's end refitted on the PSFs drawn with
replacement (run.sh). Writes the base table with sigma_residuals replaced by
the replicates' standard deviation (sigma_bootstrap) and sigma =
hypot(sigma_bootstrap, sigma_cells), or with --max hypot(max(sandwich,
bootstrap), sigma_cells) (what `prism calibrate --bootstrap` reports), for
against_truth.py. Prints the ratio bootstrap / sandwich to stderr.
"""
import csv
import math
import statistics
import sys


def main(args):
    use_max = args[:1] == ["--max"]
    args = args[1:] if use_max else args
    if len(args) < 3:
        sys.exit(__doc__)
    base = list(csv.DictReader(open(args[0])))
    reps = [{r["parameter"]: float(r["fitted"]) for r in csv.DictReader(open(p))} for p in args[1:]]
    out = csv.DictWriter(sys.stdout, fieldnames=list(base[0].keys()) + ["sigma_sandwich", "sigma_bootstrap"])
    out.writeheader()
    ratios = []
    for r in base:
        vals = [rep[r["parameter"]] for rep in reps]
        boot = statistics.stdev(vals)
        sand = float(r["sigma_residuals"])
        cells = float(r["sigma_cells"] or 0)
        row = dict(r)
        row["sigma_sandwich"] = sand
        row["sigma_bootstrap"] = boot
        part = max(sand, boot) if use_max else boot
        row["sigma_residuals"] = part
        row["sigma"] = math.hypot(part, cells) if math.isfinite(sand) else r["sigma"]
        out.writerow(row)
        if math.isfinite(sand) and sand > 0:
            ratios.append((boot / sand, r["parameter"]))
    ratios.sort()
    print(f"{len(reps)} replicates; bootstrap / sandwich: median {statistics.median(x for x, _ in ratios):.2f}, "
          f"range {ratios[0][0]:.2f} ({ratios[0][1]}) .. {ratios[-1][0]:.2f} ({ratios[-1][1]})", file=sys.stderr)


if __name__ == "__main__":
    main(sys.argv[1:])
