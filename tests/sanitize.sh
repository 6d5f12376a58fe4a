#!/usr/bin/env bash
# The whole test suite under AddressSanitizer + UndefinedBehaviorSanitizer:
# a clang-16 build in build-sanitize/ (-DPRISM_SANITIZE=ON, benchmarks left
# out), then ctest with a test per core. Any sanitizer report, a leak at exit
# included, fails its test (tests/sanitizer_defaults.cpp holds the runtime's
# options). .ci/run runs it after the normal suite.
#   tests/sanitize.sh [CTEST ARGS ...]     e.g. -R hdr to run the files named so
set -euo pipefail
cd "$(dirname "$0")/.."
tools/ensure-packages.sh clang-16 libclang-rt-16-dev
CC=clang-16 CXX=clang++-16 cmake -S . -B build-sanitize -DCMAKE_BUILD_TYPE=Release -DPRISM_SANITIZE=ON -DPRISM_BENCH=OFF >/dev/null
cmake --build build-sanitize -j"$(nproc)"
cd build-sanitize
exec ctest --output-on-failure -j"$(nproc)" "$@"
