#!/usr/bin/env bash
# The whole test suite under AddressSanitizer + UndefinedBehaviorSanitizer:
# the clang-16 build in build-sanitize/ that the fuzz harnesses share
# (tools/sanitizer-build.sh), then ctest with a test per core. Any sanitizer
# report, a leak at exit included, fails its test (tests/sanitizer_defaults.cpp
# holds the runtime's options). The cases run there at the sizes that reach
# their code, not the sizes of their figures (tests/support.h,
# under_sanitizer). .ci/run runs it after the normal suite.
#   tests/sanitize.sh [CTEST ARGS ...]     e.g. -R hdr to run the files named so
set -euo pipefail
cd "$(dirname "$0")/.."
tools/sanitizer-build.sh
cd build-sanitize
exec ctest --output-on-failure -j"$(nproc)" "$@"
