// Scene files (host/scene/scene.h): JSON from users.
#include "fuzz/fuzz.h"
#include "host/scene/scene.h"

namespace prism::fuzz {

void scene(const uint8_t* data, size_t size) {
  auto j = prism::fuzz::json_of(data, size);
  if (!j) return;
  try {
    prism::Scene s = prism::parse_scene(*j, "fuzz-scene.json");
    prism::validate(s.optics);
  } catch (const std::runtime_error&) {
  } catch (const std::invalid_argument&) {  // validate(): the design cannot be built, with the reason
  }
}

}  // namespace prism::fuzz

PRISM_FUZZ_MAIN(scene)
