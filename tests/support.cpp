#include "support.h"

namespace prism::test {

vk::Context& gpu() {
  static vk::Context ctx(vk::ContextOptions{"", true});
  return ctx;
}

void check_validation_clean() {
  const auto& m = gpu().validation_messages();
  INFO("validation layer messages: " << m.size() << (m.empty() ? "" : ", first: " + m.front()));
  CHECK(m.empty());
}

OpticalSystem small_system(LensModel model) {
  OpticalSystem s = builtin_scene("prototype").optics;
  s.lens_model = model;
  // The seven lenslets of a central row keep the reference fast; an outer row
  // would image near sources off the sensor.
  s.lenslets = std::vector<LensletGeometry>(s.lenslets.begin() + 14, s.lenslets.begin() + 21);
  return s;
}

}  // namespace prism::test
