// What accuracy costs in time for the forward model and Fisher information:
//   1. rays per second, Vulkan backend vs the double-precision CPU reference;
//   2. CRLB against rays per lenslet, analysis binning and Fisher estimator,
//      relative to a very large ray count, with the time each took;
//   3. the cost of each optional effect per ray.
// Prints tables; every figure names the machine and the device. Times are
// medians over repeats (these machines are noisy).
#include <cmath>
#include <cstdio>
#include <cstring>
#include <string>

#include "bench_util.h"
#include "engine/forward.h"
#include "engine/ref/forward_ref.h"
#include "host/scene/scene.h"

using namespace prism;

namespace {

struct Options {
  std::string device;
  unsigned max_rays = 262144;        // largest ray count in the convergence table
  unsigned reference_rays = 1048576; // "very large": the reference CRLB
  int repeats = 3;
  bool skip_convergence = false;
};

double crlb3d(const FisherResult& f) { return crlb_from_fisher(f.poisson, f.photons).r3_mm; }

void throughput(vk::Context& ctx, const Options& o) {
  Scene scene = builtin_scene("prototype");
  TraceSettings t;
  t.rays_per_lenslet = 16384;
  t.binning = 8;
  std::vector<glm::dvec3> one{{1.0, -2.0, 25.0}};
  std::vector<glm::dvec3> many;
  for (int i = 0; i < 16; ++i) many.push_back({-10.0 + 1.3 * i, 0.5 * i - 4.0, 2.5 + 3.0 * i});
  ForwardVulkan fw(ctx, scene.optics, t);
  double rays = double(fw.rays_per_source());
  fw.fisher(one);  // warm up: pipeline compilation, first allocation
  std::vector<double> kernel_ms;
  double vk_one = bench::median_seconds(o.repeats + 2, [&] {
    fw.fisher(one);
    kernel_ms.push_back(fw.last_kernel_ms());
  });
  double vk_many = bench::median_seconds(o.repeats, [&] { fw.fisher(many); }) / double(many.size());
  double cpu_one = bench::median_seconds(o.repeats, [&] { ref::fisher(scene.optics, t, one[0]); });
  std::printf("\n## 1. Throughput: trace + splat + Fisher, prototype (real lenses), %u rays/lenslet, 8x8 binning\n",
              t.rays());
  std::printf("%-44s %12s %14s\n", "path", "s/source", "Mrays/s");
  std::printf("%-44s %12.4f %14.2f\n", "Vulkan, 1 source per call (wall)", vk_one, rays / vk_one * 1e-6);
  std::printf("%-44s %12.4f %14.2f\n", "Vulkan, 1 source per call (kernel timestamps)", bench::median(kernel_ms) * 1e-3,
              rays / (bench::median(kernel_ms) * 1e-3) * 1e-6);
  std::printf("%-44s %12.4f %14.2f\n", "Vulkan, 16 sources per call (wall)", vk_many, rays / vk_many * 1e-6);
  std::printf("%-44s %12.4f %14.2f\n", "CPU reference (double, 1 thread)", cpu_one, rays / cpu_one * 1e-6);
  std::printf("ratio Vulkan (16 per call) / CPU reference: %.1fx faster\n", cpu_one / vk_many);
}

void convergence(vk::Context& ctx, const Options& o) {
  Scene scene = builtin_scene("prototype");
  std::vector<glm::dvec3> depths{{0, 0, 2.5}, {0, 0, 25.0}, {0, 0, 47.5}};
  std::printf("\n## 2. CRLB (3D, Poisson) against rays per lenslet, binning and estimator\n");
  std::printf("prototype, real lenses, 6280 photons, sources on the axis at depths 2.5, 25, 47.5 mm;\n");
  std::printf("reference: split estimator at %u rays/lenslet, same binning. err = |crlb / reference - 1|.\n",
              o.reference_rays);
  std::printf("%-4s %-6s %9s %10s %10s %10s %10s %9s %8s\n", "bin", "est.", "rays", "s (3 src)", "z=2.5", "z=25",
              "z=47.5", "max err", "");
  for (unsigned binning : {4u, 8u, 16u, 32u}) {
    TraceSettings ref_t;
    ref_t.rays_per_lenslet = o.reference_rays;
    ref_t.binning = binning;
    ForwardVulkan ref_fw(ctx, scene.optics, ref_t);
    auto ref = ref_fw.fisher(depths);
    std::printf("%-4u %-6s %9u %10s %10.4g %10.4g %10.4g %9s %8s\n", binning, "split", ref_t.rays(), "-",
                crlb3d(ref[0]), crlb3d(ref[1]), crlb3d(ref[2]), "(ref)", "");
    for (auto est : {FisherEstimator::naive, FisherEstimator::split})
      for (unsigned rays = 1024; rays <= o.max_rays; rays *= 4) {
        TraceSettings t = ref_t;
        t.rays_per_lenslet = rays;
        t.estimator = est;
        ForwardVulkan fw(ctx, scene.optics, t);
        std::vector<FisherResult> res;
        double s = bench::median_seconds(o.repeats, [&] { res = fw.fisher(depths); });
        double worst = 0;
        for (size_t i = 0; i < depths.size(); ++i) worst = std::max(worst, std::abs(crlb3d(res[i]) / crlb3d(ref[i]) - 1));
        std::printf("%-4u %-6s %9u %10.3f %10.4g %10.4g %10.4g %9.3f %8s\n", binning, to_string(est), t.rays(), s,
                    crlb3d(res[0]), crlb3d(res[1]), crlb3d(res[2]), worst, worst <= 0.02 ? "<= 2%" : "");
        std::fflush(stdout);
      }
  }
}

void effects(vk::Context& ctx, const Options& o) {
  std::printf("\n## 3. Cost of each effect per ray (Vulkan, prototype, 16384 rays/lenslet, 16 sources)\n");
  std::printf("%-36s %12s %10s %12s\n", "scene effects", "ns/ray", "vs plain", "photons");
  std::vector<glm::dvec3> many;
  for (int i = 0; i < 16; ++i) many.push_back({-10.0 + 1.3 * i, 0.5 * i - 4.0, 2.5 + 3.0 * i});
  TraceSettings t;
  t.rays_per_lenslet = 16384;
  t.binning = 8;
  double plain_ns = 0;
  for (int variant = 0; variant < 5; ++variant) {
    Scene scene = builtin_scene("prototype");
    Effects& e = scene.optics.effects;
    const char* name = "none (real lenses)";
    if (variant == 1) { scene.optics.lens_model = LensModel::thin; name = "none (thin lenses)"; }
    if (variant == 2) { e.holder_vignetting = true; name = "holder_vignetting"; }
    if (variant == 3) { e.scintillator_refraction = true; name = "scintillator_refraction"; }
    if (variant == 4) { e.holder_vignetting = e.scintillator_refraction = true; name = "both"; }
    ForwardVulkan fw(ctx, scene.optics, t);
    std::vector<FisherResult> res = fw.fisher(many);
    double s = bench::median_seconds(o.repeats, [&] { res = fw.fisher(many); });
    double ns = s / (double(fw.rays_per_source()) * many.size()) * 1e9;
    if (variant == 0) plain_ns = ns;
    std::printf("%-36s %12.2f %9.2fx %12.1f\n", name, ns, ns / plain_ns, res[5].photons);
  }
}

}  // namespace

int main(int argc, char** argv) {
  Options o;
  for (int i = 1; i < argc; ++i) {
    std::string a = argv[i];
    auto next = [&] {
      if (i + 1 >= argc) throw std::runtime_error(a + " needs a value");
      return std::string(argv[++i]);
    };
    if (a == "--device") o.device = next();
    else if (a == "--max-rays") o.max_rays = unsigned(std::stoul(next()));
    else if (a == "--reference-rays") o.reference_rays = unsigned(std::stoul(next()));
    else if (a == "--repeats") o.repeats = std::stoi(next());
    else if (a == "--skip-convergence") o.skip_convergence = true;
    else {
      std::printf("usage: bench_forward [--device D] [--max-rays N] [--reference-rays N] [--repeats R] [--skip-convergence]\n");
      return a == "--help" ? 0 : 2;
    }
  }
  vk::Context ctx(vk::ContextOptions{o.device});
  std::printf("# bench_forward\n# machine: %s\n# device: %s\n# times: median of %d repeats\n",
              bench::machine_line().c_str(), ctx.describe().c_str(), o.repeats);
  throughput(ctx, o);
  effects(ctx, o);
  if (!o.skip_convergence) convergence(ctx, o);
  return 0;
}
