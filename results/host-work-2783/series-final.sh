#!/bin/bash
# final = eadac68; base = 83e37a1; exhaustive = final --level 2; alternated
run() { local tag=$1; shift; /usr/bin/time -f "$tag wall %e cpu %U+%S" "$@" 2>&1 | grep -E 'events/s|time:|wall' | tr '\n' ' ' | sed 's/$/\n/' | sed -E 's/; 0 vertices flagged//; s/time: support scans/scans/'; }
for i in 1 2; do
  run final$i ./prism-final reconstruct --dictionary d2783 --events vol.events --out sf.csv --model none --device cpu
  run base$i ./prism-base reconstruct --dictionary d2783 --events vol.events --out sb.csv --model none --device cpu
  run exh$i ./prism-final reconstruct --dictionary d2783 --events vol.events --out sx2.csv --model none --device cpu --level 2
done
run final3 ./prism-final reconstruct --dictionary d2783 --events vol.events --out sf.csv --model none --device cpu
run base3 ./prism-base reconstruct --dictionary d2783 --events vol.events --out sb.csv --model none --device cpu
