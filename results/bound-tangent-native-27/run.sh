#!/bin/bash
# Clicks at the sensor's 6.9 um pixels on a 27-PSF full-resolution dictionary:
# the scan's NLL bound before (PRISM_BEFORE: a build of 7d2989d) and after its
# tangents (36fbe89), the search alone, at two floors. docs/reconstruction.md "The bound at a
# high floor". Run from an empty directory; PRISM and PRISM_BEFORE name the binaries.
set -e
P=${PRISM:-prism}
$P dictionary build --scene prototype --grid-x-mm -5:5:5 --grid-y-mm -5:5:5 --grid-depth-mm 15:25:5 --binning 1 \
  --rays 1024 --device cpu --out d27
$P simulate --scene prototype --vertex 0,0,20,100 --jitter-mm 5 --events 100 --binning 1 --rays 1024 \
  --stratification 1 --seed 13 --device cpu --out nat.events
for dr in 1e-6 3.9e-9; do
  "$PRISM_BEFORE" reconstruct --dictionary d27 --events nat.events --out before-$dr.csv --model none --device cpu --dark-rate $dr > rec-before-dr$dr.log 2>&1
  $P reconstruct --dictionary d27 --events nat.events --out after-$dr.csv --model none --device cpu --dark-rate $dr > rec-after-dr$dr.log 2>&1
done
