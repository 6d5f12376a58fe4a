#!/usr/bin/env bash
# Issue 18: the whole 1210-PSF calibration at 110 um on lavapipe's machine, staged.
# prism at f46b597 (frozen copy ./prism). Each stage resumable.
set -euo pipefail
cd /work/exp23
P=./prism
G=(--grid-x-mm=-25:25:5 --grid-y-mm=-25:25:5 --grid-depth-mm 5:50:5 --exposures 9 --max-us 2e6)
T="/usr/bin/time -v"
[[ -f stacks.done ]] || { $T $P dictionary simulate-hdr --scene camera-as-built.json --out stacks "${G[@]}" --seed 1 > simulate.log 2>&1 && touch stacks.done; }
[[ -f merged.done ]] || { $T $P dictionary merge-hdr --stacks stacks --out merged --backend cpu > merge.log 2>&1 && touch merged.done; }
# Stage 1: every 50th PSF from the nominal scene, every default (coarse to fine).
[[ -s s1.json ]] || $T $P calibrate --merged merged --scene camera-nominal.json --every 50 --cells-check 1 --out s1.json --csv s1.csv --checkpoint s1-reached.json > s1.log 2>&1
# Stage 2: every 10th from stage 1's end, on the model's pixels.
[[ -s s2.json ]] || $T $P calibrate --merged merged --scene s1.json --every 10 --coarse-levels 0 --cells-check 1 --out s2.json --csv s2.csv --checkpoint s2-reached.json > s2.log 2>&1
# Stage 3: all 1210 from stage 2's end, on the model's pixels, the default cells check.
[[ -s s3.json ]] || $T $P calibrate --merged merged --scene s2.json --coarse-levels 0 --out s3.json --csv s3.csv --checkpoint s3-reached.json > s3.log 2>&1
echo done
