#include "compare.h"

#include <algorithm>
#include <sstream>

namespace prism::test {

Comparison compare(std::span<const double> expect, std::span<const double> got, Tolerance tol) {
  Comparison c;
  c.tolerance = tol;
  const size_t n = std::min(expect.size(), got.size());
  c.count = n;
  for (size_t i = 0; i < n; ++i) {
    const double e = expect[i], g = got[i], d = std::abs(g - e);
    const double allowed = tol.abs + tol.rel * std::abs(e);
    // NaN anywhere is a mismatch with an infinite excess; equal infinities agree.
    double ratio;
    if (std::isnan(e) || std::isnan(g))
      ratio = INFINITY;
    else if (e == g)
      ratio = 0;
    else
      ratio = allowed > 0 ? d / allowed : INFINITY;
    if (std::isfinite(d)) c.max_abs_diff = std::max(c.max_abs_diff, d);
    if (ratio > c.worst_ratio || c.worst == Comparison::none)
      c.worst_ratio = ratio, c.worst = i, c.worst_expect = e, c.worst_got = g;
    if (ratio > 1) {
      ++c.mismatches;
      if (c.first == Comparison::none) c.first = i, c.first_expect = e, c.first_got = g;
    }
  }
  if (expect.size() != got.size()) {
    ++c.mismatches;
    if (c.first == Comparison::none) c.first = n;
  }
  return c;
}

std::string Comparison::report(const std::string& what) const {
  std::ostringstream s;
  s.precision(9);
  s << what << ": " << mismatches << " of " << count << " outside |got - expect| <= " << tolerance.abs << " + "
    << tolerance.rel << " |expect|";
  if (count == 0) s << " (nothing compared)";
  if (first != none) s << "; first at " << first << ": expected " << first_expect << ", got " << first_got;
  if (worst != none)
    s << "; worst at " << worst << ": expected " << worst_expect << ", got " << worst_got << " (" << worst_ratio
      << " x the allowance)";
  s << "; max |difference| " << max_abs_diff;
  return s.str();
}

double peak_abs(std::span<const double> values) {
  double p = 0;
  for (double v : values) p = std::max(p, std::abs(v));
  return p;
}

}  // namespace prism::test
