// The refinement's optimiser (host/reconstruct/levenberg_marquardt.h) on
// functions whose optimum is known: an exact quadratic (the Fisher
// information is the curvature: one step), a pseudo-Huber valley whose
// curvature far from the optimum is much less than the Fisher information
// says (the binary likelihood of sharp-edged images away from the truth),
// and optima beyond a bound.
#include <cmath>

#include <doctest/doctest.h>

#include "host/reconstruct/levenberg_marquardt.h"

namespace {

// NLL = sum_i w_i * (sqrt(1 + (x_i - t_i)^2 / s_i^2) - 1) * s_i^2 (pseudo-
// Huber: quadratic within s_i of t_i, linear beyond) or, with s_i = 0, the
// quadratic w_i (x_i - t_i)^2 / 2. The "Fisher information" given to the
// optimiser is diag(w_i): the curvature at the optimum, as the expected
// information at the truth would be.
struct Valley {
  std::vector<double> x, t, w, s, lo_, hi_;
  double nll = 0;
  int* renders = nullptr;

  size_t n() const { return x.size(); }
  double param(size_t i) const { return x[i]; }
  void set(size_t i, double v) { x[i] = v; }
  double lo(size_t i) const { return lo_[i]; }
  double hi(size_t i) const { return hi_[i]; }
  Valley unrendered() const {
    Valley v = *this;
    v.nll = INFINITY;
    return v;
  }
  double term(size_t i) const {
    const double d = x[i] - t[i];
    return s[i] > 0 ? w[i] * s[i] * s[i] * (std::sqrt(1 + d * d / (s[i] * s[i])) - 1) : 0.5 * w[i] * d * d;
  }
  void render() {
    ++*renders;
    nll = 0;
    for (size_t i = 0; i < n(); ++i) nll += term(i);
  }
  void derivatives(std::vector<double>& grad, std::vector<double>& fisher) const {
    grad.assign(n(), 0.0);
    fisher.assign(n() * n(), 0.0);
    for (size_t i = 0; i < n(); ++i) {
      const double d = x[i] - t[i];
      grad[i] = s[i] > 0 ? w[i] * d / std::sqrt(1 + d * d / (s[i] * s[i])) : w[i] * d;
      fisher[i * n() + i] = w[i];
    }
  }
};

Valley valley(std::vector<double> start, std::vector<double> truth, std::vector<double> scale, int& renders) {
  const size_t n = start.size();
  Valley v{start, truth, std::vector<double>(n, 50.0), scale, std::vector<double>(n, -1e3), std::vector<double>(n, 1e3)};
  v.renders = &renders;
  v.render();
  return v;
}

}  // namespace

TEST_CASE("Levenberg-Marquardt: an exact quadratic in one step, no extrapolation") {
  int renders = 0;
  Valley v = valley({3.0, -2.0}, {0.5, 0.25}, {0.0, 0.0}, renders);
  const int steps = prism::levenberg_marquardt(v, 20);
  CHECK(v.x[0] == doctest::Approx(0.5).epsilon(1e-3));
  CHECK(v.x[1] == doctest::Approx(0.25).epsilon(1e-3));
  CAPTURE(renders);
  CHECK(steps <= 3);
  // The start, then per step one render (the damping 1e-3 leaves a quadratic
  // gaining about what it predicts: rho ~ 1, nothing to extrapolate).
  CHECK(renders <= 1 + steps);
}

TEST_CASE("Levenberg-Marquardt: curvature far below the Fisher information's, the steps lengthen") {
  // 100 widths from the optimum the Fisher step is 1 / 100 of the distance:
  // without extrapolation 20 steps would end ~80 widths short.
  int renders = 0;
  Valley v = valley({100.0, -60.0}, {0.0, 0.0}, {1.0, 1.0}, renders);
  const int steps = prism::levenberg_marquardt(v, 20);
  CAPTURE(steps);
  CAPTURE(renders);
  CAPTURE(v.x[0]);
  CAPTURE(v.x[1]);
  CHECK(std::abs(v.x[0]) < 1e-2);
  CHECK(std::abs(v.x[1]) < 1e-2);
  CHECK(renders < 60);
}

TEST_CASE("Levenberg-Marquardt: an optimum beyond a bound ends on it, extrapolations clamped") {
  int renders = 0;
  Valley v = valley({100.0, 5.0}, {-50.0, 0.0}, {1.0, 0.0}, renders);
  v.lo_[0] = 20.0;
  const int steps = prism::levenberg_marquardt(v, 20);
  CAPTURE(steps);
  CHECK(v.x[0] == 20.0);  // held on the bound the gradient pushes against
  CHECK(v.x[1] == doctest::Approx(0.0).scale(1.0).epsilon(1e-3));
}
