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
  // Seven lenslets of the prototype's first row keep the reference fast.
  s.lenslets.resize(7);
  return s;
}

}  // namespace prism::test
