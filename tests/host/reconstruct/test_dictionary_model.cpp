// The refinement's model from a dictionary alone (refine.h,
// make_dictionary_model): it is the stored PSF at a node, its gradient is the
// derivative of its values, and the refinement with it finds a source
// between the nodes and planes.
#include <unistd.h>

#include <cmath>
#include <filesystem>

#include "host/dictionary/build.h"
#include "host/reconstruct/refine.h"
#include "support.h"

namespace fs = std::filesystem;

namespace {

constexpr int binning = 16;

prism::Scene thin_row() {
  prism::Scene s;
  s.name = "thin row";
  s.optics = prism::test::small_system(prism::LensModel::thin);
  return s;
}

// x in {-2, 0, 2}, y in {-1, 1}, depth 10..30 every 2.5 mm: 54 PSFs of the
// thin-lens row, footprint splat at 4096 cells (smooth at 110 um).
struct ThinDictionary {
  std::string dir = (fs::temp_directory_path() / ("prism-dictmodel-test-" + std::to_string(::getpid()))).string();
  std::unique_ptr<prism::DictionaryReader> reader;
  ThinDictionary() {
    prism::DictionaryBuildOptions o;
    o.grid = {{-2.0, 0.0, 2.0}, {-1.0, 1.0}, {10.0, 12.5, 15.0, 17.5, 20.0, 22.5, 25.0, 27.5, 30.0}};
    o.base_binning = binning;
    o.rays_per_lenslet = 4096;
    o.splat = prism::Splat::footprint;
    prism::build_dictionary(prism::test::gpu(), thin_row(), dir + "/dict", o);
    reader = std::make_unique<prism::DictionaryReader>(dir + "/dict");
  }
  ~ThinDictionary() { fs::remove_all(dir); }
};
ThinDictionary& dictionary() {
  static ThinDictionary d;
  return d;
}

}  // namespace

TEST_CASE("dictionary model: the stored PSF at a node, and a gradient that is the derivative of its values") {
  auto& d = dictionary();
  auto model = prism::make_dictionary_model(*d.reader, 0);
  const auto& m = d.reader->manifest();

  // At a node every blend weight but one is zero and the cubic shift is zero:
  // the model is that PSF, normalised to the sensor.
  const glm::dvec3 node(0.0, 1.0, 17.5);
  auto at = model->render(std::span(&node, 1))[0];
  const auto stored = d.reader->read_level(m.grid.index(m.grid.nearest_node(node)), 0);
  double sum = 0;
  for (float v : stored.p) sum += v;
  REQUIRE(at.pixels.size() > 100);
  double worst = 0;
  for (const auto& px : at.pixels) worst = std::max(worst, std::abs(px.p - stored.p[px.index] / sum));
  CHECK(worst < 1e-9);

  // Between nodes and planes: central differences of P against dP/dtheta,
  // over the pixels that carry the light (the model is C1 in x, y; linear in
  // depth between planes, so the step stays inside one plane interval).
  const glm::dvec3 theta(0.7, -0.4, 21.3);
  auto centre = model->render(std::span(&theta, 1))[0];
  double pmax = 0;
  for (const auto& px : centre.pixels) pmax = std::max(pmax, px.p);
  const double h = 1e-4;
  for (int axis = 0; axis < 3; ++axis) {
    CAPTURE(axis);
    glm::dvec3 lo = theta, hi = theta;
    lo[axis] -= h;
    hi[axis] += h;
    auto a = model->render(std::span(&lo, 1))[0], b = model->render(std::span(&hi, 1))[0];
    double err = 0, scale = 0;
    for (const auto& px : centre.pixels) {
      if (px.p < 0.05 * pmax) continue;
      const auto* pa = a.find(px.index);
      const auto* pb = b.find(px.index);
      const double fd = ((pb ? pb->p : 0.0) - (pa ? pa->p : 0.0)) / (2 * h);
      err = std::max(err, std::abs(fd - px.g[axis]));
      scale = std::max(scale, std::abs(px.g[axis]));
    }
    REQUIRE(scale > 0);
    CHECK(err < 1e-3 * scale);
  }
}

TEST_CASE("dictionary model: the refinement finds a source between nodes and planes within a few CRLBs") {
  auto& d = dictionary();
  auto model = prism::make_dictionary_model(*d.reader, 0);
  const auto& m = d.reader->manifest();
  // Truth: the forward model, footprint at 16384 cells, other strata.
  prism::TraceSettings t = prism::refine_trace_settings(binning);
  t.rays_per_lenslet = 16384;
  t.stratification = 1;
  prism::ForwardTruth truth(prism::test::gpu(), thin_row(), t, 8);
  prism::RefineSettings rs;
  prism::Refiner refiner(*model, thin_row(), m.level_grid(0), rs);
  // Two sources half-way between planes and off the lateral nodes; starts
  // 0.5 mm away from each.
  for (const glm::dvec3 at : {glm::dvec3(0.8, 0.3, 18.75), glm::dvec3(-1.1, -0.6, 26.25)}) {
    CAPTURE(at.z);
    auto e = prism::test::sample_event(truth, {{at, 400.0}}, 5, 1);
    prism::ReconstructedVertex v;
    v.x_mm = at.x + 0.3, v.y_mm = at.y - 0.2, v.depth_mm = at.z + 0.5, v.alpha = 300;
    auto out = refiner.refine(e, {v});
    REQUIRE(out.size() == 1);
    CHECK(out[0].refined);
    const glm::dvec3 err = glm::dvec3(out[0].x_mm, out[0].y_mm, out[0].depth_mm) - at;
    INFO("error (mm) ", err.x, ", ", err.y, ", ", err.z, "; CRLB ", out[0].crlb_x_mm, ", ", out[0].crlb_y_mm, ", ",
         out[0].crlb_z_mm);
    // Blending two planes 2.5 mm apart is not the PSF between them: each
    // lenslet image is two images at the planes' positions rather than one
    // in between, which biases depth and, off axis, the lateral position
    // (measured here: 0.17 and 0.10 mm lateral, 0.38 and 0.29 mm in depth at
    // 400 photons, where the CRLB is 0.02 and 0.11-0.17 mm). The bounds are
    // a tenth and a quarter of the plane spacing.
    CHECK(std::hypot(err.x, err.y) < 0.25);
    CHECK(std::abs(err.z) < 0.625);
  }
  prism::test::check_validation_clean();
}
