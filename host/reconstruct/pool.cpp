#include "host/reconstruct/pool.h"

#include <algorithm>
#include <exception>
#include <stdexcept>
#include <string>
#include <thread>

#include "host/util/format.h"
#include "host/util/memory.h"

namespace prism {

ReconstructionPool::ReconstructionPool(const DictionaryReader& reader, int click_level, ReconstructionSettings s,
                                       const PoolOptions& o)
    : settings_(s) {
  const auto& m = reader.manifest();
  if (settings_.search_level < 0) settings_.search_level = default_search_level(m, click_level, settings_.tau_mm);
  if (settings_.search_level < click_level || settings_.search_level >= m.levels)
    throw std::invalid_argument("search level " + std::to_string(settings_.search_level) + ": choose a level from " +
                                std::to_string(click_level) + " (the clicks' own) to " + std::to_string(m.levels - 1) +
                                " (the coarsest in " + reader.dir() + ")");
  const double shifts = scan_shifts(m, settings_.search_level, settings_.tau_mm);
  if (shifts > max_scan_shifts)
    throw std::invalid_argument("the support scan on level " + std::to_string(settings_.search_level) + " with tau " +
                                format_number(settings_.tau_mm) + " mm holds " + format_number(shifts) +
                                " shifts of the PSFs per click, more than " + format_number(max_scan_shifts) +
                                ": choose a coarser --level or a smaller --tau-mm");
  const bool on_device = o.backend != ReconstructionBackend::cpu;
  const unsigned n = std::max(1u, o.threads);
  {
    // The host budget holds the summed-area tables and the tile cache; the
    // scan level on a CPU device is host memory too.
    const int L = settings_.search_level;
    MemoryEstimate memory("the support search on level " + std::to_string(L) + " of " +
                          std::to_string(m.grid.size()) + " PSFs (" + std::to_string(m.level_width(L)) + " x " +
                          std::to_string(m.level_height(L)) + " px each)");
    memory.add("summed-area tables and tiles (--budget-mib)", double(o.host_budget_bytes));
    if (on_device && o.ctx) {
      const bool rows = DictionaryService::device_rows(m, L, o.ctx, o.device_half, ServiceBudget{}.device_bytes);
      memory.add_device_buffers(double(DictionaryService::device_bytes(m, L, o.device_half, rows)), o.ctx->is_cpu());
    }
    memory.require_within_limit("Use a smaller --budget-mib or a coarser --level");
  }
  ServiceBudget budget;
  budget.host_bytes = o.host_budget_bytes / n;
  if (on_device) {
    // One worker: the device scans, n threads descend, each through a
    // service of its own (the first holds the scan level on the device, the
    // coarse tables and the tile cache, which the others share; each
    // service's share of the budget adds to the cache's room).
    services_.push_back(std::make_unique<DictionaryService>(reader, o.ctx, settings_.search_level, budget, o.device_half));
    for (unsigned t = 1; t < n; ++t) services_.push_back(std::make_unique<DictionaryService>(*services_[0], budget));
    std::vector<DictionaryService*> helpers;
    for (unsigned t = 1; t < n; ++t) helpers.push_back(services_[t].get());
    workers_.push_back(std::make_unique<Reconstructor>(*services_[0], click_level, settings_, o.backend, o.ctx, helpers));
    return;
  }
  for (unsigned t = 0; t < n; ++t) {  // the cpu backend: workers that each scan and descend
    services_.push_back(std::make_unique<DictionaryService>(reader, nullptr, settings_.search_level, budget));
    workers_.push_back(std::make_unique<Reconstructor>(*services_.back(), click_level, settings_, o.backend, o.ctx));
  }
}

ReconstructionPool::~ReconstructionPool() = default;

std::vector<std::vector<ReconstructedVertex>> ReconstructionPool::run(std::span<const Event> events) {
  if (workers_.size() == 1) return workers_[0]->run(events);
  std::vector<std::vector<ReconstructedVertex>> out(events.size());
  const size_t n = workers_.size();
  std::vector<std::exception_ptr> failures(n);
  std::vector<std::thread> pool;
  for (size_t t = 0; t < n; ++t)
    pool.emplace_back([&, t] {
      try {
        for (size_t i = t; i < events.size(); i += n) out[i] = std::move(workers_[t]->run(events.subspan(i, 1)).at(0));
      } catch (...) {
        failures[t] = std::current_exception();
      }
    });
  for (auto& th : pool) th.join();
  for (auto& f : failures)
    if (f) std::rethrow_exception(f);
  return out;
}

ReconstructionTimings ReconstructionPool::timings() const {
  ReconstructionTimings sum;
  for (const auto& w : workers_) {
    const auto& t = w->timings();
    sum.scan_s += t.scan_s;
    sum.scan_wait_s += t.scan_wait_s;
    sum.scan_kernel_ms += t.scan_kernel_ms;
    sum.host_s += t.host_s;
    sum.scans += t.scans;
    sum.scan_fallbacks += t.scan_fallbacks;
    sum.scan_fits += t.scan_fits;
    sum.scan_candidates += t.scan_candidates;
    sum.scan_device_bytes = std::max(sum.scan_device_bytes, t.scan_device_bytes);
  }
  return sum;
}

ServiceStats ReconstructionPool::dictionary_stats() const {
  ServiceStats sum;
  for (const auto& d : services_) sum += d->stats();
  return sum;
}

}  // namespace prism
