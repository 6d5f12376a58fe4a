// The calibration's blur term (host/calibrate/source_blur.h): a lenslet's
// image of a Gaussian source as its point image convolved with the Gaussian
// sigma^2 J J^T. Checked against the engine's own source_extent (a random
// source offset per footprint cell, many cells and stratifications averaged
// so that its speckle is small), its derivative by sigma against central
// differences, and the calibration's blurred model on the calibrate kernels
// (lavapipe) against the CPU reference.
#include <cmath>
#include <string>

#include "engine/ref/forward_ref.h"
#include "host/calibrate/calibrate.h"
#include "host/calibrate/source_blur.h"
#include "support.h"

namespace {

// Lenslet `lens` of the small test system (real lenses) alone.
prism::OpticalSystem one_lens(size_t lens) {
  prism::OpticalSystem s = prism::test::small_system(prism::LensModel::real);
  s.lenslets = {s.lenslets.at(lens)};
  return s;
}

prism::TraceSettings settings(unsigned cells, uint32_t stratification) {
  prism::TraceSettings t = prism::TraceSettings::defaults_for(prism::Splat::footprint);
  t.rays_per_lenslet = cells;
  t.stratification = stratification;
  t.binning = 16;  // 110 um, the calibration's pixels
  return t;
}

// The point image and its derivatives by the source, as the calibration's
// renderer hands them to the blur.
prism::LensImage point_image(const prism::OpticalSystem& s, const glm::dvec3& theta) {
  const prism::AnalysisGrid grid = prism::AnalysisGrid::of(s, 16);
  const prism::ref::SparseImage img = prism::ref::psf(s, settings(1024, 0), theta);
  prism::LensImage out{grid.width, grid.height, 4, {}, {}};
  for (const auto& [key, px] : img.pixels) {
    const auto v = img.value(key);
    out.keys.push_back(key);
    out.values.insert(out.values.end(), v.begin(), v.end());
  }
  return out;
}

// The lenslet's image motion as the calibration takes it: its chief ray's,
// in 110 um pixels per mm.
std::array<double, 6> chief_ray_motion(const prism::OpticalSystem& s, const glm::dvec3& theta) {
  const auto J = prism::chief_ray_motion(s, settings(1024, 0), theta, 0);
  REQUIRE(J.has_value());
  return *J;
}

std::vector<double> dense(const prism::LensImage& img, size_t channel) {
  std::vector<double> out(size_t(img.width) * size_t(img.height), 0.0);
  for (size_t i = 0; i < img.keys.size(); ++i) out[size_t(img.keys[i])] += img.values[i * img.channels + channel];
  return out;
}

// sum |a - b| / sum b.
double l1(const std::vector<double>& a, const std::vector<double>& b) {
  double d = 0, n = 0;
  for (size_t i = 0; i < a.size(); ++i) d += std::abs(a[i] - b[i]), n += b[i];
  return d / n;
}

}  // namespace

TEST_CASE("blur term: a lenslet's image of a Gaussian source is its point image blurred by sigma^2 J J^T") {
  // Sources where the images are small (deep, and the long lenses), where a
  // 0.25 mm source blurs them by about a pixel: there the point image is far
  // from the extended source's. Near-face discs of short lenses are blurred
  // relatively less, and the engine's speckle hides what is left.
  constexpr double sigma = 0.25;
  struct Case {
    size_t lens;
    glm::dvec3 theta;
  };
  const int strata = prism::test::under_sanitizer ? 2 : 8;
  for (const Case c : {Case{6, {5, -5, 40}}, Case{6, {0, 2, 25}}, Case{5, {3, 1, 15}}, Case{4, {2, 1, 15}}}) {
    CAPTURE(c.lens);
    CAPTURE(c.theta.z);
    const prism::OpticalSystem point = one_lens(c.lens);
    prism::OpticalSystem extended = point;
    extended.effects.source_extent = true;
    extended.effects.source_sigma_mm = sigma;
    const prism::LensImage img = point_image(point, c.theta);
    const std::array<double, 6> J = chief_ray_motion(point, c.theta);
    const std::vector<double> model = dense(prism::blur(img, prism::source_blur_kernel(J, sigma), false), 0);
    // The engine's extended source, averaged over stratifications: `truth`
    // and an independent `again`, whose difference is its own noise.
    auto engine = [&](uint32_t first) {
      std::vector<double> sum(model.size(), 0.0);
      for (int k = 0; k < strata; ++k)
        for (const auto& [key, px] : prism::ref::psf(extended, settings(65536, first + uint32_t(k)), c.theta).pixels)
          sum[size_t(key)] += px[0] / strata;
      return sum;
    };
    const std::vector<double> truth = engine(1), again = engine(101), unblurred = dense(img, 0);
    const double noise = l1(again, truth), of_model = l1(model, truth), of_point = l1(unblurred, truth);
    MESSAGE("lenslet " << c.lens << " at depth " << c.theta.z << ": J (px/mm) " << J[0] << " " << J[1] << " " << J[2]
                       << " / " << J[3] << " " << J[4] << " " << J[5] << "; L1 to the engine's extended source: "
                       << "point " << of_point << ", blurred " << of_model << ", the engine's own noise " << noise);
    // A thin-lens-like magnification: about (lens to sensor) / (source distance), in pixels.
    CHECK(std::abs(J[0]) > 2);
    CHECK(std::abs(J[4]) > 2);
    CHECK(of_model < 0.35 * of_point);
    CHECK(of_model < 0.08);
  }
}

TEST_CASE("blur term: the blurred image's derivative by sigma is the kernel's, exactly") {
  const prism::OpticalSystem s = one_lens(4);
  const prism::LensImage img = point_image(s, {-3, 1, 30});
  const std::array<double, 6> J = prism::centroid_jacobian(img);
  // A sharp image's centroid moves as its chief ray does (the calibration's
  // fallback where the chief ray misses).
  const std::array<double, 6> chief = chief_ray_motion(s, {-3, 1, 30});
  CHECK(J[0] == doctest::Approx(chief[0]).epsilon(0.05));
  CHECK(J[4] == doctest::Approx(chief[4]).epsilon(0.05));
  for (double sigma : {0.05, 0.25, 0.8}) {
    CAPTURE(sigma);
    const prism::LensImage at = prism::blur(img, prism::source_blur_kernel(J, sigma), true);
    REQUIRE(at.channels == 5);
    const double h = 1e-5 * sigma;
    const std::vector<double> up = dense(prism::blur(img, prism::source_blur_kernel(J, sigma + h), false), 0),
                              down = dense(prism::blur(img, prism::source_blur_kernel(J, sigma - h), false), 0),
                              analytic = dense(at, 4);
    double worst = 0, largest = 0;
    for (size_t i = 0; i < up.size(); ++i) {
      worst = std::max(worst, std::abs((up[i] - down[i]) / (2 * h) - analytic[i]));
      largest = std::max(largest, std::abs(analytic[i]));
    }
    CAPTURE(worst);
    CAPTURE(largest);
    CHECK(largest > 0);
    CHECK(worst < 1e-6 * largest);
    // Light is moved, not made: away from the sensor's edges every channel
    // keeps its sum, and the derivative by sigma sums to 0.
    const std::vector<double> b = dense(img, 0), blurred = dense(at, 0), depth = dense(img, 3), blurred_depth = dense(at, 3);
    double sb = 0, sblur = 0, sd = 0, sdblur = 0, sds = 0;
    for (size_t i = 0; i < b.size(); ++i)
      sb += b[i], sblur += blurred[i], sd += depth[i], sdblur += blurred_depth[i], sds += analytic[i];
    CHECK(sblur == doctest::Approx(sb).epsilon(1e-12));
    CHECK(sdblur == doctest::Approx(sd).epsilon(1e-9));
    CHECK(std::abs(sds) < 1e-9 * sb);
  }
}

TEST_CASE("blur term: the kernel's shape follows the image's motion") {
  // J = diag(3, 3) sideways and nothing in depth: an isotropic Gaussian of
  // 3 sigma pixels; moving in x only: a line along x.
  const prism::BlurKernel round = prism::source_blur_kernel({3, 0, 0, 0, 3, 0}, 1.0);
  const int R = round.radius, n = 2 * R + 1;
  CHECK(R >= 12);  // four sigma
  auto at = [&](const prism::BlurKernel& k, int dx, int dy) {
    return k.g[size_t(dy + k.radius) * size_t(2 * k.radius + 1) + size_t(dx + k.radius)];
  };
  CHECK(at(round, 3, 0) == doctest::Approx(at(round, 0, 3)));
  CHECK(at(round, 3, 0) / at(round, 0, 0) == doctest::Approx(std::exp(-0.5)).epsilon(1e-6));
  double sum = 0;
  for (double g : round.g) sum += g;
  CHECK(sum == doctest::Approx(1.0).epsilon(1e-12));
  CHECK(n * n == int(round.g.size()));
  const prism::BlurKernel line = prism::source_blur_kernel({2, 0, 0, 0, 0, 0}, 1.0);
  CHECK(at(line, 2, 0) / at(line, 0, 0) == doctest::Approx(std::exp(-0.5)).epsilon(1e-6));
  CHECK(at(line, 0, 1) < 1e-100);
}

TEST_CASE("blur term: the calibrate kernels and the CPU reference give the same blurred model") {
  // One evaluation with derivatives (no step), on lavapipe and on the
  // reference: the blur and its pass by the source are the host's, the
  // renders the device's. Three lenslets as built, a 0.25 mm source.
  prism::OpticalSystem s = prism::test::small_system(prism::LensModel::real);
  s.lenslets = {s.lenslets.begin() + 3, s.lenslets.begin() + 6};
  s.effects.source_extent = true;
  s.effects.source_sigma_mm = 0.25;
  prism::CalibrationOptions o;
  o.settings = settings(1024, 0);
  // One coarser level, so that chi2 at the start is an evaluation of its own
  // on the model's pixels, without derivatives (on the model's pixels alone
  // the start's chi2 is the first evaluation's, with them).
  o.max_steps = 0, o.coarse_levels = 1;
  const prism::AnalysisGrid grid = prism::AnalysisGrid::of(s, 16);
  std::vector<prism::MeasuredPsf> psfs;
  for (const glm::dvec3 theta : {glm::dvec3(-6, -3, 6), glm::dvec3(2, 3, 30)}) {
    prism::MeasuredPsf m{theta, std::vector<float>(size_t(grid.width) * size_t(grid.height), 0.0f), "psf", {}};
    for (const auto& [key, px] : prism::ref::psf(s, settings(4096, 1), theta).pixels) m.p[size_t(key)] = float(px[0]);
    psfs.push_back(std::move(m));
  }
  const auto free = prism::calibration_parameters(s, {"lens_xy", "source_extent"});
  const prism::CalibrationResult cpu = prism::calibrate(s, psfs, free, o);
  o.device = &prism::test::gpu();
  const prism::CalibrationResult device = prism::calibrate(s, psfs, free, o);
  CHECK(device.chi2_start == doctest::Approx(cpu.chi2_start).epsilon(1e-3));
  // The same model with derivatives (the result's chi2) and without (the
  // start's, as a step's trial is evaluated).
  CHECK(cpu.chi2 == doctest::Approx(cpu.chi2_start).epsilon(1e-9));
  CHECK(device.chi2 == doctest::Approx(device.chi2_start).epsilon(1e-3));
  REQUIRE(device.estimates.size() == cpu.estimates.size());
  for (size_t j = 0; j < cpu.estimates.size(); ++j) {
    CAPTURE(cpu.estimates[j].parameter.name());
    REQUIRE(std::isfinite(cpu.estimates[j].sigma));
    CHECK(device.estimates[j].sigma == doctest::Approx(cpu.estimates[j].sigma).epsilon(1e-2));
  }
}
