// The finer levels' tiles of a PSF dictionary, as stored (half-float bits),
// in one LRU cache shared by the dictionary services of a process's host
// threads (host/dictionary/service.h). Shared because the threads descend
// events from the same volume: with a cache each, two threads decoded
// nearly every tile twice (97,241 tiles for 1000 volume events against
// 60,366 on one thread; results/shared-tiles-2783). Thread-safe.
//
// A tile is read on a miss by the caller's own function, outside the lock
// (decoding is most of a miss's time), into room reserved first, so that the
// cache's bytes never pass its room. A caller pins the tiles whose values it
// is reading; a pinned tile is never evicted. A pin that would need a pinned
// tile's room fails instead (pin() returns null): the caller unpins what it
// holds and reads one tile at a time, pinning each with `wait`, which waits
// for other callers' pins and reads to end rather than fail while any are
// under way. Only a caller that holds nothing waits: one holding pins never
// waits, and a tile's read must not take room (a service opens the tile's
// file before it pins), so the callers cannot wait for one another in a
// circle.
//
// Both threads look tiles up all the time (1.8 million look-ups for 1000
// events), so a look-up writes nothing it need not: tiles are found through
// a table per (PSF, level) rather than a tree, and evicted by the clock
// (second chance) rather than by a list kept in order of use. With a tree
// and a list the shared cache read 38% fewer tiles and still cost more host
// time than a cache per thread.
#pragma once
#include <condition_variable>
#include <cstdint>
#include <functional>
#include <memory>
#include <mutex>
#include <utility>
#include <span>
#include <tuple>
#include <vector>

namespace prism {

class TileCache {
 public:
  using Key = std::tuple<size_t, int, int, int>;  // psf, level, tile x, tile y
  // A cached tile: tile_values halves; a value is the half times scale.
  struct Tile {
    const uint16_t* bits;
    float scale;
  };
  // What one caller's look-ups did (each service counts its own).
  struct Counts {
    uint64_t hits = 0, misses = 0, evictions = 0;
  };
  // Reads a tile into the span and returns its scale (PsfFile::read_tile).
  using Reader = std::function<float(std::span<uint16_t>)>;

  // What the cache holds tiles of: PSFs, each with levels of these sizes.
  struct Shape {
    size_t psfs = 0;
    int tile_px = 0;
    std::vector<std::pair<int, int>> level_px;  // width, height per level
  };
  explicit TileCache(const Shape& shape);
  ~TileCache();
  TileCache(const TileCache&) = delete;
  TileCache& operator=(const TileCache&) = delete;

  // Adds a service's share of the host budget to the room.
  void add_room(uint64_t bytes);
  // Other memory held within the same room (a service's open PSF files):
  // unpinned tiles are evicted to make room for it. False where the room
  // cannot hold it; `wait` as pin's (the caller holding nothing).
  bool take_room(uint64_t bytes, Counts& counts, bool wait);
  void give_room(uint64_t bytes);
  uint64_t tile_bytes() const { return tile_values_ * sizeof(uint16_t); }

  // The tile at key, pinned until unpin(), read with `read` on a miss (which
  // must not take room from this cache). Null when the room is too small for
  // one more tile without evicting a pinned one; with `wait` (the caller
  // holding nothing) only when no tile at all is pinned or being read. If
  // `read` throws, nothing is cached and the exception propagates.
  const Tile* pin(const Key& key, const Reader& read, Counts& counts, bool wait = false);
  // The tile at key pinned if it is cached, else null (nothing counted).
  const Tile* pin_cached(const Key& key, Counts& counts);
  void unpin(std::span<const Tile* const> tiles);
  // Pinned tiles of all callers (zero when none is reading).
  size_t pinned() const;

  uint64_t bytes() const;       // tiles cached or being read, and the room taken
  uint64_t peak_bytes() const;  // the most at any moment

 private:
  struct Entry : Tile {
    int pins = 0;
    bool used = false;  // looked up since the clock last passed it
    Entry** slot;       // its place in the table of its PSF and level
  };
  // The tiles' memory: blocks of 2 MiB carved into tiles, an evicted tile's
  // room reused. A block is one allocation and, where the kernel gives
  // transparent huge pages, one page fault; a tile each cost both (6% of a
  // 1000-event search's CPU time went to allocating and first touching
  // tiles). The room counts the tiles handed out, not the last block's room
  // not yet handed out (under 2 MiB).
  class Slabs {
   public:
    explicit Slabs(size_t values);  // values per tile
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
  // Under the lock: the table slot of key (the table made at its first use).
  Entry*& slot(const Key& key);
  // Under the lock: a cached tile found, marked used and pinned.
  const Tile* hit(Entry* e, Counts& counts);
  // Under the lock: evicts unpinned tiles, the clock's way, until `need`
  // more bytes fit; false if they cannot.
  bool make_room(uint64_t need, Counts& counts);
  // Under the lock: waits until make_room(need) succeeds (false where it
  // cannot: without `wait`, or with no tile pinned or being read); `found`
  // ends the wait early (another caller cached the tile meanwhile).
  bool wait_for_room(std::unique_lock<std::mutex>& lock, uint64_t need, Counts& counts, bool wait,
                     const std::function<bool()>& found);
  void account(int64_t delta);

  const size_t tile_values_;
  const int levels_;
  std::vector<std::pair<int, int>> tiles_xy_;  // per level: tiles across and down
  mutable std::mutex mutex_;
  std::condition_variable unpinned_;  // signalled when pins are released while a caller waits
  uint64_t room_ = 0, bytes_ = 0, peak_ = 0;
  size_t pinned_ = 0, waiting_ = 0, reading_ = 0;  // tiles pinned, callers waiting, reads under way
  std::vector<std::unique_ptr<Entry*[]>> tables_;  // per (PSF, level): its tiles' entries, null where not cached
  std::vector<std::unique_ptr<Entry>> resident_;   // the cached tiles, in the clock's circle
  size_t hand_ = 0;                                // the clock's hand: the next to look at in resident_
  std::vector<std::unique_ptr<Entry>> spare_;      // entries to reuse
  Slabs slabs_;
};

}  // namespace prism
