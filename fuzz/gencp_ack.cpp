// GenCP acknowledges from the camera (hw/gencp.h): a malformed one is
// nullopt with the reason, never an exception or a read past the packet.
#include "fuzz/fuzz.h"
#include "hw/gencp.h"

namespace prism::fuzz {

void gencp_ack(const uint8_t* data, size_t size) {
  std::string why;
  // A copy of exactly `size` bytes, so that AddressSanitizer sees a read past it.
  const std::vector<uint8_t> packet(data, data + size);
  (void)prism::hw::parse_ack(packet, why);
}

}  // namespace prism::fuzz

PRISM_FUZZ_MAIN(gencp_ack)
