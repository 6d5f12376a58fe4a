// The device math of shaders/common/*.glsl compiled as C++ (float, GLM), so
// host code and tests can call the very functions the kernels run. Buffer and
// push-constant structs are checked against their std430 sizes here.
#pragma once
#include <glm/glm.hpp>

namespace prism::shared {
using namespace glm;
using uint = unsigned int;
#define PRISM_FN inline
#include "common/optics.glsl"
#include "common/footprint.glsl"
#undef PRISM_FN

static_assert(sizeof(Lenslet) == 56, "Lenslet must match its std430 layout");
static_assert(sizeof(DesignRange) == 16, "DesignRange must match its std430 layout");
static_assert(sizeof(TraceParams) == 108, "TraceParams must match its std430 push-constant layout");
}  // namespace prism::shared
