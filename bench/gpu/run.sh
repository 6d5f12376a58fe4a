#!/usr/bin/env bash
# One timed session on a machine with a Vulkan GPU (docs/performance.md "On a GPU"):
# bench_forward, the main job of ./setup.sh demo, bench_reconstruct and the
# test files (validation layer on), in that order unless STEPS names others,
# each stopped at its share of a time budget. Logs and CSVs go to OUT; a
# summary is printed last.
#
#   bench/gpu/run.sh OUT [BUDGET_SECONDS [STEPS]]
#       BUDGET_SECONDS  default 540
#       STEPS           comma list of forward, demo, reconstruct, tests
#                       (default all four, in that order)
#   PRISM_GPU_TEST_FILES="engine/test_footprint.cpp ..."   only these test files
#
# Where the machine lacks the build dependencies, bench/gpu/bundle.sh packs
# the binaries: this script unpacks .gpu/bundle.tar.gz when it is there.
# The device: $PRISM_DEVICE, default gpu (a GPU, never lavapipe).
set -uo pipefail
root="$(cd "$(dirname "$0")/../.." && pwd)"
out="${1:?usage: bench/gpu/run.sh OUT [BUDGET_SECONDS [STEPS]]}"
budget="${2:-540}"
steps="${3:-forward,demo,reconstruct,tests}"
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

# The test files, several at once (each its own process, as ctest runs
# them), validation layer on. Not the MPI test (no mpirun there) nor the
# Python and camera tests (not in prism_tests). The longest files first
# (ctest's measured costs on lavapipe), so that none is left to the end.
run_tests() {
  local files="${PRISM_GPU_TEST_FILES:-}"
  [[ -n "$files" ]] || files=$(cd tests && ls engine/*.cpp host/*/*.cpp host/*.cpp | grep -v cmd/test_mpi |
    awk '{print (/calibrate\/test_calibrate|test_refine|test_reconstruct|test_footprint|test_diffraction|test_forward_vulkan|test_cli|test_evaluate/ ? 0 : 1), $0}' |
    sort -k1,1n -s | cut -d' ' -f2)
  local t0=$SECONDS left=$((budget - (SECONDS - start) - 10))
  ((left < 20)) && { note "== tests: skipped, budget spent"; return; }
  echo $files | tr ' ' '\n' | xargs -P 8 -I{} sh -c 't=$(date +%s); n=$(echo {} | tr / _); timeout -k 5 '"$left"' \
    build/tests/prism_tests --source-file="*tests/{}" >"'"$out"'/tests/$n.log" 2>&1; echo "$? $(($(date +%s) - t)) s {}"' \
    >"$out/tests.rc"
  note "== tests: $((SECONDS - t0)) s (stopped after $left s); failed or stopped: $(awk '$1 != 0' "$out/tests.rc" | wc -l) of $(wc -l <"$out/tests.rc")"
  sort -k2,2nr "$out/tests.rc" | awk '{print "   rc " $0}' | tee -a "$summary"
}

# The main job of ./setup.sh demo, each command timed.
run_demo() {
  mkdir -p "$out/demo"
  step demo-dictionary 150 $prism dictionary build --scene prototype --out "$out/demo/dictionary" --binning 16 \
    --rays 4096 --splat point
  step demo-simulate 60 $prism simulate --scene prototype --vertex 1,1,31,100 --events 1000 --binning 16 --seed 1 \
    --out "$out/demo/events.events"
  step demo-reconstruct 60 $prism reconstruct --dictionary "$out/demo/dictionary" --events "$out/demo/events.events" \
    --vertices 1 --out "$out/demo/vertices.csv" --model none
  step demo-evaluate 120 $prism evaluate --dictionary "$out/demo/dictionary" --experiments volume --volume-events 8 \
    --volume-x-mm -15,15 --volume-y-mm -15,15 --volume-depth-mm 2,48 --model scene --out "$out/demo/volume"
  rm -rf "$out/demo/dictionary"  # large; its manifest is in the log
}

for s in ${steps//,/ }; do
  case "$s" in
    forward) step bench_forward 90 build/bench/bench_forward --device "$PRISM_DEVICE" --sections throughput,passes ;;
    demo) run_demo ;;
    reconstruct) step bench_reconstruct 200 build/bench/bench_reconstruct --device "$PRISM_DEVICE" \
                   --out "$out/bench-reconstruct" --groups backend,coarse,K,refine,native ;;
    tests) run_tests ;;
    *) note "unknown step $s (forward, demo, reconstruct, tests)"; exit 2 ;;
  esac
done

note "== total $((SECONDS - start)) s"
for f in bench_forward demo-reconstruct demo-evaluate bench_reconstruct; do
  [[ -f "$out/$f.log" ]] && { echo "---- $f"; tail -n 30 "$out/$f.log"; }
done
