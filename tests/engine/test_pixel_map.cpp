// The reference's pixel map (engine/ref/pixel_map.h) against std::map: the
// same values for every key however the keys come (a row's neighbours, a
// stride that collides in a power-of-two table, random), across its growth,
// and iteration in the order the keys were first used.
#include <doctest/doctest.h>

#include <array>
#include <map>
#include <random>
#include <vector>

#include "engine/ref/pixel_map.h"

TEST_CASE("pixel map: the values of std::map for every key, iterated in first-use order") {
  struct Pattern {
    const char* name;
    std::vector<int64_t> keys;
  };
  std::vector<Pattern> patterns;
  Pattern row{"a row's neighbours, touched twice", {}};
  for (int64_t k = 0; k < 5000; ++k) row.keys.push_back(419 * 150 + k), row.keys.push_back(419 * 150 + k);
  Pattern stride{"a power-of-two stride (one table slot apart times 2^k)", {}};
  for (int64_t k = 0; k < 3000; ++k) stride.keys.push_back(k << 20);
  Pattern random{"random keys over a 6696 x 4764 sensor, repeats among them", {}};
  std::mt19937_64 rng(3);
  std::uniform_int_distribution<int64_t> any(0, int64_t(6696) * 4764 - 1);
  for (int k = 0; k < 20000; ++k) random.keys.push_back(k % 3 == 2 ? random.keys[size_t(k) / 2] : any(rng));
  patterns = {row, stride, random};

  for (const Pattern& p : patterns) {
    CAPTURE(p.name);
    prism::ref::PixelMap<std::array<double, 2>> map;
    std::map<int64_t, std::array<double, 2>> want;
    std::vector<int64_t> first_use;
    for (size_t i = 0; i < p.keys.size(); ++i) {
      const int64_t key = p.keys[i];
      if (!want.count(key)) first_use.push_back(key);
      auto& v = map[key];
      v[0] += double(i), v[1] += 1;
      want[key][0] += double(i), want[key][1] += 1;
    }
    REQUIRE(map.size() == want.size());
    size_t at = 0;
    for (const auto& [key, v] : map) {
      REQUIRE(key == first_use[at++]);
      CHECK(v == want[key]);
    }
    for (const auto& [key, v] : want) {
      const auto* found = map.find(key);
      REQUIRE(found != nullptr);
      CHECK(*found == v);
    }
    CHECK_FALSE(map.contains(-1));
    CHECK_FALSE(map.contains(int64_t(1) << 40));
  }
  const prism::ref::PixelMap<int> empty;
  CHECK(empty.find(0) == nullptr);
  CHECK(empty.empty());
}
