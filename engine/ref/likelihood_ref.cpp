#include "engine/ref/likelihood_ref.h"

#include <algorithm>
#include <cmath>

namespace prism::ref {

double log_click(double lambda) { return std::log(-std::expm1(-lambda)); }

double click_curvature(double lambda) {
  // Below 1e-150 the square underflows; 1 / lambda^2 there is >= 1e300, still
  // finite. sinh overflows to inf for huge lambda: curvature 0, as it should.
  double s = std::sinh(0.5 * std::max(lambda, 1e-150));
  return 1.0 / (4.0 * s * s);
}

double click_weight(double lambda) { return 1.0 / -std::expm1(-lambda); }

namespace {

// min over [0, alpha_max] of linear alpha + offset - log_p - n log(alpha + ratio / n):
// convex, its minimum where the slope is 0 (linear only when n = 0).
double convex_bound_min(double n, double linear, double offset, double log_p, double ratio, double alpha_max) {
  if (n == 0) return offset + std::min(0.0, alpha_max * linear);
  const double a = linear > 0 ? std::clamp(n / linear - ratio / n, 0.0, alpha_max) : alpha_max;
  return offset + a * linear - log_p - n * std::log(a + ratio / n);
}

}  // namespace

double nll_lower_bound(std::span<const double> p, double s, std::span<const double> background, double alpha_max) {
  // Terms free of alpha exactly. Over the reached clicks, curved:
  // h_c >= -log(lambda) = -log(P_c) - log(alpha + b_c / P_c) and
  // sum_c log(alpha + r_c) <= n log(alpha + mean r) (log is concave); or,
  // for those the background dominates at alpha0, h_c above its tangent there
  // (h_c is convex). The larger of the two bounds.
  const double alpha0 = s > 0 ? std::min(std::max(double(background.size()), 1.0) / s, alpha_max) : alpha_max;
  double fixed = 0, n = 0, q = 0, log_p = 0, ratio = 0;
  double curved = 0, curved_log_p = 0, curved_ratio = 0, tangent_slope = 0, tangent_offset = 0;
  for (size_t c = 0; c < background.size(); ++c) {
    const double b = background[c];
    fixed -= b;
    if (p[c] <= 0) {
      fixed -= log_click(b);
      continue;
    }
    n += 1, q += p[c], log_p += std::log(p[c]), ratio += b / p[c];
    if (b <= alpha0 * p[c]) {
      curved += 1, curved_log_p += std::log(p[c]), curved_ratio += b / p[c];
    } else {
      const double lambda0 = b + alpha0 * p[c];
      const double slope = -p[c] / std::expm1(lambda0);  // h'(alpha0)
      tangent_slope += slope;
      tangent_offset += -log_click(lambda0) - alpha0 * slope;
    }
  }
  const double off_clicks = s - q;  // the mass the clicks do not see
  const double all_curved = convex_bound_min(n, off_clicks, fixed, log_p, ratio, alpha_max);
  if (curved == n) return all_curved;
  return std::max(all_curved, convex_bound_min(curved, off_clicks + tangent_slope, fixed + tangent_offset,
                                               curved_log_p, curved_ratio, alpha_max));
}

double fit_weights(std::span<const std::vector<double>* const> p, std::span<const double> s,
                   std::span<const double> background, std::vector<double>& alpha, int max_iterations,
                   double alpha_max) {
  const size_t K = alpha.size(), C = background.size();
  std::vector<double> lam(C), trial(K), grad(K), dir(K);
  auto eval = [&](const std::vector<double>& a) {
    double f = 0;
    for (size_t k = 0; k < K; ++k) f += a[k] * s[k];
    for (size_t c = 0; c < C; ++c) {
      double l = background[c];
      for (size_t k = 0; k < K; ++k) l += a[k] * (*p[k])[c];
      lam[c] = l;
      f -= l + log_click(l);
    }
    return f;
  };
  for (double& a : alpha) a = std::clamp(a, 0.0, alpha_max);
  double f = eval(alpha);
  std::vector<double> H(K * K);
  for (int it = 0; it < max_iterations; ++it) {
    std::fill(H.begin(), H.end(), 0.0);
    for (size_t k = 0; k < K; ++k) grad[k] = s[k];
    for (size_t c = 0; c < C; ++c) {
      double w = click_weight(lam[c]), h = click_curvature(lam[c]);
      for (size_t k = 0; k < K; ++k) {
        double pk = (*p[k])[c];
        if (pk == 0) continue;
        grad[k] -= pk * w;
        for (size_t j = 0; j < K; ++j) H[k * K + j] += pk * (*p[j])[c] * h;
      }
    }
    // Free variables: not held at a bound by the sign of their gradient.
    std::vector<size_t> free;
    for (size_t k = 0; k < K; ++k)
      if (!(alpha[k] <= 0 && grad[k] >= 0) && !(alpha[k] >= alpha_max && grad[k] <= 0)) free.push_back(k);
    if (free.empty()) break;
    // Solve H_FF d = -g_F by Gaussian elimination (K <= 8) with a relative ridge.
    const size_t F = free.size();
    std::vector<double> A(F * F), b(F);
    double diag_max = 0;
    for (size_t i = 0; i < F; ++i) diag_max = std::max(diag_max, H[free[i] * K + free[i]]);
    for (size_t i = 0; i < F; ++i) {
      for (size_t j = 0; j < F; ++j) A[i * F + j] = H[free[i] * K + free[j]];
      A[i * F + i] += 1e-9 * diag_max + 1e-300;
      b[i] = -grad[free[i]];
    }
    for (size_t i = 0; i < F; ++i) {
      size_t piv = i;
      for (size_t r = i + 1; r < F; ++r)
        if (std::abs(A[r * F + i]) > std::abs(A[piv * F + i])) piv = r;
      for (size_t j = 0; j < F; ++j) std::swap(A[i * F + j], A[piv * F + j]);
      std::swap(b[i], b[piv]);
      for (size_t r = i + 1; r < F; ++r) {
        double m = A[r * F + i] / A[i * F + i];
        for (size_t j = i; j < F; ++j) A[r * F + j] -= m * A[i * F + j];
        b[r] -= m * b[i];
      }
    }
    std::fill(dir.begin(), dir.end(), 0.0);
    for (size_t i = F; i-- > 0;) {
      double v = b[i];
      for (size_t j = i + 1; j < F; ++j) v -= A[i * F + j] * dir[free[j]];
      dir[free[i]] = v / A[i * F + i];
    }
    // Backtracking along the projected path (Armijo).
    bool accepted = false;
    double ft = f, step_max = 0;
    std::vector<double> lam_accepted;
    for (double t = 1; t > 1e-12; t *= 0.5) {
      double decrease = 0;
      step_max = 0;
      for (size_t k = 0; k < K; ++k) {
        trial[k] = std::clamp(alpha[k] + t * dir[k], 0.0, alpha_max);
        decrease += grad[k] * (trial[k] - alpha[k]);
        step_max = std::max(step_max, std::abs(trial[k] - alpha[k]) / (1 + alpha[k]));
      }
      if (step_max == 0) break;
      ft = eval(trial);
      if (ft <= f + 1e-4 * decrease) {
        accepted = true;
        break;
      }
    }
    if (!accepted) {
      eval(alpha);  // lam back to the current point
      break;
    }
    bool converged = f - ft <= 1e-12 * (1 + std::abs(f)) && step_max < 1e-9;
    alpha = trial;
    f = ft;
    if (converged) break;
  }
  return f;
}

double initial_alpha(std::span<const double> p, double s, double alpha_max) {
  double reached = double(std::count_if(p.begin(), p.end(), [](double v) { return v > 0; }));
  return std::clamp(std::max(reached, 1.0) / std::max(s, 1e-3), 1e-3, alpha_max);
}

}  // namespace prism::ref
