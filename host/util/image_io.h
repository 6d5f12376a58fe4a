// Writing images: OpenEXR (float, exact) and PNG (8-bit preview). Files are
// written to a temporary name and renamed, so a crash never leaves half a file.
#pragma once
#include <string>
#include <vector>

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

// Write `path` through a temporary file in the same directory: the callback
// writes to the temporary path, which is renamed over `path` only on success.
template <class F> void write_atomically(const std::string& path, F&& write);
void rename_into_place(const std::string& tmp, const std::string& path);
std::string temporary_path_for(const std::string& path);

template <class F> void write_atomically(const std::string& path, F&& write) {
  std::string tmp = temporary_path_for(path);
  write(tmp);
  rename_into_place(tmp, path);
}

}  // namespace prism
