#!/usr/bin/env bash
# Issue 18's volume comparison again, at 4f19ede (the refinement has changed
# since ../run.sh's runs), with the model fitted from the summed merge's
# PSFs: the from-nominal fit of ../hdr-bias/summed-from-nominal/ (every
# default parameter, seed-1 stacks), its sensor put back to the 6.9 um
# pixels (fitted-hdr-summed.json here). The oracle, the fit, the dictionary
# alone and the nominal prototype on the same 40 events; the measured
# dictionary as ../run.sh builds it. Resumable (--resume).
#   results/calibration-volume/summed-volume/run.sh [WORK]
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
repo="$(cd "$here/../../.." && pwd)"
prism="$repo/build/host/prism"
work="${1:-/tmp/calibration-volume-summed}"
mkdir -p "$work" && cd "$work"
[[ -d asbuilt-dict ]] || $prism dictionary build --scene prototype-as-built --out asbuilt-dict --binning 16 --rays 4096 --splat point
common=(--dictionary asbuilt-dict --truth-scene prototype-as-built --experiments volume --volume-x-mm -15,15
        --volume-y-mm -15,15 --volume-depth-mm 2,48 --seed 1 --resume --volume-events 40)
$prism evaluate "${common[@]}" --scene prototype-as-built --model scene --out vol-as-built
$prism evaluate "${common[@]}" --scene "$here/fitted-hdr-summed.json" --model scene --out vol-fitted-hdr-summed
$prism evaluate "${common[@]}" --model dictionary --out vol-dictionary
$prism evaluate "${common[@]}" --scene prototype --model scene --out vol-nominal
"$repo/results/calibration-volume/compare.py" as-built=vol-as-built fitted-hdr-summed=vol-fitted-hdr-summed \
  dictionary=vol-dictionary nominal=vol-nominal
