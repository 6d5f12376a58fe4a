// Levenberg-Marquardt with bounds on a Fisher-information model, the
// refinement's optimiser (refine.cpp), and the Cholesky solve it rests on.
// A header of its own so that its convergence can be tested on functions
// whose optimum is known (tests/host/reconstruct/test_levenberg_marquardt.cpp).
#pragma once

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <vector>

namespace prism {

// Cholesky solve of the n x n SPD system A x = b in place (b becomes x);
// false when A is not positive definite.
inline bool solve_spd(std::vector<double> A, std::vector<double>& b, size_t n) {
  for (size_t j = 0; j < n; ++j) {
    double d = A[j * n + j];
    for (size_t k = 0; k < j; ++k) d -= A[j * n + k] * A[j * n + k];
    if (!(d > 0)) return false;
    d = std::sqrt(d);
    A[j * n + j] = d;
    for (size_t i = j + 1; i < n; ++i) {
      double s = A[i * n + j];
      for (size_t k = 0; k < j; ++k) s -= A[i * n + k] * A[j * n + k];
      A[i * n + j] = s / d;
    }
  }
  for (size_t i = 0; i < n; ++i) {
    double s = b[i];
    for (size_t k = 0; k < i; ++k) s -= A[i * n + k] * b[k];
    b[i] = s / A[i * n + i];
  }
  for (size_t i = n; i-- > 0;) {
    double s = b[i];
    for (size_t k = i + 1; k < n; ++k) s -= A[k * n + i] * b[k];
    b[i] = s / A[i * n + i];
  }
  return true;
}

// Levenberg-Marquardt on the Fisher information from `f` (rendered), holding
// parameters on a bound that the gradient pushes outward. The damping scales
// the diagonal (mu = 1 halves a step along an uncorrelated axis); a rejected
// step raises it at once to at least kRejectedMu, because the binary
// likelihood of sharp-edged PSFs is far from quadratic beyond a fraction of
// a pixel (a click left outside a disc edge costs -log(dark)).
//
// Away from an optimum the Fisher information can also overstate the
// curvature along the step by a large factor: a start 0.3 mm off in depth
// near the face crawled at 0.005 mm a step, each gaining twice what the
// quadratic model predicted, and spent its whole budget. So every accepted
// step also measures the curvature along itself (from its gain, its slope
// and its Fisher curvature) and the next step is stretched by Fisher's over
// the measured one, at most 4x per step and kMaxStretch in all; a rejected
// stretched step is retried unstretched before the damping rises. This
// costs no render of its own.
//
// Stops when a step gains less than kGainNll: NLL differences that small
// mean nothing next to the 0.5 of one standard error. Returns the steps
// accepted.
//
// `Fit` (refine.cpp's is one) has n() parameters, param(i), set(i, v) and
// bounds lo(i) <= v <= hi(i); render() sets its nll at the parameters set;
// derivatives(grad, fisher) gives the NLL's gradient and the Fisher
// information (n x n, row-major) at the rendered parameters; unrendered() is
// a copy waiting for render().
template <class Fit>
int levenberg_marquardt(Fit& f, int max_steps) {
  constexpr double kRejectedMu = 0.1, kGainNll = 1e-3, kMaxMu = 1e4, kMaxStretch = 32;
  const size_t N = f.n();
  double mu = 1e-3, stretch = 1;
  int steps = 0;
  std::vector<double> grad, fisher;
  while (steps < max_steps) {
    f.derivatives(grad, fisher);
    std::vector<size_t> act;
    for (size_t i = 0; i < N; ++i) {
      const double v = f.param(i);
      const bool held = (v <= f.lo(i) && grad[i] > 0) || (v >= f.hi(i) && grad[i] < 0);
      if (!held && fisher[i * N + i] > 0) act.push_back(i);
    }
    if (act.empty()) break;
    const size_t m = act.size();
    bool accepted = false;
    while (!accepted && mu <= kMaxMu) {
      std::vector<double> A(m * m), step(m);
      for (size_t a = 0; a < m; ++a) {
        for (size_t b = 0; b < m; ++b) A[a * m + b] = fisher[act[a] * N + act[b]];
        A[a * m + a] *= 1.0 + mu;
        step[a] = -grad[act[a]];
      }
      if (!solve_spd(A, step, m)) {
        mu = std::max(mu * 4, kRejectedMu);
        continue;
      }
      Fit trial = f.unrendered();
      bool moved = false;
      for (size_t a = 0; a < m; ++a) {
        const size_t i = act[a];
        const double v = std::clamp(f.param(i) + stretch * step[a], f.lo(i), f.hi(i));
        moved = moved || v != f.param(i);
        trial.set(i, v);
      }
      if (!moved) return steps;
      trial.render();
      if (!(trial.nll < f.nll)) {
        if (stretch > 1) stretch = 1;
        else mu = std::max(mu * 4, kRejectedMu);
        continue;
      }
      // The step taken (t, clamped): its slope g.t, its Fisher curvature
      // t.F.t, and the curvature its gain implies, t.H.t = 2 (-g.t - gain).
      const double gain = f.nll - trial.nll;
      double slope = 0, fisher_curvature = 0;
      for (size_t a = 0; a < m; ++a) {
        const double ta = trial.param(act[a]) - f.param(act[a]);
        double ft = 0;
        for (size_t b = 0; b < m; ++b) ft += fisher[act[a] * N + act[b]] * (trial.param(act[b]) - f.param(act[b]));
        slope += grad[act[a]] * ta;
        fisher_curvature += ta * ft;
      }
      const double curvature = 2 * (-slope - gain);
      const double longer = curvature > 0 ? fisher_curvature / curvature : 4 * stretch;
      stretch = std::clamp(longer, 1.0, std::min(4 * stretch, kMaxStretch));
      f = std::move(trial);
      accepted = true;
      mu = std::max(mu / 4, 1e-6);
      ++steps;
      if (gain < kGainNll) return steps;
    }
    if (!accepted) break;
  }
  return steps;
}

}  // namespace prism
