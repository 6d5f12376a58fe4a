// Double-precision reference of the support search (paper eqs. 17-18),
// written separately from shaders/support_scan.comp: for one event and every
// PSF of a dictionary level, the whole-pixel shift within +-radius with the
// lowest gradient correlation <g, P(shifted)> = S - sum_c w_c P(c - shift),
// w_c = 1 / (1 - exp(-lambda_c)), and the weight fitted there against the
// event's current model. The host's reconstruction uses the same shift search
// to carry candidates down to finer levels.
#pragma once
#include <cstddef>
#include <span>
#include <vector>

#include <glm/glm.hpp>

#include "engine/support_scan.h"

namespace prism::ref {

// One level of a PSF dictionary as the search reads it (the host's
// dictionary service provides it).
class ScanSource {
 public:
  virtual ~ScanSource() = default;
  virtual size_t psf_count() const = 0;
  // P of PSF `psf` at each pixel of this level (0 off the sensor).
  virtual std::vector<float> values(size_t psf, std::span<const glm::ivec2> pixels) = 0;
  // S: the mass of PSF `psf` still on the sensor after a shift by `shift` pixels.
  virtual double mass_shifted(size_t psf, glm::ivec2 shift) = 0;
  // Shifts of PSF `psf` are searched within +-radius pixels per axis.
  virtual int radius_px(size_t psf) const = 0;
};

// The shift around `center` on multiples of `step` within +-reach (and within
// +-radius of the origin) with the lowest S - sum_c w_c P(c - shift); ties go
// to the first in row-major order from the lowest shift, as on the device.
glm::ivec2 best_shift(ScanSource& level, size_t psf, std::span<const glm::ivec2> clicks, std::span<const double> w,
                      glm::ivec2 center, int reach, int step = 1);

// The scan of one event: per PSF its best shift within its radius (on
// multiples of settings.step_px) and the weight fitted there by projected
// Newton against the event's rates (event.rate: lambda at each click,
// background included). One score per PSF, in PSF order.
std::vector<SupportScore> support_scan(ScanSource& level, const ScanEvent& event, const ScanSettings& settings);

}  // namespace prism::ref
