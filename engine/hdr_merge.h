// HDR merge of calibration exposures (paper Sec. III.A.2): per pixel, the
// valid exposures' summed signal (raw - dark) over their summed time T (the
// paper takes the mean of the (raw - dark) / T; why not: shaders/common/hdr.glsl,
// hdr_estimate), kept only with enough valid exposures, linear response and
// a normal dark level; the result normalised to sum 1. Vulkan kernel (shaders/hdr_merge.comp)
// here, double-precision reference in engine/ref/hdr_merge_ref.h.
#pragma once
#include <array>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "engine/vk/context.h"

namespace prism {

// Every threshold of the merge, in one place (the command line sets each).
struct HdrOptions {
  unsigned min_valid_exposures = 3;  // valid exposures a kept pixel needs (paper: 3); 2..16
  double min_correlation = 0.95;     // Pearson r of (raw - dark) against T must exceed this (paper: 0.95); -1..1
  double saturation_margin = 0.05;   // raw >= (1 - margin) * (2^bit_depth - 1) is saturated: the last percent
                                     // of a pixel's range is non-linear and noise there is clipped; 0..0.5
  double floor_sigmas = 5.0;         // raw - dark must exceed this many dark-frame noise sigmas; >= 0
  double floor_min_dn = 16.0;        // ... and this many DN, so one quantisation step is <= 1/16 of it; >= 0
  double hot_dark_spreads = 10.0;    // hot pixel: dark level above the frame median by more than this many
                                     // robust spreads (1.4826 MAD) of the per-pixel dark levels; > 0
  std::string dark_model = "auto";   // dark level against T: "linear" (offset + rate * T, needs darks at two or
                                     // more times), "constant" (the darks' mean at every T), "auto": linear
                                     // when the darks span two or more times, else constant
  void validate() const;             // throws std::invalid_argument naming the field
};

// One position's frames in memory: 16-bit samples, row-major.
struct HdrFrames {
  std::string name;  // for messages: the stack directory
  int width = 0;
  int height = 0;
  unsigned bit_depth = 12;
  std::vector<double> exposure_s;                // exposure times, seconds
  std::vector<std::vector<uint16_t>> exposures;  // one frame per exposure time
  std::vector<double> dark_s;                    // dark exposure times, seconds
  std::vector<std::vector<uint16_t>> darks;
  size_t pixels() const { return size_t(width) * size_t(height); }
  void validate() const;  // sizes, counts and limits; throws naming `name`
};

// Frame-level dark statistics both backends take as input.
struct HdrDarkStats {
  double median_dn = 0;      // median per-pixel dark level at the longest dark time
  double spread_dn = 0;      // 1.4826 * MAD of the per-pixel dark levels (noise + fixed pattern)
  double read_noise_dn = 0;  // temporal noise of one dark frame (from frame differences; spatial if one dark)
  double longest_s = 0;      // the longest dark time
};
HdrDarkStats hdr_dark_stats(const HdrFrames& f);

// The thresholds in DN for one stack.
struct HdrLimits {
  double saturation_dn;  // raw >= this: saturated
  double floor_dn;       // raw - dark <= this: lost in noise/quantisation
  double hot_dark_dn;    // dark level at the longest dark time above this: hot
  bool dark_linear;      // dark model: offset + rate * T
};
HdrLimits hdr_limits(const HdrFrames& f, const HdrOptions& o, const HdrDarkStats& s);

enum class HdrReason : uint32_t { kept = 0, hot_dark = 1, saturated = 2, faint = 3, nonlinear = 4 };
constexpr size_t kHdrReasons = 5;
const char* to_string(HdrReason r);

struct HdrResult {
  int width = 0;
  int height = 0;
  std::vector<float> psf;          // normalised to sum 1 over kept pixels; 0 where rejected
  std::vector<uint32_t> status;    // reason (bits 0..7), valid count (8..15), valid mask (16..31)
  double sum_dn_per_s = 0;         // sum of the kept pixels' estimates before normalising
  std::array<uint64_t, kHdrReasons> pixels_by_reason{};
  std::vector<uint64_t> kept_using_exposure;  // per exposure: kept pixels that used it
  HdrDarkStats dark;
  HdrLimits limits{};
  static HdrReason reason(uint32_t status) { return HdrReason(status & 0xffu); }
  static uint32_t valid_count(uint32_t status) { return (status >> 8) & 0xffu; }
};

// What both backends start from: the frames and options checked (throws naming
// the stack or option), the dark statistics and the limits in DN.
struct HdrSetup {
  HdrDarkStats dark;
  HdrLimits limits;
};
HdrSetup hdr_setup(const HdrFrames& f, const HdrOptions& o);

// Normalise raw estimates (DN/s) and count; both backends end here. Throws
// naming the stack when no pixel is kept.
HdrResult hdr_finish(const HdrFrames& f, std::vector<float> estimate, std::vector<uint32_t> status,
                     const HdrDarkStats& dark, const HdrLimits& limits);

class HdrMergeVulkan {
 public:
  // buffer_budget_bytes caps the frames buffer of one band (and so the rows per
  // band); the device's maxStorageBufferRange caps it too.
  explicit HdrMergeVulkan(vk::Context& ctx, uint64_t buffer_budget_bytes = ~0ull);
  ~HdrMergeVulkan();
  HdrResult merge(const HdrFrames& f, const HdrOptions& o);
  uint32_t last_bands() const { return last_bands_; }
  double last_kernel_ms() const { return last_kernel_ms_; }

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
  uint32_t last_bands_ = 0;
  double last_kernel_ms_ = 0;
};

}  // namespace prism
