// What a design sweep costs and what its accuracy buys:
//   1. designs scored per second, Vulkan backend vs the double-precision CPU
//      reference, on the same designs and settings;
//   2. how the ranking of a fixed set of designs (the prototype and random
//      balanced focal assignments of its 42 positions) changes as rays (cells)
//      per lenslet and volume samples grow, for the point and the footprint
//      splat: Kendall tau against a high-accuracy ranking of the same splat,
//      with the time per design.
// Every figure names the machine and the device.
#include <cmath>
#include <cstdio>
#include <cstring>
#include <random>
#include <string>

#include "bench_util.h"
#include "host/sweep/sweep.h"

using namespace prism;

namespace {

struct Options {
  std::string device;
  size_t designs = 8;               // in the ranking table
  unsigned reference_rays = 16384;  // the high-accuracy ranking
  int cpu_designs = 2;              // scored by the CPU reference in table 1
};

DesignSpace focal_space(int lateral, int depth) {
  nlohmann::json j = {{"base", "prototype"},
                      {"focal_mm", {3, 4.5, 6, 7.5, 9, 12, 15}},
                      {"samples", {{"lateral", lateral}, {"depth", depth}}}};
  return DesignSpace::parse(j, "bench-focal-assignment");
}

// Kendall's tau-a between two score lists over the same designs (1: same order).
double kendall_tau(const std::vector<double>& a, const std::vector<double>& b) {
  double s = 0, n = 0;
  for (size_t i = 0; i < a.size(); ++i)
    for (size_t j = 0; j < i; ++j) {
      double x = (a[i] - a[j]) * (b[i] - b[j]);
      s += x > 0 ? 1 : x < 0 ? -1 : 0;
      n += 1;
    }
  return n > 0 ? s / n : 1;
}

std::vector<double> scores(const DesignSpace& space, const std::vector<Design>& designs, const TraceSettings& t,
                           Backend backend, vk::Context* ctx, double* seconds_per_design) {
  std::vector<double> v;
  auto start = std::chrono::steady_clock::now();
  for (const auto& d : designs) v.push_back(evaluate_design(space, d, t, backend, ctx).objectives.mean_crlb_3d_mm);
  *seconds_per_design = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count() / double(designs.size());
  return v;
}

}  // namespace

int main(int argc, char** argv) {
  Options o;
  for (int i = 1; i < argc; ++i) {
    if (!std::strcmp(argv[i], "--device") && i + 1 < argc) o.device = argv[++i];
    else if (!std::strcmp(argv[i], "--designs") && i + 1 < argc) o.designs = std::stoul(argv[++i]);
    else if (!std::strcmp(argv[i], "--reference-rays") && i + 1 < argc) o.reference_rays = unsigned(std::stoul(argv[++i]));
    else {
      std::fprintf(stderr, "usage: bench_sweep [--device D] [--designs N] [--reference-rays R]\n");
      return 2;
    }
  }
  vk::Context ctx(vk::ContextOptions{o.device});
  std::printf("# machine: %s\n# device: %s\n", bench::machine_line().c_str(), ctx.describe().c_str());

  // The designs: the prototype and random balanced rearrangements of it.
  DesignSpace space = focal_space(3, 6);
  std::mt19937_64 rng(2024);
  std::vector<Design> designs{*space.encode(space.base)};
  while (designs.size() < o.designs) designs.push_back(space.random(rng));

  // 1. Throughput at the sweep's default trace settings on a small sample grid.
  {
    DesignSpace small = focal_space(1, 3);
    // The point splat, as the figures in docs/performance.md were measured.
    TraceSettings t = TraceSettings::defaults_for(Splat::point);
    t.rays_per_lenslet = 4096;
    t.binning = 32;
    std::vector<Design> few(designs.begin(), designs.begin() + o.cpu_designs);
    double vk_s = 0, cpu_s = 0;
    scores(small, few, t, Backend::vulkan, &ctx, &vk_s);  // warm up
    auto dev = scores(small, few, t, Backend::vulkan, &ctx, &vk_s);
    // All designs in one multi-design dispatch, as the sweep scores a batch.
    double batched_s = bench::median_seconds(3, [&] { evaluate_designs(small, few, t, Backend::vulkan, &ctx); }) /
                       double(few.size());
    auto cpu = scores(small, few, t, Backend::cpu, nullptr, &cpu_s);
    std::printf("\n## 1. Designs per second: 42 lenslets (real), %u rays/lenslet, 32x32 binning, %s\n", t.rays(),
                small.samples.describe().c_str());
    std::printf("%-36s %12s %12s\n", "backend", "s/design", "designs/s");
    std::printf("%-36s %12.3f %12.3f\n", "Vulkan (one design per call)", vk_s, 1 / vk_s);
    std::printf("%-36s %12.3f %12.3f\n", "Vulkan (all designs in one dispatch)", batched_s, 1 / batched_s);
    std::printf("%-36s %12.3f %12.3f\n", "CPU reference (double, 1 thread)", cpu_s, 1 / cpu_s);
    double err = 0;
    for (size_t i = 0; i < dev.size(); ++i) err = std::max(err, std::abs(dev[i] / cpu[i] - 1));
    std::printf("ratio: Vulkan (batched) %.1fx faster than the CPU reference; largest difference in mean 3D CRLB: %.2f%%\n",
                cpu_s / batched_s, 100 * err);
  }

  // 2. Ranking against accuracy, per splat: each against its own
  // high-accuracy ranking (the two splats' scores differ by design: the
  // point splat's tent blurs the box pixels), and the two references against
  // each other.
  std::vector<std::vector<double>> references;
  for (Splat splat : {Splat::point, Splat::footprint}) {
    TraceSettings ref_t = TraceSettings::defaults_for(splat);
    ref_t.rays_per_lenslet = o.reference_rays;
    ref_t.binning = 32;
    double ref_s = 0;
    auto reference = scores(space, designs, ref_t, Backend::vulkan, &ctx, &ref_s);
    references.push_back(reference);
    double lo = *std::min_element(reference.begin(), reference.end());
    double hi = *std::max_element(reference.begin(), reference.end());
    std::printf("\n## 2%s. Ranking of %zu designs (prototype + random balanced focal assignments) vs accuracy, %s splat\n",
                splat == Splat::point ? "a" : "b", designs.size(), to_string(splat));
    std::printf("reference: %u %s/lenslet, 32x32 binning, %s: %.3f s/design; mean 3D CRLB spans %.4f..%.4f mm (%.1f%%)\n",
                ref_t.rays(), splat == Splat::point ? "rays" : "cells", space.samples.describe().c_str(), ref_s, lo, hi,
                100 * (hi / lo - 1));
    std::printf("%-10s %-10s %10s %12s %14s %14s\n", "rays", "samples", "s/design", "kendall_tau", "same_best",
                "max_rel_err");
    for (auto [lateral, depth] : {std::pair{1, 3}, std::pair{3, 3}, std::pair{3, 6}}) {
      DesignSpace sp = focal_space(lateral, depth);
      for (unsigned rays : {256u, 1024u, 4096u}) {
        TraceSettings t = ref_t;
        t.rays_per_lenslet = rays;
        double s = 0;
        auto v = scores(sp, designs, t, Backend::vulkan, &ctx, &s);
        bool same_best = std::min_element(v.begin(), v.end()) - v.begin() ==
                         std::min_element(reference.begin(), reference.end()) - reference.begin();
        double err = 0;
        for (size_t i = 0; i < v.size(); ++i) err = std::max(err, std::abs(v[i] / reference[i] - 1));
        std::printf("%-10u %-10zu %10.3f %12.3f %14s %13.1f%%\n", t.rays(), sp.samples.positions().size(), s,
                    kendall_tau(v, reference), same_best ? "yes" : "no", 100 * err);
        std::fflush(stdout);
      }
    }
  }
  std::printf("\nthe two references' rankings against each other (point vs footprint): Kendall tau %.3f\n",
              kendall_tau(references[0], references[1]));
  std::printf("(max_rel_err: largest |score / reference - 1|, which includes the change of sample grid)\n");
  return 0;
}
