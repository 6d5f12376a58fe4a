// Small helpers for the benchmarks: medians over repeats, and a line naming
// the machine and the device so every figure says where it was measured.
#pragma once
#include <algorithm>
#include <cstdint>
#include <chrono>
#include <fstream>
#include <string>
#include <thread>
#include <vector>

#include <sys/resource.h>

namespace prism::bench {

// The process's peak resident set so far, bytes (Linux reports KiB).
inline uint64_t peak_rss_bytes() {
  rusage u{};
  getrusage(RUSAGE_SELF, &u);
  return uint64_t(u.ru_maxrss) * 1024;
}

inline double median(std::vector<double> v) {
  std::sort(v.begin(), v.end());
  size_t n = v.size();
  return n % 2 ? v[n / 2] : 0.5 * (v[n / 2 - 1] + v[n / 2]);
}

// Median wall time in seconds of `repeats` calls to f().
template <class F> double median_seconds(int repeats, F&& f) {
  std::vector<double> t;
  for (int i = 0; i < repeats; ++i) {
    auto start = std::chrono::steady_clock::now();
    f();
    t.push_back(std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count());
  }
  return median(t);
}

inline std::string host_cpu() {
  std::ifstream in("/proc/cpuinfo");
  std::string line;
  while (std::getline(in, line))
    if (line.rfind("model name", 0) == 0) return line.substr(line.find(':') + 2);
  return "unknown CPU";
}

inline std::string machine_line() {
  return host_cpu() + ", " + std::to_string(std::thread::hardware_concurrency()) + " hardware threads";
}

}  // namespace prism::bench
