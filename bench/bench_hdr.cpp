// HDR merge throughput (paper Sec. III.A.2): Mpixel/s of one synthetic
// 7-exposure + 3-dark stack, the Vulkan kernel against the double-precision
// CPU reference, at a small and a sensor-sized frame (the latter in bands of
// rows, as full-resolution stacks exceed one storage buffer). Medians over
// repeats; the machine and the device are named.
#include <cstdio>
#include <string>

#include "bench_util.h"
#include "engine/hdr_merge.h"
#include "engine/ref/hdr_merge_ref.h"
#include "host/dictionary/hdr_stack.h"

using namespace prism;

int main(int argc, char** argv) {
  std::string device;
  int repeats = 3;
  std::vector<std::pair<int, int>> sizes{{1024, 768}, {3348, 2382}};  // the latter: the sensor binned 2 x 2
  for (int i = 1; i < argc; ++i) {
    std::string a = argv[i];
    if (a == "--device" && i + 1 < argc) device = argv[++i];
    else if (a == "--repeats" && i + 1 < argc) repeats = std::stoi(argv[++i]);
    else if (a == "--full") sizes.push_back({6696, 4764});
    else {
      std::printf("usage: bench_hdr [--device D] [--repeats R] [--full (adds 6696 x 4764: ~0.7 GB of frames)]\n");
      return a == "--help" ? 0 : 2;
    }
  }
  vk::Context ctx(vk::ContextOptions{device});
  std::printf("# bench_hdr\n# machine: %s\n# device: %s\n# times: median of %d repeats, wall clock including "
              "uploads and downloads; 7 exposures + 3 darks, 12-bit\n",
              bench::machine_line().c_str(), ctx.describe().c_str(), repeats);
  std::printf("%-12s %6s %12s %12s %14s %14s %8s\n", "frame", "bands", "vulkan s", "kernel s", "vulkan Mpx/s",
              "cpu ref Mpx/s", "ratio");
  HdrMergeVulkan merger(ctx);
  HdrOptions o;
  for (auto [w, h] : sizes) {
    HdrFrames f = simulate_hdr_frames(synthetic_psf(w, h), w, h, log_spaced_times(20e-6, 0.2, 7), {0.2, 0.2, 0.2},
                                      SyntheticSensor{}, 1);
    merger.merge(f, o);  // warm up: pipeline, first allocation
    std::vector<double> kernel_s;
    double vk_s = bench::median_seconds(repeats, [&] {
      merger.merge(f, o);
      kernel_s.push_back(merger.last_kernel_ms() * 1e-3);
    });
    double cpu_s = bench::median_seconds(repeats, [&] { ref::hdr_merge(f, o); });
    double mpx = double(f.pixels()) * 1e-6;
    std::printf("%5d x %-4d %6u %12.4f %12.4f %14.2f %14.2f %7.1fx\n", w, h, merger.last_bands(), vk_s,
                bench::median(kernel_s), mpx / vk_s, mpx / cpu_s, cpu_s / vk_s);
    std::fflush(stdout);
  }
  return 0;
}
