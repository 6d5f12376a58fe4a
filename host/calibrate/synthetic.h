// Synthetic as-built systems and their "measured" PSFs, for calibration's
// tests and benchmarks and `prism dictionary simulate-hdr` (issue 18): what a
// calibration must recover, with noise as a camera and the HDR merge give it. The as-built system itself,
// synthetic_as_built, is a scene's (host/scene/scene.h: the built-in
// "prototype-as-built").
#pragma once
#include <cstdint>

#include <glm/glm.hpp>

#include "engine/hdr_merge.h"
#include "host/calibrate/calibrate.h"
#include "host/dictionary/hdr_stack.h"
#include "host/scene/scene.h"

namespace prism {

// PSF theta of `truth`, rendered by the CPU reference with `settings` (render
// the truth apart from the model that fits it: more cells, another
// stratification), as `prism camera capture-hdr` would record it: 7
// exposures (20 us .. 0.2 s) and 3 darks of SyntheticSensor's 12-bit sensor,
// the brightest pixel at 2e6 DN/s.
HdrFrames synthetic_exposures(const OpticalSystem& truth, const TraceSettings& settings, const glm::dvec3& theta,
                              uint64_t seed);

// ... merged as `prism dictionary merge-hdr` does (the CPU reference).
MeasuredPsf synthetic_measured_psf(const OpticalSystem& truth, const TraceSettings& settings, const glm::dvec3& theta,
                                   uint64_t seed);

}  // namespace prism
