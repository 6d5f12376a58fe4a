// The memory a command may use, and estimates of its large allocations that
// are checked against it before the work starts: a request far beyond the
// machine is refused with the estimate and the option to change, instead of
// ending in std::bad_alloc, a Vulkan out-of-memory error or the OOM killer.
#pragma once
#include <cstdint>
#include <stdexcept>
#include <string>
#include <utility>
#include <vector>

namespace prism {

struct ResourceError : std::runtime_error {
  using std::runtime_error::runtime_error;
};

// Physical memory of this machine, or its control group's limit when that is
// smaller (containers, batch jobs), in bytes.
uint64_t machine_memory_bytes();

// The limit estimates are checked against: default_memory_fraction of
// machine_memory_bytes() (the rest for the Vulkan driver, its shader
// compiler and the system) unless set (`--max-memory`, PRISM_MAX_MEMORY).
inline constexpr double default_memory_fraction = 0.75;
uint64_t memory_limit_bytes();
void set_memory_limit_bytes(uint64_t bytes);
void use_default_memory_limit();
// Where the limit came from, for messages: "75% of this machine's 7.8 GiB"
// or "--max-memory".
std::string memory_limit_origin();

// "8G", "512M", "1.5GiB", "300k", "4096" (bytes): K, M, G, T are powers of
// 1024, with or without "iB"/"B". Throws std::invalid_argument naming `option`.
uint64_t parse_memory_size(const std::string& text, const std::string& option);
// "1.5 GiB", "312 MiB", "900 B".
std::string format_bytes(double bytes);

// The large allocations of one piece of work, each named. Sizes are doubles:
// products of user-given sizes (sensor pixels x levels x PSFs) never wrap.
class MemoryEstimate {
 public:
  explicit MemoryEstimate(std::string work) : work_(std::move(work)) {}
  MemoryEstimate& add(std::string part, double bytes);
  // A device's buffers count only on a CPU device (lavapipe), where they are
  // host memory; a GPU's own memory is the Vulkan driver's to refuse.
  MemoryEstimate& add_device_buffers(double bytes, bool cpu_device) {
    return cpu_device ? add("the device's buffers, host memory on a CPU device", bytes) : *this;
  }
  double total_bytes() const;
  // Throws ResourceError when the total exceeds memory_limit_bytes(), with
  // the total, its parts (largest first), the limit and its origin, and
  // `to_reduce`: the options that make it smaller.
  void require_within_limit(const std::string& to_reduce) const;

 private:
  std::string work_;
  std::vector<std::pair<std::string, double>> parts_;
};

}  // namespace prism
