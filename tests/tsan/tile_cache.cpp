// The shared tile cache (host/dictionary/tile_cache.h) under ThreadSanitizer:
// four threads pin up to five tiles at a time of a small dictionary's shape,
// each read by a filler that writes the tile's own tag, in room for 12 tiles
// (so batches are at times refused and fall back, as
// DictionaryService::values does, to one tile at a time with `wait`), some
// found by pin_cached, while taking and giving back other room (open files). Every tile read must hold
// its tag while pinned; at the end nothing stays pinned and the cache is
// within its room. A data race is TSan's report (halt_on_error: the run
// fails). tests/sanitize.sh builds and runs it; it needs no Vulkan, no files.
#include <atomic>
#include <cstdio>
#include <random>
#include <span>
#include <thread>
#include <vector>

#include "host/dictionary/tile_cache.h"

int main() {
  using prism::TileCache;
  TileCache::Shape shape{6, 8, {{40, 24}, {20, 12}, {10, 6}}};
  TileCache cache(shape);
  const uint64_t room = 12 * cache.tile_bytes();
  cache.add_room(room);
  std::atomic<long> wrong{0}, refused{0}, pins{0};
  std::vector<std::thread> threads;
  for (int t = 0; t < 4; ++t)
    threads.emplace_back([&, t] {
      std::mt19937 rng{uint32_t(t)};
      TileCache::Counts counts;
      for (int round = 0; round < 20000; ++round) {
        std::vector<const TileCache::Tile*> held;
        std::vector<uint16_t> tags;
        const int n = 1 + int(rng() % 5);
        for (int k = 0; k < n; ++k) {
          const size_t psf = rng() % shape.psfs;
          const int level = int(rng() % 2), tx = int(rng() % 3), ty = int(rng() % 2);
          const auto tag = uint16_t(psf * 1000 + size_t(level) * 100 + size_t(tx) * 10 + size_t(ty));
          auto fill = [tag](std::span<uint16_t> bits) {
            for (uint16_t& b : bits) b = tag;
            return float(tag);
          };
          // One tile at a time once a batch is refused, as the service does,
          // holding nothing: then also room for a file, waited for.
          const bool alone = held.empty() && k == n - 1;
          const bool file = alone && rng() % 3 == 0 && cache.take_room(100, counts, true);
          const TileCache::Tile* tile = rng() % 2 ? cache.pin_cached({psf, level, tx, ty}, counts) : nullptr;
          if (!tile) tile = cache.pin({psf, level, tx, ty}, fill, counts, alone);
          if (file) cache.give_room(100);
          if (!tile) {
            ++refused;
            continue;
          }
          ++pins;
          held.push_back(tile);
          tags.push_back(tag);
          if (rng() % 3 == 0 && cache.take_room(100, counts, false)) cache.give_room(100);  // holding pins: no wait
        }
        for (size_t j = 0; j < held.size(); ++j)
          wrong += held[j]->bits[0] != tags[j] || held[j]->bits[cache.tile_bytes() / 2 - 1] != tags[j] ||
                   held[j]->scale != float(tags[j]);
        if (!held.empty()) cache.unpin(held);
      }
    });
  for (auto& th : threads) th.join();
  std::printf("tsan tile_cache: %ld pins, %ld refused, %ld wrong; %zu pinned at the end, peak %llu of %llu bytes\n",
              pins.load(), refused.load(), wrong.load(), cache.pinned(), (unsigned long long)cache.peak_bytes(),
              (unsigned long long)room);
  const bool ok = wrong == 0 && cache.pinned() == 0 && cache.peak_bytes() <= room && pins > 0 && refused > 0;
  if (!ok) std::printf("tsan tile_cache: FAILED\n");
  return ok ? 0 : 1;
}
