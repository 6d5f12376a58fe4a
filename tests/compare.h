// One way to compare a result with its reference, for every backend
// comparison (ncnn's testutil): element i agrees when
//   |got_i - expect_i| <= abs + rel * |expect_i|,
// and a failure names the first and the worst mismatch with their index,
// expected and actual values, so it explains itself.
//
//   auto c = prism::test::compare(expect, got, {.abs = 3e-4 * peak});
//   CHECK_MESSAGE(c.ok(), c.report("pixel values"));
#pragma once
#include <cmath>
#include <cstddef>
#include <limits>
#include <span>
#include <string>
#include <vector>

namespace prism::test {

struct Tolerance {
  double abs = 0;  // absolute allowance, in the values' units
  double rel = 0;  // allowance per unit of |expect|
};

struct Comparison {
  static constexpr size_t none = std::numeric_limits<size_t>::max();
  size_t count = 0;       // elements compared
  size_t mismatches = 0;  // elements outside the tolerance (NaN in either counts)
  Tolerance tolerance;
  // The first mismatch, and the worst element (largest excess over its allowance).
  size_t first = none, worst = none;
  double first_expect = 0, first_got = 0;
  double worst_expect = 0, worst_got = 0;
  double worst_ratio = 0;     // |got - expect| / allowance at the worst element (> 1: a mismatch)
  double max_abs_diff = 0;    // over all elements
  bool ok() const { return mismatches == 0 && count > 0; }
  // "pixel values: 3 of 4096 outside |d| <= 1e-6 + 1e-4 |expect|; first at 17: expected 0.5, got 0.51; ..."
  std::string report(const std::string& what) const;
};

// expect[i] against got[i]; sizes must match (a size mismatch is reported as
// one mismatch at index min(size)).
Comparison compare(std::span<const double> expect, std::span<const double> got, Tolerance tol);

// Any arithmetic element types, converted to double.
template <class A, class B>
Comparison compare_values(const A& expect, const B& got, Tolerance tol) {
  std::vector<double> e(std::begin(expect), std::end(expect)), g(std::begin(got), std::end(got));
  return compare(e, g, tol);
}

// The largest |value| (for tolerances relative to a peak).
double peak_abs(std::span<const double> values);

}  // namespace prism::test
