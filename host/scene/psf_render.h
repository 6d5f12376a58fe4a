// One point source's expected-photon image on the analysis grid, with its
// derivatives: the computation behind `prism psf` and the Python module's
// psf().
#pragma once
#include <string>

#include <glm/glm.hpp>

#include "engine/forward.h"
#include "host/scene/crlb_study.h"
#include "host/util/memory.h"

namespace prism {

// The image as 4 floats per pixel (b, db/dx, db/dy, db/ddepth), rows from
// the sensor's first; without `derivatives` the last three are 0 (the device
// then returns 4 bytes per pixel instead of 32). `memory` gets the image's
// parts added and is checked before anything is allocated (the caller adds
// its own, e.g. a preview). ctx is used only by the Vulkan backend.
PixelImage render_psf(const Scene& scene, const TraceSettings& settings, const glm::dvec3& source_mm,
                      bool derivatives, Backend backend, vk::Context* ctx, MemoryEstimate& memory);

}  // namespace prism
