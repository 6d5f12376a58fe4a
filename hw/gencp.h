// GenCP over the U3V control endpoints: packet encoding/parsing (pure, fuzzed
// in tests/hw) and one transaction function that owns request ids, retries,
// pending acknowledges and status-to-error mapping (cf. Aravis
// arvuvdevice.c _send_cmd_and_receive_ack).
#pragma once
#include <optional>
#include <stdexcept>
#include <string>

#include "hw/bytes.h"
#include "hw/u3v_regs.h"

namespace prism::hw {

class UsbDevice;

// The device answered with a GenCP status other than success.
class GenCpError : public std::runtime_error {
 public:
  GenCpError(const std::string& what, uint16_t status);
  uint16_t status;
};

std::string status_text(uint16_t status);

Bytes encode_readmem(uint16_t request_id, uint64_t address, uint16_t count);
Bytes encode_writemem(uint16_t request_id, uint64_t address, std::span<const uint8_t> data);

struct Ack {
  uint16_t status = 0;
  uint16_t command = 0;
  uint16_t request_id = 0;
  Bytes scd;  // command-specific data
};
// Parses an acknowledge; on malformed input returns nullopt and says why in `why`.
std::optional<Ack> parse_ack(std::span<const uint8_t> packet, std::string& why);

class GenCp {
 public:
  explicit GenCp(UsbDevice& dev);
  Bytes read(uint64_t address, size_t count);
  void write(uint64_t address, std::span<const uint8_t> data);
  uint32_t read32(uint64_t address) { return get32(read(address, 4), 0); }
  uint64_t read64(uint64_t address) { return get64(read(address, 8), 0); }
  void write32(uint64_t address, uint32_t v);
  void write64(uint64_t address, uint64_t v);

  // From SBRM: largest command and acknowledge transfers the device handles.
  void set_transfer_limits(uint32_t max_cmd, uint32_t max_ack);
  // From ABRM: how long the device may take to acknowledge (ms).
  void set_response_timeout(unsigned ms) { timeout_ms_ = ms; }

  unsigned retries = 0;       // commands sent again after a timeout
  unsigned pending_acks = 0;  // PENDING_ACKs received
  unsigned stale_acks = 0;    // acks for an older request id, skipped

 private:
  Bytes transact(const Bytes& command, uint16_t request_id, uint16_t expected_ack);
  bool send(const Bytes& command);
  std::optional<Ack> receive(unsigned timeout_ms);

  UsbDevice& dev_;
  uint16_t next_id_ = 1;
  size_t max_cmd_ = 128, max_ack_ = 128;  // small and safe until SBRM gives the real limits
  unsigned timeout_ms_ = 1000;
  static constexpr int kAttempts = 3;
};

}  // namespace prism::hw
