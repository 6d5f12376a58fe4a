// Reconstruction with all the workers a backend has: the device backends use
// one Reconstructor (a batch goes to the device whole); the CPU reference
// runs one Reconstructor and one dictionary service per thread (the tile
// cache is not shared), events dealt round-robin.
#pragma once
#include <memory>
#include <span>
#include <vector>

#include "engine/vk/context.h"
#include "host/dictionary/service.h"
#include "host/reconstruct/reconstruct.h"

namespace prism {

struct PoolOptions {
  ReconstructionBackend backend = ReconstructionBackend::vulkan;
  vk::Context* ctx = nullptr;        // required by the device backends
  unsigned threads = 1;              // host threads: the cpu backend's workers (each scans and descends); with a
                                     // device backend, threads descending events beside the device's scan
  uint64_t host_budget_bytes = 1ull << 30;  // summed-area tables, tiles and open files, all workers together
  bool device_half = false;          // the scan level on the device as half floats
};

class ReconstructionPool {
 public:
  // settings.search_level < 0 takes default_search_level(); the services are
  // made with the search level as their coarse level.
  ReconstructionPool(const DictionaryReader& reader, int click_level, ReconstructionSettings settings,
                     const PoolOptions& options);
  ~ReconstructionPool();

  // Per event, its K vertices (Reconstructor::run).
  std::vector<std::vector<ReconstructedVertex>> run(std::span<const Event> events);

  unsigned workers() const { return unsigned(workers_.size()); }
  unsigned host_threads() const { return unsigned(services_.size()); }  // one service per host thread
  int search_level() const { return settings_.search_level; }
  const ReconstructionSettings& settings() const { return settings_; }
  ReconstructionTimings timings() const;  // summed over the workers
  ServiceStats dictionary_stats() const;  // the tiles read and skipped, summed over the workers

 private:
  ReconstructionSettings settings_;
  std::vector<std::unique_ptr<DictionaryService>> services_;
  std::vector<std::unique_ptr<Reconstructor>> workers_;
};

}  // namespace prism
