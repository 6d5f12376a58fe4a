#!/bin/bash
# A/B: the same clicks (truth: the new footprint at 4096 cells, stratification 1) refined by the old (centroid) and new (rasterised) model
cd /work/exp/ab
new=/work/exp/fd/prism-head; old=/work/exp/fd/prism-old
while read i v; do
  [[ -s ev$i.events ]] || $new simulate --vertex $v --events 1 --rays 4096 --stratification 1 --binning 16 --seed $((100+i)) --out ev$i.events > /dev/null 2>&1
  for b in new old; do
    [[ -s $b-$i.csv ]] || { bin=${!b}; $bin reconstruct --dictionary /work/exp/dark/d2783 --events ev$i.events --model scene --out $b-$i.csv.part > $b-$i.log 2>&1 && mv $b-$i.csv.part $b-$i.csv; }
  done
  echo "$i done $(date +%T)"
done < positions.txt
echo alldone
