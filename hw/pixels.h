// PFNC pixel formats the driver unpacks, and unpacking to 16-bit samples.
#pragma once
#include <cstdint>
#include <span>
#include <string>
#include <vector>

namespace prism::hw {

inline constexpr uint32_t kMono8 = 0x01080001;    // 8 bits per pixel
inline constexpr uint32_t kMono12 = 0x01100005;   // 12 bits in a little-endian 16-bit word
inline constexpr uint32_t kMono12p = 0x010C0047;  // 12 bits, two pixels in 3 bytes, LSB first
inline constexpr uint32_t kMono16 = 0x01100007;   // 16 bits little-endian

std::string pixel_format_name(uint32_t pfnc);
uint32_t pixel_format_from_name(const std::string& name);  // throws for unsupported names
unsigned bit_depth(uint32_t pfnc);                         // significant bits per sample
// Bytes an image of w x h takes in `pfnc` on the wire.
uint64_t image_bytes(uint32_t pfnc, uint32_t width, uint32_t height);
// Unpacks to one uint16 per pixel (value range 0 .. 2^bit_depth - 1).
std::vector<uint16_t> unpack(uint32_t pfnc, std::span<const uint8_t> raw, uint32_t width, uint32_t height);

}  // namespace prism::hw
