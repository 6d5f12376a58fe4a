#include "host/calibrate/synthetic.h"

#include <algorithm>
#include <cmath>
#include <stdexcept>
#include <string>

#include "engine/ref/forward_ref.h"
#include "engine/ref/hdr_merge_ref.h"

namespace prism {

HdrFrames synthetic_exposures(const OpticalSystem& truth, const TraceSettings& settings, const glm::dvec3& theta,
                              uint64_t seed, const SyntheticCapture& capture) {
  if (capture.exposures < 2 || !(capture.min_us > 0) || !(capture.max_us > capture.min_us) || capture.darks < 1 ||
      !(capture.peak_dn_per_s > 0))
    throw std::invalid_argument("synthetic capture: give 2 or more exposures, min_us > 0, max_us > min_us, 1 or more "
                                "darks and a peak rate > 0");
  const AnalysisGrid grid = AnalysisGrid::of(truth, settings.binning);
  std::vector<double> b(size_t(grid.width) * size_t(grid.height), 0.0);
  double peak = 0;
  for (const auto& [key, px] : ref::psf(truth, settings, theta).pixels)
    b[size_t(key)] = px[0], peak = std::max(peak, px[0]);
  if (!(peak > 0)) throw std::invalid_argument("synthetic PSF: no light on the sensor from this source");
  for (double& v : b) v *= capture.peak_dn_per_s / peak;
  const std::vector<double> times = log_spaced_times(capture.min_us * 1e-6, capture.max_us * 1e-6, capture.exposures);
  return simulate_hdr_frames(b, grid.width, grid.height, times, dark_times(times, capture.darks), SyntheticSensor{}, seed);
}

MeasuredPsf synthetic_measured_psf(const OpticalSystem& truth, const TraceSettings& settings, const glm::dvec3& theta,
                                   uint64_t seed) {
  return {theta, ref::hdr_merge(synthetic_exposures(truth, settings, theta, seed), {}).psf,
          "synthetic (" + std::to_string(theta.x) + ", " + std::to_string(theta.y) + ", " + std::to_string(theta.z) + ")"};
}

}  // namespace prism
