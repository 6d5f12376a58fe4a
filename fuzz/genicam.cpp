// A camera's GenICam XML (hw/genicam.h), read from the device: parsed into a
// node map over 64 KiB of register memory, then every feature the scripted
// test camera has read and a few written.
#include <cstring>
#include <map>

#include "fuzz/fuzz.h"
#include "hw/genicam.h"

namespace {

struct Memory : prism::hw::RegisterPort {
  std::vector<uint8_t> bytes = std::vector<uint8_t>(1 << 16, 0x5a);
  prism::hw::Bytes read(uint64_t address, size_t count) override {
    if (address > bytes.size() || count > bytes.size() - address) throw std::runtime_error("read outside the registers");
    return prism::hw::Bytes(bytes.begin() + long(address), bytes.begin() + long(address + count));
  }
  void write(uint64_t address, std::span<const uint8_t> data) override {
    if (address > bytes.size() || data.size() > bytes.size() - address)
      throw std::runtime_error("write outside the registers");
    std::memcpy(bytes.data() + address, data.data(), data.size());
  }
};

}  // namespace

namespace prism::fuzz {

void genicam(const uint8_t* data, size_t size) {
  const std::string xml(reinterpret_cast<const char*>(data), size);
  Memory port;
  try {
    prism::hw::NodeMap map(xml, port);
    for (const char* name : {"Width", "Height", "PixelFormat", "ExposureTime", "Gain", "AcquisitionStart",
                             "AcquisitionStop", "BinningHorizontal", "BinningVertical", "SensorWidth", "Root"}) {
      try {
        if (!map.has(name)) continue;
        (void)map.type(name);
        (void)map.get_string(name);
        if (map.type(name) == "Enumeration") (void)map.enum_entries(name);
        if (map.type(name) == "Integer" || map.type(name) == "Float") (void)map.range(name);
        map.set_string(name, "1");
      } catch (const std::runtime_error&) {
      }
    }
  } catch (const std::runtime_error&) {
  }
}

}  // namespace prism::fuzz

PRISM_FUZZ_MAIN(genicam)
