// The as-built forward model: lenslets tilted about their centres and a
// sensor moved within its plane and tilted (OpticalSystem::as_built, traced
// through specialisation constant AS_BUILT). Checked against closed forms the
// kernels do not use (the ideal thin lens images a point exactly, in its own
// frame; a sensor moved by whole pixels moves the image by whole pixels; the
// light a tilted disc collects is its solid angle), and the Vulkan kernels
// against the double reference on tilted real lenses.
#include <cmath>

#include "compare.h"
#include "engine/forward.h"
#include "engine/ref/forward_ref.h"
#include "engine/ref/thin_lens_oracle.h"
#include "support.h"

namespace {

using prism::test::channel;
using prism::test::gpu;

constexpr double kDeg = M_PI / 180.0;

// v -> Ry(ay) Rx(ax) v, written out here apart from the engine's tilt_matrix.
glm::dvec3 turned(glm::dvec3 v, double ax_deg, double ay_deg) {
  const double ax = ax_deg * kDeg, ay = ay_deg * kDeg;
  const glm::dvec3 after_x(v.x, std::cos(ax) * v.y - std::sin(ax) * v.z, std::sin(ax) * v.y + std::cos(ax) * v.z);
  return {std::cos(ay) * after_x.x + std::sin(ay) * after_x.z, after_x.y,
          -std::sin(ay) * after_x.x + std::cos(ay) * after_x.z};
}
glm::dvec3 unturned(glm::dvec3 v, double ax_deg, double ay_deg) {
  const double ax = ax_deg * kDeg, ay = ay_deg * kDeg;
  const glm::dvec3 before_y(std::cos(ay) * v.x - std::sin(ay) * v.z, v.y, std::sin(ay) * v.x + std::cos(ay) * v.z);
  return {before_y.x, std::cos(ax) * before_y.y + std::sin(ax) * before_y.z,
          -std::sin(ax) * before_y.y + std::cos(ax) * before_y.z};
}

prism::OpticalSystem one_thin_lens(double tilt_x_deg, double tilt_y_deg) {
  prism::OpticalSystem sys;
  sys.lens_model = prism::LensModel::thin;
  prism::LensletGeometry l{1.0, -0.5, 3.0, 9.0};
  l.tilt_x_deg = tilt_x_deg;
  l.tilt_y_deg = tilt_y_deg;
  sys.lenslets = {l};
  return sys;
}

prism::TraceSettings point(unsigned rays, unsigned binning) {
  prism::TraceSettings t;
  t.rays_per_lenslet = rays;
  t.binning = binning;
  t.splat = prism::Splat::point;
  return t;
}

prism::TraceSettings footprint(unsigned rays, unsigned binning) {
  prism::TraceSettings t = point(rays, binning);
  t.splat = prism::Splat::footprint;
  t.estimator = prism::FisherEstimator::naive;
  return t;
}

}  // namespace

TEST_CASE("as built: a tilted ideal thin lens images a point where the lens equation puts it in the lens's frame") {
  // In its own frame the thin lens sends every ray from S through the image
  // I = c - (S - c)_lateral b / a at distance b behind it (1/a + 1/b = 1/f).
  // So each ray leaves the aperture point p toward c + R (I - c), and lands
  // where that line meets the sensor; on a tilted sensor, in its own axes.
  for (auto [tx, ty, stx, sty] : {std::tuple{2.0, -1.5, 0.0, 0.0}, std::tuple{-3.0, 0.5, 0.8, -1.2}}) {
    CAPTURE(tx);
    CAPTURE(stx);
    prism::OpticalSystem sys = one_thin_lens(tx, ty);
    sys.sensor_pose = {0.21, -0.13, stx, sty};
    const glm::dvec3 c(1.0, -0.5, 0.0);
    const glm::dvec3 source(2.3, 1.1, -(17.0 + sys.working_distance_mm));
    const glm::dvec3 s_local = c + unturned(source - c, tx, ty);
    const double a = -s_local.z, f = 9.0, b = 1.0 / (1.0 / f - 1.0 / a);
    const glm::dvec3 image_local(c.x - (s_local.x - c.x) * b / a, c.y - (s_local.y - c.y) * b / a, b);
    const glm::dvec3 image = c + turned(image_local - c, tx, ty);
    const glm::dvec3 s0(0.21, -0.13, sys.lens_to_sensor_mm);
    const glm::dvec3 ex = turned({1, 0, 0}, stx, sty), ey = turned({0, 1, 0}, stx, sty), n = turned({0, 0, 1}, stx, sty);
    double worst = 0;
    for (double u : {-0.6, -0.3, 0.0, 0.4, 0.6})
      for (double v : {-0.7, 0.0, 0.5}) {
        const glm::dvec3 p = c + turned({1.5 * u, 1.5 * v, 0.0}, tx, ty);  // on the tilted lens plane
        auto got = prism::ref::trace_ray(sys, 0, source, p - source);
        REQUIRE(got.has_value());
        const glm::dvec3 d = image - p;
        const glm::dvec3 h = p + d * (glm::dot(s0 - p, n) / glm::dot(d, n)) - s0;
        worst = std::max(worst, glm::length(*got - glm::dvec2(glm::dot(h, ex), glm::dot(h, ey))));
      }
    CHECK(worst < 1e-9);  // mm
  }
}

TEST_CASE("as built: a sensor moved by whole pixels moves every image by whole pixels") {
  // A hit at x on the moved sensor lands at x - offset: the image shifts by
  // the offset in pixels, b and its derivatives alike. Tolerance: the float
  // landing points go through the as-built path's turns (identity here).
  auto nominal = prism::test::small_system(prism::LensModel::real);
  auto moved = nominal;
  const int dx = 3, dy = -2;
  const unsigned binning = 8;
  const double px = nominal.pixel_um * 1e-3 * binning;
  moved.sensor_pose.offset_x_mm = dx * px;
  moved.sensor_pose.offset_y_mm = dy * px;
  REQUIRE(moved.as_built());
  const glm::dvec3 theta(1.3, -0.7, 25.0);
  for (auto t : {point(256, binning), footprint(256, binning)}) {
    std::string splat = prism::to_string(t.splat);
    CAPTURE(splat);
    prism::ForwardVulkan a(gpu(), nominal, t), b(gpu(), moved, t);
    auto want = a.psf(theta), got = b.psf(theta);
    for (int c = 0; c < 4; ++c) {
      auto w = channel(want, c), g = channel(got, c);
      std::vector<double> shifted_want, kept_got;
      for (int row = 4; row < want.height - 4; ++row)
        for (int col = 4; col < want.width - 4; ++col) {
          shifted_want.push_back(w[size_t(row + dy) * want.width + size_t(col + dx)]);
          kept_got.push_back(g[size_t(row) * want.width + size_t(col)]);
        }
      // The footprint's split pieces go to the pixel of their centroid, which
      // the float landing points can move across a border: 1e-3 of the peak
      // as in test_footprint.cpp. The point splat's derivative channels jump
      // where a hit crosses a pixel-centre line: 1e-3 of their peak as in
      // test_forward_vulkan.cpp (2e-4 held on lavapipe, whose float rounding
      // the two renders share; an H200 went 4% past it at 4 of 5e5 pixels).
      const bool pt = t.splat == prism::Splat::point;
      const double tol = pt && c == 0 ? 2e-4 : 1e-3;
      auto cmp = prism::test::compare(shifted_want, kept_got, {.abs = tol * prism::test::peak_abs(w)});
      CHECK_MESSAGE(cmp.ok(), cmp.report("channel " + std::to_string(c) + " (moved sensor vs nominal shifted)"));
    }
  }
  prism::test::check_validation_clean();
}

TEST_CASE("as built: a tilted lens collects the solid angle of its tilted disc") {
  // Thin lens, all its light on the sensor: the total is photons / (4 pi)
  // times the solid angle of the turned disc, integrated here on a polar grid
  // (cos to the disc's normal over r^2). At 8 degrees the tilt costs about
  // 1% of the light, so the emitters' correction for the turned disc matters.
  const glm::dvec3 theta(0.4, -0.3, 12.0);
  for (double tilt : {0.0, 8.0}) {
    CAPTURE(tilt);
    prism::OpticalSystem sys = one_thin_lens(tilt, 0.5 * tilt);
    const glm::dvec3 c(1.0, -0.5, 0.0), normal = turned({0, 0, 1}, tilt, 0.5 * tilt);
    const glm::dvec3 s(theta.x, theta.y, -(theta.z + sys.working_distance_mm));
    double omega = 0;
    const int nr = 400, nphi = 400;
    for (int i = 0; i < nr; ++i)
      for (int j = 0; j < nphi; ++j) {
        const double r = 1.5 * (i + 0.5) / nr, phi = 2 * M_PI * (j + 0.5) / nphi;
        const glm::dvec3 p = c + turned({r * std::cos(phi), r * std::sin(phi), 0.0}, tilt, 0.5 * tilt);
        const glm::dvec3 d = p - s;
        const double len = glm::length(d);
        omega += glm::dot(d, normal) / (len * len * len) * r * (1.5 / nr) * (2 * M_PI / nphi);
      }
    const auto t = point(16384, 16);
    const double want = t.photons_emitted / (4 * M_PI) * omega;
    CHECK(prism::ref::psf(sys, t, theta).photons() == doctest::Approx(want).epsilon(2e-4));
    prism::ForwardVulkan fw(gpu(), sys, t);
    CHECK(fw.psf(theta).photons() == doctest::Approx(want).epsilon(2e-4));
  }
  prism::test::check_validation_clean();
}

TEST_CASE("as built: Vulkan equals the double reference on tilted real lenses and a tilted, moved sensor") {
  auto sys = prism::test::small_system(prism::LensModel::real);
  for (size_t i = 0; i < sys.lenslets.size(); ++i) {
    sys.lenslets[i].tilt_x_deg = 0.9 * std::sin(double(i));
    sys.lenslets[i].tilt_y_deg = -0.7 * std::cos(double(i));
  }
  sys.sensor_pose = {0.05, -0.08, 0.6, -0.4};
  auto flipped = sys;
  flipped.curved_toward_sensor = true;
  auto holder = sys;
  holder.effects.holder_vignetting = true;
  holder.effects.holder_bore_mm = 3.0;
  struct Case {
    std::string name;
    prism::OpticalSystem sys;
    prism::TraceSettings t;
    glm::dvec3 theta;
  } cases[] = {{"point splat", sys, point(400, 8), {1.7, -2.3, 21.0}},
               {"footprint", sys, footprint(1024, 8), {1.3, -0.7, 25.0}},
               {"footprint, near the face", sys, footprint(1024, 8), {8.0, 3.0, 2.0}},
               {"footprint, flat face first", flipped, footprint(1024, 8), {1.3, -0.7, 25.0}},
               {"footprint, holder 3 mm", holder, footprint(1024, 8), {8.0, 3.0, 2.0}}};
  for (const auto& k : cases) {
    CAPTURE(k.name);
    auto ref = prism::ref::psf(k.sys, k.t, k.theta);
    prism::ForwardVulkan fw(gpu(), k.sys, k.t);
    auto image = fw.psf(k.theta);
    REQUIRE(ref.photons() > 0);
    CHECK(image.photons() == doctest::Approx(ref.photons()).epsilon(1e-5));
    // The CRLB where every lit pixel holds many rays (test_forward_vulkan.cpp's
    // header: a pixel reached by one ray with a tiny bilinear fraction weighs
    // 1/b in the Fisher sum, and float's landing error moves it a lot). The
    // point splat's 400 rays per lenslet at 55 um are too few for that: its
    // CRLB is compared at 880 um pixels (at 55 um an H200 gave 14% less than
    // the reference while its pixels matched).
    auto ft = k.t;
    if (ft.splat == prism::Splat::point) ft.binning = 128;
    const auto fref = ft.binning == k.t.binning ? ref : prism::ref::psf(k.sys, ft, k.theta);
    const double ref_crlb = prism::crlb_from_fisher(prism::ref::fisher_of(fref, 0.0, ft.estimator).poisson, fref.photons()).r3_mm;
    prism::ForwardVulkan ffw(gpu(), k.sys, ft);
    const auto got_fisher = ffw.fisher(std::vector<glm::dvec3>{k.theta}).front();
    CHECK(prism::crlb_from_fisher(got_fisher.poisson, got_fisher.photons).r3_mm == doctest::Approx(ref_crlb).epsilon(2e-3));
    // Pixel by pixel as test_forward_vulkan.cpp and test_footprint.cpp (float
    // landing points, about 1e-4 mm off the double ones here), except for a
    // handful of pixels of the 5e5: a point ray within that of a pixel
    // centre line (its derivative taps jump there) or a footprint piece whose
    // centroid sits on a border goes to the neighbour in one of the two.
    const bool pt = k.t.splat == prism::Splat::point;
    for (int c = 0; c < 4; ++c) {
      auto want = channel(ref, c), got = channel(image, c);
      const double tol = c == 0 ? (pt ? 3e-4 : 1e-3) : (pt ? 1e-3 : 2e-3);
      auto cmp = prism::test::compare(want, got, {.abs = tol * prism::test::peak_abs(want)});
      CHECK_MESSAGE(cmp.mismatches <= 8, cmp.report("channel " + std::to_string(c) + " (Vulkan vs reference)"));
    }
  }
  // The tilts matter: the same system untilted gives another image.
  auto nominal = prism::test::small_system(prism::LensModel::real);
  auto untilted = prism::ref::psf(nominal, point(400, 8), {1.7, -2.3, 21.0});
  auto tilted = prism::ref::psf(sys, point(400, 8), {1.7, -2.3, 21.0});
  auto differ = prism::test::compare(channel(untilted, 0), channel(tilted, 0), {.abs = 0.05 * prism::test::peak_abs(channel(untilted, 0))});
  CHECK_FALSE(differ.ok());
  prism::test::check_validation_clean();
}

TEST_CASE("as built: scenes carry tilts and the sensor's pose, refuse large tilts, and leave nominal JSON as it was") {
  nlohmann::json j = prism::to_json(prism::builtin_scene("prototype"));
  CHECK_FALSE(j["lenslets"][0].contains("tilt_x_deg"));
  CHECK_FALSE(j["sensor"].contains("offset_x_mm"));
  j["lenslets"][3]["tilt_x_deg"] = 0.8;
  j["lenslets"][3]["tilt_y_deg"] = -0.3;
  j["sensor"]["offset_x_mm"] = 0.12;
  j["sensor"]["tilt_y_deg"] = 0.4;
  prism::Scene s = prism::parse_scene(j, "as-built.json");
  CHECK(s.optics.as_built());
  CHECK(s.optics.lenslets[3].tilt_x_deg == 0.8);
  CHECK(s.optics.sensor_pose.tilt_y_deg == 0.4);
  // Round trip.
  prism::Scene again = prism::parse_scene(prism::to_json(s), "again.json");
  CHECK(prism::to_json(again) == prism::to_json(s));
  j["lenslets"][3]["tilt_x_deg"] = 12.0;
  CHECK_THROWS_WITH(prism::parse_scene(j, "as-built.json"), doctest::Contains("lenslets[3].tilt_x_deg"));
  // Nothing not as built is traced as built.
  CHECK_FALSE(prism::builtin_scene("prototype").optics.as_built());
}
