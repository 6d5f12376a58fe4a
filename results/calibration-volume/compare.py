#!/usr/bin/env python3
"""Issue 18's comparison: the same as-built events refined with each model.

Reads <dir>/volume-events.csv of each model's `prism evaluate` run (given as
NAME=DIR) and prints one row per model over the events every run has done
(the runs grow at their own pace; a comparison is only fair on the same
events): catastrophic count (3D error > 3 mm), mean and median 3D error, RMSE and
median |error| / CRLB per axis over the other events, the mean photon-count
error, and the seconds per event.

    results/calibration-volume/compare.py nominal=DIR fitted=DIR as-built=DIR dictionary=DIR
"""
import csv
import math
import statistics
import sys

CATASTROPHIC_MM = 3.0  # engine/defaults.h: catastrophic_error_mm
TRUE_PHOTONS = 100.0   # the runs' --volume-photons


def read(path):
    try:
        with open(path) as f:
            return {int(r["event"]): r for r in csv.DictReader(f)}
    except FileNotFoundError:
        sys.exit(f"{path}: not there; a run still going writes it when done (or now: `prism evaluate` with its "
                 "options and --journal-only)")


def main(args):
    if not args or any("=" not in a for a in args):
        sys.exit(__doc__)
    runs = [(a.split("=", 1)[0], read(a.split("=", 1)[1] + "/volume-events.csv")) for a in args]
    common = sorted(set.intersection(*(set(events) for _, events in runs)))
    if not common:
        sys.exit("no event is in every run")
    print(f"{len(common)} events in every run (indices {common[0]}..{common[-1]})")
    print("| model | events | > 3 mm | mean / median 3D (mm) | RMSE x / y / z (mm) | median error / CRLB x / y / z"
          " | mean abs(alpha - 100) | s / event |")
    print("|---|---|---|---|---|---|---|---|")
    for name, events in runs:
        rows = [events[i] for i in common]
        err3d = [float(r["err3d_mm"]) for r in rows]
        good = [r for r, e in zip(rows, err3d) if e <= CATASTROPHIC_MM]
        axes = [("x_mm", "est_x_mm", "crlb_x_mm"), ("y_mm", "est_y_mm", "crlb_y_mm"),
                ("depth_mm", "est_depth_mm", "crlb_z_mm")]
        rmse, ratio = [], []
        for truth, est, bound in axes:
            errs = [float(r[est]) - float(r[truth]) for r in good]
            rmse.append(math.sqrt(sum(e * e for e in errs) / len(errs)) if errs else math.nan)
            ratio.append(statistics.median(abs(e) / float(r[bound]) for e, r in zip(errs, good)) if errs else math.nan)
        alpha = statistics.mean(abs(float(r["alpha"]) - TRUE_PHOTONS) for r in rows)
        seconds = [float(r["seconds"]) for r in rows if r["seconds"]]
        print(f"| {name} | {len(rows)} | {len(rows) - len(good)} | {statistics.mean(err3d):.3f} / {statistics.median(err3d):.3f} | "
              f"{rmse[0]:.3f} / {rmse[1]:.3f} / {rmse[2]:.3f} | {ratio[0]:.2f} / {ratio[1]:.2f} / {ratio[2]:.2f} | "
              f"{alpha:.1f} | {statistics.median(seconds) if seconds else math.nan:.0f} |")


if __name__ == "__main__":
    main(sys.argv[1:])
