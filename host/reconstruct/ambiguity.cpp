#include "host/reconstruct/ambiguity.h"

#include <algorithm>
#include <cmath>
#include <vector>

namespace prism {

namespace {

// D at the impostor's photons alpha1, with its gradient in alpha1 and the
// impostor's position, and the binary Fisher metric of the impostor's
// position (the curvature of D where the two patterns meet).
struct Terms {
  double kl = 0, variance = 0;
  double d_alpha = 0, dd_alpha = 0;  // dD/dalpha1 and its second derivative
  glm::dvec3 grad{0.0};              // dD/dtheta1
  glm::dmat3 metric{0.0};
};

Terms terms(const SourceImage& a, double alpha0, const SourceImage& b, double alpha1, double dark) {
  Terms t;
  const double q_dark = -std::expm1(-dark);
  // Every pixel where either image has light, in index order (both are sorted).
  size_t i = 0, j = 0;
  while (i < a.pixels.size() || j < b.pixels.size()) {
    const ModelPixel* pa = nullptr;
    const ModelPixel* pb = nullptr;
    if (j == b.pixels.size() || (i < a.pixels.size() && a.pixels[i].index < b.pixels[j].index)) pa = &a.pixels[i++];
    else if (i == a.pixels.size() || b.pixels[j].index < a.pixels[i].index) pb = &b.pixels[j++];
    else pa = &a.pixels[i++], pb = &b.pixels[j++];
    const double l0 = dark + (pa ? alpha0 * pa->p : 0.0), l1 = dark + (pb ? alpha1 * pb->p : 0.0);
    const double q0 = pa ? -std::expm1(-l0) : q_dark, q1 = pb ? -std::expm1(-l1) : q_dark;
    const double log_ratio = std::log(q1 / q0);  // log of the click probabilities, impostor over truth
    t.kl += -q0 * log_ratio + (1 - q0) * (l1 - l0);
    const double llr = log_ratio + (l1 - l0);  // a click's log-ratio less a non-click's (l0 - l1)
    t.variance += q0 * (1 - q0) * llr * llr;
    if (!pb) continue;
    const double slope = 1 - q0 / q1;  // dD/dlambda1
    const double w = std::exp(-l1) / q1;  // (1 - q1) / q1
    t.d_alpha += pb->p * slope;
    t.dd_alpha += pb->p * pb->p * q0 * w / q1;
    const glm::dvec3 dl = alpha1 * pb->g;  // dlambda1 / dtheta1
    t.grad += dl * slope;
    t.metric += glm::outerProduct(dl, dl) * w;
  }
  return t;
}

// The impostor's photons that minimise D (projected Newton, D is convex in
// alpha1: each term's second derivative is q0 (1 - q1) / q1^2 p^2 >= 0).
Terms fit_photons(const SourceImage& a, double alpha0, const SourceImage& b, double& alpha1, double dark) {
  Terms t = terms(a, alpha0, b, alpha1, dark);
  for (int it = 0; it < 50; ++it) {
    if (!(t.dd_alpha > 0)) break;
    double next = std::max(0.0, alpha1 - t.d_alpha / t.dd_alpha);
    Terms u = terms(a, alpha0, b, next, dark);
    while (u.kl > t.kl && std::abs(next - alpha1) > 1e-12 * std::max(1.0, alpha1)) {
      next = 0.5 * (next + alpha1);
      u = terms(a, alpha0, b, next, dark);
    }
    const bool done = std::abs(next - alpha1) <= 1e-9 * std::max(1.0, alpha1);
    if (u.kl <= t.kl) alpha1 = next, t = u;
    if (done) break;
  }
  return t;
}

double normal_tail(double z) { return 0.5 * std::erfc(z / std::sqrt(2.0)); }  // P(N(0,1) > z)

}  // namespace

Divergence divergence(const SourceImage& truth, double alpha0, const SourceImage& impostor, double& alpha1,
                      double dark_rate) {
  const Terms t = fit_photons(truth, alpha0, impostor, alpha1, dark_rate);
  return {t.kl, t.variance};
}

Ambiguity ambiguity(SourceModel& model, const Scene& scene, const glm::dvec3& theta, double photons,
                    const AmbiguitySettings& s) {
  const RefineBounds bounds = RefineBounds::of(scene);
  const double r = s.min_separation_mm;
  const glm::dvec3 source[] = {theta};
  const SourceImage truth = model.render(source)[0];
  const double alpha0 = std::isnan(photons) ? truth.photons : photons;
  Ambiguity out;
  if (!(alpha0 > 0) || truth.pixels.empty()) return out;  // no light on the sensor: nothing to tell apart

  auto inside = [&](const glm::dvec3& p) {
    return glm::all(glm::greaterThanEqual(p, bounds.lo)) && glm::all(glm::lessThanEqual(p, bounds.hi));
  };
  // Held at least r from the source: a point inside the ball goes to its surface.
  auto held = [&](glm::dvec3 p) {
    p = glm::clamp(p, bounds.lo, bounds.hi);
    const glm::dvec3 d = p - theta;
    const double n = glm::length(d);
    if (n < r && n > 0) p = glm::clamp(theta + d * (r / n), bounds.lo, bounds.hi);
    return p;
  };

  // Candidates: lattice aliases out to 2 pitches, and depth moves.
  std::vector<glm::dvec3> cand;
  const double scale = scene.optics.alias_scale(theta.z);
  for (const glm::dvec2& v : lattice_vectors(scene.optics, 2.0)) cand.push_back(theta + glm::dvec3(v * scale, 0.0));
  for (double k : {1.0, 2.0, 4.0})
    for (double sign : {-1.0, 1.0}) cand.push_back(theta + glm::dvec3(0, 0, sign * k * r));
  std::erase_if(cand, [&](const glm::dvec3& p) { return !inside(p) || glm::length(p - theta) < r; });
  if (cand.empty()) return out;

  struct Found {
    glm::dvec3 at;
    double alpha, kl, variance;
  };
  std::vector<Found> found;
  const auto images = model.render(cand);
  for (size_t k = 0; k < cand.size(); ++k) {
    double alpha1 = alpha0;
    const Terms t = fit_photons(truth, alpha0, images[k], alpha1, s.dark_rate);
    found.push_back({cand[k], alpha1, t.kl, t.variance});
  }
  std::sort(found.begin(), found.end(), [](const Found& a, const Found& b) { return a.kl < b.kl; });

  // The best few refined: Levenberg-Marquardt on D over the position, the
  // photons refitted at each trial (D is then a function of position alone,
  // and its gradient the partial one at the fitted photons).
  for (size_t k = 0; k < found.size() && k < size_t(std::max(0, s.refined)); ++k) {
    Found& f = found[k];
    const glm::dvec3 at[] = {f.at};
    SourceImage img = model.render(at)[0];
    Terms t = fit_photons(truth, alpha0, img, f.alpha, s.dark_rate);
    double mu = 1e-3;
    for (int step = 0; step < s.iterations && mu < 1e6; ++step) {
      glm::dmat3 A = t.metric;
      for (int c = 0; c < 3; ++c) A[c][c] *= 1 + mu;
      if (!(std::abs(glm::determinant(A)) > 0)) break;
      const glm::dvec3 trial = held(f.at - glm::inverse(A) * t.grad);
      if (glm::length(trial - f.at) < 1e-7) break;
      const glm::dvec3 tp[] = {trial};
      SourceImage ti = model.render(tp)[0];
      double ta = f.alpha;
      const Terms tt = fit_photons(truth, alpha0, ti, ta, s.dark_rate);
      if (tt.kl < t.kl) {
        const bool small = t.kl - tt.kl < 1e-4 * std::max(1.0, t.kl);
        f.at = trial, f.alpha = ta, img = std::move(ti), t = tt;
        mu = std::max(mu / 4, 1e-6);
        if (small) break;
      } else {
        mu *= 4;
      }
    }
    f.kl = t.kl;
    f.variance = t.variance;
  }
  std::sort(found.begin(), found.end(), [](const Found& a, const Found& b) { return a.kl < b.kl; });

  // Distinct impostors (refined ones may meet): the best within r / 2 stands for the rest.
  std::vector<Found> distinct;
  for (const Found& f : found) {
    bool seen = false;
    for (const Found& d : distinct) seen = seen || glm::length(d.at - f.at) < 0.5 * r;
    if (!seen) distinct.push_back(f);
  }
  out.kl = distinct.front().kl;
  out.impostor_mm = distinct.front().at;
  out.impostor_photons = distinct.front().alpha;
  out.impostors = int(distinct.size());
  double p = 0;
  for (const Found& f : distinct)
    p += f.variance > 0 ? normal_tail(f.kl / std::sqrt(f.variance)) : (f.kl > 0 ? 0.0 : 0.5);
  out.p_confusion = std::min(1.0, p);
  return out;
}

}  // namespace prism
