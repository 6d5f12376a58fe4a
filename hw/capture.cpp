#include "hw/capture.h"

#include <cmath>
#include <fstream>
#include <nlohmann/json.hpp>

#include "engine/hdr_times.h"
#include "hw/camera.h"
#include "hw/pixels.h"

namespace prism::hw {
namespace {

// Grabs one frame at the current settings and writes it as 16-bit LE samples.
void grab(Camera& cam, const std::filesystem::path& file, nlohmann::json& meta) {
  Frame frame;
  StreamResult r = cam.stream(1, [&](Frame&& f) { frame = std::move(f); });
  if (r.delivered != 1) {
    std::string why = r.error;
    for (auto& [reason, n] : r.drops) why += "; dropped " + std::to_string(n) + " (" + reason + ")";
    throw std::runtime_error("no frame for " + file.filename().string() + ": " + why);
  }
  std::vector<uint16_t> px = unpack(frame.pixel_format, frame.data, frame.width, frame.height);
  std::ofstream os(file, std::ios::binary);
  for (uint16_t v : px) os.put(char(v & 0xFF)).put(char(v >> 8));
  if (!os) throw std::runtime_error("cannot write " + file.string() + "; check the disk and permissions");
  meta["width"] = frame.width;
  meta["height"] = frame.height;
  meta["pixel_format"] = pixel_format_name(frame.pixel_format);
  meta["bit_depth"] = bit_depth(frame.pixel_format);
}

}  // namespace

std::vector<double> log_exposures(double lo, double hi, unsigned m) {
  if (m == 0 || lo <= 0 || hi < lo) throw std::runtime_error("exposure range must satisfy 0 < min <= max and m >= 1");
  return log_spaced_times(lo, hi, m);
}

std::filesystem::path capture_hdr(Camera& cam, Stage& stage, const CaptureOptions& opt, std::ostream& progress) {
  auto [lo, hi] = cam.features().range("ExposureTime");
  double min_us = opt.min_us.value_or(lo), max_us = opt.max_us.value_or(hi);
  if (!std::isfinite(min_us) || !std::isfinite(max_us))
    throw std::runtime_error("camera's ExposureTime has no range; pass --min-us and --max-us");
  std::vector<double> times = log_exposures(min_us, max_us, opt.exposures);
  std::filesystem::create_directories(opt.out_dir);

  nlohmann::json meta;
  meta["format_version"] = kStackFormatVersion;
  meta["source"] = {{"x_mm", opt.x_mm}, {"y_mm", opt.y_mm}, {"depth_mm", opt.depth_mm}};
  meta["camera"] = {{"vendor", cam.bootstrap().manufacturer},
                    {"model", cam.bootstrap().model},
                    {"serial", cam.bootstrap().serial}};
  meta["exposures"] = nlohmann::json::array();
  meta["darks"] = nlohmann::json::array();
  stage.move_to(opt.x_mm, opt.y_mm, opt.depth_mm);

  const unsigned total = opt.exposures + opt.darks;
  unsigned done = 0;
  auto shoot = [&](double us, const std::string& name, const char* list) {
    cam.features().set_float("ExposureTime", us);
    double actual = cam.features().get_float("ExposureTime");  // the camera may round
    grab(cam, opt.out_dir / name, meta);
    meta[list].push_back({{"exposure_us", actual}, {"file", name}});
    progress << "[" << ++done << "/" << total << "] " << name << " at " << actual << " us\n" << std::flush;
  };
  stage.set_source(true);
  for (unsigned i = 0; i < times.size(); ++i) shoot(times[i], "exposure_" + std::to_string(i) + ".raw", "exposures");
  // Darks at several exposure times, so that the merge subtracts each pixel's
  // dark current at each exposure's own time (engine/hdr_times.h says why).
  stage.set_source(false);
  const std::vector<double> dark_us = dark_times(times, opt.darks);
  for (unsigned i = 0; i < dark_us.size(); ++i) shoot(dark_us[i], "dark_" + std::to_string(i) + ".raw", "darks");

  auto manifest = opt.out_dir / "stack.json";
  std::ofstream(manifest) << meta.dump(2) << "\n";
  return manifest;
}

}  // namespace prism::hw
