#!/usr/bin/env python3
"""Reconstruct single-vertex events at random positions and plot each
event's error against its CRLB, axis by axis (docs/reconstruction.md "Accuracy over the
whole volume" does the same at scale with `prism evaluate`).

    PYTHONPATH=build/python python3 examples/reconstruct_vs_crlb.py \\
        --dictionary out/prototype-dictionary --events 20 --out errors.png

The truth is rendered with 4x the refinement model's cells and another
stratification, so the estimator never sees its own model. With the
prototype's real lenses refinement takes about 20 s per event on a CPU
device; --quick builds a small thin-lens dictionary of the unifocal f9
array in --work and reconstructs 6 events near it (about a minute).
"""
import argparse
import os

import matplotlib
import numpy as np

import prism

matplotlib.use("Agg")  # files only; no window
import matplotlib.pyplot as plt  # noqa: E402


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--dictionary", help="a dictionary folder (default with --quick: a small one built in --work)")
    p.add_argument("--events", type=int, default=20, help="events, each at its own random position")
    p.add_argument("--photons", type=float, default=100.0, help="expected detected photons per event")
    p.add_argument("--seed", type=int, default=1)
    p.add_argument("--out", default="errors-vs-crlb.png", help="the figure")
    p.add_argument("--quick", action="store_true", help="a small thin-lens dictionary and 6 events")
    p.add_argument("--work", default="out/example", help="where --quick builds its dictionary")
    p.add_argument("--device", default=None)
    args = p.parse_args()

    if args.quick:
        os.makedirs(args.work, exist_ok=True)
        scene = {"base": "unifocal-f9", "lens_model": "thin"}
        d = prism.build_dictionary(os.path.join(args.work, "dictionary"), scene, grid_x_mm=[-5, 0, 5],
                                   grid_y_mm=[-5, 0, 5], grid_depth_mm=[15, 20, 25, 30], binning=16, rays=1024,
                                   device=args.device)
        box = dict(x=(-3, 3), y=(-3, 3), depth=(16, 29))
        args.events = 6
    else:
        if not args.dictionary:
            p.error("--dictionary DIR (e.g. out/prototype-dictionary from ./setup.sh demo), or --quick")
        d = prism.Dictionary(args.dictionary)
        box = dict(x=(d.grid_x_mm.min() * 0.6, d.grid_x_mm.max() * 0.6),
                   y=(d.grid_y_mm.min() * 0.6, d.grid_y_mm.max() * 0.6),
                   depth=(max(2.0, d.grid_depth_mm.min()), d.grid_depth_mm.max()))
    print(d)

    rng = np.random.default_rng(args.seed)
    truth = np.column_stack([rng.uniform(*box["x"], args.events), rng.uniform(*box["y"], args.events),
                             rng.uniform(*box["depth"], args.events)])
    # Each event from its own position: one simulate call per position, the
    # truth at 4x the model's cells (refinement: 1024) and stratification 1.
    events = []
    for i, (x, y, depth) in enumerate(truth):
        (e,) = prism.simulate(d.scene, [(x, y, depth, args.photons)], 1, seed=args.seed * 100003 + i,
                              binning=d.base_binning, rays=4096, stratification=1, device=args.device)
        events.append((i, e.vertices, e.clicks))
    table = prism.reconstruct(d, events, device=args.device,
                              progress=lambda done, total: print(f"\rreconstructed {done} of {total}", end=""))
    print()

    estimate = np.column_stack([table["x_mm"], table["y_mm"], table["depth_mm"]])
    error = np.abs(estimate - truth)
    crlb = np.column_stack([table["crlb_x_mm"], table["crlb_y_mm"], table["crlb_z_mm"]])
    error_3d = np.linalg.norm(estimate - truth, axis=1)
    print(f"median 3D error {np.median(error_3d):.3f} mm; beyond 3 mm: {np.sum(error_3d > 3)} of {len(error_3d)}")
    print("median |error| / CRLB x, y, depth: " + " / ".join(f"{v:.2f}" for v in np.median(error / crlb, axis=0)))

    fig, ax = plt.subplots(figsize=(5.5, 5), constrained_layout=True)
    for k, (name, marker) in enumerate((("x", "o"), ("y", "s"), ("depth", "^"))):
        ax.loglog(crlb[:, k], error[:, k], marker, mfc="none", label=name)
    lo, hi = np.nanmin(crlb) / 3, max(np.nanmax(crlb), np.nanmax(error)) * 3
    ax.loglog([lo, hi], [lo, hi], "k-", lw=0.8, label="|error| = CRLB")
    ax.set_xlabel("CRLB at the estimate (mm)")
    ax.set_ylabel("|error| against the truth (mm)")
    ax.set_title(f"{d.scene.name}: {len(truth)} events, {args.photons:g} photons\n({prism.device_name(args.device)})",
                 fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.savefig(args.out, dpi=120)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
