// Sweep space files (host/sweep/space.h): JSON from users.
#include "fuzz/fuzz.h"
#include "host/sweep/space.h"

namespace prism::fuzz {

void space(const uint8_t* data, size_t size) {
  auto j = prism::fuzz::json_of(data, size);
  if (!j) return;
  try {
    prism::DesignSpace s = prism::DesignSpace::parse(*j, "fuzz-space.json", prism::fuzz::scratch().string());
    std::mt19937_64 rng(1);
    if (s.size() > 0) s.scene_of(s.random(rng), "fuzz");
  } catch (const std::runtime_error&) {
  }
}

}  // namespace prism::fuzz

PRISM_FUZZ_MAIN(space)
