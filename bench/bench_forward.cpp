// What accuracy costs in time for the forward model and Fisher information:
//   1. throughput, Vulkan vs the double-precision CPU reference, point rays and
//      footprint cells;
//   2. the CRLB's error against time, point splat vs footprint splat, at the
//      native 6.9 um pixels and binned 27.6 and 110 um: for thin lenses
//      against the exact box-pixel oracle (engine/ref/thin_lens_oracle.h), for
//      real lenses, with and without the diffraction effect, against the
//      footprint at 4x the largest cell count; each row also against 4x its
//      own rays (the acceptance's measure of the defaults);
//   3. the cost of each optional effect per ray;
//   4. where a render of the refinement's model spends its time: the
//      footprint's passes, one by one, and the share of the large pass (the
//      rim's pieces still large after the split, rasterised in tiles).
// Prints tables; every figure names the machine and the device. Times are
// medians over repeats (these machines are noisy).
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <random>
#include <span>
#include <string>
#include <vector>

#include "bench_util.h"
#include "engine/forward.h"
#include "engine/ref/forward_ref.h"
#include "engine/ref/thin_lens_oracle.h"
#include "host/reconstruct/refine.h"  // refine_trace_settings
#include "host/scene/scene.h"

using namespace prism;

namespace {

// The lens models of the convergence table: thin (against the oracle), real,
// and real with the diffraction effect (both against their own footprint at
// 4x the largest cell count).
enum class Variant { thin, real, real_diffraction };

const char* to_string(Variant v) {
  return v == Variant::thin ? "thin" : v == Variant::real ? "real" : "real+diffraction";
}

struct Options {
  std::string device;
  unsigned max_rays = 65536;  // largest ray (or cell) count per lenslet in the convergence table
  // At the native pixels (binning 1): the default, so the reference is 4x it
  // (the acceptance's measure); every band of rows there re-traces the cells.
  unsigned max_rays_native = defaults::rays_per_lenslet;
  int repeats = 3;
  bool skip_convergence = false;
  std::vector<std::string> sections{"throughput", "effects", "convergence", "passes", "masked"};
  std::vector<unsigned> binnings{16, 4, 1};
  std::vector<unsigned> passes_binnings{16};
  std::vector<unsigned> masked_binnings{4};  // the masked section's pixels (1: a whole render there takes a minute)  // the passes table's pixels (1: the sensor's own, 3-4x longer per render)
  std::vector<Variant> variants{Variant::thin, Variant::real, Variant::real_diffraction};
};

std::string fixed(double x, int digits) {
  char b[32];
  std::snprintf(b, sizeof b, "%.*f", digits, x);
  return b;
}
// The items of a comma-separated option value ("16,4,1").
std::vector<std::string> comma_list(const std::string& list) {
  std::vector<std::string> out;
  for (size_t at = 0; at <= list.size();) {
    const size_t end = std::min(list.find(',', at), list.size());
    out.push_back(list.substr(at, end - at));
    at = end + 1;
  }
  return out;
}

// A relative error, marked '<' when within 1%.
std::string within(double err) { return fixed(err, 4) + (err <= 0.01 ? "<" : ""); }

double crlb3d(const FisherResult& f) { return crlb_from_fisher(f.poisson, f.photons).r3_mm; }

void throughput(vk::Context& ctx, const Options& o) {
  Scene scene = builtin_scene("prototype");
  TraceSettings t = TraceSettings::defaults_for(Splat::point);
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
  TraceSettings tf = TraceSettings::defaults_for(Splat::footprint);
  tf.rays_per_lenslet = t.rays_per_lenslet;
  tf.binning = t.binning;
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
  // The acceptance positions of issue 11: on the axis at depths 2.5, 10, 25,
  // 40, 47.5 mm, and one point off the axis.
  std::vector<glm::dvec3> sources{{0, 0, 2.5}, {0, 0, 10.0}, {0, 0, 25.0}, {0, 0, 40.0}, {0, 0, 47.5}, {6.0, -4.0, 15.0}};
  std::printf("\n## 2. CRLB (3D, Poisson) error against time: point splat (split estimator) vs footprint splat "
              "(naive)\n");
  std::printf("prototype, 6280 photons; sources on the axis at depths 2.5, 10, 25, 40, 47.5 mm and at (6, -4, 15) mm.\n");
  std::printf("Thin lenses: error against the exact box-pixel oracle. Real lenses (with and without the diffraction\n"
              "effect): against the footprint at 4x the largest cell count (its self-convergence).\n"
              "err = max over the sources of |crlb / reference - 1|; 'vs 4x' = the same against the next row of\n"
              "the same splat (4x the rays), the acceptance's measure of the default (%u cells, marked *).\n",
              defaults::rays_per_lenslet);
  std::printf("%-16s %-5s %-10s %9s %10s %9s %9s %9s %9s %9s %9s %9s %9s\n", "lens", "pixel", "splat", "rays",
              "s (6 src)", "z=2.5", "z=10", "z=25", "z=40", "z=47.5", "off-axis", "max err", "vs 4x");
  for (Variant variant : o.variants)
    for (unsigned binning : o.binnings) {
      Scene scene = builtin_scene("prototype");
      scene.optics.lens_model = variant == Variant::thin ? LensModel::thin : LensModel::real;
      scene.optics.effects.diffraction = variant == Variant::real_diffraction;
      const OpticalSystem& sys = scene.optics;
      TraceSettings base;
      base.binning = binning;
      unsigned max_rays = binning == 1 ? o.max_rays_native : o.max_rays;
      std::vector<double> exact;
      const char* pixel = binning == 1 ? "6.9" : binning == 4 ? "27.6" : binning == 16 ? "110" : "?";
      if (variant == Variant::thin) {
        for (const auto& s : sources) exact.push_back(crlb3d(ref::thin_lens_fisher(sys, base, s)));
      } else {
        TraceSettings t = TraceSettings::defaults_for(Splat::footprint);
        t.binning = binning;
        t.rays_per_lenslet = 4 * max_rays;
        ForwardVulkan fw(ctx, sys, t);
        for (const auto& f : fw.fisher(sources)) exact.push_back(crlb3d(f));
      }
      auto row = [&](const char* splat, const std::string& rays, const std::string& secs, const std::vector<double>& v,
                     const std::string& err, const std::string& vs4) {
        std::printf("%-16s %-5s %-10s %9s %10s", to_string(variant), pixel, splat, rays.c_str(), secs.c_str());
        for (double x : v) std::printf(" %9.4g", x);
        std::printf(" %9s %9s\n", err.c_str(), vs4.c_str());
        std::fflush(stdout);
      };
      row(variant == Variant::thin ? "oracle" : "footprint", variant == Variant::thin ? "exact" : "4x max", "-", exact,
          "(ref)", "");
      for (Splat splat : {Splat::point, Splat::footprint}) {
        if (variant == Variant::real_diffraction && splat == Splat::point) continue;  // the footprint's case
        std::vector<Converged> rows;
        for (unsigned rays = (splat == Splat::point ? 4096u : 1024u); rays <= max_rays; rays *= 4) {
          TraceSettings t = base;
          t.splat = splat;
          t.estimator = TraceSettings::default_estimator(splat);
          t.rays_per_lenslet = rays;
          rows.push_back(measure(ctx, sys, t, sources, exact, o.repeats));
        }
        // The footprint's last row: its 4x is the reference itself for real lenses.
        for (size_t r = 0; r < rows.size(); ++r) {
          const Converged& c = rows[r];
          const std::vector<double>& next = r + 1 < rows.size() ? rows[r + 1].crlb : exact;
          double vs4 = 0;  // infinite (not estimated) on either side: no agreement
          for (size_t i = 0; i < sources.size(); ++i)
            vs4 = std::isinf(c.crlb[i]) || std::isinf(next[i]) ? INFINITY : std::max(vs4, std::abs(c.crlb[i] / next[i] - 1));
          bool four_x = r + 1 < rows.size() || (variant != Variant::thin && splat == Splat::footprint);
          std::string rays = std::to_string(c.rays) + (splat == Splat::footprint && c.rays == defaults::rays_per_lenslet ? "*" : "");
          row(to_string(splat), rays, fixed(c.seconds, 3), c.crlb, within(c.worst), four_x ? within(vs4) : "");
        }
      }
    }
  std::printf("('<': within 1%%)\n");
}

void effects(vk::Context& ctx, const Options& o) {
  std::printf("\n## 3. Cost of each effect per ray, point splat (Vulkan, prototype, 16384 rays/lenslet, 16 sources)\n");
  std::printf("%-36s %12s %10s %12s\n", "scene effects", "ns/ray", "vs plain", "photons");
  std::vector<glm::dvec3> many;
  for (int i = 0; i < 16; ++i) many.push_back({-10.0 + 1.3 * i, 0.5 * i - 4.0, 2.5 + 3.0 * i});
  TraceSettings t = TraceSettings::defaults_for(Splat::point);
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

// Section 4: the refinement renders the scene's model (footprint, 1024
// cells per lenslet, with derivatives) dozens of times per event. Each
// dispatch's device time, by pass: the first over the cells, the split
// levels (the real lenses' rim cells and their large pieces, retraced and
// rasterised), the cut cells.
void passes_at(vk::Context& ctx, const Options& o, unsigned binning) {
  Scene scene = builtin_scene("prototype");
  const TraceSettings t = refine_trace_settings(binning);
  ForwardVulkan fw(ctx, scene.optics, t);
  std::printf("\n## 4. Where a refinement render's time goes: prototype (real lenses), %u cells/lenslet, %.1f um, "
              "with derivatives; device ms per pass\n",
              t.rays(), 1e3 * fw.grid().pixel_mm);
  for (glm::dvec3 theta : {glm::dvec3(4.0, -6.0, 2.0), glm::dvec3(7.2, 12.3, 35.5), glm::dvec3(3.0, 7.0, 45.0)}) {
    fw.psf(theta);  // warm up: compilation, the lists grown to fit
    std::vector<std::string> names;
    std::vector<std::vector<double>> ms;
    for (int r = 0; r < o.repeats + 2; ++r) {
      fw.psf(theta);
      std::vector<std::string> seen;
      std::vector<double> row;
      for (const auto& k : fw.last_kernel_times()) {
        // A kernel's n-th dispatch in the call: the split's levels.
        int n = int(std::count(seen.begin(), seen.end(), k.kernel));
        seen.push_back(k.kernel);
        row.push_back(k.ms);
        if (r == 0) names.push_back(k.kernel + (n > 0 || k.kernel.find("split") != std::string::npos ? " #" + std::to_string(n) : ""));
      }
      if (row.size() != names.size()) continue;  // a list overflowed and the call started again
      ms.push_back(row);
    }
    std::printf("source (%.1f, %.1f, %.1f) mm:\n", theta.x, theta.y, theta.z);
    double total = 0;
    std::vector<double> med(names.size());
    for (size_t i = 0; i < names.size(); ++i) {
      std::vector<double> v;
      for (const auto& row : ms) v.push_back(row[i]);
      total += med[i] = bench::median(v);
    }
    double large = 0;
    for (size_t i = 0; i < names.size(); ++i) {
      std::printf("  %-36s %8.1f ms %6.1f%%\n", names[i].c_str(), med[i], 100 * med[i] / total);
      if (names[i].rfind("psf_footprint_large", 0) == 0) large += med[i];
    }
    std::printf("  %-36s %8.1f ms\n", "all passes", total);
    std::printf("  the large pass's share: %.1f%% (the render costs %.2fx what it would without it)\n", 100 * large / total,
                total / (total - large));
  }
}

void passes(vk::Context& ctx, const Options& o) {
  for (unsigned binning : o.passes_binnings) passes_at(ctx, o, binning);
}

// Section 5: a render restricted to the tiles around an event's clicks
// (TileMask) against the whole image, as a refinement at the sensor's own
// pixels would render: the prototype with the Airy square, the
// refinement's cells, 100 clicks drawn from the 110 um image's light and
// placed at random within their 110 um pixel, every tile within 32 pixels
// of one marked. Wall time of psf() (kernels, the image's fill, read-back
// and conversion) and the kernels' share.
void masked(vk::Context& ctx, const Options& o) {
  Scene scene = builtin_scene("prototype");
  scene.optics.effects.diffraction = true;
  scene.optics.effects.wavelength_nm = defaults::wavelength_nm;
  ForwardVulkan coarse(ctx, scene.optics, refine_trace_settings(16));
  for (unsigned binning : o.masked_binnings) {
    const TraceSettings t = refine_trace_settings(binning);
    ForwardVulkan fw(ctx, scene.optics, t);
    std::printf("\n## 5. A render masked to the tiles around 100 clicks against the whole image: prototype with "
                "diffraction, %u cells/lenslet, %.1f um, with derivatives (median of %d)\n",
                t.rays(), 1e3 * fw.grid().pixel_mm, o.repeats);
    std::printf("| source (mm) | tiles marked | whole: wall, kernels (s) | masked: wall, kernels (s) | whole / masked (wall) |\n"
                "|---|---|---|---|---|\n");
    for (glm::dvec3 theta : {glm::dvec3(-4.0, 2.0, 5.0), glm::dvec3(1.0, -2.0, 10.0), glm::dvec3(3.0, 4.0, 20.0)}) {
      const PixelImage c = coarse.psf(theta);
      std::vector<double> cdf;
      double sum = 0;
      for (size_t i = 0; i < c.data.size() / 4; ++i) cdf.push_back(sum += c.data[4 * i]);
      std::mt19937_64 rng(7);
      const int per = int(16 / binning);
      TileMask mask = TileMask::of(fw.grid());
      for (int k = 0; k < 100; ++k) {
        const size_t i = size_t(std::lower_bound(cdf.begin(), cdf.end(), std::uniform_real_distribution<double>(0, sum)(rng)) -
                                cdf.begin());
        mask.mark_around(int(i % size_t(c.width)) * per + int(rng() % unsigned(per)),
                         int(i / size_t(c.width)) * per + int(rng() % unsigned(per)), 32);
      }
      auto time = [&](auto&& render) {
        render();  // warm up: compilation, the lists grown to fit
        std::vector<double> wall, kernels;
        for (int r = 0; r < o.repeats; ++r) {
          const auto start = std::chrono::steady_clock::now();
          render();
          wall.push_back(std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count());
          kernels.push_back(fw.last_kernel_ms() / 1e3);
        }
        return std::make_pair(bench::median(wall), bench::median(kernels));
      };
      const auto whole = time([&] { fw.psf(theta); });
      const auto part = time([&] { fw.psf(theta, mask); });
      std::printf("| (%.0f, %.0f, %.0f) | %zu of %d | %.2f, %.2f | %.2f, %.2f | %.1fx |\n", theta.x, theta.y, theta.z,
                  mask.count(), mask.tiles_w * mask.tiles_h, whole.first, whole.second, part.first, part.second,
                  whole.first / part.first);
    }
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
    else if (a == "--max-rays-native") o.max_rays_native = unsigned(std::stoul(next()));
    else if (a == "--binnings") {
      o.binnings.clear();
      for (const std::string& v : comma_list(next())) o.binnings.push_back(unsigned(std::stoul(v)));
    }
    else if (a == "--passes-binnings") {
      o.passes_binnings.clear();
      for (const std::string& v : comma_list(next())) o.passes_binnings.push_back(unsigned(std::stoul(v)));
    }
    else if (a == "--masked-binnings") {
      o.masked_binnings.clear();
      for (const std::string& v : comma_list(next())) o.masked_binnings.push_back(unsigned(std::stoul(v)));
    }
    else if (a == "--variants") {
      o.variants.clear();
      for (const std::string& v : comma_list(next())) {
        if (v == "thin") o.variants.push_back(Variant::thin);
        else if (v == "real") o.variants.push_back(Variant::real);
        else if (v == "real+diffraction") o.variants.push_back(Variant::real_diffraction);
        else throw std::runtime_error("--variants: unknown '" + v + "' (thin, real, real+diffraction)");
      }
    }
    else if (a == "--repeats") o.repeats = std::stoi(next());
    else if (a == "--skip-convergence") o.skip_convergence = true;
    else if (a == "--sections") {
      o.sections.clear();
      for (const std::string& v : comma_list(next())) {
        if (v != "throughput" && v != "effects" && v != "convergence" && v != "passes" && v != "masked")
          throw std::runtime_error("--sections: unknown '" + v + "' (throughput, effects, convergence, passes, masked)");
        o.sections.push_back(v);
      }
    }
    else {
      std::printf("usage: bench_forward [--device D] [--max-rays N] [--max-rays-native N] [--binnings 16,4,1] "
                  "[--passes-binnings 16] [--masked-binnings 4] [--variants thin,real,real+diffraction] [--repeats R] "
                  "[--skip-convergence] [--sections throughput,effects,convergence,passes,masked]\n");
      return a == "--help" ? 0 : 2;
    }
  }
  vk::Context ctx(vk::ContextOptions{o.device});
  std::printf("# bench_forward\n# machine: %s\n# device: %s\n# times: median of %d repeats\n",
              bench::machine_line().c_str(), ctx.describe().c_str(), o.repeats);
  auto wanted = [&](const char* name) { return std::find(o.sections.begin(), o.sections.end(), name) != o.sections.end(); };
  if (wanted("throughput")) throughput(ctx, o);
  if (wanted("effects")) effects(ctx, o);
  if (wanted("convergence") && !o.skip_convergence) convergence(ctx, o);
  if (wanted("passes")) passes(ctx, o);
  if (wanted("masked")) masked(ctx, o);
  return 0;
}
