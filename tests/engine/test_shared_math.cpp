// The device math of shaders/common, compiled as C++ (float), against the
// independent double reference, ray by ray: the kernels' own functions are
// checked without a Vulkan driver, with derivatives by the source's position
// and by the scene's parameters (the calibrate kernels' seeds).
#include <cmath>

#include "engine/ref/forward_ref.h"
#include "engine/forward.h"
#include "support.h"

namespace {

using prism::SceneParam;
namespace sh = prism::shared;

// Thin or real lenses, with the scintillator face or not, nominal or as
// built (every lenslet tilted its own way, the sensor moved and tilted).
prism::OpticalSystem system_of(prism::LensModel model, bool face, bool built) {
  auto sys = prism::test::small_system(model);
  sys.effects.scintillator_refraction = face;
  if (built) {
    for (size_t l = 0; l < sys.lenslets.size(); ++l)
      sys.lenslets[l].tilt_x_deg = 1.3 * std::sin(double(l) + 0.5), sys.lenslets[l].tilt_y_deg = -std::cos(double(l));
    sys.sensor_pose = {0.07, -0.11, 0.9, 0.6};
  }
  return sys;
}

// Every ray of every lenslet from theta, traced by the shared math and the
// reference with derivatives by `tangents`; returns how many were compared.
int compare_rays(const prism::OpticalSystem& sys, bool built, const prism::Tangents& tangents) {
  prism::TraceSettings t;
  t.rays_per_lenslet = 64;
  sh::TraceParams P{};
  P.lens_to_sensor_mm = float(sys.lens_to_sensor_mm);
  P.working_distance_mm = float(sys.working_distance_mm);
  P.photons_per_sr = float(t.photons_emitted / (4 * M_PI));
  P.scint_index = float(sys.effects.scintillator_index);
  P.sensor_offset_x_mm = float(sys.sensor_pose.offset_x_mm);
  P.sensor_offset_y_mm = float(sys.sensor_pose.offset_y_mm);
  P.sensor_tilt_x_rad = float(sys.sensor_pose.tilt_x_deg * M_PI / 180);
  P.sensor_tilt_y_rad = float(sys.sensor_pose.tilt_y_deg * M_PI / 180);
  P.source_sigma_mm = float(sys.effects.source_sigma_mm);
  sh::set_tangents(P, tangents);
  const int model = sys.lens_model == prism::LensModel::real ? sh::LENS_REAL : sh::LENS_THIN;
  const bool face = sys.effects.scintillator_refraction;
  const glm::dvec3 theta{2.5, -1.5, 12.0};
  const auto lenses = prism::device_lenslets(sys, t);
  int compared = 0;
  for (size_t l = 0; l < sys.lenslets.size(); ++l) {
    const uint32_t strata = lenses[l].strata;
    const double area = M_PI * lenses[l].radius_mm * lenses[l].radius_mm / double(strata * strata);
    for (uint32_t s = 0; s < t.rays(); ++s) {
      const glm::dvec2 u(sh::aperture_sample(uint32_t(l), s, strata, 0));
      const glm::dvec3 per_sigma = prism::ref::source_offset_per_sigma(sys, uint32_t(l), s, 0);
      auto r = prism::ref::trace_point(sys, t, theta, per_sigma, l, u, area, tangents);
      auto h = sh::trace_sample(glm::vec3(theta), lenses[l], uint32_t(l), s, P, model, face, false,
                                sys.effects.source_extent, built);
      REQUIRE(h.ok == r.ok);
      // Grazing rays that land far off the sensor amplify float rounding; they carry no signal.
      if (!r.ok || std::abs(r.x_mm) > 0.5 * sys.sensor_width_mm() || std::abs(r.y_mm) > 0.5 * sys.sensor_height_mm())
        continue;
      CAPTURE(l);
      CAPTURE(s);
      CHECK(h.x_mm.v == doctest::Approx(r.x_mm).epsilon(1e-5).scale(10.0));
      CHECK(h.y_mm.v == doctest::Approx(r.y_mm).epsilon(1e-5).scale(10.0));
      CHECK(h.weight.v == doctest::Approx(r.weight).epsilon(1e-4));
      for (int a = 0; a < 3; ++a) {
        CAPTURE(a);
        CHECK(h.x_mm.d[a] == doctest::Approx(r.dx[a]).epsilon(1e-3).scale(1.0));
        CHECK(h.y_mm.d[a] == doctest::Approx(r.dy[a]).epsilon(1e-3).scale(1.0));
        CHECK(h.weight.d[a] == doctest::Approx(r.dweight[a]).epsilon(1e-3).scale(r.weight));
      }
      ++compared;
    }
  }
  return compared;
}

}  // namespace

TEST_CASE("shared GLSL math compiled as C++ traces rays like the reference") {
  for (auto model : {prism::LensModel::thin, prism::LensModel::real})
    for (bool face : {false, true})
      for (bool built : {false, true}) {
        std::string model_name = prism::to_string(model);
        CAPTURE(model_name);
        CAPTURE(face);
        CAPTURE(built);
        CHECK(compare_rays(system_of(model, face, built), built, prism::source_tangents) > 200);
      }
}

TEST_CASE("shared GLSL math: derivatives by scene parameters are the reference's, ray by ray") {
  // Each lenslet parameter named for lenslet 3 (the others' rays must have
  // none of it) and for every lenslet's own; each global one.
  const prism::Tangents sets[] = {
      {{{SceneParam::lens_x, 3}, {SceneParam::lens_y, 3}, {SceneParam::lens_focal, 3}}},
      {{{SceneParam::lens_tilt_x, 3}, {SceneParam::lens_tilt_y, 3}, {SceneParam::lens_focal}}},
      {{{SceneParam::lens_x}, {SceneParam::lens_tilt_y}, {SceneParam::lens_to_sensor}}},
      {{{SceneParam::working_distance}, {SceneParam::sensor_offset_x}, {SceneParam::sensor_offset_y}}},
      {{{SceneParam::sensor_tilt_x}, {SceneParam::sensor_tilt_y}, {SceneParam::source_depth}}}};
  for (auto model : {prism::LensModel::thin, prism::LensModel::real})
    for (bool face : {false, true})
      for (size_t k = 0; k < std::size(sets); ++k) {
        std::string model_name = prism::to_string(model);
        CAPTURE(model_name);
        CAPTURE(face);
        CAPTURE(k);
        // Derivatives by tilts need the as-built path, as the calibrate kernels always take.
        CHECK(compare_rays(system_of(model, face, true), true, sets[k]) > 200);
      }
  // The blur term: an extended source's sigma, beside the source's position.
  for (auto model : {prism::LensModel::thin, prism::LensModel::real}) {
    auto extended = system_of(model, true, true);
    extended.effects.source_extent = true;
    extended.effects.source_sigma_mm = 0.4;
    CHECK(compare_rays(extended, true, {{{SceneParam::source_sigma}, {SceneParam::source_x}, {SceneParam::lens_x, 2}}}) >
          200);
  }
  // Flipped lenses move their curved face's centre with the focal length.
  auto flipped = system_of(prism::LensModel::real, false, true);
  flipped.curved_toward_sensor = true;
  CHECK(compare_rays(flipped, true, sets[0]) > 200);
}
