// Little-endian field access for wire formats (GenCP, U3V leader/trailer).
#pragma once
#include <cstddef>
#include <cstdint>
#include <span>
#include <string>
#include <vector>

namespace prism::hw {

using Bytes = std::vector<uint8_t>;

inline uint64_t get_le(std::span<const uint8_t> b, size_t off, size_t n) {
  uint64_t v = 0;
  for (size_t i = 0; i < n; ++i) v |= uint64_t(b[off + i]) << (8 * i);
  return v;
}
inline uint16_t get16(std::span<const uint8_t> b, size_t off) { return uint16_t(get_le(b, off, 2)); }
inline uint32_t get32(std::span<const uint8_t> b, size_t off) { return uint32_t(get_le(b, off, 4)); }
inline uint64_t get64(std::span<const uint8_t> b, size_t off) { return get_le(b, off, 8); }

inline void put_le(Bytes& b, uint64_t v, size_t n) {
  for (size_t i = 0; i < n; ++i) b.push_back(uint8_t(v >> (8 * i)));
}
inline void set_le(std::span<uint8_t> b, size_t off, uint64_t v, size_t n) {
  for (size_t i = 0; i < n; ++i) b[off + i] = uint8_t(v >> (8 * i));
}

// A fixed-size, NUL-padded string field (ABRM names).
inline std::string get_string(std::span<const uint8_t> b, size_t off, size_t n) {
  std::string s;
  for (size_t i = 0; i < n && b[off + i] != 0; ++i) s.push_back(char(b[off + i]));
  return s;
}

}  // namespace prism::hw
