// Calibration stacks as `prism camera capture-hdr` writes them (hw/README.md,
// "The capture stack"): a directory with stack.json and 16-bit little-endian
// raw frames. Reading checks everything the merge relies on and names the file
// and field at fault. Also synthetic stacks from a known PSF (tests, benchmarks).
#pragma once
#include <cstdint>
#include <string>
#include <vector>

#include <glm/glm.hpp>
#include <nlohmann/json.hpp>

#include "engine/hdr_merge.h"
#include "engine/hdr_times.h"  // log_spaced_times, dark_times: as capture-hdr takes them

namespace prism {

constexpr int kHdrStackFormatVersion = 1;

struct HdrStack {
  std::string dir;
  std::string pixel_format;                         // e.g. "Mono12p"
  glm::dvec3 source_mm{0.0};                        // x_mm, y_mm, depth_mm
  nlohmann::json camera;                            // vendor/model/serial as captured (may be null)
  std::vector<std::string> exposure_files, dark_files;  // relative to dir
  HdrFrames frames;                                 // times in seconds
};

// Reads dir/stack.json and its raw frames. Throws std::runtime_error naming
// the file and field (missing, wrong type, wrong size, out-of-range sample).
HdrStack read_hdr_stack(const std::string& dir);
// All of that but the samples: stack.json, the memory the merge needs and
// each raw file's size; frames left empty (to check every stack before work).
HdrStack read_hdr_stack_header(const std::string& dir);
// `path` itself when it holds stack.json, else its subdirectories that do
// (sorted); throws when there are none.
std::vector<std::string> find_hdr_stacks(const std::string& path);
// Writes stack.json and the raws (file names default to exposure_<i>.raw,
// dark_<i>.raw); creates dir.
void write_hdr_stack(const std::string& dir, const HdrStack& stack);

// A sensor for synthetic stacks: raw = clip(round(offset + dark_rate * T +
// T * p + shot noise + read noise)), clipped to 0 .. 2^bit_depth - 1.
struct SyntheticSensor {
  unsigned bit_depth = 12;
  double offset_dn = 64;              // black level
  double read_noise_dn = 2;           // Gaussian, per frame
  double gain_dn_per_e = 0.25;        // shot noise variance = gain * signal_dn
  double dark_rate_dn_per_s = 5;      // ordinary pixels' dark current
  double hot_rate_dn_per_s = 2e4;     // hot pixels' dark current
  std::vector<size_t> hot_pixels;     // pixel indices
};

// A known PSF in DN/s spanning more than four decades: two Gaussian spots,
// a faint wide spot and a defocus disc on a zero background.
std::vector<double> synthetic_psf(int width, int height, double peak_dn_per_s = 4e6);
HdrFrames simulate_hdr_frames(const std::vector<double>& psf_dn_per_s, int width, int height,
                              const std::vector<double>& exposure_s, const std::vector<double>& dark_s,
                              const SyntheticSensor& sensor, uint64_t seed);

}  // namespace prism
