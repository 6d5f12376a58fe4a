#!/bin/bash
# old-exhaustive.sh NEW BASE: the base binary's exhaustive level 2 (the scan as it was) alternated
# with the new default, on the 1000 volume events in d2783 (run in the directory holding both)
new=$1 base=$2
run() { local tag=$1; shift; /usr/bin/time -f "$tag wall %e cpu %U+%S" "$@" 2>&1 | grep -E 'events/s|time:|wall' | tr '\n' ' ' | sed 's/$/\n/' | sed -E 's/; 0 vertices flagged//; s/time: support scans/scans/'; }
search() { echo "$1" reconstruct --dictionary d2783 --events vol.events --out "$2" --model none --device cpu "${@:3}"; }
for i in 1 2; do
  run new$i $(search "$new" new.csv)
  run base-exh$i $(search "$base" base-exhaustive.csv --level 2)
done
run new3 $(search "$new" new.csv)
