// Serving a PSF dictionary under a memory budget. The coarse level the support
// search correlates against stays resident on the device, packed into storage
// buffers of at most maxStorageBufferRange (128 MiB on lavapipe), each PSF's
// values (float, or half floats at the store's scale) followed by its
// summed-area table in float (and on a CPU device by the scan's row table);
// the tables stay on the host too, in double. Finer levels are read tile by
// tile, only around the pixels asked for, into an LRU cache that never exceeds the host
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
  // counts them), tiles and open files of its own within `budget`, nothing
  // on a device. `first` must outlive it.
  DictionaryService(const DictionaryService& first, ServiceBudget budget);

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

  const ServiceStats& stats() const { return stats_; }

 private:
  using TileKey = std::tuple<size_t, int, int, int>;  // psf, level, tile x, tile y
  // A tile as stored (half-float bits, half the bytes of floats: twice the
  // tiles in the same budget); a value is the half times scale, exactly the
  // float the file reads as.
  struct Tile {
    uint16_t* bits;  // tile_px^2 values in slabs_
    float scale;
    std::list<TileKey>::iterator lru;
  };
  // The tiles' memory: blocks of 2 MiB carved into tiles, an evicted tile's
  // room reused. A block is one allocation and, where the kernel gives
  // transparent huge pages, one page fault; a tile each cost both (6% of a
  // 1000-event search's CPU time went to allocating and first touching
  // tiles). The budget counts the tiles handed out, not the last block's
  // room not yet handed out (under 2 MiB per service).
  class TileSlabs {
   public:
    explicit TileSlabs(size_t values);  // values per tile
    uint16_t* take();
    void give(uint16_t* tile) { free_.push_back(tile); }

   private:
    struct Free {
      void operator()(uint16_t* p) const;
    };
    size_t values_, per_block_;  // values per tile, tiles per block
    size_t left_ = 0;            // tiles of the last block not yet handed out
    std::vector<std::unique_ptr<uint16_t, Free>> blocks_;
    std::vector<uint16_t*> free_;
  };
  const Tile& tile(size_t i, int level, int tx, int ty);
  PsfFile& open_file(size_t i);
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
  std::map<TileKey, Tile> tiles_;
  TileSlabs slabs_;
  std::list<TileKey> lru_;  // front: most recent
  std::list<PsfFile> files_;  // open PSF files, front: most recently read
  ServiceStats stats_;
};

}  // namespace prism
