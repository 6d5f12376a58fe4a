#!/usr/bin/env python3
"""The paper's Fig. 3: the 3D CRLB against depth of the multifocal prototype
beside the unifocal array and the single lens of each focal length (3, 9 and
15 mm), one panel per focal length, Poisson pixels, 6280 photons emitted.

    PYTHONPATH=build/python python3 examples/fig3_crlb.py --out fig3.png

At the defaults (footprint splat, the converged cells per lenslet, 110 um
analysis pixels, depths 0..50 mm in steps of 2.5) this takes a few minutes on
a CPU device; --quick draws a coarse version in about a minute. The numbers
are `prism crlb`'s (README "Results: CRLB against depth"), where the rows
flagged "moving" (not converged in the rays) are discussed.
"""
import argparse

import matplotlib
import numpy as np

import prism

matplotlib.use("Agg")  # files only; no window
import matplotlib.pyplot as plt  # noqa: E402


def main():
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", default="fig3-crlb.png", help="the figure (.png, .svg or .pdf)")
    p.add_argument("--quick", action="store_true", help="depths every 10 mm, 1024 cells per lenslet, 220 um pixels")
    p.add_argument("--device", default=None, help="Vulkan device (prism.devices()); default $PRISM_DEVICE or auto")
    args = p.parse_args()

    depth_mm = np.arange(0.0, 50.01, 10.0 if args.quick else 2.5)
    options = dict(rays=1024, binning=32) if args.quick else {}
    names = ["prototype"] + [f"{kind}-f{f}" for f in (3, 9, 15) for kind in ("unifocal", "single")]
    tables = {name: prism.crlb(name, depth_mm=depth_mm, device=args.device, **options) for name in names}
    for name, table in tables.items():
        print(f"{name:>14}: " + " ".join(f"{v:.3g}" for v in table["crlb_3d_mm"]))
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.2), sharey=True, constrained_layout=True)
    for ax, focal in zip(axes, (3, 9, 15)):
        for name, style in (("prototype", "-"), (f"unifocal-f{focal}", "-"), (f"single-f{focal}", "--")):
            table = tables[name]
            moving = table["flag"] == "moving"
            line, = ax.semilogy(table["depth_mm"], table["crlb_3d_mm"], style, label=f"{name} ({table['lens_model'][0]})")
            # Rows not converged in the rays: open markers.
            ax.semilogy(table["depth_mm"][moving], table["crlb_3d_mm"][moving], "o", mfc="none", color=line.get_color())
        ax.set_title(f"focal length {focal} mm")
        ax.set_xlabel("depth from the scintillator face (mm)")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    axes[0].set_ylabel("3D CRLB (mm)")
    fig.suptitle(f"3D CRLB against depth, Poisson pixels, 6280 photons emitted ({prism.device_name(args.device)}; "
                 "open markers: not converged in the rays)", fontsize=9)
    fig.savefig(args.out, dpi=120)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
