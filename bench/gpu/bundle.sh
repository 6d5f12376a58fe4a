#!/usr/bin/env bash
# Pack what bench/gpu/run.sh needs into one file, for a machine that has a
# Vulkan GPU driver but none of PRISM's build dependencies (the GPU figures in
# docs/performance.md were made this way): the built binaries (stripped),
# the shared libraries they load that are not the C and C++ runtimes, the
# Vulkan validation layer (the tests run with it on), PLplot's cairo driver
# and data (the plots), and the one reference file a test reads from ../shared.
#
#   bench/gpu/bundle.sh [OUT]      default OUT: .gpu/bundle.tar.gz (git ignores .gpu/)
#
# Build first (./setup.sh test, or cmake --build build). The binaries are
# unpacked at their build paths (build/host/prism, ...), so the tests find
# the command-line binary where the build put it.
set -euo pipefail
root="$(cd "$(dirname "$0")/../.." && pwd)"
out="${1:-$root/.gpu/bundle.tar.gz}"
binaries=(build/host/prism build/bench/bench_forward build/bench/bench_reconstruct build/bench/bench_dictionary
          build/tests/prism_tests)
stage="$(mktemp -d)"
trap 'rm -rf "$stage"' EXIT
cd "$root"
for b in "${binaries[@]}"; do
  [[ -x "$b" ]] || { echo "bundle.sh: $b is missing; build first (cmake --build build)" >&2; exit 1; }
  mkdir -p "$stage/$(dirname "$b")"
  strip -o "$stage/$b" "$b"
done
# The libraries: everything ldd resolves, less glibc, the C++ runtime (the
# GPU machine's own, newer, serve) and the Vulkan loader (run.sh's caller
# brings the GPU machine's loader and ICD).
mkdir -p "$stage/.gpu/lib" "$stage/.gpu/layer" "$stage/.gpu/shared/reference" "$stage/.gpu/plplot/drivers"
plplot_drivers="$(echo /usr/lib/x86_64-linux-gnu/plplot*/drivers)"
cp "$plplot_drivers"/cairo.* "$stage/.gpu/plplot/drivers/"
cp -r /usr/share/plplot*/. "$stage/.gpu/plplot/"
ldd "${binaries[@]}" "$plplot_drivers/cairo.so" | awk '/=> \//{print $3}' | sort -u |
  grep -Ev '/(libc|libm|libpthread|libdl|librt|ld-linux-x86-64|libstdc\+\+|libgcc_s|libvulkan)\.so' |
  while read -r lib; do cp -L "$lib" "$stage/.gpu/lib/"; done
layer=/usr/share/vulkan/explicit_layer.d/VkLayer_khronos_validation.json
cp -L "$(dirname "$(ldconfig -p | awk '/libVkLayer_khronos_validation.so /{print $NF; exit}')")/libVkLayer_khronos_validation.so" \
  "$stage/.gpu/layer/"
sed 's|"library_path": "[^"]*"|"library_path": "./libVkLayer_khronos_validation.so"|' "$layer" \
  > "$stage/.gpu/layer/VkLayer_khronos_validation.json"
cp ../shared/reference/lens-landing-optiland.csv "$stage/.gpu/shared/reference/"
mkdir -p "$(dirname "$out")"
tar -czf "$out" -C "$stage" build .gpu
echo "bundle.sh: wrote $out ($(du -h "$out" | cut -f1)) at $(git rev-parse --short HEAD)$(git diff --quiet || echo ' + uncommitted changes')"
