#include "host/util/image_io.h"

#include <png.h>
#include <unistd.h>

#include <OpenEXR/ImfChannelList.h>
#include <OpenEXR/ImfFrameBuffer.h>
#include <OpenEXR/ImfHeader.h>
#include <OpenEXR/ImfInputFile.h>
#include <OpenEXR/ImfOutputFile.h>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <memory>
#include <stdexcept>

namespace prism {

void write_exr(const std::string& path, int width, int height, const std::vector<ExrChannel>& channels) {
  write_atomically(path, [&](const std::string& tmp) {
    try {
      Imf::Header header(width, height);
      for (const auto& c : channels) header.channels().insert(c.name, Imf::Channel(Imf::FLOAT));
      Imf::FrameBuffer fb;
      for (const auto& c : channels)
        fb.insert(c.name, Imf::Slice(Imf::FLOAT, (char*)c.data, sizeof(float) * c.stride,
                                     sizeof(float) * c.stride * size_t(width)));
      Imf::OutputFile file(tmp.c_str(), header);
      file.setFrameBuffer(fb);
      file.writePixels(height);
    } catch (const std::exception& e) {
      throw std::runtime_error("cannot write " + path + ": " + e.what());
    }
  });
}

std::vector<float> read_exr_channel(const std::string& path, const std::string& channel, int& width, int& height) {
  try {
    Imf::InputFile file(path.c_str());
    auto dw = file.header().dataWindow();
    width = dw.max.x - dw.min.x + 1;
    height = dw.max.y - dw.min.y + 1;
    if (!file.header().channels().findChannel(channel))
      throw std::runtime_error("no channel '" + channel + "'");
    std::vector<float> data(size_t(width) * height);
    Imf::FrameBuffer fb;
    fb.insert(channel, Imf::Slice(Imf::FLOAT, (char*)(data.data() - dw.min.x - dw.min.y * width), sizeof(float),
                                  sizeof(float) * size_t(width)));
    file.setFrameBuffer(fb);
    file.readPixels(dw.min.y, dw.max.y);
    return data;
  } catch (const std::exception& e) {
    throw std::runtime_error("cannot read " + path + ": " + e.what());
  }
}

namespace {
// 8-bit rows, `channels` bytes a pixel (1: gray, 3: RGB), written whole.
void write_png(const std::string& path, int w, int h, int channels, const std::vector<png_byte>& pixels) {
  write_atomically(path, [&](const std::string& tmp) {
    std::unique_ptr<FILE, int (*)(FILE*)> f(std::fopen(tmp.c_str(), "wb"), &std::fclose);
    if (!f) throw std::runtime_error("cannot write " + path);
    png_structp png = png_create_write_struct(PNG_LIBPNG_VER_STRING, nullptr, nullptr, nullptr);
    png_infop info = png_create_info_struct(png);
    if (setjmp(png_jmpbuf(png))) {
      png_destroy_write_struct(&png, &info);
      throw std::runtime_error("cannot encode PNG " + path);
    }
    png_init_io(png, f.get());
    png_set_IHDR(png, info, w, h, 8, channels == 3 ? PNG_COLOR_TYPE_RGB : PNG_COLOR_TYPE_GRAY, PNG_INTERLACE_NONE,
                 PNG_COMPRESSION_TYPE_DEFAULT, PNG_FILTER_TYPE_DEFAULT);
    png_write_info(png, info);
    for (int r = 0; r < h; ++r) png_write_row(png, const_cast<png_byte*>(&pixels[size_t(r) * w * channels]));
    png_write_end(png, nullptr);
    png_destroy_write_struct(&png, &info);
  });
}

// Box-downsampled sums so that the longer side is at most max_side pixels.
std::vector<double> box_down(int width, int height, const float* data, int stride, int max_side, int& w, int& h) {
  int factor = std::max(1, (std::max(width, height) + max_side - 1) / max_side);
  w = (width + factor - 1) / factor, h = (height + factor - 1) / factor;
  std::vector<double> box(size_t(w) * h, 0.0);
  for (int r = 0; r < height; ++r)
    for (int c = 0; c < width; ++c) box[size_t(r / factor) * w + c / factor] += data[(size_t(r) * width + c) * stride];
  return box;
}
}  // namespace

void write_png_preview(const std::string& path, int width, int height, const float* data, int stride, int max_side) {
  int w, h;
  const std::vector<double> box = box_down(width, height, data, stride, max_side, w, h);
  // Scale to the 99.5th percentile of lit pixels: a few focused spots would
  // otherwise leave every defocused disc black.
  std::vector<double> lit;
  for (double v : box)
    if (v > 0) lit.push_back(v);
  double peak = 0;
  if (!lit.empty()) {
    auto k = lit.begin() + std::ptrdiff_t(0.995 * double(lit.size() - 1));
    std::nth_element(lit.begin(), k, lit.end());
    peak = *k;
  }
  std::vector<png_byte> pixels(box.size());
  for (size_t i = 0; i < box.size(); ++i)
    pixels[i] = png_byte(peak > 0 ? std::lround(255.0 * std::min(1.0, std::sqrt(std::max(0.0, box[i]) / peak))) : 0);
  write_png(path, w, h, 1, pixels);
}

void write_png_signed(const std::string& path, int width, int height, const float* data, double limit, int max_side) {
  int w, h;
  const std::vector<double> box = box_down(width, height, data, 1, max_side, w, h);
  std::vector<png_byte> pixels(3 * box.size());
  for (size_t i = 0; i < box.size(); ++i) {
    // White at 0, toward red for positive and blue for negative values.
    const double t = limit > 0 ? std::clamp(box[i] / limit, -1.0, 1.0) : 0.0;
    const png_byte fade = png_byte(std::lround(255.0 * (1.0 - std::abs(t))));
    pixels[3 * i + 0] = t < 0 ? fade : 255;
    pixels[3 * i + 1] = fade;
    pixels[3 * i + 2] = t > 0 ? fade : 255;
  }
  write_png(path, w, h, 3, pixels);
}

}  // namespace prism
