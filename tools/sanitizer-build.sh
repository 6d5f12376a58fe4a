#!/usr/bin/env bash
# The clang build that the sanitizer suite (tests/sanitize.sh) and the fuzz
# harnesses (fuzz/run.sh) share, in build-sanitize/: everything under
# AddressSanitizer + UndefinedBehaviorSanitizer, the harnesses beside the
# tests, and libFuzzer's coverage instrumentation on the code that reads
# outside data alone (fuzz/coverage-allowlist.txt), so the suite's numerics
# run at a sanitizer build's usual speed. One build for both spares CI a
# second compile of the engine and host libraries.
#   tools/sanitizer-build.sh [TARGET ...]    no target: everything
set -euo pipefail
cd "$(dirname "$0")/.."
tools/ensure-packages.sh clang-16 libclang-rt-16-dev
CC=clang-16 CXX=clang++-16 cmake -S . -B build-sanitize -DCMAKE_BUILD_TYPE=Release -DPRISM_FUZZ=ON \
  -DPRISM_BENCH=OFF >/dev/null
targets=()
(($#)) && targets=(--target "$@")
cmake --build build-sanitize -j"$(nproc)" "${targets[@]}"
