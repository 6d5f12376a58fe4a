#!/bin/bash
# series.sh NEW BASE: two prism binaries on the 1000 volume events, the
# default search alternated with BASE and with NEW's exhaustive level 2
# (--level 2), then once more each. series-first.txt: NEW = 3e8254c's
# binary, BASE = 83e37a1's (its last lines, four interleaved pairs, were run
# by hand the same way); series-final.txt: NEW = eadac68's, BASE = 83e37a1's.
new=$1 base=$2
run() { local tag=$1; shift; /usr/bin/time -f "$tag wall %e cpu %U+%S" "$@" 2>&1 | grep -E 'events/s|time:|wall' | tr '\n' ' ' | sed 's/$/\n/' | sed -E 's/; 0 vertices flagged//; s/time: support scans/scans/'; }
# search BINARY CSV [OPTIONS]: the arguments of one search (/usr/bin/time
# runs a program, not a shell function).
search() { echo "$1" reconstruct --dictionary d2783 --events vol.events --out "$2" --model none --device cpu "${@:3}"; }
for i in 1 2; do
  run new$i $(search "$new" new.csv)
  run base$i $(search "$base" base.csv)
  run exh$i $(search "$new" exhaustive.csv --level 2)
done
run new3 $(search "$new" new.csv)
run base3 $(search "$base" base.csv)
