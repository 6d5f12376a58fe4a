// The comparison harness itself (compare.h): it must fail where it should,
// and say where.
#include "compare.h"
#include "support.h"

TEST_CASE("comparison harness: tolerance, first and worst mismatch, NaN and sizes") {
  using prism::test::compare;
  const std::vector<double> expect{1.0, 2.0, 3.0, 4.0};
  CHECK(compare(expect, expect, {}).ok());

  // Index 1 is off by 0.01 (allowed 1e-3 + 1e-3 * 2), index 3 by 0.1: both
  // mismatch, the first is 1, the worst is 3.
  auto c = compare(expect, std::vector<double>{1.0, 2.01, 3.0, 4.1}, {.abs = 1e-3, .rel = 1e-3});
  CHECK_FALSE(c.ok());
  CHECK(c.mismatches == 2);
  CHECK(c.first == 1);
  CHECK(c.first_got == 2.01);
  CHECK(c.worst == 3);
  CHECK(c.worst_ratio == doctest::Approx(0.1 / (1e-3 + 4e-3)));
  CHECK(c.max_abs_diff == doctest::Approx(0.1));
  const std::string r = c.report("values");
  CHECK(r.find("2 of 4") != std::string::npos);
  CHECK(r.find("first at 1: expected 2, got 2.01") != std::string::npos);
  CHECK(r.find("worst at 3") != std::string::npos);

  // Within tolerance: relative allowance grows with |expect|.
  CHECK(compare(std::vector<double>{1000.0}, std::vector<double>{1000.9}, {.rel = 1e-3}).ok());
  CHECK_FALSE(compare(std::vector<double>{1.0}, std::vector<double>{1.9}, {.rel = 1e-3}).ok());

  // NaN never agrees; equal infinities do.
  CHECK_FALSE(compare(std::vector<double>{1.0}, std::vector<double>{NAN}, {.abs = 1e9}).ok());
  CHECK(compare(std::vector<double>{INFINITY}, std::vector<double>{INFINITY}, {}).ok());
  // A size mismatch and an empty comparison fail.
  CHECK_FALSE(compare(expect, std::vector<double>{1.0, 2.0, 3.0}, {.abs = 1}).ok());
  CHECK_FALSE(compare(std::vector<double>{}, std::vector<double>{}, {}).ok());
}
