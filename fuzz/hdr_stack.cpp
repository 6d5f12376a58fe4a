// HDR calibration stacks (host/dictionary/hdr_stack.h): stack.json from a
// capture, with raw frames beside it (exposure_0.raw and dark_0.raw, 8 x 8
// samples of 256, are there to be named).
#include "fuzz/fuzz.h"
#include "host/dictionary/hdr_stack.h"

namespace prism::fuzz {

void hdr_stack(const uint8_t* data, size_t size) {
  static const auto dir = [] {
    const auto d = prism::fuzz::scratch() / "stack";
    std::filesystem::create_directories(d);
    std::vector<uint8_t> frame(8 * 8 * 2, 0);
    for (size_t i = 1; i < frame.size(); i += 2) frame[i] = 1;  // 256, little-endian
    prism::fuzz::write_file(d / "exposure_0.raw", frame.data(), frame.size());
    prism::fuzz::write_file(d / "dark_0.raw", frame.data(), frame.size());
    return d;
  }();
  prism::fuzz::write_file(dir / "stack.json", data, size);
  try {
    (void)prism::read_hdr_stack(dir.string());
  } catch (const std::runtime_error&) {
  }
}

}  // namespace prism::fuzz

PRISM_FUZZ_MAIN(hdr_stack)
