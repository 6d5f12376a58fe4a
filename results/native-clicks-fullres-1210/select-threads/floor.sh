#!/bin/bash
# 6.9 um clicks: the search's own floor above the dark rate, chosen on seed 6, checked on seed 5.
cd /work/exp/nat1210
P=/work/main/build/host/prism
ev=${1:-native-b1-s6.events}; shift
for sdr in "$@"; do
  n=floor-$(basename $ev .events)-$sdr
  $P reconstruct --dictionary /work/exp/dict/fullres-1210 --events $ev --out $n.csv --model none --device cpu --search-dark-rate $sdr > rec-$n.log 2>&1
  echo "$n: $(grep 'events/s' rec-$n.log) | $(grep 'fitted' rec-$n.log | sed 's/.*(//')"
  PYTHONPATH=/work/main/build/python /usr/bin/python3 /work/main/results/native-clicks-fullres-1210/score.py $ev $n.csv
done
