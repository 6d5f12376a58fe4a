// Scenes: the built-ins follow DESIGN.md, and a bad scene names its field.
#include <cmath>
#include <fstream>
#include <map>

#include "host/scene/scene.h"
#include "support.h"

namespace {
std::string error_of(const std::string& json_text) {
  try {
    prism::parse_scene(nlohmann::json::parse(json_text), "test.json");
  } catch (const prism::SceneError& e) {
    return e.what();
  }
  return "";
}
}  // namespace

TEST_CASE("prototype: 42 lenslets, six of each focal length, centroid on the axis, neighbours differ") {
  auto s = prism::builtin_scene("prototype");
  const auto& ls = s.optics.lenslets;
  REQUIRE(ls.size() == 42);
  std::map<double, int> count;
  double cx = 0, cy = 0;
  for (const auto& l : ls) {
    ++count[l.focal_mm];
    cx += l.x_mm;
    cy += l.y_mm;
  }
  CHECK(count.size() == 7);
  for (const auto& [f, n] : count) CHECK(n == 6);
  CHECK(std::abs(cx) < 1e-9);
  CHECK(std::abs(cy) < 1e-9);
  for (size_t i = 0; i < ls.size(); ++i)
    for (size_t j = 0; j < i; ++j) {
      double d = std::hypot(ls[i].x_mm - ls[j].x_mm, ls[i].y_mm - ls[j].y_mm);
      CHECK(d >= 4.0 - 1e-9);                                  // 4 mm pitch, no overlap
      if (d < 4.0 + 1e-9) CHECK(ls[i].focal_mm != ls[j].focal_mm);  // hex neighbours differ
    }
  CHECK(s.optics.lens_model == prism::LensModel::real);
}

TEST_CASE("single-lens references: one thin lens with the array's total aperture") {
  auto s = prism::builtin_scene("single-f9");
  REQUIRE(s.optics.lenslets.size() == 1);
  CHECK(s.optics.lenslets[0].diameter_mm == doctest::Approx(3.0 * std::sqrt(42.0)));
  CHECK(s.optics.lens_model == prism::LensModel::thin);
  // A plano-convex lens that wide cannot reach f = 9 mm: the real model is refused.
  s.optics.lens_model = prism::LensModel::real;
  CHECK_THROWS_WITH_AS(prism::validate(s.optics), doctest::Contains("cannot have f = 9"), std::invalid_argument);
}

TEST_CASE("every built-in scene round-trips through JSON") {
  for (const auto& name : prism::builtin_scene_names()) {
    auto s = prism::builtin_scene(name);
    auto back = prism::parse_scene(prism::to_json(s), name);
    CHECK(back.optics.lenslets.size() == s.optics.lenslets.size());
    CHECK(back.optics.lens_model == s.optics.lens_model);
    CHECK(back.optics.lenslets.back().focal_mm == s.optics.lenslets.back().focal_mm);
    // Everything, the as-built's tilts and sensor pose included.
    CHECK_MESSAGE(prism::to_json(back) == prism::to_json(s), name);
  }
}

TEST_CASE("prototype-as-built is the prototype moved by synthetic_as_built's known amounts") {
  const auto nominal = prism::builtin_scene("prototype"), built = prism::builtin_scene("prototype-as-built");
  REQUIRE(built.optics.lenslets.size() == nominal.optics.lenslets.size());
  // Lenslet 1 (k = 2): the doc's formulas, by hand.
  const auto &l = built.optics.lenslets[1], &n = nominal.optics.lenslets[1];
  CHECK(l.x_mm - n.x_mm == doctest::Approx(0.04 * std::sin(3.4)));
  CHECK(l.y_mm - n.y_mm == doctest::Approx(0.03 * std::cos(4.6)));
  CHECK(l.focal_mm / n.focal_mm == doctest::Approx(1 + 0.02 * std::sin(2.2)));
  CHECK(l.tilt_x_deg == doctest::Approx(0.5 * std::sin(3.6)));
  CHECK(l.tilt_y_deg == doctest::Approx(-0.4 * std::cos(1.4)));
  CHECK(built.optics.lens_to_sensor_mm - nominal.optics.lens_to_sensor_mm == doctest::Approx(0.15));
  CHECK(built.optics.working_distance_mm - nominal.optics.working_distance_mm == doctest::Approx(-0.1));
  CHECK(built.optics.sensor_pose.tilt_x_deg == 0.3);
  CHECK(built.optics.as_built());
  CHECK(built.volume.depth_max_mm == nominal.volume.depth_max_mm);
}

TEST_CASE("a bad scene names the file, the field and why") {
  CHECK(error_of(R"({"lenslets": [{"x_mm": 0, "y_mm": 0, "focal_mm": -3}]})").find("lenslets[0].focal_mm: must be > 0") !=
        std::string::npos);
  CHECK(error_of(R"({"lenslets": [{"x_mm": 0, "y_mm": 0, "focal_mm": "three"}]})").find("lenslets[0].focal_mm: must be a number") !=
        std::string::npos);
  CHECK(error_of(R"({"base": "prototype", "sensor": {"pixel_um": 0}})").find("sensor.pixel_um") != std::string::npos);
  CHECK(error_of(R"({"base": "prototype", "lens_modle": "thin"})").find("lens_modle: unknown field") != std::string::npos);
  CHECK(error_of(R"({"base": "prototype", "effects": ["glow"]})").find("unknown effect 'glow'") != std::string::npos);
  CHECK(error_of(R"({"lenslets": [{"x_mm": 0, "y_mm": 0, "focal_mm": 9}, {"x_mm": 1, "y_mm": 0, "focal_mm": 9}]})")
            .find("lenslets[1]: overlaps lenslets[0]") != std::string::npos);
  CHECK(error_of(R"({"lenslets": [{"x_mm": 400, "y_mm": 0, "focal_mm": 9}]})").find("off the sensor") != std::string::npos);
  CHECK(error_of(R"({"base": "prototype", "volume": {"depth_mm": [50, 0]}})").find("volume.depth_mm") != std::string::npos);
  CHECK(error_of(R"({"base": "prototype"})").empty());
}

TEST_CASE("a scene file that is not JSON gives its line") {
  std::string path = "bad-scene-test.json";
  {
    std::ofstream out(path);
    out << "{\n  \"base\": \"prototype\",\n  \"lens_model\": thin\n}\n";
  }
  CHECK_THROWS_WITH_AS(prism::load_scene(path), doctest::Contains("bad-scene-test.json:3"), prism::SceneError);
  {
    std::ofstream out(path);  // a number beyond a double: nlohmann's out_of_range, not a parse error
    out << "{\n  \"base\": \"prototype\",\n  \"volume\": {\"depth_mm\": [0, 5e400]}\n}\n";
  }
  CHECK_THROWS_WITH_AS(prism::load_scene(path), doctest::Contains("bad-scene-test.json:3: not valid JSON (number overflow"),
                       prism::SceneError);
  std::remove(path.c_str());
  CHECK_THROWS_WITH_AS(prism::load_scene("protoype"), doctest::Contains("not a built-in"), prism::SceneError);
}

TEST_CASE("scene effects parse with their parameters") {
  auto s = prism::parse_scene(nlohmann::json::parse(R"({"base": "prototype", "effects": [
      "scintillator_refraction", {"name": "holder_vignetting", "bore_mm": 3.0},
      {"name": "detection_efficiency", "value": 0.4}]})"), "fx.json");
  CHECK(s.optics.effects.scintillator_refraction);
  CHECK(s.optics.effects.scintillator_index == doctest::Approx(1.58));
  CHECK(s.optics.effects.holder_vignetting);
  CHECK(s.optics.effects.holder_bore_mm == 3.0);
  CHECK(s.optics.effects.detection_efficiency == 0.4);
}
