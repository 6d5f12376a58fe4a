#!/usr/bin/env bash
# The whole test suite under AddressSanitizer + UndefinedBehaviorSanitizer:
# the clang-16 build in build-sanitize/ that the fuzz harnesses share
# (tools/sanitizer-build.sh), then ctest with a test per core. Any sanitizer
# report, a leak at exit included, fails its test (tests/sanitizer_defaults.cpp
# holds the runtime's options). The cases run there at the sizes that reach
# their code, not the sizes of their figures (tests/support.h,
# under_sanitizer). Before it, the tile cache that the host threads share
# under ThreadSanitizer (tests/tsan/tile_cache.cpp: its own
# small build, as ThreadSanitizer cannot share a build with
# AddressSanitizer). .ci/run runs this after the normal suite.
#   tests/sanitize.sh [CTEST ARGS ...]     e.g. -R hdr to run the files named so
set -euo pipefail
cd "$(dirname "$0")/.."
tools/sanitizer-build.sh
clang++-16 -std=c++20 -O1 -g -fsanitize=thread -I. tests/tsan/tile_cache.cpp \
  host/dictionary/tile_cache.cpp -o build-sanitize/tsan-tile-cache
TSAN_OPTIONS=halt_on_error=1 build-sanitize/tsan-tile-cache
cd build-sanitize
exec ctest --output-on-failure -j"$(nproc)" "$@"
