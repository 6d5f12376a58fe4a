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

// How the synthetic camera records a stack: `exposures` times spread
// log-uniformly over [min_us, max_us] and `darks` dark frames spread over
// them (engine/hdr_times.h, as capture-hdr takes them), the PSF's brightest
// pixel at peak_dn_per_s. The faintest light the merge keeps is 16 DN over
// its third longest exposure (it needs 3 valid ones): 8.6e-4 of the peak by
// default, 7e-5 with 9 exposures up to 2 s.
struct SyntheticCapture {
  unsigned exposures = 7, darks = 3;
  double min_us = 20, max_us = 2e5;
  double peak_dn_per_s = 2e6;
};

// PSF theta of `truth`, rendered by the CPU reference with `settings` (render
// the truth apart from the model that fits it: more cells, another
// stratification), as `prism camera capture-hdr` would record it with
// SyntheticSensor's 12-bit sensor.
HdrFrames synthetic_exposures(const OpticalSystem& truth, const TraceSettings& settings, const glm::dvec3& theta,
                              uint64_t seed, const SyntheticCapture& capture = {});

// ... merged as `prism dictionary merge-hdr` does (the CPU reference).
MeasuredPsf synthetic_measured_psf(const OpticalSystem& truth, const TraceSettings& settings, const glm::dvec3& theta,
                                   uint64_t seed);

}  // namespace prism
