#include "engine/fisher.h"

#include <algorithm>
#include <cmath>
#include <limits>

namespace prism {

namespace {
// Eigenvalues of a symmetric 3x3 matrix (trigonometric method), ascending.
std::array<double, 3> eigenvalues(const Sym3& a) {
  double p1 = a[1] * a[1] + a[2] * a[2] + a[4] * a[4];
  double q = (a[0] + a[3] + a[5]) / 3.0;
  double p2 = (a[0] - q) * (a[0] - q) + (a[3] - q) * (a[3] - q) + (a[5] - q) * (a[5] - q) + 2.0 * p1;
  double p = std::sqrt(p2 / 6.0);
  if (p == 0) return {q, q, q};
  double b0 = (a[0] - q) / p, b1 = a[1] / p, b2 = a[2] / p, b3 = (a[3] - q) / p, b4 = a[4] / p, b5 = (a[5] - q) / p;
  double det_b = b0 * (b3 * b5 - b4 * b4) - b1 * (b1 * b5 - b4 * b2) + b2 * (b1 * b4 - b3 * b2);
  double r = std::clamp(det_b / 2.0, -1.0, 1.0);
  double phi = std::acos(r) / 3.0;
  double e1 = q + 2.0 * p * std::cos(phi);
  double e3 = q + 2.0 * p * std::cos(phi + 2.0 * M_PI / 3.0);
  double e2 = 3.0 * q - e1 - e3;
  std::array<double, 3> e{e3, e2, e1};
  std::sort(e.begin(), e.end());
  return e;
}
}  // namespace

Crlb crlb_from_fisher(const Sym3& I, double photons) {
  const double inf = std::numeric_limits<double>::infinity();
  Crlb c{inf, inf, inf, inf, false, "singular"};
  bool finite = std::all_of(I.begin(), I.end(), [](double v) { return std::isfinite(v); });
  if (!(photons > 0) || !finite) {
    c.flag = photons > 0 ? "singular" : "no_photons";
    return c;
  }
  auto e = eigenvalues(I);
  if (!(e[2] > 0) || e[0] <= 1e-9 * e[2]) return c;
  // Inverse by cofactors.
  double a = I[0], b = I[1], d = I[2], e_ = I[3], f = I[4], g = I[5];
  double c00 = e_ * g - f * f, c01 = -(b * g - f * d), c02 = b * f - e_ * d;
  double det = a * c00 + b * c01 + d * c02;
  double inv_xx = c00 / det;
  double inv_yy = (a * g - d * d) / det;
  double inv_zz = (a * e_ - b * b) / det;
  if (!(inv_xx > 0 && inv_yy > 0 && inv_zz > 0)) return c;
  c.x_mm = std::sqrt(inv_xx);
  c.y_mm = std::sqrt(inv_yy);
  c.depth_mm = std::sqrt(inv_zz);
  c.r3_mm = std::sqrt(inv_xx + inv_yy + inv_zz);
  c.identifiable = true;
  c.flag = "ok";
  return c;
}

}  // namespace prism
