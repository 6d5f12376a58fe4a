// A progress line on stderr for long work: redrawn in place on a terminal,
// a line every 10% otherwise (logs, CI).
#pragma once
#include <chrono>
#include <cstddef>
#include <string>

namespace prism {

class Progress {
 public:
  // shown = false: silent (the MPI ranks other than 0, which report for all).
  Progress(std::string what, size_t total, bool shown = true);
  void update(size_t done);  // call as work completes; prints when due
  void finish();

 private:
  std::string what_;
  size_t total_;
  bool tty_;
  bool shown_;
  int last_decile_ = -1;
  std::chrono::steady_clock::time_point start_ = std::chrono::steady_clock::now();
  std::chrono::steady_clock::time_point last_draw_{};
};

}  // namespace prism
