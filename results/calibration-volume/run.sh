#!/usr/bin/env bash
# Issue 18's comparison, as run for this folder: the synthetic as-built
# prototype's events reconstructed with its "measured" dictionary and refined
# with four models (the nominal scene, the fitted one, the as-built oracle,
# the dictionary's PSFs interpolated). Resumable: rerun it with a larger N
# (the first argument, default 30) and each model's journal is extended to N
# events. Work goes to WORK (the second argument, default /tmp/calibration-volume).
#   results/calibration-volume/run.sh [N] [WORK]
set -euo pipefail
repo="$(cd "$(dirname "$0")/../.." && pwd)"
prism="$repo/build/host/prism"
n="${1:-30}"
work="${2:-/tmp/calibration-volume}"
mkdir -p "$work" && cd "$work"

# The measured dictionary: the as-built system's default 2783-PSF grid, as
# the issue-10 runs build the prototype's (point splat, 4096 rays, 110 um).
[[ -d asbuilt-dict ]] || $prism dictionary build --scene prototype-as-built --out asbuilt-dict --binning 16 --rays 4096 --splat point
# What the calibration fits: 24 PSFs of the as-built system over the field,
# rendered as a camera's box pixels see them (footprint, 4096 cells,
# stratification 1: not the model's 1024 cells), without noise.
[[ -d calib-psfs ]] || $prism dictionary build --scene prototype-as-built --out calib-psfs --binning 16 --rays 4096 \
  --splat footprint --stratification 1 --grid-x-mm=-10,10 --grid-y-mm=-10,0,10 --grid-depth-mm 5,15,30,45
# The fit from the nominal prototype, every default parameter (216).
[[ -s fitted.json ]] || { $prism calibrate --dictionary calib-psfs --scene prototype --out fitted.json.part \
  --csv fitted-params.csv --residuals residuals && mv fitted.json.part fitted.json; }

# The same events (seed 1, x and y in +-15 mm, depth 2..48, 100 photons;
# truth from the as-built scene) for every model; --resume extends a journal.
common=(--dictionary asbuilt-dict --truth-scene prototype-as-built --experiments volume --volume-x-mm -15,15
        --volume-y-mm -15,15 --volume-depth-mm 2,48 --seed 1 --resume --volume-events "$n")
$prism evaluate "${common[@]}" --scene prototype --model scene --out vol-nominal
$prism evaluate "${common[@]}" --scene fitted.json --model scene --out vol-fitted
$prism evaluate "${common[@]}" --scene prototype-as-built --model scene --out vol-as-built
$prism evaluate "${common[@]}" --model dictionary --out vol-dictionary
"$repo/results/calibration-volume/compare.py" nominal=vol-nominal fitted=vol-fitted as-built=vol-as-built \
  dictionary=vol-dictionary
