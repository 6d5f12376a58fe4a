// The processes of one job that share a piece of work (`prism dictionary
// build`, `evaluate` and `sweep` under an MPI launcher; host/cmd/ranks.h makes
// one per rank). The library decides what each process takes; the command
// layer supplies the means of exchange, so the library never links MPI. A
// plain run is the default: one process that takes everything.
#pragma once
#include <cstddef>
#include <functional>
#include <string>
#include <string_view>
#include <vector>

namespace prism {

struct WorkShare {
  size_t index = 0;  // this process, 0..count-1
  size_t count = 1;
  // Item k of a sequence every process enumerates the same way is this
  // process's when k mod count = index: neighbours go to different processes,
  // so work whose cost drifts along the sequence stays balanced.
  bool takes(size_t k) const { return k % count == index; }
  size_t taken_of(size_t n) const { return (n + count - 1 - index) / count; }  // how many of 0..n-1
  bool leads() const { return index == 0; }  // writes what the job writes
  // Collective when count > 1: every process calls them, the same number of
  // times in the same order. all_gather returns every process's bytes, in
  // process order, on every process.
  std::function<std::vector<std::string>(std::string_view mine)> all_gather;
  std::function<void()> barrier;
  void wait_for_all() const {
    if (count > 1) barrier();
  }
};

}  // namespace prism
