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

#include <nlohmann/json.hpp>

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
  // Collective: items 0..n-1 done in turn (item i by the process that takes
  // it); `mine` holds this process's results in item order, and every
  // process gets all n, in item order.
  std::vector<nlohmann::json> gather_items(size_t n, const nlohmann::json& mine) const {
    std::vector<nlohmann::json> all(n);
    const auto parts = all_gather(mine.dump());
    for (size_t r = 0; r < parts.size(); ++r) {
      const auto theirs = nlohmann::json::parse(parts[r]);
      for (size_t k = 0; k < theirs.size(); ++k) all.at(r + k * count) = theirs[k];
    }
    return all;
  }
};

}  // namespace prism
