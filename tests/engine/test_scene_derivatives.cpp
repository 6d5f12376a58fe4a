// The double reference's derivatives with respect to the scene's parameters
// (ref::Tangents; what calibration fits, issue 18): forward mode through the
// lens positions, focal lengths, tilts, distances and the sensor's pose,
// against central differences of its own pixel values. Footprint splat, whose
// pixel values are smooth in every parameter (exact areas of moving cells);
// an as-built real-lens array with tilts and a moved, tilted sensor, and an
// extended source (whose sigma is the blur term), so that no parameter sits
// at a special value. Then the calibrate kernels (the same
// derivatives on the device) against the reference.
#include <cmath>
#include <functional>
#include <string>
#include <utility>

#include "compare.h"
#include "engine/forward.h"
#include "engine/ref/forward_ref.h"
#include "host/scene/scene.h"
#include "support.h"

namespace {

using prism::ref::Param;
using prism::ref::Tangent;
using prism::test::channel;

struct Parameter {
  std::string name;
  Tangent tangent;
  double step;  // of the central difference (mm or degrees)
  std::function<void(prism::OpticalSystem&, double)> move;
};

// Every lenslet (lens < 0) or one.
void each_lens(prism::OpticalSystem& s, int lens, const std::function<void(prism::LensletGeometry&)>& f) {
  for (size_t i = 0; i < s.lenslets.size(); ++i)
    if (lens < 0 || size_t(lens) == i) f(s.lenslets[i]);
}

std::vector<Parameter> parameters() {
  std::vector<Parameter> p;
  for (int lens : {1, -1}) {
    const std::string at = lens < 0 ? " (every lenslet)" : " (lenslet 1)";
    p.push_back({"lens x" + at, {Param::lens_x, lens}, 1e-4,
                 [=](auto& s, double h) { each_lens(s, lens, [&](auto& l) { l.x_mm += h; }); }});
    p.push_back({"lens y" + at, {Param::lens_y, lens}, 1e-4,
                 [=](auto& s, double h) { each_lens(s, lens, [&](auto& l) { l.y_mm += h; }); }});
    p.push_back({"focal length" + at, {Param::lens_focal, lens}, 1e-4,
                 [=](auto& s, double h) { each_lens(s, lens, [&](auto& l) { l.focal_mm += h; }); }});
    p.push_back({"lens tilt x" + at, {Param::lens_tilt_x, lens}, 1e-3,
                 [=](auto& s, double h) { each_lens(s, lens, [&](auto& l) { l.tilt_x_deg += h; }); }});
    p.push_back({"lens tilt y" + at, {Param::lens_tilt_y, lens}, 1e-3,
                 [=](auto& s, double h) { each_lens(s, lens, [&](auto& l) { l.tilt_y_deg += h; }); }});
  }
  p.push_back({"lens to sensor", {Param::lens_to_sensor}, 1e-4, [](auto& s, double h) { s.lens_to_sensor_mm += h; }});
  p.push_back({"working distance", {Param::working_distance}, 1e-4,
               [](auto& s, double h) { s.working_distance_mm += h; }});
  p.push_back({"sensor offset x", {Param::sensor_offset_x}, 1e-4,
               [](auto& s, double h) { s.sensor_pose.offset_x_mm += h; }});
  p.push_back({"sensor offset y", {Param::sensor_offset_y}, 1e-4,
               [](auto& s, double h) { s.sensor_pose.offset_y_mm += h; }});
  p.push_back({"sensor tilt x", {Param::sensor_tilt_x}, 1e-3, [](auto& s, double h) { s.sensor_pose.tilt_x_deg += h; }});
  p.push_back({"sensor tilt y", {Param::sensor_tilt_y}, 1e-3, [](auto& s, double h) { s.sensor_pose.tilt_y_deg += h; }});
  return p;
}

// The blur term and two others, on an extended source (as_built(face, true)).
std::vector<Parameter> extended_parameters() {
  return {{"source sigma", {Param::source_sigma}, 1e-4, [](auto& s, double h) { s.effects.source_sigma_mm += h; }},
          {"lens x (lenslet 1)", {Param::lens_x, 1}, 1e-4, [](auto& s, double h) { s.lenslets[1].x_mm += h; }},
          {"working distance", {Param::working_distance}, 1e-4,
           [](auto& s, double h) { s.working_distance_mm += h; }}};
}

prism::OpticalSystem as_built(bool face, bool extended = false) {
  auto s = prism::test::small_system(prism::LensModel::real);
  s.lenslets = std::vector<prism::LensletGeometry>(s.lenslets.begin() + 2, s.lenslets.begin() + 5);
  for (size_t i = 0; i < s.lenslets.size(); ++i) {
    s.lenslets[i].tilt_x_deg = 0.8 * std::sin(double(i) + 1.0);
    s.lenslets[i].tilt_y_deg = -0.6 * std::cos(double(i) + 0.3);
  }
  s.sensor_pose = {0.04, -0.06, 0.5, -0.3};
  s.effects.scintillator_refraction = face;
  // An extended source (the blur term): each cell's rays from its own point.
  s.effects.source_extent = extended;
  s.effects.source_sigma_mm = 0.15;
  return s;
}

// Footprint at 256 cells on 110 um pixels; the source off axis at depth 12.
prism::TraceSettings settings() {
  prism::TraceSettings t;
  t.splat = prism::Splat::footprint;
  t.rays_per_lenslet = 256;
  t.binning = 16;
  return t;
}
const glm::dvec3 theta(1.3, -0.7, 12.0);

// "(x, y, depth)", for a capture.
std::string position(const glm::dvec3& at) {
  return "(" + std::to_string(at.x) + ", " + std::to_string(at.y) + ", " + std::to_string(at.z) + ")";
}

// sum |got - want| and sum |want| over an image.
std::pair<double, double> l1_difference(const std::vector<double>& got, const std::vector<double>& want) {
  double differ = 0, sum = 0;
  for (size_t i = 0; i < want.size(); ++i) differ += std::abs(got[i] - want[i]), sum += std::abs(want[i]);
  return {differ, sum};
}

}  // namespace

TEST_CASE("reference derivatives with respect to the scene's parameters equal central differences of its pixels") {
  const auto t = settings();
  const std::pair<bool, bool> cases[] = {{false, false}, {false, true}, {true, false}, {true, true}};
  for (const auto& [extended, face] : cases) {
    CAPTURE(extended);
    CAPTURE(face);
    const auto sys = as_built(face, extended);
    const auto all = extended ? extended_parameters() : parameters();
    // A footprint piece that changes its split across the step makes a
    // pixel's difference jump. Cells share their corners, so that happens
    // at a couple of pixels; an extended source traces each cell from its
    // own point, and any cell's cut can move (4 pixels seen with the face).
    const int jumps = extended ? 6 : 2;
    for (size_t first = 0; first < all.size(); first += 3) {
      prism::ref::Tangents tangents = prism::ref::source_tangents;
      const size_t n = std::min<size_t>(3, all.size() - first);
      for (size_t k = 0; k < n; ++k) tangents[k] = all[first + k].tangent;
      const auto analytic = prism::ref::psf(sys, t, theta, tangents);
      for (size_t k = 0; k < n; ++k) {
        const Parameter& p = all[first + k];
        CAPTURE(p.name);
        auto plus = sys, minus = sys;
        p.move(plus, p.step);
        p.move(minus, -p.step);
        const auto bp = channel(prism::ref::psf(plus, t, theta), 0), bm = channel(prism::ref::psf(minus, t, theta), 0);
        std::vector<double> fd(bp.size());
        for (size_t i = 0; i < fd.size(); ++i) fd[i] = (bp[i] - bm[i]) / (2 * p.step);
        const auto got = channel(analytic, 1 + int(k));
        const double peak = prism::test::peak_abs(fd);
        REQUIRE(peak > 0);  // the parameter moves the image
        auto cmp = prism::test::compare(fd, got, {.abs = 2e-3 * peak});
        CHECK_MESSAGE(cmp.mismatches <= jumps, cmp.report("d b / d " + p.name + " (forward mode vs central differences)"));
      }
    }
  }
}

// Sources far off an f = 3 mm lenslet's axis: the prototype as built, its
// corner lenslet 41, seen from the other side of the array. Many of its rays
// leave the flat face near the critical angle, grazing, and would land metres
// off the sensor; a footprint corner there had a landing derivative of order
// 1 / cos^3 of the refracted angle, and the pixels' forward-mode derivatives
// by the lens's tilt and focal length were 2.5-14x their central differences
// (calibration stalled on them, docs/calibration.md). Such corners now count
// as stopped beyond a band around the sensor (shared::lands_by_sensor).
TEST_CASE("reference derivatives stay in their linear range where an f = 3 mm lenslet's rays leave near the critical angle") {
  const auto sys = prism::builtin_scene("prototype-as-built").optics;
  const int lens = 41;
  REQUIRE(sys.lenslets[lens].focal_mm == doctest::Approx(3.0).epsilon(0.05));
  prism::TraceSettings t = settings();
  t.rays_per_lenslet = 1024;
  const Parameter tilt{"lens tilt x (lenslet 41)", {Param::lens_tilt_x, lens}, 1e-3,
                       [=](auto& s, double h) { s.lenslets[lens].tilt_x_deg += h; }};
  const Parameter focal{"focal length (lenslet 41)", {Param::lens_focal, lens}, 1e-4,
                        [=](auto& s, double h) { s.lenslets[lens].focal_mm += h; }};
  for (const glm::dvec3 at : {glm::dvec3(10, -10, 30), glm::dvec3(-10, -10, 30), glm::dvec3(-10, 0, 30), glm::dvec3(-10, -10, 45)}) {
    const std::string source = position(at);
    CAPTURE(source);
    const auto analytic = prism::ref::psf(sys, t, at, {tilt.tangent, focal.tangent, {Param::source_x}}, lens);
    for (int k = 0; k < 2; ++k) {
      const Parameter& p = k == 0 ? tilt : focal;
      CAPTURE(p.name);
      auto plus = sys, minus = sys;
      p.move(plus, p.step);
      p.move(minus, -p.step);
      const auto bp = channel(prism::ref::psf(plus, t, at, prism::ref::source_tangents, lens), 0);
      const auto bm = channel(prism::ref::psf(minus, t, at, prism::ref::source_tangents, lens), 0);
      std::vector<double> fd(bp.size());
      for (size_t i = 0; i < fd.size(); ++i) fd[i] = (bp[i] - bm[i]) / (2 * p.step);
      const auto got = channel(analytic, 1 + k);
      // Over the image: a few pixels near the band's edge bend within the
      // step (about 1% of the sum at these steps); before the band the
      // forward derivatives were 2.5-14 times the differences' sum here.
      const auto [differ, sum] = l1_difference(got, fd);
      REQUIRE(sum > 0);  // the parameter moves the image
      CHECK_MESSAGE(differ <= 0.05 * sum, "sum |forward - central difference| = " << differ << " against sum |central difference| = "
                                                                                  << sum << " (5% allowed)");
    }
  }
}

TEST_CASE("reference derivatives: the default tangents are the source's, and every lenslet's equals the sum of each") {
  const auto t = settings();
  const auto sys = as_built(false);
  const auto plain = prism::ref::psf(sys, t, theta);
  const auto named = prism::ref::psf(sys, t, theta, {{{Param::source_x}, {Param::source_y}, {Param::source_depth}}});
  for (int c = 0; c < 4; ++c) {
    auto cmp = prism::test::compare(channel(plain, c), channel(named, c), {});
    CHECK_MESSAGE(cmp.ok(), cmp.report("channel " + std::to_string(c)));
  }
  const auto every = prism::ref::psf(sys, t, theta, {{{Param::lens_focal, -1}, {Param::lens_focal, 0}, {Param::lens_focal, 1}}});
  const auto third = prism::ref::psf(sys, t, theta, {{{Param::lens_focal, 2}, {Param::lens_focal, 2}, {Param::lens_focal, 2}}});
  const auto all = channel(every, 1), a = channel(every, 2), b = channel(every, 3), c = channel(third, 1);
  std::vector<double> sum(all.size());
  for (size_t i = 0; i < sum.size(); ++i) sum[i] = a[i] + b[i] + c[i];
  auto cmp = prism::test::compare(all, sum, {.abs = 1e-12 * prism::test::peak_abs(all)});
  CHECK_MESSAGE(cmp.ok(), cmp.report("d b / d every focal length vs the sum over lenslets"));
}

TEST_CASE("calibrate kernels: Vulkan derivatives by scene parameters equal the reference's, whole and lenslet by lenslet") {
  auto point = settings();
  point.splat = prism::Splat::point;
  point.estimator = prism::FisherEstimator::split;
  point.rays_per_lenslet = 400;
  // (extended source, face): the extended source once, for the blur term;
  // under the sanitizers without the face, whose reference code the
  // central-difference test above runs there (the reference's passes are
  // most of this test's time).
  std::vector<std::pair<bool, bool>> cases{{false, false}, {true, false}};
  if (!prism::test::under_sanitizer) cases.push_back({false, true});
  for (const auto& [extended, face] : cases)
    for (const auto& t : {settings(), point}) {
      const std::string splat = prism::to_string(t.splat);
      CAPTURE(extended);
      CAPTURE(face);
      CAPTURE(splat);
      const auto sys = as_built(face, extended);
      const auto all = extended ? extended_parameters() : parameters();
      prism::ForwardVulkan fw(prism::test::gpu(), sys, t, prism::ForwardVulkan::default_image_budget_bytes,
                              prism::ForwardVulkan::Derivatives::scene);
      for (size_t first = 0; first < all.size(); first += 3) {
        prism::Tangents tangents = prism::source_tangents;
        const size_t n = std::min<size_t>(3, all.size() - first);
        for (size_t k = 0; k < n; ++k) tangents[k] = all[first + k].tangent;
        // The whole image, and lenslet 1's alone (calibration's passes).
        for (int only : {-1, 1}) {
          CAPTURE(only);
          const auto want = prism::ref::psf(sys, t, theta, tangents, only);
          const auto got = fw.psf(theta, tangents, only);
          for (int c = 0; c <= int(n); ++c) {
            const std::string what = c == 0 ? std::string("b") : "d b / d " + all[first + size_t(c) - 1].name;
            const auto w = channel(want, c);
            const double peak = prism::test::peak_abs(w);
            if (c > 0 && only == 1 && all[first + size_t(c) - 1].tangent.lens == 1) REQUIRE(peak > 0);
            // Float against double, as the as-built test (test_as_built.cpp) allows.
            const double tol = c == 0 ? 1e-3 : 2e-3;
            auto cmp = prism::test::compare(w, channel(got, c), {.abs = tol * std::max(peak, 1e-30)});
            CHECK_MESSAGE(cmp.mismatches <= 8, cmp.report(what + " (Vulkan vs reference)"));
          }
        }
      }
    }
  prism::test::check_validation_clean();
}

TEST_CASE("calibrate kernels: a forward model moved to another scene traces it as one made for it") {
  const auto t = settings();
  const auto built = as_built(false);
  auto nominal = built;
  for (auto& l : nominal.lenslets) l.tilt_x_deg = l.tilt_y_deg = 0;
  nominal.sensor_pose = {};
  nominal.lens_to_sensor_mm -= 0.2;
  nominal.lenslets[0].focal_mm *= 1.02;
  prism::ForwardVulkan moved(prism::test::gpu(), nominal, t, prism::ForwardVulkan::default_image_budget_bytes,
                             prism::ForwardVulkan::Derivatives::scene);
  (void)moved.psf(theta);
  moved.set_scene(built);
  prism::ForwardVulkan fresh(prism::test::gpu(), built, t, prism::ForwardVulkan::default_image_budget_bytes,
                             prism::ForwardVulkan::Derivatives::scene);
  const prism::Tangents tangents{{{Param::lens_focal, 0}, {Param::lens_to_sensor}, {Param::sensor_tilt_x}}};
  const auto a = moved.psf(theta, tangents), b = fresh.psf(theta, tangents);
  for (int c = 0; c < 4; ++c) {
    // Equal but for the order of the kernels' atomic float sums.
    auto cmp = prism::test::compare(channel(a, c), channel(b, c), {.abs = 1e-5 * prism::test::peak_abs(channel(b, c))});
    CHECK_MESSAGE(cmp.ok(), cmp.report("channel " + std::to_string(c) + " (set_scene vs a fresh forward model)"));
  }
  // What set_scene cannot change is refused by name.
  auto fewer = built;
  fewer.lenslets.pop_back();
  CHECK_THROWS_WITH_AS(moved.set_scene(fewer), doctest::Contains("number of lenslets"), std::invalid_argument);
  auto face = built;
  face.effects.scintillator_refraction = true;
  CHECK_THROWS_WITH_AS(moved.set_scene(face), doctest::Contains("effects"), std::invalid_argument);
  // A plain forward model refuses scene tangents and a tilted scene.
  prism::ForwardVulkan plain(prism::test::gpu(), nominal, t);
  CHECK_THROWS_AS(plain.psf(theta, tangents), std::logic_error);
  CHECK_THROWS_WITH_AS(plain.set_scene(built), doctest::Contains("as built"), std::invalid_argument);
  prism::test::check_validation_clean();
}

// The band on the device (trace_corner, footprint_raster.glsl): lenslet 41 of
// the prototype as built from across the array (the case above) and from its
// own side, Vulkan against the reference.
TEST_CASE("calibrate kernels: corners beyond the sensor's band are stopped on the device as in the reference") {
  const auto sys = prism::builtin_scene("prototype-as-built").optics;
  const int lens = 41;
  prism::TraceSettings t = settings();
  t.rays_per_lenslet = 1024;
  const prism::Tangents tangents{{{Param::lens_tilt_x, lens}, {Param::lens_focal, lens}, {Param::lens_y, lens}}};
  prism::ForwardVulkan fw(prism::test::gpu(), sys, t, prism::ForwardVulkan::default_image_budget_bytes,
                          prism::ForwardVulkan::Derivatives::scene);
  for (const glm::dvec3 at : {glm::dvec3(10, -10, 30), glm::dvec3(10, 10, 30)}) {
    const std::string source = position(at);
    CAPTURE(source);
    const auto want = prism::ref::psf(sys, t, at, tangents, lens);
    const auto got = fw.psf(at, tangents, lens);
    const auto w0 = channel(want, 0);
    auto values = prism::test::compare(w0, channel(got, 0), {.abs = 1e-3 * prism::test::peak_abs(w0)});
    CHECK_MESSAGE(values.mismatches <= 8, values.report("b (Vulkan vs reference)"));
    // The derivatives over the image: this strong lens's steep pixels put
    // float 0.05-0.15% off double (L1) from its own side, 0.4-0.7% from
    // across the array, where cut pieces end at the band (tens to hundreds
    // of pixels beyond 2e-3 of the peak, a few of them by 0.2 of it).
    for (int c = 1; c < 4; ++c) {
      const auto [differ, sum] = l1_difference(channel(got, c), channel(want, c));
      REQUIRE(sum > 0);
      CHECK_MESSAGE(differ <= 0.01 * sum, "channel " << c << ": sum |Vulkan - reference| = " << differ
                                                     << " against sum |reference| = " << sum << " (1% allowed)");
    }
  }
  prism::test::check_validation_clean();
}
