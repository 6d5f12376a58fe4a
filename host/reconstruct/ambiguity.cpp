#include "host/reconstruct/ambiguity.h"

#include <algorithm>
#include <cmath>
#include <numbers>
#include <vector>

namespace prism {

namespace {

// Every pixel where either image has light, in index order (both are
// sorted), with the two rates and click probabilities; `pb` (the impostor's
// pixel) is null where only the truth has light.
template <class Visit>
void for_each_pixel(const SourceImage& a, double alpha0, const SourceImage& b, double alpha1, double dark,
                    Visit&& visit) {
  const double q_dark = -std::expm1(-dark);
  size_t i = 0, j = 0;
  while (i < a.pixels.size() || j < b.pixels.size()) {
    const ModelPixel* pa = nullptr;
    const ModelPixel* pb = nullptr;
    if (j == b.pixels.size() || (i < a.pixels.size() && a.pixels[i].index < b.pixels[j].index)) pa = &a.pixels[i++];
    else if (i == a.pixels.size() || b.pixels[j].index < a.pixels[i].index) pb = &b.pixels[j++];
    else pa = &a.pixels[i++], pb = &b.pixels[j++];
    const double l0 = dark + (pa ? alpha0 * pa->p : 0.0), l1 = dark + (pb ? alpha1 * pb->p : 0.0);
    const double q0 = pa ? -std::expm1(-l0) : q_dark, q1 = pb ? -std::expm1(-l1) : q_dark;
    visit(l0, l1, q0, q1, pb);
  }
}

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
  for_each_pixel(a, alpha0, b, alpha1, dark, [&](double l0, double l1, double q0, double q1, const ModelPixel* pb) {
    const double log_ratio = std::log(q1 / q0);  // log of the click probabilities, impostor over truth
    t.kl += -q0 * log_ratio + (1 - q0) * (l1 - l0);
    const double llr = log_ratio + (l1 - l0);  // a click's log-ratio less a non-click's (l0 - l1)
    t.variance += q0 * (1 - q0) * llr * llr;
    if (!pb) return;
    const double slope = 1 - q0 / q1;     // dD/dlambda1
    const double w = std::exp(-l1) / q1;  // (1 - q1) / q1
    t.d_alpha += pb->p * slope;
    t.dd_alpha += pb->p * pb->p * q0 * w / q1;
    const glm::dvec3 dl = alpha1 * pb->g;  // dlambda1 / dtheta1
    t.grad += dl * slope;
    t.metric += glm::outerProduct(dl, dl) * w;
  });
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

// The source's position covariance on the binary sensor (its CRLB), the
// photons a nuisance: the inverse of the Schur complement of the photons in
// the Fisher information sum_i w_i grad(lambda_i) grad(lambda_i)^T over
// (x, y, depth, alpha), w = (1 - q) / q. Zero where it is singular.
glm::dmat3 position_covariance(const SourceImage& img, double alpha, double dark) {
  glm::dmat3 pp(0.0);
  glm::dvec3 pa(0.0);
  double aa = 0;
  for (const ModelPixel& m : img.pixels) {
    const double l = dark + alpha * m.p, w = std::exp(-l) / -std::expm1(-l);
    const glm::dvec3 d = alpha * m.g;
    pp += glm::outerProduct(d, d) * w;
    pa += d * (m.p * w);
    aa += m.p * m.p * w;
  }
  const glm::dmat3 schur = aa > 0 ? pp - glm::outerProduct(pa, pa) / aa : pp;
  return std::abs(glm::determinant(schur)) > 0 ? glm::inverse(schur) : glm::dmat3(0.0);
}

double normal_tail(double z) { return 0.5 * std::erfc(z / std::sqrt(2.0)); }  // P(N(0,1) > z)

// P(S >= 0) for the event's log-likelihood ratio S = sum_i X_i, impostor
// over truth, each pixel contributing X_i = log(q1 / q0) with probability q0
// (a click) and log((1 - q1) / (1 - q0)) = l0 - l1 otherwise, the clicks
// drawn from the truth. The Lugannani-Rice saddlepoint approximation on the
// cumulant generating function K(s) = sum_i log(q0 e^(s a_i) + (1 - q0)
// e^(s b_i)): K(0) = K(1) = 0, K'(0) = -D, and the saddlepoint s* in (0, 1)
// where K' = 0 gives the Chernoff exponent -K(s*). Unlike the Gaussian
// Phi(-D / sqrt(V)) its relative error stays small far into the tail, where
// the few pixels that separate two patterns make S skewed.
double impostor_wins(const SourceImage& a, double alpha0, const SourceImage& b, double alpha1, double dark) {
  struct Pixel {
    double q0, click, no_click;
  };
  std::vector<Pixel> px;
  double kl = 0;
  for_each_pixel(a, alpha0, b, alpha1, dark, [&](double l0, double l1, double q0, double q1, const ModelPixel*) {
    px.push_back({q0, std::log(q1 / q0), l0 - l1});
    kl += -q0 * px.back().click - (1 - q0) * px.back().no_click;
  });
  if (!(kl > 0)) return 0.5;  // the impostor images as the truth does
  // K, K' and K'' at s (each pixel's tilted click probability pi).
  struct Cumulants {
    double k = 0, k1 = 0, k2 = 0;
  };
  auto cumulants = [&](double s) {
    Cumulants c;
    for (const Pixel& p : px) {
      const double x = s * p.click, y = s * p.no_click, m = std::max(x, y);
      const double ec = p.q0 * std::exp(x - m), en = (1 - p.q0) * std::exp(y - m);
      const double pi = ec / (ec + en), d = p.click - p.no_click;
      c.k += m + std::log(ec + en);
      c.k1 += pi * p.click + (1 - pi) * p.no_click;
      c.k2 += pi * (1 - pi) * d * d;
    }
    return c;
  };
  // K' rises from -D at 0 to the reverse divergence at 1: Newton kept in a bracket.
  double lo = 0, hi = 1, s = 0.5;
  Cumulants c = cumulants(s);
  for (int it = 0; it < 100 && hi - lo > 1e-12; ++it) {
    (c.k1 < 0 ? lo : hi) = s;
    double next = c.k2 > 0 ? s - c.k1 / c.k2 : 0.5 * (lo + hi);
    if (!(next > lo && next < hi)) next = 0.5 * (lo + hi);
    if (std::abs(next - s) < 1e-14) break;
    s = next;
    c = cumulants(s);
  }
  const double w = std::sqrt(std::max(0.0, -2 * c.k)), u = s * std::sqrt(c.k2);
  // Near the mean (w -> 0) the two terms cancel; the normal tail is the limit there.
  if (w < 1e-3 || u < 1e-3) return normal_tail(w);
  const double phi = std::exp(-0.5 * w * w) / std::sqrt(2 * std::numbers::pi);
  return std::clamp(normal_tail(w) + phi * (1 / u - 1 / w), 0.0, 1.0);
}

}  // namespace

Divergence divergence(const SourceImage& truth, double alpha0, const SourceImage& impostor, double& alpha1,
                      double dark_rate) {
  const Terms t = fit_photons(truth, alpha0, impostor, alpha1, dark_rate);
  return {t.kl, t.variance, impostor_wins(truth, alpha0, impostor, alpha1, dark_rate)};
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
  // Held at least `radius` from the source: a point inside the ball goes to its surface.
  auto held = [&](glm::dvec3 p, double radius) {
    p = glm::clamp(p, bounds.lo, bounds.hi);
    const glm::dvec3 d = p - theta;
    const double n = glm::length(d);
    if (n < radius && n > 0) p = glm::clamp(theta + d * (radius / n), bounds.lo, bounds.hi);
    return p;
  };

  // Candidates: lattice aliases out to 2 pitches, depth moves, and r along
  // the direction the CRLB is worst in (the slope of the truth's own basin
  // that the landing rule below needs; near the depth axis for most sources).
  struct Candidate {
    glm::dvec3 at;
    bool alias;  // a lattice alias, not a move along the weakest direction or in depth
  };
  std::vector<Candidate> cand;
  const glm::dvec3 weakest = largest_eigenvector(position_covariance(truth, alpha0, s.dark_rate));
  for (double sign : {-1.0, 1.0}) cand.push_back({theta + sign * r * weakest, false});
  const double scale = scene.optics.alias_scale(theta.z);
  for (const glm::dvec2& v : lattice_vectors(scene.optics, 2.0))
    cand.push_back({theta + glm::dvec3(v * scale, 0.0), true});
  for (double k : {1.0, 2.0, 4.0})
    for (double sign : {-1.0, 1.0}) cand.push_back({theta + glm::dvec3(0, 0, sign * k * r), false});
  std::erase_if(cand, [&](const Candidate& c) { return !inside(c.at) || glm::length(c.at - theta) < r; });
  if (cand.empty()) return out;

  struct Found {
    glm::dvec3 at;
    double alpha, kl;
    SourceImage image;
    bool alias = false;  // as Candidate's
    bool refined = false;
  };
  std::vector<Found> found;
  std::vector<glm::dvec3> at;
  for (const Candidate& c : cand) at.push_back(c.at);
  const auto images = model.render(at);
  for (size_t k = 0; k < cand.size(); ++k) {
    double alpha1 = alpha0;
    const Terms t = fit_photons(truth, alpha0, images[k], alpha1, s.dark_rate);
    found.push_back({cand[k].at, alpha1, t.kl, images[k], cand[k].alias});
  }
  auto by_kl = [](const Found& a, const Found& b) { return a.kl < b.kl; };
  std::sort(found.begin(), found.end(), by_kl);

  // Levenberg-Marquardt on D over the impostor's position, held `radius`
  // from the source, the photons refitted at each trial (D is then a
  // function of position alone, and its gradient the partial one at the
  // fitted photons).
  auto refine = [&](Found& f, double radius) {
    f.at = held(f.at, radius);
    const glm::dvec3 at[] = {f.at};
    SourceImage img = model.render(at)[0];
    Terms t = fit_photons(truth, alpha0, img, f.alpha, s.dark_rate);
    double mu = 1e-3;
    for (int step = 0; step < s.iterations && mu < 1e6; ++step) {
      // Held on the sphere with D falling inwards: the step in its tangent
      // plane (a step projected back onto the sphere gains little, and the
      // descent would stop short of the sphere's best point).
      glm::dmat3 M = t.metric;
      glm::dvec3 g = t.grad;
      const glm::dvec3 out_of = f.at - theta;
      if (glm::length(out_of) < radius * (1 + 1e-6) && glm::dot(g, out_of) > 0) {
        const glm::dvec3 n = glm::normalize(out_of);
        const glm::dmat3 P = glm::dmat3(1.0) - glm::outerProduct(n, n);
        M = P * M * P + glm::outerProduct(n, n) * (M[0][0] + M[1][1] + M[2][2]);
        g = P * g;
      }
      if (!(std::abs(glm::determinant(M)) > 0)) break;
      // Converged when the Newton step would gain less than a thousandth of
      // a nat (p_confusion, about e^-D, then moves by 0.1%), or 1e-4 of D
      // where D is large and p_confusion negligible. (Stopping on a small
      // achieved gain instead left D a damped step short: two runs differing
      // in the renders' last bits reported optima 0.5 nats apart.)
      if (0.5 * glm::dot(g, glm::inverse(M) * g) < std::max(1e-3, 1e-4 * t.kl)) break;
      glm::dmat3 A = M;
      for (int c = 0; c < 3; ++c) A[c][c] *= 1 + mu;
      // At most r / 2 a step: far from the truth the metric (the curvature
      // where the two patterns meet) can ask for long steps across D's
      // pixel-scale ridges, and where they land would hang on the renders'
      // last bits.
      glm::dvec3 delta = -(glm::inverse(A) * g);
      if (glm::length(delta) > 0.5 * r) delta *= 0.5 * r / glm::length(delta);
      const glm::dvec3 trial = held(f.at + delta, radius);
      if (glm::length(trial - f.at) < 1e-7) break;
      const glm::dvec3 tp[] = {trial};
      SourceImage ti = model.render(tp)[0];
      double ta = f.alpha;
      const Terms tt = fit_photons(truth, alpha0, ti, ta, s.dark_rate);
      if (tt.kl < t.kl) {
        f.at = trial, f.alpha = ta, img = std::move(ti), t = tt;
        mu = std::max(mu / 4, 1e-6);
      } else {
        mu *= 4;
      }
    }
    f.kl = t.kl;
    f.image = std::move(img);
    f.refined = true;
  };
  for (size_t k = 0; k < found.size() && k < size_t(std::max(0, s.refined)); ++k) refine(found[k], r);
  std::sort(found.begin(), found.end(), by_kl);
  out.kl = found.front().kl;
  out.impostor_mm = found.front().at;
  out.impostor_photons = found.front().alpha;

  // Where an event that prefers an impostor puts its estimate (ambiguity.h):
  // an impostor in a basin of its own, off the sphere of radius r, is where
  // the estimate lands; one held on the sphere is the slope of the truth's
  // own basin, and the estimate lands about halfway, so the impostor whose
  // win lands it r away is the one 2r away, refined on that sphere. Moves
  // along the weakest direction or in depth that were not refined are
  // dropped: they probe the truth's own slope (its refined point stands for
  // them) or basins less likely than the refined ones; unrefined lattice
  // aliases count as they are (a hex array has six alike).
  auto on_sphere = [&](const Found& f) { return glm::length(f.at - theta) < r * (1 + 1e-6); };
  std::vector<Found> landing;
  for (Found f : found) {
    if (!f.refined && !f.alias) continue;
    if (!on_sphere(f)) {
      landing.push_back(f);
    } else {
      f.at = theta + 2.0 * (f.at - theta);
      refine(f, 2 * r);
      landing.push_back(f);
    }
  }
  std::sort(landing.begin(), landing.end(), by_kl);

  // Distinct impostors (refined ones may meet): the best within r / 2 stands for the rest.
  std::vector<Found> distinct;
  for (const Found& f : landing) {
    bool seen = false;
    for (const Found& d : distinct) seen = seen || glm::length(d.at - f.at) < 0.5 * r;
    if (!seen) distinct.push_back(f);
  }
  out.impostors = int(distinct.size());
  if (distinct.empty()) return out;
  double p = 0;
  for (const Found& f : distinct) p += impostor_wins(truth, alpha0, f.image, f.alpha, s.dark_rate);
  out.p_confusion = std::min(1.0, p);
  return out;
}

}  // namespace prism
