// Dual numbers in double for the CPU references: a value and its gradient
// over theta = (x, y, depth), by operator overloading. Written apart from the
// device's dual.glsl so that a reference and a kernel cannot share a bug.
#pragma once
#include <cmath>

#include <glm/glm.hpp>

namespace prism::ref {

struct D {
  double v = 0;
  glm::dvec3 d{0.0};
  D() = default;
  D(double value) : v(value) {}  // NOLINT: constants convert implicitly
  D(double value, glm::dvec3 grad) : v(value), d(grad) {}
};
inline D operator+(D a, D b) { return {a.v + b.v, a.d + b.d}; }
inline D operator-(D a, D b) { return {a.v - b.v, a.d - b.d}; }
inline D operator-(D a) { return {-a.v, -a.d}; }
inline D operator*(D a, D b) { return {a.v * b.v, a.d * b.v + b.d * a.v}; }
inline D operator/(D a, D b) { return {a.v / b.v, (a.d * b.v - b.d * a.v) / (b.v * b.v)}; }
inline D sqrt(D a) {
  double s = std::sqrt(a.v);
  return {s, a.d / (2.0 * s)};
}
inline D atan(D a) { return {std::atan(a.v), a.d / (1.0 + a.v * a.v)}; }
inline D acos(D a) { return {std::acos(a.v), -a.d / std::sqrt(1.0 - a.v * a.v)}; }
inline D sin(D a) { return {std::sin(a.v), a.d * std::cos(a.v)}; }
inline D cos(D a) { return {std::cos(a.v), -a.d * std::sin(a.v)}; }
inline D abs(D a) { return a.v < 0 ? -a : a; }

}  // namespace prism::ref
