#!/bin/bash
# Native 6.9 um clicks on the full-resolution 1210-PSF dictionary: host threads and the select level.
# usage: run.sh NAME [prism reconstruct options...]
cd /work/exp/nat1210
name=$1; shift
P=/work/main/build/host/prism
/usr/bin/time -v $P reconstruct --dictionary /work/exp/dict/fullres-1210 --events native-b1.events --out $name.csv --model none --device cpu "$@" > rec-$name.log 2> time-$name.log
echo "$name ($*): $(grep 'events/s' rec-$name.log) | $(grep 'time:' rec-$name.log) | RSS $(grep Maximum time-$name.log | awk '{print $6/1024}') MiB"
grep 'tiles' rec-$name.log
PYTHONPATH=/work/main/build/python /usr/bin/python3 /work/main/results/native-clicks-fullres-1210/score.py native-b1.events $name.csv
