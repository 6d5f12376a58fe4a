// What accuracy costs in time for the forward model and Fisher information:
//   1. throughput, Vulkan vs the double-precision CPU reference, point rays and
//      footprint cells;
//   2. the CRLB's error against time, point splat vs footprint splat, at the
//      native 6.9 um pixels and binned 27.6 and 110 um: for thin lenses
//      against the exact box-pixel oracle (engine/ref/thin_lens_oracle.h), for
//      real lenses against the footprint at 4x the cells;
//   3. the cost of each optional effect per ray.
// Prints tables; every figure names the machine and the device. Times are
// medians over repeats (these machines are noisy).
#include <cmath>
#include <cstdio>
#include <cstring>
#include <span>
#include <string>
#include <vector>

#include "bench_util.h"
#include "engine/forward.h"
#include "engine/ref/forward_ref.h"
#include "engine/ref/thin_lens_oracle.h"
#include "host/scene/scene.h"

using namespace prism;

namespace {

struct Options {
  std::string device;
  unsigned max_rays = 262144;  // largest ray (or cell) count per lenslet in the convergence table
  int repeats = 3;
  bool skip_convergence = false;
  std::vector<unsigned> binnings{16, 4, 1};
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
  TraceSettings tf = t;
  tf.splat = Splat::footprint;
  tf.estimator = FisherEstimator::naive;
  ForwardVulkan ff(ctx, scene.optics, tf);
  ff.fisher(one);
  double fp_many = bench::median_seconds(o.repeats, [&] { ff.fisher(many); }) / double(many.size());
  double fp_cpu = bench::median_seconds(o.repeats, [&] { ref::fisher(scene.optics, tf, one[0]); });
  std::printf("\n## 1. Throughput: trace + splat + Fisher, prototype (real lenses), %u rays or cells/lenslet, 8x8 "
              "binning (55 um)\n",
              t.rays());
  std::printf("%-52s %12s %18s\n", "path", "s/source", "M rays (cells)/s");
  std::printf("%-52s %12.4f %18.2f\n", "point, Vulkan, 1 source per call (wall)", vk_one, rays / vk_one * 1e-6);
  std::printf("%-52s %12.4f %18.2f\n", "point, Vulkan, 1 source per call (kernel timestamps)",
              bench::median(kernel_ms) * 1e-3, rays / (bench::median(kernel_ms) * 1e-3) * 1e-6);
  std::printf("%-52s %12.4f %18.2f\n", "point, Vulkan, 16 sources per call (wall)", vk_many, rays / vk_many * 1e-6);
  std::printf("%-52s %12.4f %18.2f\n", "point, CPU reference (double, 1 thread)", cpu_one, rays / cpu_one * 1e-6);
  std::printf("%-52s %12.4f %18.2f\n", "footprint, Vulkan, 16 sources per call (wall)", fp_many, rays / fp_many * 1e-6);
  std::printf("%-52s %12.4f %18.2f\n", "footprint, CPU reference (double, 1 thread)", fp_cpu, rays / fp_cpu * 1e-6);
  std::printf("ratios: point Vulkan / CPU reference %.1fx faster; footprint Vulkan / CPU reference %.1fx faster; "
              "a footprint cell costs %.1fx a point ray\n",
              cpu_one / vk_many, fp_cpu / fp_many, fp_many / vk_many);
}

// One row of the convergence table: a splat at some rays, its time and its
// worst relative error over the sources against `exact`.
struct Converged {
  unsigned rays = 0;
  double seconds = 0, worst = 0;
  std::vector<double> crlb;
};

Converged measure(vk::Context& ctx, const OpticalSystem& sys, TraceSettings t, const std::vector<glm::dvec3>& sources,
                  const std::vector<double>& exact, int repeats) {
  ForwardVulkan fw(ctx, sys, t);
  std::vector<FisherResult> res = fw.fisher(std::span<const glm::dvec3>(sources.data(), 1));  // warm up
  Converged c;
  c.rays = t.rays();
  c.seconds = bench::median_seconds(repeats, [&] { res = fw.fisher(sources); });
  for (size_t i = 0; i < sources.size(); ++i) {
    c.crlb.push_back(crlb3d(res[i]));
    c.worst = std::max(c.worst, std::abs(c.crlb.back() / exact[i] - 1));
  }
  return c;
}

void convergence(vk::Context& ctx, const Options& o) {
  std::vector<glm::dvec3> sources{{0, 0, 2.5}, {0, 0, 25.0}, {0, 0, 47.5}, {6.0, -4.0, 15.0}};
  std::printf("\n## 2. CRLB (3D, Poisson) error against time: point splat (split estimator) vs footprint splat "
              "(naive)\n");
  std::printf("prototype, 6280 photons; sources on the axis at depths 2.5, 25, 47.5 mm and at (6, -4, 15) mm.\n");
  std::printf("Thin lenses: error against the exact box-pixel oracle. Real lenses: against the footprint at 4x the\n"
              "largest cell count (its self-convergence). err = max over the sources of |crlb / exact - 1|.\n");
  std::printf("%-5s %-5s %-10s %9s %10s %10s %10s %10s %10s %9s\n", "lens", "pixel", "splat", "rays", "s (4 src)",
              "z=2.5", "z=25", "z=47.5", "off-axis", "max err");
  for (LensModel model : {LensModel::thin, LensModel::real})
    for (unsigned binning : o.binnings) {
      Scene scene = builtin_scene("prototype");
      scene.optics.lens_model = model;
      const OpticalSystem& sys = scene.optics;
      TraceSettings base;
      base.binning = binning;
      std::vector<double> exact;
      const char* pixel = binning == 1 ? "6.9" : binning == 4 ? "27.6" : binning == 16 ? "110" : "?";
      if (model == LensModel::thin) {
        for (const auto& s : sources) exact.push_back(crlb3d(ref::thin_lens_fisher(sys, base, s)));
      } else {
        TraceSettings t = base;
        t.splat = Splat::footprint;
        t.estimator = FisherEstimator::naive;
        t.rays_per_lenslet = 4 * o.max_rays;
        ForwardVulkan fw(ctx, sys, t);
        for (const auto& f : fw.fisher(sources)) exact.push_back(crlb3d(f));
      }
      std::printf("%-5s %-5s %-10s %9s %10s %10.4g %10.4g %10.4g %10.4g %9s\n", to_string(model), pixel,
                  model == LensModel::thin ? "oracle" : "footprint", model == LensModel::thin ? "exact" : "4x max", "-",
                  exact[0], exact[1], exact[2], exact[3], "(ref)");
      for (Splat splat : {Splat::point, Splat::footprint})
        for (unsigned rays = (splat == Splat::point ? 4096u : 256u); rays <= o.max_rays; rays *= 4) {
          TraceSettings t = base;
          t.splat = splat;
          t.estimator = TraceSettings::default_estimator(splat);
          t.rays_per_lenslet = rays;
          Converged c = measure(ctx, sys, t, sources, exact, o.repeats);
          std::printf("%-5s %-5s %-10s %9u %10.3f %10.4g %10.4g %10.4g %10.4g %9.4f%s\n", to_string(model), pixel,
                      to_string(splat), c.rays, c.seconds, c.crlb[0], c.crlb[1], c.crlb[2], c.crlb[3], c.worst,
                      c.worst <= 0.01 ? "  <= 1%" : "");
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
    else if (a == "--binnings") {
      o.binnings.clear();
      std::string list = next();
      for (size_t at = 0; at < list.size();) {
        size_t end = list.find(',', at);
        o.binnings.push_back(unsigned(std::stoul(list.substr(at, end - at))));
        at = end == std::string::npos ? list.size() : end + 1;
      }
    }
    else if (a == "--repeats") o.repeats = std::stoi(next());
    else if (a == "--skip-convergence") o.skip_convergence = true;
    else {
      std::printf("usage: bench_forward [--device D] [--max-rays N] [--binnings 16,4,1] [--repeats R] "
                  "[--skip-convergence]\n");
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
