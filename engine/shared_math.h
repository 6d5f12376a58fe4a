// The device math of shaders/common/*.glsl compiled as C++ (float, GLM), so
// host code and tests can call the very functions the kernels run. Buffer and
// push-constant structs are checked against their std430 sizes here.
#pragma once
#include <glm/glm.hpp>

#include "engine/optical_system.h"  // SceneParam

namespace prism::shared {
using namespace glm;
using uint = unsigned int;
#define PRISM_FN inline
// The calibrate kernels' seeds (optics.glsl): here the slots are always
// those TraceParams names, so host code sets tangent0..2 (set_tangents
// below; source_tangents for d/d(x, y, depth)).
#define PRISM_CALIBRATE 1
#include "common/optics.glsl"
#include "common/footprint.glsl"
#undef PRISM_FN
#undef PRISM_CALIBRATE

static_assert(sizeof(Lenslet) == 56, "Lenslet must match its std430 layout");
static_assert(sizeof(DesignRange) == 16, "DesignRange must match its std430 layout");
static_assert(sizeof(TraceParams) == 124, "TraceParams must match its std430 push-constant layout");
static_assert(sizeof(TraceParams) <= 128, "push constants beyond 128 bytes are not on every Vulkan device");
static_assert(PARAM_SOURCE_X == uint(SceneParam::source_x) && PARAM_LENS_X == uint(SceneParam::lens_x) &&
                  PARAM_LENS_TILT_Y == uint(SceneParam::lens_tilt_y) &&
                  PARAM_LENS_TO_SENSOR == uint(SceneParam::lens_to_sensor) &&
                  PARAM_SENSOR_TILT_Y == uint(SceneParam::sensor_tilt_y) &&
                  PARAM_SOURCE_SIGMA == uint(SceneParam::source_sigma),
              "the kernels' PARAM_* must follow SceneParam's order");

// A slot of TraceParams: PARAM_* | (lenslet + 1) << 8, 0 for every lenslet's own.
inline uint32_t tangent_code(const Tangent& t) {
  return uint32_t(t.param) | (t.lens >= 0 ? uint32_t(t.lens + 1) << 8 : 0u);
}
inline void set_tangents(TraceParams& p, const Tangents& t) {
  p.tangent0 = tangent_code(t[0]);
  p.tangent1 = tangent_code(t[1]);
  p.tangent2 = tangent_code(t[2]);
}
}  // namespace prism::shared
