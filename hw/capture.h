// Calibration capture for the HDR merge: for one source position, m exposures
// spread log-uniformly plus dark frames, written as a stack directory:
// 16-bit little-endian .raw frames and a stack.json manifest (hw/README.md).
#pragma once
#include <filesystem>
#include <optional>
#include <ostream>
#include <vector>

namespace prism::hw {

class Camera;

// The LED source positioner. Out of scope for now: NoStage stands in for it.
class Stage {
 public:
  virtual ~Stage() = default;
  virtual void move_to(double x_mm, double y_mm, double depth_mm) = 0;
  virtual void set_source(bool on) = 0;  // off for dark frames
};

class NoStage : public Stage {
 public:
  void move_to(double, double, double) override {}
  void set_source(bool) override {}
};

// m exposure times from lo to hi (microseconds), equally spaced in log.
std::vector<double> log_exposures(double lo_us, double hi_us, unsigned m);

struct CaptureOptions {
  std::filesystem::path out_dir;
  unsigned exposures = 7, darks = 3;
  std::optional<double> min_us, max_us;  // default: the camera's ExposureTime range
  double x_mm = 0, y_mm = 0, depth_mm = 0;
};

inline constexpr int kStackFormatVersion = 1;

// Captures and writes the stack; progress lines go to `progress`. Returns the manifest path.
std::filesystem::path capture_hdr(Camera& cam, Stage& stage, const CaptureOptions& opt, std::ostream& progress);

}  // namespace prism::hw
