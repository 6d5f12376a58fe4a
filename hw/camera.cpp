#include "hw/camera.h"

namespace prism::hw {

Camera::Camera(const std::string& serial) : dev_(ctx_, serial), gencp_(dev_) {
  boot_ = read_bootstrap(gencp_);
  nodes_ = std::make_unique<NodeMap>(fetch_genicam_xml(gencp_, boot_.manifest_address), *this);
}

Camera::~Camera() = default;

StreamLayout Camera::configure_stream(uint32_t max_transfer_bytes) {
  if (boot_.stream_channels == 0 || !dev_.stream_in)
    throw std::runtime_error("camera has no USB3 Vision stream interface");
  const uint64_t sirm = boot_.sirm_address;
  gencp_.write32(sirm + u3v::kSirmControl, 0);  // SIRM may only change while disabled
  uint64_t payload = gencp_.read64(sirm + u3v::kSirmRequiredPayload);
  uint32_t leader = gencp_.read32(sirm + u3v::kSirmRequiredLeader);
  uint32_t trailer = gencp_.read32(sirm + u3v::kSirmRequiredTrailer);
  StreamLayout l = plan_layout(payload, boot_.payload_alignment, leader, trailer, max_transfer_bytes);
  gencp_.write32(sirm + u3v::kSirmMaxLeader, l.max_leader);
  gencp_.write32(sirm + u3v::kSirmPayloadTransferSize, l.transfer_size);
  gencp_.write32(sirm + u3v::kSirmPayloadTransferCount, l.transfer_count);
  gencp_.write32(sirm + u3v::kSirmFinalTransfer1, l.final1);
  gencp_.write32(sirm + u3v::kSirmFinalTransfer2, l.final2);
  gencp_.write32(sirm + u3v::kSirmMaxTrailer, l.max_trailer);
  return l;
}

StreamResult Camera::stream(unsigned frames, const std::function<void(Frame&&)>& on_frame,
                            const StreamOptions& opt) {
  StreamLayout l = configure_stream(opt.max_transfer_bytes);
  gencp_.write32(boot_.sirm_address + u3v::kSirmControl, u3v::kSirmEnable);
  nodes_->execute("AcquisitionStart");
  StreamResult r = run_stream(dev_, l, frames, on_frame, opt);
  // Stopping fails once the camera is gone; the stream result already says why.
  try {
    nodes_->execute("AcquisitionStop");
    gencp_.write32(boot_.sirm_address + u3v::kSirmControl, 0);
  } catch (const std::exception& e) {
    if (r.error.empty()) r.error = std::string("stopping acquisition: ") + e.what();
  }
  return r;
}

}  // namespace prism::hw
