// `prism camera ...`: list USB3 Vision cameras, get/set GenICam features,
// stream frames, and capture an HDR calibration stack (see hw/README.md).
#include <chrono>
#include <iostream>
#include <memory>

#include "host/cmd/commands.h"
#include "host/cmd/options.h"
#include "hw/camera.h"
#include "hw/capture.h"

namespace prism::cmd {
namespace {

struct CameraArgs {
  std::string serial, feature, value;
  unsigned frames = 100;
  hw::CaptureOptions capture;
  double min_us = 0, max_us = 0;
};

void list() {
  hw::UsbContext ctx;
  auto cams = hw::list_cameras(ctx);
  if (cams.empty()) std::cout << "no USB3 Vision camera found\n";
  for (const auto& c : cams)
    std::printf("bus %03u device %03u  %04x:%04x  %s %s  serial %s  speed %s\n", c.bus, c.address, c.vendor_id,
                c.product_id, c.vendor.c_str(), c.model.c_str(), c.serial.c_str(), c.speed.c_str());
}

void stream(const CameraArgs& a) {
  hw::Camera cam(a.serial);
  auto start = std::chrono::steady_clock::now();
  hw::StreamResult r = cam.stream(a.frames, [&](hw::Frame&& f) {
    if (f.block_id % 10 == 0) std::cerr << "frame " << f.block_id << " (" << f.width << "x" << f.height << ")\r";
  });
  double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  std::cout << r.delivered << " frames in " << s << " s (" << (s > 0 ? r.delivered / s : 0) << " fps)\n";
  if (r.frames_dropped) std::cout << r.frames_dropped << " frames dropped\n";
  for (const auto& [why, n] : r.drops) std::cout << "dropped " << n << ": " << why << "\n";
  if (r.stalls_cleared) std::cout << "stream endpoint stalls cleared: " << r.stalls_cleared << "\n";
  if (!r.error.empty()) throw std::runtime_error(r.error);
}

void capture(CameraArgs& a) {
  hw::Camera cam(a.serial);
  hw::NoStage stage;  // the LED stage is not driven yet: the source must already be in place
  if (a.min_us > 0) a.capture.min_us = a.min_us;
  if (a.max_us > 0) a.capture.max_us = a.max_us;
  auto manifest = hw::capture_hdr(cam, stage, a.capture, std::cerr);
  std::cout << "wrote " << manifest.string() << "\n";
}

}  // namespace

void add_camera(CLI::App& app) {
  auto a = std::make_shared<CameraArgs>();
  CLI::App* cam = app.add_subcommand("camera", "USB3 Vision camera: list, features, streaming, HDR capture");
  cam->require_subcommand(1);
  cam->add_option("--serial", a->serial, "camera serial number (default: the first camera found)");

  cam->add_subcommand("list", "list USB3 Vision cameras")->callback(list);

  CLI::App* get = cam->add_subcommand("get", "print a GenICam feature");
  get->add_option("FEATURE", a->feature, "e.g. ExposureTime, Width, PixelFormat")->required();
  get->callback([a] {
    hw::Camera c(a->serial);
    std::cout << c.features().get_string(a->feature) << "\n";
  });

  CLI::App* set = cam->add_subcommand("set", "set a GenICam feature (a command feature runs with any value)");
  set->add_option("FEATURE", a->feature)->required();
  set->add_option("VALUE", a->value)->required();
  set->callback([a] {
    hw::Camera c(a->serial);
    c.features().set_string(a->feature, a->value);
    if (c.features().type(a->feature) != "Command")
      std::cout << a->feature << " = " << c.features().get_string(a->feature) << "\n";
  });

  CLI::App* st = cam->add_subcommand("stream", "stream frames and report rate and drops");
  st->add_option("--frames", a->frames, "frames to receive")->capture_default_str();
  st->callback([a] { stream(*a); });

  CLI::App* hdr = cam->add_subcommand("capture-hdr", "capture an HDR calibration stack for one source position");
  hdr->add_option("--out", a->capture.out_dir, "output directory (stack.json + .raw frames)")->required();
  hdr->add_option("--exposures", a->capture.exposures, "number of exposure times")->capture_default_str();
  hdr->add_option("--darks", a->capture.darks, darks_help)->capture_default_str()->check(CLI::Range(1u, 64u));
  hdr->add_option("--min-us", a->min_us, "shortest exposure in us (default: the camera's minimum)");
  hdr->add_option("--max-us", a->max_us, "longest exposure in us (default: the camera's maximum)");
  hdr->add_option("--x-mm", a->capture.x_mm, "source x position (mm)");
  hdr->add_option("--y-mm", a->capture.y_mm, "source y position (mm)");
  hdr->add_option("--depth-mm", a->capture.depth_mm, "source depth (mm)");
  hdr->callback([a] { capture(*a); });
}

}  // namespace prism::cmd
