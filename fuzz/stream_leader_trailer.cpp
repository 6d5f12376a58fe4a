// USB3 Vision stream leaders and trailers (hw/stream.h): the first byte picks
// which parser gets the rest.
#include "fuzz/fuzz.h"
#include "hw/stream.h"

namespace prism::fuzz {

void stream_leader_trailer(const uint8_t* data, size_t size) {
  if (size == 0) return;
  std::string why;
  const std::vector<uint8_t> block(data + 1, data + size);
  if (data[0] & 1) (void)prism::hw::parse_trailer(block, why);
  else (void)prism::hw::parse_leader(block, why);
}

}  // namespace prism::fuzz

PRISM_FUZZ_MAIN(stream_leader_trailer)
