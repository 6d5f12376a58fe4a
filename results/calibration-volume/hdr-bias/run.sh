#!/usr/bin/env bash
# Issue 18: lenslet 31/3 tilt-x bias. E1: a new noise seed (101). E2: seed 1, truth at 65536 cells.
set -euo pipefail
cd /work/exp19
P=/work/main/build/host/prism
G=(--grid-x-mm=-10,10 --grid-y-mm=-10,0,10 --grid-depth-mm 5,15,30,45 --exposures 9 --max-us 2e6)
[[ -d e1/merged ]] || { $P dictionary simulate-hdr --scene camera-as-built.json --out e1/stacks "${G[@]}" --seed 101 && \
  $P dictionary merge-hdr --stacks e1/stacks --out e1/merged --backend cpu; }
[[ -s e1/fitted.json ]] || { /usr/bin/time -v $P calibrate --merged e1/merged --scene start.json --coarse-levels 0 --out e1/fitted.json --csv e1/params.csv > e1/log 2>&1; }
[[ -d e2/merged ]] || { $P dictionary simulate-hdr --scene camera-as-built.json --out e2/stacks "${G[@]}" --seed 1 --rays 65536 && \
  $P dictionary merge-hdr --stacks e2/stacks --out e2/merged --backend cpu; }
[[ -s e2/fitted.json ]] || { /usr/bin/time -v $P calibrate --merged e2/merged --scene start.json --coarse-levels 0 --out e2/fitted.json --csv e2/params.csv > e2/log 2>&1; }
echo done
