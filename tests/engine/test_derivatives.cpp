// Forward-mode derivatives of the CPU reference against central finite
// differences, per ray, for every lens model and effect: landing point and
// photon weight with respect to (x, y, depth).
#include <cmath>

#include "engine/ref/forward_ref.h"
#include "support.h"

using prism::ref::SampleHit;

namespace {

void check_against_fd(const prism::OpticalSystem& sys, const glm::dvec3& theta) {
  prism::TraceSettings t;
  t.rays_per_lenslet = 64;
  const double h = 1e-6;  // mm; double rounding ~1e-16 * 50 mm / 1e-6 = 5e-9 relative
  int compared = 0;
  for (size_t lens = 0; lens < sys.lenslets.size(); ++lens)
    for (uint32_t s = 0; s < t.rays(); s += 7) {
      SampleHit c = prism::ref::trace_sample(sys, t, theta, lens, s);
      if (!c.ok) continue;
      for (int axis = 0; axis < 3; ++axis) {
        glm::dvec3 step(0.0);
        step[axis] = h;
        SampleHit p = prism::ref::trace_sample(sys, t, theta + step, lens, s);
        SampleHit m = prism::ref::trace_sample(sys, t, theta - step, lens, s);
        if (!p.ok || !m.ok) continue;  // the ray crosses a clipping edge here
        double fd_x = (p.x_mm - m.x_mm) / (2 * h), fd_y = (p.y_mm - m.y_mm) / (2 * h);
        double fd_w = (p.weight - m.weight) / (2 * h);
        CAPTURE(lens);
        CAPTURE(s);
        CAPTURE(axis);
        // Central differences of the landing point lose ~1e-6 relative to
        // rounding through three refractions and an 18.5 mm lever arm.
        CHECK(c.dx[axis] == doctest::Approx(fd_x).epsilon(1e-5).scale(1.0));
        CHECK(c.dy[axis] == doctest::Approx(fd_y).epsilon(1e-5).scale(1.0));
        CHECK(c.dweight[axis] == doctest::Approx(fd_w).epsilon(1e-5).scale(c.weight));
        ++compared;
      }
    }
  CHECK(compared > 20);
}

}  // namespace

TEST_CASE("reference derivatives match finite differences: thin lens") {
  auto sys = prism::test::small_system(prism::LensModel::thin);
  check_against_fd(sys, {1.3, -2.1, 17.0});
  check_against_fd(sys, {-8.0, 4.0, 2.0});
}

TEST_CASE("reference derivatives match finite differences: real plano-convex lens") {
  auto sys = prism::test::small_system(prism::LensModel::real);
  check_against_fd(sys, {1.3, -2.1, 17.0});
  check_against_fd(sys, {-8.0, 4.0, 2.0});
}

TEST_CASE("reference derivatives match finite differences: scintillator refraction and holder") {
  auto sys = prism::test::small_system(prism::LensModel::real);
  sys.effects.scintillator_refraction = true;
  sys.effects.holder_vignetting = true;
  sys.effects.holder_bore_mm = 2.5;
  check_against_fd(sys, {1.3, -2.1, 17.0});
  check_against_fd(sys, {1.0, -1.0, 0.5});
}

TEST_CASE("reference derivatives match finite differences: extended source") {
  auto sys = prism::test::small_system(prism::LensModel::real);
  sys.effects.source_extent = true;
  sys.effects.source_sigma_mm = 0.4;
  check_against_fd(sys, {1.3, -2.1, 17.0});
}
