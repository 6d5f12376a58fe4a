#!/bin/bash
# MPI scaling of `prism dictionary build`, `simulate`, `reconstruct`,
# `evaluate` and `sweep` on this machine:
# one process against `mpirun -n 2`, alternated REPEATS times, medians, the
# outputs compared byte for byte. Every rank's lavapipe runs one thread
# (LP_NUM_THREADS=1), so two ranks on two cores do not oversubscribe them;
# each rank also runs its host work on its own thread beside the device's.
#
#   bench/mpi_scaling.sh [BUILD_DIR] [REPEATS] [ROWS]   (defaults: build, 3, all)
#
# ROWS: an extended regular expression; only the commands whose row it
# matches are run (e.g. 'evaluate|sweep').
#
# Inputs are made in a scratch folder: the default 110 um dictionary of the
# prototype (about a minute), events at random positions over the volume
# (forward truth, 100 photons), reconstructed with the search alone; the
# volume experiment refined with the dictionary model; a short sweep. About
# 40 minutes with 3 repeats on 2 cores (evaluate 2 and sweep 5 minutes a
# pair).
set -euo pipefail
build=${1:-build}
repeats=${2:-3}
rows=${3:-.}
prism=$(realpath "$build/host/prism")
source=$(realpath "$(dirname "$0")/..")
[ -x "$prism" ] || { echo "no $prism: build first (README \"Set up\")" >&2; exit 1; }
command -v mpirun > /dev/null || { echo "no mpirun: apt-get install openmpi-bin libopenmpi-dev" >&2; exit 1; }
export LP_NUM_THREADS=1
mpi=(mpirun --allow-run-as-root -n 2)
work=$(mktemp -d /tmp/prism-mpi-scaling.XXXXXX)
trap 'rm -rf "$work"' EXIT
cd "$work"

echo "# machine: $(nproc) cores, $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2 | xargs)"
echo "# device: $("$prism" devices | head -1) (each rank its own, LP_NUM_THREADS=1)"
echo "# $(mpirun --version | head -1)"
"$prism" dictionary build --scene prototype --out dict --binning 16 --rays 4096 --splat point > /dev/null 2>&1

# Wall seconds of a command; "failed" when it fails (compare stops then).
seconds() {
  local t0 t1
  t0=$(date +%s.%N)
  "$@" > "$work/last.log" 2>&1 || { echo failed; return; }
  t1=$(date +%s.%N)
  echo "$t1 - $t0" | bc
}
median() { printf '%s\n' "$@" | sort -g | awk '{a[NR]=$1} END {print (NR % 2) ? a[(NR + 1) / 2] : (a[NR / 2] + a[NR / 2 + 1]) / 2}'; }

# Whether two output folders hold the same figures: every file but the
# journals, with the columns of seconds measured left out of the CSVs.
same_figures() {
  python3 - "$1" "$2" <<'PY'
import csv, io, os, sys
def figures(d):
    out = {}
    for name in sorted(os.listdir(d)):
        if name.endswith(".jsonl"): continue
        data = open(os.path.join(d, name), "rb").read()
        if name.endswith(".csv"):
            rows = list(csv.reader(io.StringIO(data.decode())))
            keep = [i for i, c in enumerate(rows[0]) if c != "seconds"]
            data = [[r[i] for i in keep if i < len(r)] for r in rows]
        out[name] = data
    return out
sys.exit(0 if figures(sys.argv[1]) == figures(sys.argv[2]) else 1)
PY
}

# One command alone and under two ranks, REPEATS times each, alternated.
# EXACT=1: the two outputs must be the same bytes; otherwise say whether
# (EXACT=figures: whether they hold the same figures, as above).
compare() {
  local what=$1 exact=$2 out=$3; shift 3
  [[ "$what" =~ $rows ]] || return 0
  local one=() two=() same="same bytes"
  for ((i = 0; i < repeats; ++i)); do
    rm -rf "1-$out" "2-$out"  # a dictionary folder left would be resumed
    one+=("$(seconds "$prism" "$@" --out "1-$out")")
    two+=("$(seconds "${mpi[@]}" "$prism" "$@" --out "2-$out")")
    if [[ " ${one[*]} ${two[*]} " == *" failed "* ]]; then
      echo "$what: a run failed:" >&2
      cat "$work/last.log" >&2
      exit 1
    fi
    if [ "$exact" = figures ]; then
      if [ "$same" != "figures differ" ]; then
        same_figures "1-$out" "2-$out" && same="same figures (times aside)" || same="figures differ"
      fi
    elif ! diff -rq "1-$out" "2-$out" > /dev/null; then
      [ "$exact" = 1 ] && { echo "$what: the outputs of 1 and 2 ranks differ" >&2; exit 1; }
      same="bytes differ"
    fi
  done
  local m1 m2
  m1=$(median "${one[@]}")
  m2=$(median "${two[@]}")
  printf '%-62s %8.2f s %8.2f s %6.2fx  %s\n' "$what" "$m1" "$m2" "$(echo "$m1 / $m2" | bc -l)" "$same"
}

printf '%-62s %10s %10s %7s\n' "command (medians of $repeats)" "1 process" "2 ranks" "speed-up"
compare "dictionary build: 242 PSFs (2 depths), point splat, 1024 rays" 0 built \
  dictionary build --grid-depth-mm 10,30 --binning 16 --rays 1024 --splat point
# Forward truth with jitter: each event renders its own PSF on the device,
# whose float sums come in no fixed order, so even two single-process runs
# may differ in the last bits (host/events/simulate.h); the search is exact.
compare "simulate: 160 events, forward truth, a PSF each (1024 cells)" 0 events \
  simulate --vertex 0,0,25 --jitter-mm 15 --events 160 --binning 16 --rays 1024 --seed 7
reconstruct_row="reconstruct: 300 events over the volume, the search alone"
if [[ "$reconstruct_row" =~ $rows ]]; then
  "$prism" simulate --vertex 0,0,25 --jitter-mm 15 --events 300 --binning 16 --rays 1024 --seed 9 --out volume.events \
    > /dev/null 2>&1
fi
compare "$reconstruct_row" 1 csv reconstruct --dictionary dict --events volume.events --model none
# The volume experiment with the dictionary model's refinement: the events
# are shared, the CRLB study is made whole by each rank.
compare "evaluate: 16 volume events, the dictionary model's refinement" figures evaluation \
  evaluate --dictionary dict --experiments volume --volume-events 16 --volume-x-mm -15,15 --volume-y-mm -15,15 \
  --volume-depth-mm 2,48 --model dictionary
# A sweep's batches of 8 designs, 4 a rank (footprint splat: a design's
# last bits depend on the designs beside it in a dispatch, docs/mpi.md).
compare "sweep: 16 designs of focal-assignment.json, batches of 8, 256 cells" figures sweep \
  sweep --space "$source/host/sweep/spaces/focal-assignment.json" --budget 16 --batch 8 --rays 256
