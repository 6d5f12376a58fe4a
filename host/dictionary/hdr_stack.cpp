#include "host/dictionary/hdr_stack.h"

#include <algorithm>
#include <bit>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <random>
#include <stdexcept>

#include "host/util/format.h"
#include "host/util/json_file.h"
#include "host/util/image_io.h"
#include "host/util/memory.h"

namespace fs = std::filesystem;

namespace prism {

namespace {

[[noreturn]] void fail(const std::string& file, const std::string& what) { throw std::runtime_error(file + ": " + what); }

const nlohmann::json& field(const nlohmann::json& j, const char* key, const std::string& file, const std::string& at) {
  if (!j.is_object() || !j.contains(key)) fail(file, "missing field '" + at + key + "'");
  return j.at(key);
}

double number(const nlohmann::json& j, const char* key, const std::string& file, const std::string& at = "") {
  const auto& v = field(j, key, file, at);
  if (!v.is_number()) fail(file, "field '" + at + key + "' must be a number, not " + v.dump());
  return v.get<double>();
}

// A raw frame's size against stack.json's.
void check_raw_size(const fs::path& path, const HdrFrames& f) {
  const std::string name = path.string();
  std::error_code ec;
  auto bytes = fs::file_size(path, ec);
  if (ec) fail(name, "missing raw frame (listed in stack.json): recapture the stack or fix its file name");
  uint64_t want = uint64_t(f.pixels()) * 2;
  if (bytes < want)
    fail(name, "truncated: " + std::to_string(bytes) + " bytes, expected " + std::to_string(want) + " (2 x " +
                   std::to_string(f.width) + " x " + std::to_string(f.height) + "); recapture this stack");
  if (bytes > want)
    fail(name, std::to_string(bytes) + " bytes, expected " + std::to_string(want) + ": the frame is not " +
                   std::to_string(f.width) + " x " + std::to_string(f.height) + " 16-bit samples as stack.json says");
}

std::vector<uint16_t> read_raw(const fs::path& path, const HdrFrames& f) {
  const std::string name = path.string();
  check_raw_size(path, f);
  const uint64_t want = uint64_t(f.pixels()) * 2;
  std::vector<uint16_t> v(f.pixels());
  std::ifstream in(path, std::ios::binary);
  in.read(reinterpret_cast<char*>(v.data()), std::streamsize(want));
  if (!in) fail(name, "read error");
  // Samples are little-endian on disk; so is every host this builds for.
  static_assert(std::endian::native == std::endian::little, "raw frames are little-endian");
  const uint32_t top = (1u << f.bit_depth) - 1u;
  for (size_t i = 0; i < v.size(); ++i)
    if (v[i] > top)
      fail(name, "sample " + std::to_string(v[i]) + " at (x " + std::to_string(i % f.width) + ", y " +
                     std::to_string(i / f.width) + ") exceeds the " + std::to_string(f.bit_depth) +
                     "-bit range of stack.json's bit_depth: wrong bit_depth or not an unpacked frame");
  return v;
}

// Reads exposures[] or darks[]: times (seconds) and file names.
void read_list(const nlohmann::json& j, const char* key, const std::string& file, std::vector<double>& times_s,
               std::vector<std::string>& files) {
  const auto& list = field(j, key, file, "");
  if (!list.is_array()) fail(file, std::string("field '") + key + "' must be an array");
  for (size_t i = 0; i < list.size(); ++i) {
    std::string at = std::string(key) + "[" + std::to_string(i) + "].";
    double us = number(list[i], "exposure_us", file, at);
    if (!(us > 0)) fail(file, "field '" + at + "exposure_us' must be > 0, not " + list[i]["exposure_us"].dump());
    const auto& name = field(list[i], "file", file, at);
    if (!name.is_string()) fail(file, "field '" + at + "file' must be a string");
    times_s.push_back(us * 1e-6);
    files.push_back(name.get<std::string>());
  }
}

}  // namespace

HdrStack read_hdr_stack_header(const std::string& dir) {
  HdrStack s;
  s.dir = dir;
  std::error_code ec;
  if (!fs::is_directory(dir, ec))
    fail(dir, fs::exists(dir, ec) ? "a file, not a capture-hdr stack directory" : "no such stack directory");
  std::string file = (fs::path(dir) / "stack.json").string();
  std::ifstream in(file);
  if (!in) fail(file, "missing: not a capture-hdr stack directory");
  nlohmann::json j;
  try {
    j = parse_json_file(in);
  } catch (const JsonDuplicateKey& e) {
    fail(file, e.what());
  } catch (const std::exception& e) {
    fail(file, std::string("not valid JSON: ") + e.what());
  }
  double version = number(j, "format_version", file);
  if (version != kHdrStackFormatVersion)
    fail(file, "format_version " + j["format_version"].dump() + " is not supported (this prism reads version " +
                   std::to_string(kHdrStackFormatVersion) + ")");
  HdrFrames& f = s.frames;
  f.name = dir;
  double w = number(j, "width", file), h = number(j, "height", file), bits = number(j, "bit_depth", file);
  if (!(w >= 1 && h >= 1 && w == std::floor(w) && h == std::floor(h) && w * h < 1e9))
    fail(file, "width/height " + j["width"].dump() + " x " + j["height"].dump() + " is not a frame size");
  if (!(bits >= 1 && bits <= 16 && bits == std::floor(bits)))
    fail(file, "field 'bit_depth' must be 1..16, not " + j["bit_depth"].dump());
  f.width = int(w);
  f.height = int(h);
  f.bit_depth = unsigned(bits);
  if (j.contains("pixel_format") && j["pixel_format"].is_string()) s.pixel_format = j["pixel_format"];
  const auto& src = field(j, "source", file, "");
  s.source_mm = {number(src, "x_mm", file, "source."), number(src, "y_mm", file, "source."),
                 number(src, "depth_mm", file, "source.")};
  if (j.contains("camera")) s.camera = j["camera"];
  read_list(j, "exposures", file, f.exposure_s, s.exposure_files);
  read_list(j, "darks", file, f.dark_s, s.dark_files);
  if (f.exposure_s.size() < 3)
    fail(file, "field 'exposures' lists " + std::to_string(f.exposure_s.size()) +
                   " exposures; the merge needs at least 3 (paper: m = 7): recapture with more --exposures");
  if (f.exposure_s.size() > 16) fail(file, "field 'exposures' lists more than 16 exposures; the merge takes 16");
  if (f.dark_s.empty()) fail(file, "field 'darks' is empty: the merge needs at least one dark frame");
  const double px = w * h, frames = double(f.exposure_s.size() + f.dark_s.size());
  MemoryEstimate memory("the HDR stack " + dir + " (" + std::to_string(f.width) + " x " + std::to_string(f.height) +
                        " px)");
  memory.add(format_number(frames) + " frames of 16-bit pixels", 2 * frames * px)
      .add("the merged PSF, its status and validity mask", 16 * px);
  memory.require_within_limit("Merge it on a machine with more memory");
  for (const auto& names : {s.exposure_files, s.dark_files})
    for (const auto& name : names) check_raw_size(fs::path(dir) / name, f);
  return s;
}

HdrStack read_hdr_stack(const std::string& dir) {
  HdrStack s = read_hdr_stack_header(dir);
  HdrFrames& f = s.frames;
  for (const auto& name : s.exposure_files) f.exposures.push_back(read_raw(fs::path(dir) / name, f));
  for (const auto& name : s.dark_files) f.darks.push_back(read_raw(fs::path(dir) / name, f));
  return s;
}

std::vector<std::string> find_hdr_stacks(const std::string& path) {
  if (fs::exists(fs::path(path) / "stack.json")) return {path};
  std::error_code ec;
  std::vector<std::string> out;
  for (const auto& e : fs::directory_iterator(path, ec))
    if (e.is_directory() && fs::exists(e.path() / "stack.json")) out.push_back(e.path().string());
  if (ec) throw std::runtime_error(path + ": cannot list: " + ec.message());
  if (out.empty()) throw std::runtime_error(path + ": no stack.json in it or in its subdirectories");
  std::sort(out.begin(), out.end());
  return out;
}

void write_hdr_stack(const std::string& dir, const HdrStack& s) {
  const HdrFrames& f = s.frames;
  fs::create_directories(dir);
  auto name_of = [](const std::vector<std::string>& names, const char* stem, size_t i) {
    return i < names.size() ? names[i] : std::string(stem) + std::to_string(i) + ".raw";
  };
  auto write_raw = [&](const std::string& name, const std::vector<uint16_t>& v) {
    std::string path = (fs::path(dir) / name).string();
    write_atomically(path, [&](const std::string& tmp) {
      std::ofstream out(tmp, std::ios::binary);
      out.write(reinterpret_cast<const char*>(v.data()), std::streamsize(v.size() * 2));
      if (!out) throw std::runtime_error("cannot write " + path);
    });
  };
  nlohmann::json j = {{"format_version", kHdrStackFormatVersion},
                      {"width", f.width},
                      {"height", f.height},
                      {"pixel_format", s.pixel_format.empty() ? "Mono" + std::to_string(f.bit_depth) : s.pixel_format},
                      {"bit_depth", f.bit_depth},
                      {"source", {{"x_mm", s.source_mm.x}, {"y_mm", s.source_mm.y}, {"depth_mm", s.source_mm.z}}},
                      {"exposures", nlohmann::json::array()},
                      {"darks", nlohmann::json::array()}};
  if (!s.camera.is_null()) j["camera"] = s.camera;
  for (size_t i = 0; i < f.exposures.size(); ++i) {
    std::string name = name_of(s.exposure_files, "exposure_", i);
    write_raw(name, f.exposures[i]);
    j["exposures"].push_back({{"exposure_us", f.exposure_s[i] * 1e6}, {"file", name}});
  }
  for (size_t i = 0; i < f.darks.size(); ++i) {
    std::string name = name_of(s.dark_files, "dark_", i);
    write_raw(name, f.darks[i]);
    j["darks"].push_back({{"exposure_us", f.dark_s[i] * 1e6}, {"file", name}});
  }
  std::string path = (fs::path(dir) / "stack.json").string();
  write_atomically(path, [&](const std::string& tmp) {
    std::ofstream out(tmp);
    out << j.dump(2) << '\n';
    if (!out) throw std::runtime_error("cannot write " + path);
  });
}

std::vector<double> synthetic_psf(int width, int height, double peak) {
  std::vector<double> p(size_t(width) * height, 0.0);
  struct Spot {
    double x, y, sigma, peak;
  };
  // Two focused spots (the bright one 3.6 decades above the disc), a wide faint spot.
  const Spot spots[] = {{0.30 * width, 0.40 * height, 2.0, peak},
                        {0.65 * width, 0.30 * height, 3.0, peak / 8},
                        {0.45 * width, 0.75 * height, 6.0, peak / 40}};
  const double disc_x = 0.72 * width, disc_y = 0.68 * height, disc_r = 0.1 * width, disc_level = peak / 800;
  for (int y = 0; y < height; ++y)
    for (int x = 0; x < width; ++x) {
      double v = 0;
      for (const Spot& s : spots) {
        double r2 = (x - s.x) * (x - s.x) + (y - s.y) * (y - s.y);
        v += s.peak * std::exp(-0.5 * r2 / (s.sigma * s.sigma));
      }
      // Defocus disc: the pixel's covered fraction from 4 x 4 sub-samples (a soft edge).
      int inside = 0;
      for (int sy = 0; sy < 4; ++sy)
        for (int sx = 0; sx < 4; ++sx) {
          double dx = x + (sx + 0.5) / 4 - 0.5 - disc_x, dy = y + (sy + 0.5) / 4 - 0.5 - disc_y;
          inside += dx * dx + dy * dy <= disc_r * disc_r;
        }
      v += disc_level * inside / 16.0;
      p[size_t(y) * width + x] = v;
    }
  return p;
}

HdrFrames simulate_hdr_frames(const std::vector<double>& psf, int width, int height,
                              const std::vector<double>& exposure_s, const std::vector<double>& dark_s,
                              const SyntheticSensor& s, uint64_t seed) {
  HdrFrames f;
  f.name = "synthetic stack";
  f.width = width;
  f.height = height;
  f.bit_depth = s.bit_depth;
  f.exposure_s = exposure_s;
  f.dark_s = dark_s;
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> normal(0.0, 1.0);
  std::uniform_real_distribution<double> uniform(0.5, 1.5);
  // Dark current differs from pixel to pixel (fixed for the stack).
  std::vector<double> rate(f.pixels());
  for (double& r : rate) r = s.dark_rate_dn_per_s * uniform(rng);
  for (size_t i : s.hot_pixels) rate.at(i) = s.hot_rate_dn_per_s;
  const double top = double((1u << s.bit_depth) - 1u);
  auto frame = [&](double t, bool lit) {
    std::vector<uint16_t> v(f.pixels());
    for (size_t i = 0; i < v.size(); ++i) {
      double signal = t * rate[i] + (lit ? t * psf[i] : 0.0);
      double sigma = std::sqrt(s.gain_dn_per_e * signal + s.read_noise_dn * s.read_noise_dn);
      v[i] = uint16_t(std::clamp(std::round(s.offset_dn + signal + sigma * normal(rng)), 0.0, top));
    }
    return v;
  };
  for (double t : exposure_s) f.exposures.push_back(frame(t, true));
  for (double t : dark_s) f.darks.push_back(frame(t, false));
  return f;
}

}  // namespace prism
