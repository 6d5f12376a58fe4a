// CRLB from a Fisher matrix: exact inverses, and singular or empty matrices
// flagged with infinite bounds, never NaN.
#include <cmath>

#include "engine/fisher.h"
#include "support.h"

TEST_CASE("CRLB of a diagonal and of a correlated Fisher matrix") {
  auto c = prism::crlb_from_fisher({4.0, 0.0, 0.0, 16.0, 0.0, 100.0}, 10.0);
  CHECK(c.identifiable);
  CHECK(c.x_mm == doctest::Approx(0.5));
  CHECK(c.y_mm == doctest::Approx(0.25));
  CHECK(c.depth_mm == doctest::Approx(0.1));
  CHECK(c.r3_mm == doctest::Approx(std::sqrt(0.25 + 0.0625 + 0.01)));
  // [[2,1,0],[1,2,0],[0,0,1]]: inverse xx = 2/3.
  auto d = prism::crlb_from_fisher({2.0, 1.0, 0.0, 2.0, 0.0, 1.0}, 1.0);
  CHECK(d.x_mm == doctest::Approx(std::sqrt(2.0 / 3.0)));
  CHECK(d.depth_mm == doctest::Approx(1.0));
}

TEST_CASE("singular, empty and non-finite Fisher matrices are flagged, not garbage") {
  // Rank 2: depth is invisible.
  auto s = prism::crlb_from_fisher({1.0, 0.0, 0.0, 1.0, 0.0, 0.0}, 5.0);
  CHECK_FALSE(s.identifiable);
  CHECK(s.flag == "singular");
  CHECK(std::isinf(s.x_mm));
  CHECK(std::isinf(s.r3_mm));
  // Nearly singular beyond float accuracy of the sums.
  auto n = prism::crlb_from_fisher({1.0, 1.0, 0.0, 1.0 + 1e-12, 0.0, 1.0}, 5.0);
  CHECK(n.flag == "singular");
  auto z = prism::crlb_from_fisher({0, 0, 0, 0, 0, 0}, 0.0);
  CHECK(z.flag == "no_photons");
  CHECK(std::isinf(z.depth_mm));
  auto bad = prism::crlb_from_fisher({NAN, 0, 0, 1, 0, 1}, 3.0);
  CHECK(bad.flag == "singular");
  CHECK_FALSE(std::isnan(bad.x_mm));
}
