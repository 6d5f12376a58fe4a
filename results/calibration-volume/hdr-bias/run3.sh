#!/usr/bin/env bash
# E3: the same 24 positions without noise or merge (footprint 4096 cells, stratification 1), fitted from the same start.
set -euo pipefail
cd /work/exp19
P=/work/main/build/host/prism
mkdir -p e3
[[ -d e3/psfs ]] || $P dictionary build --scene camera-as-built.json --out e3/psfs --binning 1 --rays 4096 --splat footprint \
  --stratification 1 --grid-x-mm=-10,10 --grid-y-mm=-10,0,10 --grid-depth-mm 5,15,30,45
[[ -s e3/fitted.json ]] || /usr/bin/time -v $P calibrate --dictionary e3/psfs --scene start.json --coarse-levels 0 --out e3/fitted.json --csv e3/params.csv > e3/log 2>&1
echo done
