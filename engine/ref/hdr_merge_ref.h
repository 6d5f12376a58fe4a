// Naive double-precision HDR merge: the ground truth the Vulkan kernel is
// checked against. Written without shaders/common/hdr.glsl so the two cannot
// share a bug; shares only the input statistics and limits (hdr_dark_stats,
// hdr_limits) and the final normalisation (hdr_finish).
#pragma once
#include "engine/hdr_merge.h"

namespace prism::ref {

HdrResult hdr_merge(const HdrFrames& f, const HdrOptions& o);

}  // namespace prism::ref
