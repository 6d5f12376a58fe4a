// A USB3 Vision camera: open, bootstrap, GenICam features, streaming.
// The one type the commands use; see hw/README.md for the layers below it.
#pragma once
#include <memory>

#include "hw/bootstrap.h"
#include "hw/genicam.h"
#include "hw/stream.h"
#include "hw/usb.h"

namespace prism::hw {

class Camera : public RegisterPort {
 public:
  // Opens the camera with this serial (the first one when empty), reads its
  // bootstrap registers and GenICam XML.
  explicit Camera(const std::string& serial = "");
  ~Camera() override;

  const CameraInfo& usb_info() const { return dev_.info(); }
  const Bootstrap& bootstrap() const { return boot_; }
  NodeMap& features() { return *nodes_; }
  GenCp& gencp() { return gencp_; }

  Bytes read(uint64_t address, size_t count) override { return gencp_.read(address, count); }
  void write(uint64_t address, std::span<const uint8_t> data) override { gencp_.write(address, data); }

  // Writes SIRM from the camera's required sizes and returns the layout used.
  StreamLayout configure_stream(uint32_t max_transfer_bytes = 1u << 20);
  // Configures SIRM, starts acquisition, collects `frames` frames, stops.
  StreamResult stream(unsigned frames, const std::function<void(Frame&&)>& on_frame, const StreamOptions& opt = {});

 private:
  UsbContext ctx_;
  UsbDevice dev_;
  GenCp gencp_;
  Bootstrap boot_;
  std::unique_ptr<NodeMap> nodes_;
};

}  // namespace prism::hw
