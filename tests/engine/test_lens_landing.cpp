// The real plano-convex model against landing points traced by an independent
// optics library (optiland): ../shared/reference/lens-landing-optiland.csv.
// Both backends must land every ray within 1e-4 mm and clip the same rays.
#include <cmath>
#include <fstream>
#include <map>
#include <tuple>

#include "engine/forward.h"
#include "engine/ref/forward_ref.h"
#include "support.h"

namespace {

struct LandingRow {
  double f, ct, R;
  bool flat_toward_source;
  glm::dvec3 src, dir;
  double hit_x, hit_y;
  bool ok;
  int line;
};

std::vector<LandingRow> read_landings() {
  std::string path = std::string(PRISM_SHARED_DIR) + "/reference/lens-landing-optiland.csv";
  std::ifstream in(path);
  REQUIRE_MESSAGE(in.good(), "cannot read " << path);
  std::vector<LandingRow> rows;
  std::string line;
  int n = 0;
  while (std::getline(in, line)) {
    ++n;
    if (line.empty() || line[0] == '#' || line.rfind("f_mm", 0) == 0) continue;
    std::vector<std::string> c = prism::test::csv_fields(line);
    REQUIRE_MESSAGE(c.size() == 13, path << ":" << n << ": expected 13 columns");
    REQUIRE_MESSAGE((c[2] == "toward_sensor" || c[2] == "toward_source"), path << ":" << n << ": flat_faces?");
    LandingRow r{std::stod(c[0]), std::stod(c[1]), std::stod(c[3]), c[2] == "toward_source", {std::stod(c[4]), std::stod(c[5]), std::stod(c[6])},
                 {std::stod(c[7]), std::stod(c[8]), std::stod(c[9])}, std::stod(c[10]), std::stod(c[11]),
                 c[12] == "1", n};
    rows.push_back(r);
  }
  return rows;
}

// One 3 mm lenslet on the axis with the CSV's focal length and centre thickness.
prism::OpticalSystem lens_of(const LandingRow& r) {
  prism::OpticalSystem s;
  s.lens_model = prism::LensModel::real;
  s.glass_index = 1.5168;
  s.lenslets = {{0.0, 0.0, 3.0, r.f}};
  s.curved_toward_sensor = r.flat_toward_source;
  s.edge_thickness_mm = r.ct - s.sag_mm(0);
  s.lens_to_sensor_mm = 18.5;
  return s;
}

}  // namespace

TEST_CASE("real lens lands rays where optiland does (CPU reference)") {
  auto rows = read_landings();
  REQUIRE(rows.size() > 100);
  int clipped = 0;
  for (const auto& r : rows) {
    auto sys = lens_of(r);
    CHECK(std::abs(sys.curvature_radius_mm(0) - r.R) < 1e-5);
    auto hit = prism::ref::trace_ray(sys, 0, r.src, r.dir);
    CAPTURE(r.line);
    REQUIRE(hit.has_value() == r.ok);
    if (!r.ok) {
      ++clipped;
      continue;
    }
    CHECK(std::abs(hit->x - r.hit_x) < 1e-4);
    CHECK(std::abs(hit->y - r.hit_y) < 1e-4);
  }
  CHECK(clipped > 0);  // the file does exercise clipping
}

TEST_CASE("real lens lands rays where optiland does (Vulkan)") {
  auto rows = read_landings();
  // Group rows by lens so each lens is one dispatch.
  std::map<std::tuple<double, double, bool>, std::vector<const LandingRow*>> by_lens;
  for (const auto& r : rows) by_lens[{r.f, r.ct, r.flat_toward_source}].push_back(&r);
  for (const auto& [key, group] : by_lens) {
    auto sys = lens_of(*group.front());
    std::vector<glm::vec3> pairs;
    for (const auto* r : group) {
      pairs.push_back(glm::vec3(r->src));
      pairs.push_back(glm::vec3(r->dir));
    }
    auto hits = prism::landing_points_vulkan(prism::test::gpu(), sys, 0, pairs);
    REQUIRE(hits.size() == group.size());
    for (size_t i = 0; i < group.size(); ++i) {
      CAPTURE(group[i]->line);
      REQUIRE((hits[i].z == 1.0f) == group[i]->ok);
      if (!group[i]->ok) continue;
      CHECK(std::abs(hits[i].x - group[i]->hit_x) < 1e-4);
      CHECK(std::abs(hits[i].y - group[i]->hit_y) < 1e-4);
    }
  }
  prism::test::check_validation_clean();
}
