#!/bin/bash
# base = 83e37a1 (before this session), new = 3e8254c; exhaustive = new --level 2
run() { local tag=$1; shift; /usr/bin/time -f "$tag wall %e user %U sys %S" "$@" 2>&1 | grep -E 'events/s|time:|wall' | sed "s/^/$tag: /"; }
for i in 1 2; do
  run base$i ./prism-base reconstruct --dictionary d2783 --events vol.events --out sb.csv --model none --device cpu
  run new$i ./prism-new reconstruct --dictionary d2783 --events vol.events --out sn.csv --model none --device cpu
  run exh$i ./prism-new reconstruct --dictionary d2783 --events vol.events --out sx.csv --model none --device cpu --level 2
done
run base3 ./prism-base reconstruct --dictionary d2783 --events vol.events --out sb.csv --model none --device cpu
run new3 ./prism-new reconstruct --dictionary d2783 --events vol.events --out sn.csv --model none --device cpu
