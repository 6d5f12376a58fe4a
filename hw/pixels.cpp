#include "hw/pixels.h"

#include <stdexcept>

namespace prism::hw {

std::string pixel_format_name(uint32_t f) {
  switch (f) {
    case kMono8: return "Mono8";
    case kMono12: return "Mono12";
    case kMono12p: return "Mono12p";
    case kMono16: return "Mono16";
  }
  char s[64];
  snprintf(s, sizeof s, "unsupported PFNC 0x%08x", f);
  return s;
}

uint32_t pixel_format_from_name(const std::string& n) {
  for (uint32_t f : {kMono8, kMono12, kMono12p, kMono16})
    if (pixel_format_name(f) == n) return f;
  throw std::runtime_error("pixel format '" + n + "' is not supported; use Mono8, Mono12, Mono12p or Mono16");
}

unsigned bit_depth(uint32_t f) {
  switch (f) {
    case kMono8: return 8;
    case kMono12:
    case kMono12p: return 12;
    case kMono16: return 16;
  }
  throw std::runtime_error("cannot unpack " + pixel_format_name(f) + "; set PixelFormat to Mono8/12/12p/16");
}

uint64_t image_bytes(uint32_t f, uint32_t w, uint32_t h) {
  uint64_t n = uint64_t(w) * h;
  switch (f) {
    case kMono8: return n;
    case kMono12p: return (n * 12 + 7) / 8;
    default: return bit_depth(f) ? n * 2 : 0;
  }
}

std::vector<uint16_t> unpack(uint32_t f, std::span<const uint8_t> raw, uint32_t w, uint32_t h) {
  const uint64_t n = uint64_t(w) * h;
  if (raw.size() < image_bytes(f, w, h))
    throw std::runtime_error(pixel_format_name(f) + " image of " + std::to_string(w) + "x" + std::to_string(h) +
                             " needs " + std::to_string(image_bytes(f, w, h)) + " bytes, got " +
                             std::to_string(raw.size()));
  std::vector<uint16_t> out(n);
  switch (f) {
    case kMono8:
      for (uint64_t i = 0; i < n; ++i) out[i] = raw[i];
      break;
    case kMono12:
    case kMono16: {
      const uint16_t keep = f == kMono12 ? 0x0FFF : 0xFFFF;  // Mono12 upper nibble is padding
      for (uint64_t i = 0; i < n; ++i) out[i] = uint16_t(raw[2 * i] | raw[2 * i + 1] << 8) & keep;
      break;
    }
    case kMono12p:
      for (uint64_t i = 0; i < n; ++i) {
        const uint8_t* p = &raw[i / 2 * 3];
        out[i] = i % 2 == 0 ? uint16_t(p[0] | (p[1] & 0x0F) << 8) : uint16_t(p[1] >> 4 | p[2] << 4);
      }
      break;
    default: bit_depth(f);  // throws with the advice
  }
  return out;
}

}  // namespace prism::hw
