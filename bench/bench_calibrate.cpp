// Calibration (prism calibrate, issue 18): what its model costs on the
// device (the splat kernels' calibrate variants) against the double CPU
// reference, measured in one run:
//   1. one PSF's derivative images of the whole prototype (every lenslet
//      alone, three scene parameters a pass: 42 x 4 renders for the default
//      216 parameters), 110 um pixels, 1024 footprint cells;
//   2. a whole fit: the synthetic as-built row of tests/host/calibrate (5
//      lenslets, 31 parameters, 12 HDR-merged PSFs rendered at 4096 cells
//      with another stratification), from the nominal scene, on each backend:
//      time, steps, chi2 and how far each parameter lands from the truth in
//      its own sigmas;
//   3. the whole prototype's step (216 parameters) on each backend.
// Medians over repeats; the machine and the device are named.
#include <cmath>
#include <cstdio>
#include <string>

#include "bench_util.h"
#include "engine/forward.h"
#include "engine/ref/forward_ref.h"
#include "host/calibrate/calibrate.h"
#include "host/calibrate/synthetic.h"
#include "host/scene/scene.h"

using namespace prism;

namespace {

double seconds_since(std::chrono::steady_clock::time_point t0) {
  return std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
}

// The tangent sets of one PSF's derivative images (calibrate.cpp's passes):
// per lenslet its own five parameters and the six global ones, three a pass.
std::vector<Tangents> passes_of(int lens) {
  const SceneParam all[] = {SceneParam::lens_x,          SceneParam::lens_y,          SceneParam::lens_focal,
                            SceneParam::lens_tilt_x,     SceneParam::lens_tilt_y,     SceneParam::lens_to_sensor,
                            SceneParam::working_distance, SceneParam::sensor_offset_x, SceneParam::sensor_offset_y,
                            SceneParam::sensor_tilt_x,   SceneParam::sensor_tilt_y};
  std::vector<Tangents> out;
  for (size_t first = 0; first < std::size(all); first += 3) {
    Tangents t = source_tangents;
    for (size_t k = 0; k < 3 && first + k < std::size(all); ++k) t[k] = {all[first + k], lens};
    out.push_back(t);
  }
  return out;
}

// The synthetic as-built row of tests/host/calibrate/test_calibrate.cpp.
OpticalSystem nominal_row() {
  OpticalSystem s = builtin_scene("prototype").optics;
  s.lens_model = LensModel::real;
  s.lenslets = std::vector<LensletGeometry>(s.lenslets.begin() + 16, s.lenslets.begin() + 21);
  return s;
}

}  // namespace

int main(int argc, char** argv) {
  std::string device;
  int repeats = 3;
  bool fit = true;
  for (int i = 1; i < argc; ++i) {
    std::string a = argv[i];
    if (a == "--device" && i + 1 < argc) device = argv[++i];
    else if (a == "--repeats" && i + 1 < argc) repeats = std::stoi(argv[++i]);
    else if (a == "--no-fit") fit = false;
    else {
      std::printf("usage: bench_calibrate [--device D] [--repeats R] [--no-fit (section 1 only)]\n");
      return a == "--help" ? 0 : 2;
    }
  }
  vk::Context ctx(vk::ContextOptions{device});
  std::printf("# bench_calibrate\n# machine: %s\n# device: %s\n", bench::machine_line().c_str(), ctx.describe().c_str());

  // 1. One PSF's derivative images of the prototype.
  const OpticalSystem proto = builtin_scene("prototype").optics;
  TraceSettings t = TraceSettings::defaults_for(Splat::footprint);
  t.rays_per_lenslet = defaults::calibration_rays_per_lenslet;
  t.binning = 16;
  const glm::dvec3 theta(3.0, -2.0, 20.0);
  const int L = int(proto.lenslets.size());
  size_t renders = 0;
  for (int l = 0; l < L; ++l) renders += passes_of(l).size();
  auto start = std::chrono::steady_clock::now();
  ForwardVulkan fw(ctx, proto, t, ForwardVulkan::default_image_budget_bytes, ForwardVulkan::Derivatives::scene);
  (void)fw.psf(theta, passes_of(0)[0], 0);
  (void)fw.psf_values(theta);
  const double first_use = seconds_since(start);
  double kernel_ms = 0;
  const double device_s = bench::median_seconds(repeats, [&] {
    kernel_ms = 0;
    for (int l = 0; l < L; ++l)
      for (const auto& p : passes_of(l)) {
        (void)fw.psf(theta, p, l);
        kernel_ms += fw.last_kernel_ms();
      }
  });
  const double values_s = bench::median_seconds(repeats, [&] { (void)fw.psf_values(theta); });
  const double ref_s = bench::median_seconds(repeats, [&] {
    for (int l = 0; l < L; ++l)
      for (const auto& p : passes_of(l)) (void)ref::psf(proto, t, theta, p, l);
  });
  const double ref_values_s = bench::median_seconds(repeats, [&] { (void)ref::psf(proto, t, theta); });
  std::printf("\n## 1. One PSF's model, prototype (%d lenslets, 216 parameters), %.1f um pixels, %u cells per lenslet\n"
              "# derivative images: %zu renders (each lenslet alone, 3 parameters a pass); values: one render.\n"
              "# The device's first use compiles its kernels: %.1f s here (once per process).\n",
              L, AnalysisGrid::of(proto, t.binning).pixel_mm * 1e3, t.rays(), renders, first_use);
  std::printf("%-44s %12s %12s\n", "", "derivatives s", "values s");
  std::printf("%-44s %12.3f %12.3f   (kernels %.3f s of it)\n", "device, calibrate kernels (wall)", device_s,
              values_s, kernel_ms * 1e-3);
  std::printf("%-44s %12.3f %12.3f\n", "CPU reference (double, 1 thread)", ref_s, ref_values_s);
  std::printf("ratio: the device is %.1fx the CPU reference's speed for the derivative images (the fit on the CPU "
              "runs --threads PSFs at once), %.1fx for values\n",
              ref_s / device_s, ref_values_s / values_s);
  std::fflush(stdout);
  if (!fit) return 0;

  // 2. A whole fit on each backend.
  const OpticalSystem nominal = nominal_row(), truth = synthetic_as_built(nominal);
  TraceSettings truth_settings = t;
  truth_settings.rays_per_lenslet = 4 * t.rays_per_lenslet;
  truth_settings.stratification = 1;
  std::vector<MeasuredPsf> psfs;
  uint64_t seed = 1;
  for (double depth : {6.0, 15.0, 30.0, 45.0})
    for (glm::dvec2 xy : {glm::dvec2(-6, -3), glm::dvec2(2, 3), glm::dvec2(8, -2)})
      psfs.push_back(synthetic_measured_psf(truth, truth_settings, {xy.x, xy.y, depth}, seed++));
  const auto free = calibration_parameters(nominal, calibration_default_groups());
  std::printf("\n## 2. A whole fit: 5 as-built lenslets (f = 4.5-12 mm), %zu parameters, %zu HDR-merged PSFs at 4096 "
              "cells (stratification 1), model %u cells, from the nominal scene\n",
              free.size(), psfs.size(), t.rays());
  std::printf("%-36s %9s %6s %12s %14s %14s\n", "backend", "seconds", "steps", "chi2 / dof", "RMS err/sigma",
              "max err/sigma");
  for (bool on_device : {true, false}) {
    CalibrationOptions o;
    o.settings = t;
    o.device = on_device ? &ctx : nullptr;
    o.threads = 2;
    const CalibrationResult r = calibrate(nominal, psfs, free, o);
    double sum2 = 0, worst = 0;
    for (const auto& e : r.estimates) {
      const double z = (e.value - e.parameter.get(truth)) / e.sigma;
      sum2 += z * z, worst = std::max(worst, std::abs(z));
    }
    std::printf("%-36s %9.1f %6d %12.4g %14.2f %14.2f\n",
                on_device ? "device, calibrate kernels" : "CPU reference, 2 threads", r.seconds, r.steps,
                r.reduced_chi2(), std::sqrt(sum2 / double(r.estimates.size())), worst);
    std::fflush(stdout);
  }

  // 3. The prototype's step: two PSFs of the synthetic as-built prototype,
  // every parameter free, fitted on the model's pixels alone for two steps.
  const OpticalSystem proto_truth = synthetic_as_built(proto);
  std::vector<MeasuredPsf> two{synthetic_measured_psf(proto_truth, truth_settings, {3, -2, 20}, 101),
                               synthetic_measured_psf(proto_truth, truth_settings, {-8, 5, 35}, 102)};
  const auto all = calibration_parameters(proto, calibration_default_groups());
  std::printf("\n## 3. The prototype: %zu parameters, 2 PSFs, two steps on the model's pixels; seconds per step and "
              "PSF (each step: a trial without derivatives, then the derivatives)\n",
              all.size());
  std::printf("%-36s %9s %6s %16s\n", "backend", "seconds", "steps", "s per step, PSF");
  for (bool on_device : {true, false}) {
    CalibrationOptions o;
    o.settings = t;
    o.device = on_device ? &ctx : nullptr;
    o.threads = 2;
    o.coarse_levels = 0;
    o.max_steps = 2;
    const CalibrationResult r = calibrate(proto, two, all, o);
    // The first evaluation with derivatives and the start's chi2 come before the steps.
    std::printf("%-36s %9.1f %6d %16.2f\n", on_device ? "device, calibrate kernels" : "CPU reference, 2 threads",
                r.seconds, r.steps, r.seconds / double(std::max(1, r.steps + 1)) / double(two.size()));
    std::fflush(stdout);
  }
  return 0;
}
