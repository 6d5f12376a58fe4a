#!/usr/bin/env bash
# One timed session on a machine with a Vulkan GPU (the README's GPU figures):
# the test files on the GPU (validation layer on), then the main job of
# ./setup.sh demo, bench_reconstruct and bench_forward, each step stopped at
# its share of a time budget. Logs and CSVs go to OUT; a summary is printed
# last.
#
#   bench/gpu/run.sh OUT [BUDGET_SECONDS]      default budget 540
#
# Where the machine lacks the build dependencies, bench/gpu/bundle.sh packs
# the binaries: this script unpacks .gpu/bundle.tar.gz when it is there.
# The device: $PRISM_DEVICE, default gpu (a GPU, never lavapipe).
set -uo pipefail
root="$(cd "$(dirname "$0")/../.." && pwd)"
out="${1:?usage: bench/gpu/run.sh OUT [BUDGET_SECONDS]}"
budget="${2:-540}"
mkdir -p "$out/tests"
out="$(cd "$out" && pwd)"
cd "$root"
if [[ -f .gpu/bundle.tar.gz ]]; then
  tar -xzf .gpu/bundle.tar.gz
  export LD_LIBRARY_PATH="$root/.gpu/lib${LD_LIBRARY_PATH:+:$LD_LIBRARY_PATH}"
  export VK_LAYER_PATH="$root/.gpu/layer"
  export PLPLOT_DRV_DIR="$root/.gpu/plplot/drivers" PLPLOT_LIB="$root/.gpu/plplot"
  # The test binary has the build's source folder compiled in (the prism
  # binary it runs, ../shared/reference): where this checkout lies elsewhere, link it there.
  built="$(grep -a -o -m1 '/[[:alnum:]_./+-]*/build/host/prism' build/tests/prism_tests | head -1)"
  src="${built%/build/host/prism}"
  if [[ -n "$src" && ! -e "$src" ]]; then mkdir -p "$(dirname "$src")" && ln -s "$root" "$src"; fi
  if [[ -n "$src" && ! -e "$(dirname "$src")/shared" ]]; then ln -s "$root/.gpu/shared" "$(dirname "$src")/shared"; fi
fi
export PRISM_DEVICE="${PRISM_DEVICE:-gpu}"
prism=build/host/prism
start=$SECONDS
summary="$out/summary.txt"
: >"$summary"
note() { echo "$*" | tee -a "$summary"; }

# step NAME SECONDS COMMAND...: run with stdout line-buffered into OUT/NAME.log,
# stopped after SECONDS or at the budget's end, whichever comes first.
step() {
  local name="$1" limit="$2"
  shift 2
  local left=$((budget - (SECONDS - start)))
  if ((left < 10)); then note "== $name: skipped, budget spent"; return 1; fi
  ((limit > left)) && limit=$left
  local t0=$SECONDS
  timeout -k 5 "$limit" stdbuf -oL -eL "$@" >"$out/$name.log" 2>&1
  local rc=$?
  note "== $name: rc $rc, $((SECONDS - t0)) s (limit $limit s)"
  return $rc
}

note "# $(date -u +%FT%TZ) $(git rev-parse --short HEAD 2>/dev/null || echo '?')"
note "# cpu: $(grep -m1 'model name' /proc/cpuinfo | cut -d: -f2) x $(nproc)"
command -v nvidia-smi >/dev/null && note "# $(nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader)"
step devices 30 $prism devices
cat "$out/devices.log" | tee -a "$summary"
if ! step probe 60 $prism crlb --scene prototype --depth-mm 25 --device "$PRISM_DEVICE"; then
  tail -20 "$out/probe.log"
  note "no usable $PRISM_DEVICE device: stopping"
  exit 1
fi

# 1. The test files, several at once (each its own process, as ctest runs
# them), validation layer on. Not the MPI test (no mpirun there) nor the
# Python and camera tests (not in prism_tests).
# The longest files first (ctest's measured costs on lavapipe), so that none is left to the end.
files=$(cd tests && ls engine/*.cpp host/*/*.cpp host/*.cpp | grep -v cmd/test_mpi |
  awk '{print (/calibrate\/test_calibrate|test_refine|test_reconstruct|test_footprint|test_diffraction|test_forward_vulkan|test_cli|test_evaluate/ ? 0 : 1), $0}' |
  sort -k1,1n -s | cut -d' ' -f2)
t0=$SECONDS
limit=$((budget / 4))
echo "$files" | xargs -P 8 -I{} sh -c 't=$(date +%s); n=$(echo {} | tr / _); timeout -k 5 '"$limit"' \
  build/tests/prism_tests --source-file="*tests/{}" >"'"$out"'/tests/$n.log" 2>&1; echo "$? $(($(date +%s) - t)) s {}"' \
  >"$out/tests.rc"
note "== tests: $((SECONDS - t0)) s (each file stopped after $limit s); failed or stopped: $(awk '$1 != 0' "$out/tests.rc" | wc -l) of $(wc -l <"$out/tests.rc")"
sort -k2,2nr "$out/tests.rc" | awk '{print "   rc " $0}' | tee -a "$summary"

# 2. The main job of ./setup.sh demo, each command timed.
mkdir -p "$out/demo"
step demo-dictionary 150 $prism dictionary build --scene prototype --out "$out/demo/dictionary" --binning 16 \
  --rays 4096 --splat point
step demo-simulate 60 $prism simulate --scene prototype --vertex 1,1,31,100 --events 1000 --binning 16 --seed 1 \
  --out "$out/demo/events.events"
step demo-reconstruct 60 $prism reconstruct --dictionary "$out/demo/dictionary" --events "$out/demo/events.events" \
  --vertices 1 --out "$out/demo/vertices.csv" --model none
step demo-evaluate 120 $prism evaluate --dictionary "$out/demo/dictionary" --experiments volume --volume-events 8 \
  --volume-x-mm -15,15 --volume-y-mm -15,15 --volume-depth-mm 2,48 --model scene --out "$out/demo/volume"
rm -rf "$out/demo/dictionary"   # large; its manifest is in the log

# 3. The benchmarks.
step bench_reconstruct 200 build/bench/bench_reconstruct --device "$PRISM_DEVICE" --out "$out/bench-reconstruct" \
  --groups backend,coarse,K,refine,native
step bench_forward 90 build/bench/bench_forward --device "$PRISM_DEVICE" --sections throughput,passes

note "== total $((SECONDS - start)) s"
for f in demo-reconstruct demo-evaluate bench_reconstruct bench_forward; do
  [[ -f "$out/$f.log" ]] && { echo "---- $f"; tail -n 30 "$out/$f.log"; }
done
