// The HDR merge's device math (shaders/common/hdr.glsl) compiled as C++
// (float, GLM), so the launcher shares its constants and push-constant layout
// with the kernel, and tests can call the per-pixel functions directly.
#pragma once
#include "engine/shared_math.h"

namespace prism::shared {
#define PRISM_FN inline
#include "common/hdr.glsl"
#undef PRISM_FN
static_assert(sizeof(HdrParams) == 48, "HdrParams must match its std430 push-constant layout");
}  // namespace prism::shared
