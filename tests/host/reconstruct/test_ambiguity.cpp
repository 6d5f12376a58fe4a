// The global ambiguity figure (host/reconstruct/ambiguity.h): the divergence
// against a dense evaluation written apart, its photon fit at a true minimum,
// and on the thin-lens seven-lenslet row the physics it exists for: identical
// lenslets make a lattice alias nearly indistinguishable, the prototype's
// focal lengths do not; the device's model and the double reference agree.
#include <cmath>
#include <random>

#include "host/reconstruct/ambiguity.h"
#include "support.h"

namespace {

constexpr int binning = 16;

prism::Scene row_scene(bool unifocal) {
  prism::Scene s;
  s.name = unifocal ? "unifocal row" : "thin row";
  s.optics = prism::test::small_system(prism::LensModel::thin);
  if (unifocal)
    for (auto& l : s.optics.lenslets) l.focal_mm = s.optics.lenslets[3].focal_mm;
  return s;
}

// An image on a 20 x 20 grid: a Gaussian spot at (cx, cy) with light >= 1e-6 of its peak, normalised to 1.
prism::SourceImage spot(double cx, double cy, double sigma) {
  prism::SourceImage img;
  img.photons = 1;
  double total = 0;
  for (uint32_t i = 0; i < 400; ++i) {
    const double dx = double(i % 20) - cx, dy = double(i / 20) - cy;
    const double v = std::exp(-(dx * dx + dy * dy) / (2 * sigma * sigma));
    if (v < 1e-6) continue;
    img.pixels.push_back({i, v, glm::dvec3(dx, dy, 0) * v / (sigma * sigma)});
    total += v;
  }
  for (auto& m : img.pixels) m.p /= total, m.g /= total;
  return img;
}

// D over every pixel of the grid, dark ones included, from the definition.
double dense_kl(const prism::SourceImage& a, double alpha0, const prism::SourceImage& b, double alpha1, double dark) {
  double d = 0;
  for (uint32_t i = 0; i < 400; ++i) {
    const auto* pa = a.find(i);
    const auto* pb = b.find(i);
    const double l0 = dark + alpha0 * (pa ? pa->p : 0), l1 = dark + alpha1 * (pb ? pb->p : 0);
    const double q0 = 1 - std::exp(-l0), q1 = 1 - std::exp(-l1);
    d += q0 * std::log(q0 / q1) + (1 - q0) * std::log((1 - q0) / (1 - q1));
  }
  return d;
}

double distance(const glm::dvec3& a, const glm::dvec3& b) { return glm::length(a - b); }

}  // namespace

TEST_CASE("ambiguity: the divergence of two click patterns, its photon fit, against the definition") {
  const double dark = 1e-6;
  const auto a = spot(8.0, 9.0, 1.5);
  double same = 30;
  const auto self = prism::divergence(a, 100, a, same, dark);
  CHECK(self.kl == doctest::Approx(0).epsilon(1e-9));
  CHECK(same == doctest::Approx(100).epsilon(1e-6));  // its own photons
  for (double shift : {0.3, 1.0, 3.0, 8.0}) {
    CAPTURE(shift);
    const auto b = spot(8.0 + shift, 9.0, 1.5);
    double alpha1 = 100;
    const auto d = prism::divergence(a, 100, b, alpha1, dark);
    CHECK(d.kl > 0);
    CHECK(d.variance > 0);
    CHECK(d.kl == doctest::Approx(dense_kl(a, 100, b, alpha1, dark)).epsilon(1e-9));
    // A minimum in the photons.
    CHECK(dense_kl(a, 100, b, alpha1 * 1.01, dark) >= d.kl);
    CHECK(dense_kl(a, 100, b, alpha1 * 0.99, dark) >= d.kl);
  }
  // Farther apart, easier to tell apart.
  double a1 = 100, a2 = 100;
  CHECK(prism::divergence(a, 100, spot(9.0, 9.0, 1.5), a1, dark).kl <
        prism::divergence(a, 100, spot(11.0, 9.0, 1.5), a2, dark).kl);
}

TEST_CASE("ambiguity on the thin row: identical lenslets make a near alias, the prototype's focal lengths do not") {
  // A source at depth 12: moved one lenslet pitch times (D + L) / L, every
  // image lands where its neighbour's was. With identical lenslets only the
  // ends of the row differ; with the prototype's three focal lengths each
  // image also changes its blur.
  const glm::dvec3 at(0.6, 0.3, 12.0);
  const auto settings = prism::refine_trace_settings(binning);
  auto uni = row_scene(true), multi = row_scene(false);
  auto uni_model = prism::make_scene_model(uni, settings, &prism::test::gpu());
  auto multi_model = prism::make_scene_model(multi, settings, &prism::test::gpu());
  const auto u = prism::ambiguity(*uni_model, uni, at, 100);
  const auto m = prism::ambiguity(*multi_model, multi, at, 100);
  CAPTURE(u.kl);
  CAPTURE(u.impostor_mm.x);
  CAPTURE(u.p_confusion);
  CAPTURE(m.kl);
  CAPTURE(m.impostor_mm.x);
  CAPTURE(m.p_confusion);
  CHECK(u.kl < 0.5 * m.kl);
  CHECK(u.p_confusion > 10 * m.p_confusion);
  // The unifocal row's impostor is a lattice alias along the row.
  const double site = prism::defaults::lenslet_pitch_mm * uni.optics.alias_scale(at.z);
  CHECK(std::abs(std::abs(u.impostor_mm.x - at.x) - site) < 0.3 * site);
  CHECK(std::abs(u.impostor_mm.z - at.z) < 2.0);
  CHECK(distance(u.impostor_mm, at) >= 2.0 - 1e-9);
  CHECK(m.p_confusion >= 0);
  CHECK(u.p_confusion <= 1);
  prism::test::check_validation_clean();
}

TEST_CASE("ambiguity: more photons, larger divergence, rarer confusion, and the device = the double reference") {
  const glm::dvec3 at(-0.4, 0.2, 20.0);
  auto uni = row_scene(true);
  const auto settings = prism::refine_trace_settings(binning);
  auto device = prism::make_scene_model(uni, settings, &prism::test::gpu());
  auto reference = prism::make_scene_model(uni, settings, nullptr);
  std::vector<prism::Ambiguity> by_photons;
  for (double photons : {50.0, 100.0, 200.0}) by_photons.push_back(prism::ambiguity(*device, uni, at, photons));
  for (size_t i = 1; i < by_photons.size(); ++i) {
    CAPTURE(i);
    CHECK(by_photons[i].kl > 1.5 * by_photons[i - 1].kl);  // about proportional to the photons
    CHECK(by_photons[i].kl < 2.5 * by_photons[i - 1].kl);
    CHECK(by_photons[i].p_confusion <= by_photons[i - 1].p_confusion);
  }
  const auto ref = prism::ambiguity(*reference, uni, at, 100);
  const auto dev = by_photons[1];
  CAPTURE(ref.kl);
  CAPTURE(dev.kl);
  CHECK(dev.kl == doctest::Approx(ref.kl).epsilon(0.03));
  CHECK(distance(dev.impostor_mm, ref.impostor_mm) < 0.1);
  CHECK(dev.p_confusion == doctest::Approx(ref.p_confusion).epsilon(0.1));
  prism::test::check_validation_clean();
}
