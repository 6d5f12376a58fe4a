// Writing images: OpenEXR (float, exact) and PNG (8-bit preview), each
// written whole or not at all (host/util/output_file.h).
#pragma once
#include <string>
#include <vector>

#include "host/util/output_file.h"

namespace prism {

struct ExrChannel {
  std::string name;          // "Y", "db_dx", ...
  const float* data;         // width * height values, row-major, with `stride` floats between pixels
  int stride = 1;
};

void write_exr(const std::string& path, int width, int height, const std::vector<ExrChannel>& channels);
// Reads one float channel back (tests, tools).
std::vector<float> read_exr_channel(const std::string& path, const std::string& channel, int& width, int& height);

// Square-root tone-mapped grayscale preview (white = the 99.5th percentile of
// lit pixels), box-downsampled so the longer side is at most max_side pixels.
void write_png_preview(const std::string& path, int width, int height, const float* data, int stride, int max_side = 1600);
// Signed values (residual maps): white at 0, red for positive and blue for
// negative, full colour at +-limit and beyond; box-downsampled (sums) as above.
void write_png_signed(const std::string& path, int width, int height, const float* data, double limit,
                      int max_side = 1600);

}  // namespace prism
