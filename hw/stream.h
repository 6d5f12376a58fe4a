// U3V streaming: leader / payload / trailer over the stream bulk endpoint with
// several frames of asynchronous libusb transfers in flight. A frame is handed
// out only when its trailer arrives and every check passes; anything else is
// a drop counted by reason, never a torn frame.
#pragma once
#include <functional>
#include <map>
#include <optional>
#include <string>

#include "hw/bytes.h"

namespace prism::hw {

class UsbDevice;

struct Leader {
  uint64_t block_id = 0, timestamp = 0;
  uint32_t pixel_format = 0, width = 0, height = 0;
};
struct Trailer {
  uint64_t block_id = 0, valid_payload_size = 0;
  uint16_t status = 0;
  uint32_t height = 0;
};
// Pure parsers (fuzzed in tests/hw); nullopt with the reason in `why`.
std::optional<Leader> parse_leader(std::span<const uint8_t> b, std::string& why);
std::optional<Trailer> parse_trailer(std::span<const uint8_t> b, std::string& why);

// How one frame is cut into transfers; written to SIRM before streaming.
struct StreamLayout {
  uint64_t payload_size = 0;      // bytes of image data per frame
  uint32_t max_leader = 0, max_trailer = 0;
  uint32_t transfer_size = 0, transfer_count = 0;
  uint32_t final1 = 0, final2 = 0;  // final transfers for the remainder (0 = none)
};
// Splits `payload` in transfers of at most `max_transfer` bytes, multiples of `alignment`.
StreamLayout plan_layout(uint64_t payload, uint32_t alignment, uint32_t leader, uint32_t trailer,
                         uint32_t max_transfer = 1u << 20);

struct Frame {
  uint64_t block_id = 0, timestamp = 0;
  uint32_t pixel_format = 0, width = 0, height = 0;
  Bytes data;  // exactly payload_size bytes
};

struct StreamResult {
  unsigned delivered = 0;
  // Frames the camera sent that were not delivered, counted by block id (the
  // camera numbers its frames one by one): a frame dropped for a reason, and
  // the frames missing between two frames whose leaders arrived. Frames lost
  // after the last good leader of a run (an unplug) cannot be counted.
  unsigned frames_dropped = 0;
  // Why, as events by reason: a frame whose leader was lost may add several
  // "resync" events while the stream finds the next leader.
  std::map<std::string, unsigned> drops;
  std::string error;                      // why streaming stopped early; empty when all frames came
  unsigned stalls_cleared = 0;
};

struct StreamOptions {
  unsigned frames_in_flight = 3;  // frames of transfers queued at once
  unsigned idle_timeout_ms = 3000;  // stop when no transfer completes for this long
  uint32_t max_transfer_bytes = 1u << 20;  // largest payload transfer requested from the camera
};

// Streams until `frames` frames were delivered to `on_frame`, or an error
// (unplug, timeout, usbfs memory) stops it. Frames delivered before stay delivered.
StreamResult run_stream(UsbDevice& dev, const StreamLayout& layout, unsigned frames,
                        const std::function<void(Frame&&)>& on_frame, const StreamOptions& opt = {});

}  // namespace prism::hw
