#!/bin/bash
# The native-click measurements of this stop, back to back on an otherwise idle machine.
cd /work/exp/nat1210
./run.sh new-t1-cold
./run.sh new-t1 --threads 1
./run.sh new-t2 --threads 2
./run.sh old-t1 --select-level 2 --threads 1
P=/work/main/build/host/prism
for t in 1 2; do
  /usr/bin/time -v $P reconstruct --dictionary /work/exp/dict/fullres-1210 --events native-b16.events --out b16-t$t.csv --model none --device cpu --threads $t > rec-b16-t$t.log 2> time-b16-t$t.log
  echo "b16-t$t: $(grep 'events/s' rec-b16-t$t.log) | $(grep 'time:' rec-b16-t$t.log) | RSS $(grep Maximum time-b16-t$t.log | awk '{print $6/1024}') MiB"
  PYTHONPATH=/work/main/build/python /usr/bin/python3 /work/main/results/native-clicks-fullres-1210/score.py native-b16.events b16-t$t.csv
done
echo alldone
