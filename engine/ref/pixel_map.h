// A map from pixel key (row * grid width + col) to a value, for the CPU
// reference's sparse images and the calibration's models built from them.
//
// Open addressing (linear probing) over a power-of-two table of indices into
// one vector of (key, value) entries, kept in the order the keys first came.
// std::unordered_map allocated a node per pixel and rehashed as an image
// grew: its operations, malloc and free were about a fifth of a calibration
// step of the whole prototype (perf). Here a pixel costs no allocation of its
// own, iteration walks a contiguous vector, and its order (first touch) does
// not depend on the table's size. Keys are never erased.
#pragma once

#include <cstddef>
#include <cstdint>
#include <utility>
#include <vector>

namespace prism::ref {

template <class Value>
class PixelMap {
 public:
  using Entry = std::pair<int64_t, Value>;

  // The value of `key`, value-initialised (zeros) on first use.
  Value& operator[](int64_t key) {
    if (2 * (entries_.size() + 1) > slots_.size()) grow();
    size_t s = slot_of(key);
    for (; slots_[s] != 0; s = (s + 1) & mask_)
      if (entries_[slots_[s] - 1].first == key) return entries_[slots_[s] - 1].second;
    entries_.emplace_back(key, Value{});
    slots_[s] = uint32_t(entries_.size());
    return entries_.back().second;
  }
  // The value of `key`, or nullptr where no pixel has it.
  const Value* find(int64_t key) const {
    if (entries_.empty()) return nullptr;
    for (size_t s = slot_of(key); slots_[s] != 0; s = (s + 1) & mask_)
      if (entries_[slots_[s] - 1].first == key) return &entries_[slots_[s] - 1].second;
    return nullptr;
  }
  bool contains(int64_t key) const { return find(key) != nullptr; }

  size_t size() const { return entries_.size(); }
  bool empty() const { return entries_.empty(); }
  // Entries in the order their keys were first used.
  auto begin() { return entries_.begin(); }
  auto end() { return entries_.end(); }
  auto begin() const { return entries_.begin(); }
  auto end() const { return entries_.end(); }

  // Bytes per entry at most, for memory estimates: the entry, the vector's
  // doubling slack, and at most 4 index slots per entry (the table doubles
  // when half full).
  static constexpr double bytes_per_entry_bound = 2.0 * sizeof(Entry) + 4 * sizeof(uint32_t);

 private:
  // Fibonacci hashing: the key times 2^64 / golden ratio, its top bits.
  size_t slot_of(int64_t key) const { return size_t((uint64_t(key) * 0x9E3779B97F4A7C15ull) >> shift_); }
  void grow() {
    const size_t n = slots_.empty() ? 64 : 2 * slots_.size();
    shift_ = 64;  // 64 - log2(n)
    for (size_t m = n; m > 1; m >>= 1) --shift_;
    mask_ = n - 1;
    slots_.assign(n, 0);
    for (size_t i = 0; i < entries_.size(); ++i) {
      size_t s = slot_of(entries_[i].first);
      while (slots_[s] != 0) s = (s + 1) & mask_;
      slots_[s] = uint32_t(i + 1);
    }
  }

  std::vector<Entry> entries_;
  std::vector<uint32_t> slots_;  // 1 + the entry's index; 0: empty
  size_t mask_ = 0;
  int shift_ = 64;
};

}  // namespace prism::ref
