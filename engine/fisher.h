// Fisher information and the Cramer-Rao lower bound, in double precision on the
// host (both backends reduce to this).
#pragma once
#include <array>
#include <string>

namespace prism {

// Symmetric 3x3 matrix over (x, y, depth), stored xx, xy, xz, yy, yz, zz.
using Sym3 = std::array<double, 6>;

struct FisherResult {
  double photons = 0;  // expected detected photons on the sensor
  Sym3 poisson{};      // sum_i grad b grad b^T / b
  Sym3 binary{};       // sum_i grad b grad b^T / (exp(b) - 1)
};

struct Crlb {
  double x_mm, y_mm, depth_mm, r3_mm;  // sqrt of the diagonal of I^-1, and of its trace
  bool identifiable;                   // false: I is singular (no light, or a direction it cannot see)
  std::string flag;                    // "ok", "no_photons" or "singular"
};

// Inverts I in double. A matrix whose smallest eigenvalue is below 1e-9 of its
// largest (relative to the float32 accuracy of the sums) is singular: the CRLB
// is +inf on every axis and the flag says why, never NaN or garbage.
Crlb crlb_from_fisher(const Sym3& fisher, double photons);

}  // namespace prism
