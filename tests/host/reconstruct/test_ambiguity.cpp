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

namespace {

// P(S >= 0) by drawing events: S, the log-likelihood ratio of impostor over
// truth, summed over every pixel of the 20 x 20 grid with clicks drawn from the truth.
double drawn_wins(const prism::SourceImage& a, double alpha0, const prism::SourceImage& b, double alpha1,
                  double dark, int draws) {
  std::vector<double> q0(400), click(400), no_click(400);
  for (uint32_t i = 0; i < 400; ++i) {
    const auto* pa = a.find(i);
    const auto* pb = b.find(i);
    const double l0 = dark + alpha0 * (pa ? pa->p : 0), l1 = dark + alpha1 * (pb ? pb->p : 0);
    q0[i] = -std::expm1(-l0);
    click[i] = std::log(-std::expm1(-l1) / q0[i]);
    no_click[i] = l0 - l1;
  }
  std::mt19937_64 rng(7);
  std::uniform_real_distribution<double> u(0, 1);
  int wins = 0;
  for (int n = 0; n < draws; ++n) {
    double s = 0;
    for (int i = 0; i < 400; ++i) s += u(rng) < q0[i] ? click[i] : no_click[i];
    wins += s >= 0;
  }
  return double(wins) / draws;
}

// The CRLB covariance of (x, y, depth) on the binary sensor, the photons a
// nuisance: the inverse of sum_i w_i grad(lambda_i) grad(lambda_i)^T over
// (x, y, depth, alpha), w = (1 - q) / q, its position block.
glm::dmat3 crlb_covariance(const prism::SourceImage& img, double alpha, double dark) {
  double f[4][4] = {};
  for (const auto& m : img.pixels) {
    const double l = dark + alpha * m.p, w = std::exp(-l) / -std::expm1(-l);
    const double d[4] = {alpha * m.g.x, alpha * m.g.y, alpha * m.g.z, m.p};
    for (int r = 0; r < 4; ++r)
      for (int c = 0; c < 4; ++c) f[r][c] += w * d[r] * d[c];
  }
  // Schur complement of the photons, then its inverse.
  glm::dmat3 schur;
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c) schur[c][r] = f[r][c] - f[r][3] * f[3][c] / f[3][3];
  return glm::inverse(schur);
}

}  // namespace

TEST_CASE("ambiguity: the probability that an impostor wins, saddlepoint against drawn events") {
  // Few photons and a small shift: a handful of pixels decide, S is skewed,
  // and the Gaussian Phi(-D / sqrt(V)) is off where the saddlepoint is not.
  const double dark = 1e-6;
  const auto a = spot(8.0, 9.0, 1.2);
  for (auto [shift, alpha] : {std::pair{1.0, 6.0}, std::pair{1.5, 8.0}, std::pair{2.5, 5.0}}) {
    CAPTURE(shift);
    CAPTURE(alpha);
    const auto b = spot(8.0 + shift, 9.0, 1.2);
    double alpha1 = alpha;
    const auto d = prism::divergence(a, alpha, b, alpha1, dark);
    const double drawn = drawn_wins(a, alpha, b, alpha1, dark, 200000);
    const double gaussian = 0.5 * std::erfc(d.kl / std::sqrt(2 * d.variance));
    CAPTURE(d.kl);
    CAPTURE(drawn);
    CAPTURE(gaussian);
    CAPTURE(d.p_wins);
    REQUIRE(drawn > 2e-3);  // enough drawn wins (> 400) for a 10% comparison
    CHECK(std::abs(d.p_wins / drawn - 1) < 0.1);
    // The skewed case: the Gaussian overstates the probability by 1.7x.
    if (shift == 2.5) CHECK(gaussian > 1.4 * drawn);
  }
}

namespace {

// A smooth stand-in for the scene's model: a dim Gaussian blob on an 80 x 80
// grid that moves with (x, y) and widens with depth. It moves slowly with x
// (1 px per mm, its width 6 px), so x is the one worst direction, and over
// the shifts tested its log-likelihood is close to quadratic; no pixel
// saturates.
class BlobModel : public prism::SourceModel {
  std::vector<prism::ModelPixel> render_raw(const glm::dvec3& t) override {
    const double kx = 1, ky = 20;  // pixels per mm
    const double cx = 40 + kx * t.x, cy = 40 + ky * t.y, s = 6 * std::exp((t.z - 5) / 3), ds_dz = s / 3;
    std::vector<prism::ModelPixel> out;
    for (uint32_t i = 0; i < 80 * 80; ++i) {
      const double dx = double(i % 80) - cx, dy = double(i / 80) - cy, r2 = dx * dx + dy * dy;
      const double b = std::exp(-r2 / (2 * s * s));
      if (b < 1e-9) continue;
      out.push_back({i, b, b * glm::dvec3(kx * dx / (s * s), ky * dy / (s * s), ds_dz * r2 / (s * s * s))});
    }
    return out;
  }
};

}  // namespace

TEST_CASE("ambiguity: where the likelihood is quadratic, p_confusion is the CRLB's Gaussian tail beyond r") {
  // A source whose closest impostors are no basins but the slopes of its
  // own, at a separation r of 2.5 CRLB standard deviations along the worst
  // direction: the estimate is r away when the error passes r, not r / 2
  // (the impostor held at r wins when it passes r / 2), ambiguity.h.
  const glm::dvec3 at(0.1, -0.1, 5.0);
  const double photons = 100, dark = prism::AmbiguitySettings{}.dark_rate;
  const auto scene = row_scene(false);  // its volume bounds the impostors
  BlobModel model;
  const glm::dvec3 source[] = {at};
  const auto truth = model.render(source)[0];
  const glm::dmat3 cov = crlb_covariance(truth, photons, dark);
  const double sigma = std::sqrt(cov[0][0]);  // x, the worst direction by construction
  REQUIRE(cov[0][0] > 4 * std::max(cov[1][1], cov[2][2]));
  prism::AmbiguitySettings settings;
  settings.min_separation_mm = 2.5 * sigma;
  const auto a = prism::ambiguity(model, scene, at, photons, settings);
  // P(|e| > r) for e ~ N(0, cov), drawn.
  const glm::dmat3 chol = [&] {
    glm::dmat3 l(0.0);  // lower triangular, l[c][r]
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c <= r; ++c) {
        double s = cov[c][r];
        for (int k = 0; k < c; ++k) s -= l[k][r] * l[k][c];
        l[c][r] = r == c ? std::sqrt(s) : s / l[c][c];
      }
    return l;
  }();
  std::mt19937_64 rng(11);
  std::normal_distribution<double> n01;
  int beyond = 0;
  const int draws = 400000;
  for (int n = 0; n < draws; ++n) {
    const glm::dvec3 e = chol * glm::dvec3(n01(rng), n01(rng), n01(rng));
    beyond += glm::length(e) > settings.min_separation_mm;
  }
  const double tail = double(beyond) / draws;
  CAPTURE(sigma);
  CAPTURE(a.kl);
  CAPTURE(a.impostors);
  CAPTURE(tail);
  CAPTURE(a.p_confusion);
  // 2 Phi(-2.5) = 0.0124 along the worst direction alone; counting the
  // impostors held at r would give about 2 Phi(-1.25) = 0.21.
  CHECK(std::abs(a.p_confusion / tail - 1) < 0.25);
}
