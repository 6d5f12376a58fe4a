// Serving a PSF dictionary under a memory budget. The coarse level the support
// search correlates against stays resident on the device, packed into storage
// buffers of at most maxStorageBufferRange (128 MiB on lavapipe), each PSF's
// values (float, or half floats at the store's scale) followed by its
// summed-area table in float (and on a CPU device by the scan's row table);
// the tables stay on the host too, in double. Finer levels are read tile by
// tile, only around the pixels asked for, into a cache (tile_cache.h, shared
// by the services of a process's host threads) that never exceeds the host
// budget. A dictionary far larger than memory is served this way. A pixel
// under a dark pixel of the coarse level is known to be zero: its tile is not
// read for it.
#pragma once
#include <cstdint>
#include <list>
#include <map>
#include <memory>
#include <span>
#include <tuple>
#include <vector>

#include <glm/glm.hpp>

#include "engine/support_scan.h"
#include "engine/vk/compute.h"
#include "host/dictionary/store.h"
#include "host/dictionary/tile_cache.h"

namespace prism {

struct ServiceBudget {
  uint64_t host_bytes = 1ull << 30;    // summed-area tables + tile cache + open files
  uint64_t device_bytes = 1ull << 30;  // resident coarse level
  // PSF files kept open between tile reads (most recently read first): an
  // event's carried PSFs are read level after level, tile after tile, so a
  // few open files spare most reopenings.
  int open_files = 16;
};

struct ServiceStats {
  uint64_t host_bytes = 0, host_peak_bytes = 0, device_bytes = 0;
  uint64_t tile_hits = 0, tile_misses = 0, evictions = 0;
  uint64_t bytes_read = 0;  // tile bytes fetched from disk, decompressed (half floats, as stored)
  uint64_t file_opens = 0;  // PSF files opened for tiles (the coarse level's reads not counted)
  uint64_t dark_pixels = 0;  // pixels asked for that are dark on the coarse level: zeros, no tile read
  // Another service's counts added (peaks and device bytes too: services side by side).
  ServiceStats& operator+=(const ServiceStats& o);
};

class DictionaryService {
 public:
  // ctx may be null: nothing is put on a device (CPU-only users). device_half
  // stores the coarse values on the device as half floats (half the bytes).
  DictionaryService(const DictionaryReader& reader, vk::Context* ctx, int coarse_level, ServiceBudget budget,
                    bool device_half = false);
  // A service beside `first` for another host thread: the same dictionary
  // and coarse level, the coarse level's tables shared (read-only; `first`
  // counts them) and so is the tile cache (`budget` adds to its room, which
  // holds the open files too), open files of its own, nothing on a device.
  // `first` must outlive it.
  DictionaryService(const DictionaryService& first, ServiceBudget budget);
  ~DictionaryService();
  DictionaryService(const DictionaryService&) = delete;
  DictionaryService& operator=(const DictionaryService&) = delete;

  // What the coarse level of every PSF takes on the device: values and float
  // summed-area tables, and the row tables where device_rows() says so.
  static uint64_t device_bytes(const DictionaryManifest& m, int coarse_level, bool device_half, bool rows);
  // Whether the service puts the support scan's row tables (ScanLevel::rows)
  // beside the float values: on a CPU device, where the serial scan reads
  // them, and only while the level with them fits the device budget.
  static bool device_rows(const DictionaryManifest& m, int coarse_level, const vk::Context* ctx, bool device_half,
                          uint64_t device_budget_bytes);

  const DictionaryManifest& manifest() const { return reader_.manifest(); }
  int coarse_level() const { return coarse_level_; }

  // Where PSF i's coarse level lives on the device: buffer, first word of its
  // values (float offset when not half) and of its summed-area table.
  struct Slot {
    uint32_t chunk;
    uint64_t offset;
    uint64_t sat_offset;
  };
  Slot coarse_slot(size_t i) const { return slots_.at(i); }
  const vk::Buffer& coarse_chunk(uint32_t c) const { return *chunks_.at(c); }
  size_t coarse_chunks() const { return chunks_.size(); }
  const SummedArea& coarse_mass(size_t i) const { return tables_->mass.at(i); }
  // The coarse level as the support-scan kernels read it (radii left 0 for the
  // caller); throws when the service was made without a device.
  ScanLevel scan_level() const;
  // The scale of half-float values on the device (the store's 2^15).
  static constexpr float device_half_scale = 32768.0f;

  // PSF i at `level` for each pixel; tiles are fetched and cached as needed.
  std::vector<float> values(size_t i, int level, std::span<const glm::ivec2> pixels);

  // This service's counts; host bytes are its tables, and in the first
  // service the shared tile cache's (the tiles and every service's open
  // files, whose room the cache holds).
  ServiceStats stats() const;

 private:
  // PSF i's file, opened (its room taken from the tile cache, waiting as
  // TileCache::pin does with `wait`) if it is not open; null where the room
  // cannot hold it.
  PsfFile* open_file(size_t i, bool wait);
  void account(int64_t delta);

  const DictionaryReader& reader_;
  int coarse_level_;
  ServiceBudget budget_;
  bool device_half_ = false;
  bool device_rows_ = false;
  std::vector<std::unique_ptr<vk::Buffer>> chunks_;
  std::vector<Slot> slots_;
  // The coarse level on the host, per PSF: its summed-area table and lit pixels.
  struct CoarseTables {
    std::vector<SummedArea> mass;
    std::vector<LitPixels> lit;
  };
  std::shared_ptr<CoarseTables> tables_;
  // The finer levels' tiles, shared with the services made beside this one
  // (the first service's stats count its bytes).
  std::shared_ptr<TileCache> tiles_;
  bool owns_tiles_;
  TileCache::Counts tile_counts_;
  std::list<PsfFile> files_;  // open PSF files, front: most recently read
  ServiceStats stats_;
};

}  // namespace prism
