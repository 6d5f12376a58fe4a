// The device math of shaders/common, compiled as C++ (float), against the
// independent double reference, ray by ray: the kernels' own functions are
// checked without a Vulkan driver.
#include <cmath>

#include "engine/ref/forward_ref.h"
#include "engine/forward.h"
#include "support.h"

TEST_CASE("shared GLSL math compiled as C++ traces rays like the reference") {
  for (auto model : {prism::LensModel::thin, prism::LensModel::real})
    for (bool face : {false, true})
    for (bool built : {false, true}) {
      std::string model_name = prism::to_string(model);
      CAPTURE(model_name);
      CAPTURE(face);
      CAPTURE(built);
      auto sys = prism::test::small_system(model);
      sys.effects.scintillator_refraction = face;
      if (built) {  // every lenslet tilted its own way, the sensor moved and tilted
        for (size_t l = 0; l < sys.lenslets.size(); ++l)
          sys.lenslets[l].tilt_x_deg = 1.3 * std::sin(double(l) + 0.5), sys.lenslets[l].tilt_y_deg = -std::cos(double(l));
        sys.sensor_pose = {0.07, -0.11, 0.9, 0.6};
      }
      prism::TraceSettings t;
      t.rays_per_lenslet = 64;
      namespace sh = prism::shared;
      sh::TraceParams P{};
      P.lens_to_sensor_mm = float(sys.lens_to_sensor_mm);
      P.working_distance_mm = float(sys.working_distance_mm);
      P.photons_per_sr = float(t.photons_emitted / (4 * M_PI));
      P.scint_index = float(sys.effects.scintillator_index);
      P.sensor_offset_x_mm = float(sys.sensor_pose.offset_x_mm);
      P.sensor_offset_y_mm = float(sys.sensor_pose.offset_y_mm);
      P.sensor_tilt_x_rad = float(sys.sensor_pose.tilt_x_deg * M_PI / 180);
      P.sensor_tilt_y_rad = float(sys.sensor_pose.tilt_y_deg * M_PI / 180);
      glm::dvec3 theta{2.5, -1.5, 12.0};
      int compared = 0;
      for (size_t l = 0; l < sys.lenslets.size(); ++l) {
        sh::Lenslet lens = prism::device_lenslets(sys, t)[l];
        for (uint32_t s = 0; s < t.rays(); ++s) {
          auto r = prism::ref::trace_sample(sys, t, theta, l, s);
          auto h = sh::trace_sample(glm::vec3(theta), lens, uint32_t(l), s, P,
                                    model == prism::LensModel::real ? sh::LENS_REAL : sh::LENS_THIN, face, false, false, built);
          REQUIRE(h.ok == r.ok);
          // Grazing rays that land far off the sensor amplify float rounding; they carry no signal.
          if (!r.ok || std::abs(r.x_mm) > 0.5 * sys.sensor_width_mm() || std::abs(r.y_mm) > 0.5 * sys.sensor_height_mm())
            continue;
          CHECK(h.x_mm.v == doctest::Approx(r.x_mm).epsilon(1e-5).scale(10.0));
          CHECK(h.y_mm.v == doctest::Approx(r.y_mm).epsilon(1e-5).scale(10.0));
          CHECK(h.weight.v == doctest::Approx(r.weight).epsilon(1e-4));
          for (int a = 0; a < 3; ++a) {
            CHECK(h.x_mm.d[a] == doctest::Approx(r.dx[a]).epsilon(1e-3).scale(1.0));
            CHECK(h.weight.d[a] == doctest::Approx(r.dweight[a]).epsilon(1e-3).scale(r.weight));
          }
          ++compared;
        }
      }
      CHECK(compared > 200);
    }
}
