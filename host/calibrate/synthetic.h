// Synthetic as-built systems and their "measured" PSFs, for calibration's
// tests and benchmarks (issue 18): what a calibration must recover, with
// noise as a camera and the HDR merge give it.
#pragma once
#include <cstdint>

#include <glm/glm.hpp>

#include "engine/hdr_merge.h"
#include "host/calibrate/calibrate.h"
#include "host/dictionary/hdr_stack.h"

namespace prism {

// `nominal` as built, by known amounts: lenslet i (k = i + 1) moved by
// (40 sin 1.7k, 30 cos 2.3k) um, its focal length off by 2% sin(0.9k + 0.4),
// tilted (0.5 sin(1.3k + 1), -0.4 cos 0.7k) degrees; the sensor 0.15 mm
// farther, moved by (30, -20) um and tilted (0.3, -0.2) degrees; the
// scintillator face 0.1 mm nearer.
OpticalSystem synthetic_as_built(const OpticalSystem& nominal);

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
