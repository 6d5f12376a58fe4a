#!/usr/bin/env bash
# Build the libFuzzer harnesses (clang, ASan + UBSan) in build-sanitize/,
# the tree the sanitizer suite shares (tools/sanitizer-build.sh), and run
# each from the seed corpus in fuzz/corpus/<harness>/, as many at once as
# there are cores:
#   fuzz/run.sh [runs|SECONDS] [HARNESS ...]
# runs (the default; CI): a fixed number of executions per harness (runs_of
#   below, about 8 s each on 2 cores), from a fresh corpus with a fixed
#   seed, so that how far CI gets does not hang on its machine's speed. Not
#   bit for bit: libFuzzer's scheduling varies from run to run (two runs of
#   the scene harness here added 4911 and 4814 inputs), so CI can still meet
#   a finding that a run here did not.
# SECONDS: each harness for that long, exploring, its corpus kept in
#   build-sanitize/fuzzing/corpus/<harness>/ (not the repository's).
# A crash leaves its input in build-sanitize/fuzzing/artifacts/ and makes the exit status
# 1. Needs Debian 12's clang-16 and libclang-rt-16-dev (clang 14 lacks C++20
# parenthesised aggregate initialisation, which the GLSL-shared code uses).
set -euo pipefail
cd "$(dirname "$0")/.."
mode="${1:-runs}"
shift || true
if [[ "$mode" != runs && ! "$mode" =~ ^[0-9]+$ ]]; then
  echo "fuzz/run.sh: '$mode': give 'runs' or a number of seconds, then harness names" >&2
  exit 2
fi
# Executions per harness in the fixed mode: about 8 s of each on the Intel
# Xeon here (2 cores, two harnesses at once; halved from 15 s when CI took
# 53 min: the whole CI must stay within 40 minutes, and the hour-long runs
# are where fuzzing finds things).
declare -A runs_of=([scene]=50000 [space]=50000 [manifest]=50000 [events]=30000 [psf_exr]=10000
                    [hdr_stack]=20000 [genicam]=100000 [gencp_ack]=2500000 [stream_leader_trailer]=2500000)
all=(scene space manifest events psf_exr hdr_stack genicam gencp_ack stream_leader_trailer)
harnesses=("${@:-${all[@]}}")
targets=(fuzz_seeds)
for h in "${harnesses[@]}"; do targets+=("fuzz_$h"); done
tools/sanitizer-build.sh "${targets[@]}"
bin=build-sanitize/fuzz  # the harnesses
work=build-sanitize/fuzzing  # seeds, corpora, logs and artifacts

# Seeds: the repository's corpus, plus what fuzz_seeds writes from the code
# that writes each format (so a format change brings fresh seeds).
mkdir -p $work/seeds $work/artifacts
ASAN_OPTIONS=detect_leaks=0 $bin/fuzz_seeds $work/seeds >/dev/null
mkdir -p $work/seeds/space && cp host/sweep/spaces/*.json $work/seeds/space/

# One harness per core at a time (CI has two).
fuzz_one() {
  local h=$1 corpus budget
  if [[ $mode == runs ]]; then
    corpus=$work/smoke/$h
    rm -rf "$corpus"
    budget=(-runs="${runs_of[$h]}" -reload=0)
  else
    corpus=$work/corpus/$h
    budget=(-max_total_time="$mode")
  fi
  mkdir -p "$corpus"
  local dirs=("$corpus")
  [[ -d fuzz/corpus/$h ]] && dirs+=("fuzz/corpus/$h")
  [[ -d $work/seeds/$h ]] && dirs+=("$work/seeds/$h")
  # Corpus dirs after the first are read only; -rss_limit_mb: a parser that
  # allocates beyond it on a small input is a finding. A fixed seed
  # (PRISM_FUZZ_SEED, default 1): the same binary and corpus mutate alike.
  local rc=0
  ASAN_OPTIONS=detect_leaks=1 $bin/fuzz_$h -seed="${PRISM_FUZZ_SEED:-1}" "${budget[@]}" \
      -rss_limit_mb=2048 -timeout=20 \
      -max_len=65536 -artifact_prefix=$work/artifacts/$h- -print_final_stats=1 "${dirs[@]}" \
      >"$work/$h.log" 2>&1 || rc=$?
  echo $rc >"$work/$h.status"
}
slots=$(nproc)
rm -f $work/*.status
for h in "${harnesses[@]}"; do
  while (( $(jobs -rp | wc -l) >= slots )); do wait -n || true; done
  fuzz_one "$h" &
done
wait

status=0
for h in "${harnesses[@]}"; do
  log=$work/$h.log
  if [[ "$(cat "$work/$h.status")" == 0 ]]; then
    runs=$(grep -o 'stat::number_of_executed_units: *[0-9]*' "$log" | grep -o '[0-9]*$' || echo "?")
    cov=$(grep -o 'cov: [0-9]*' "$log" | tail -1 | grep -o '[0-9]*' || echo "?")
    took=$(grep -o 'Done [0-9]* runs in [0-9]* second' "$log" | grep -o '[0-9]* second' | grep -o '[0-9]*' || echo "$mode")
    echo "fuzz $h: ${runs} executions in ${took} s, coverage ${cov} edges, no crash"
  else
    echo "fuzz $h: FAILED (log: $log; input: $work/artifacts/$h-*)" >&2
    tail -40 "$log" >&2
    status=1
  fi
done
exit $status
