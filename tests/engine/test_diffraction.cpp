// Effect diffraction: each lenslet's Airy core as a uniform square of the core's
// variance (shaders/common/blur.glsl), integrated exactly over box pixels.
// The kernels (Green's theorem along each triangle's edges, Gauss-Legendre
// between kinks) against the reference (each triangle clipped to the cells
// between the blurred pixel's kinks, integrated from polygon moments), where
// the core spans a good part of a pixel and large cells are split; the
// reference's derivatives against its own central differences; and the limit
// of a vanishing core, the geometric image.
#include <cmath>

#include "engine/forward.h"
#include "engine/ref/forward_ref.h"
#include "compare.h"
#include "host/scene/scene.h"
#include "support.h"

namespace {

using prism::test::channel;
using prism::test::gpu;

prism::TraceSettings footprint(unsigned cells, unsigned binning) {
  prism::TraceSettings t = prism::TraceSettings::defaults_for(prism::Splat::footprint);
  t.rays_per_lenslet = cells;
  t.binning = binning;
  return t;
}

double crlb_3d(const prism::FisherResult& f) { return prism::crlb_from_fisher(f.poisson, f.photons).r3_mm; }

// The prototype's f = 3 mm lenslet alone, thin or real, with diffraction.
prism::OpticalSystem f3_lenslet(prism::LensModel model) {
  auto sys = prism::builtin_scene("prototype").optics;
  sys.lenslets = {sys.lenslets[15]};
  REQUIRE(sys.lenslets[0].focal_mm == 3.0);
  sys.lens_model = model;
  sys.effects.diffraction = true;
  return sys;
}

}  // namespace

// Under the sanitizers the footprint test's diffraction case runs the same
// code at 55 um; here the reference's fine pixels took a minute there.
TEST_CASE("diffraction: Vulkan equals the reference at fine pixels, split cells included" *
          prism::test::skip_under_sanitizer) {
  // 13.8 um pixels: the core's half side (2.6 um) is a fifth of a pixel. At
  // depth 10 the f3 lenslet's image is 12 mm wide and its 1024 cells are
  // imaged ~27 px large: each is split and its pieces blurred in the split
  // pass, which must not run out of lavapipe's loop budget (light would be
  // lost silently). The real lens folds cells at its caustic, where a thin or
  // large decision can flip between float and double: there the totals and
  // the CRLB (as in test_footprint.cpp).
  for (auto model : {prism::LensModel::thin, prism::LensModel::real}) {
    CAPTURE(int(model));
    auto sys = f3_lenslet(model);
    auto t = footprint(1024, 2);
    const glm::dvec3 theta{0.3, 0.2, 10.0};
    auto ref = prism::ref::psf(sys, t, theta);
    prism::ForwardVulkan fw(gpu(), sys, t);
    auto image = fw.psf(theta);
    REQUIRE(ref.photons() > 0);
    CHECK(image.photons() == doctest::Approx(ref.photons()).epsilon(1e-5));
    for (int c = 0; c < 4 && model == prism::LensModel::thin; ++c) {
      auto want = channel(ref, c);
      auto got = channel(image, c);
      auto cmp = prism::test::compare(want, got, {.abs = (c == 0 ? 1e-3 : 2e-3) * prism::test::peak_abs(want)});
      CHECK_MESSAGE(cmp.ok(), cmp.report("channel " + std::to_string(c) + " (Vulkan vs reference)"));
    }
    const double ref_crlb = crlb_3d(prism::ref::fisher_of(ref, 0.0, prism::FisherEstimator::naive));
    CHECK(crlb_3d(fw.fisher(std::vector<glm::dvec3>{theta}).front()) == doctest::Approx(ref_crlb).epsilon(1e-3));
  }
  prism::test::check_validation_clean();
}

TEST_CASE("diffraction: the reference's derivatives are those of its values (central differences)") {
  // The blurred image is smooth in theta (the blurred pixel is continuous),
  // so central differences hold where a pixel has light; 27.6 um pixels,
  // a core half side of a quarter pixel (a longer wavelength).
  auto sys = f3_lenslet(prism::LensModel::thin);
  sys.effects.wavelength_nm = 2000;
  // Under the sanitizers 110 um pixels: the reference's work is per pixel.
  auto t = footprint(256, prism::test::under_sanitizer ? 16 : 4);
  const glm::dvec3 theta{0.3, 0.2, 20.0};
  auto at = prism::ref::psf(sys, t, theta);
  const double step = 1e-5;  // mm
  const double peak = prism::test::peak_abs(channel(at, 0));
  for (int axis = 0; axis < 3; ++axis) {
    CAPTURE(axis);
    glm::dvec3 d(0.0);
    d[axis] = step;
    auto plus = channel(prism::ref::psf(sys, t, theta + d), 0), minus = channel(prism::ref::psf(sys, t, theta - d), 0);
    auto analytic = channel(at, 1 + axis);
    std::vector<double> fd(plus.size()), want(plus.size());
    size_t lit = 0;
    auto b = channel(at, 0);
    for (size_t i = 0; i < plus.size(); ++i) {
      // Pixels with light (the rest hold none to differentiate).
      if (b[i] < 1e-3 * peak) continue;
      fd[i] = (plus[i] - minus[i]) / (2 * step);
      want[i] = analytic[i];
      ++lit;
    }
    CHECK(lit > 100);
    auto cmp = prism::test::compare(want, fd, {.abs = 1e-4 * prism::test::peak_abs(want), .rel = 1e-4});
    CHECK_MESSAGE(cmp.ok(), cmp.report("d b / d theta: forward mode vs central differences"));
  }
}

TEST_CASE("diffraction: as the core vanishes the image and the CRLB become the geometric ones") {
  auto sys = prism::test::small_system(prism::LensModel::real);
  auto t = footprint(1024, 8);
  const glm::dvec3 theta{1.3, -0.7, 25.0};
  prism::ForwardVulkan plain(gpu(), sys, t);
  const double geometric = crlb_3d(plain.fisher(std::vector<glm::dvec3>{theta}).front());
  const auto geometric_b = channel(plain.psf(theta), 0);
  double last_change = 1;
  for (double nm : {57.0, 5.7, 0.57}) {
    CAPTURE(nm);
    auto blurred = sys;
    blurred.effects.diffraction = true;
    blurred.effects.wavelength_nm = nm;
    prism::ForwardVulkan fw(gpu(), blurred, t);
    const double change = std::abs(crlb_3d(fw.fisher(std::vector<glm::dvec3>{theta}).front()) / geometric - 1);
    MESSAGE(nm << " nm: CRLB " << change * 100 << "% from the geometric one");
    CHECK(change <= last_change + 1e-4);
    last_change = change;
    // A pixel gains or loses at most the light within the core's reach of
    // its edges: a few half sides' worth of its light density.
    const double h_px = blurred.airy_half_side_mm(0) / fw.grid().pixel_mm;
    auto b = channel(fw.psf(theta), 0);
    auto cmp = prism::test::compare(geometric_b, b, {.abs = 4 * h_px * prism::test::peak_abs(geometric_b)});
    CHECK_MESSAGE(cmp.ok(), cmp.report("blurred vs geometric pixel values"));
  }
  CHECK(last_change < 1e-3);
  prism::test::check_validation_clean();
}
