#include "host/dictionary/tile_cache.h"

#include <sys/mman.h>

#include <algorithm>
#include <cstdlib>
#include <new>
#include <stdexcept>
#include <string>

namespace prism {

namespace {
constexpr size_t kSlabBytes = size_t(2) << 20;  // a huge page on x86-64 and arm64
}  // namespace

void TileCache::Slabs::Free::operator()(uint16_t* p) const { std::free(p); }

TileCache::Slabs::Slabs(size_t values)
    : values_(values), per_block_(std::max<size_t>(1, kSlabBytes / (values * sizeof(uint16_t)))) {}

uint16_t* TileCache::Slabs::take() {
  if (!free_.empty()) {
    uint16_t* tile = free_.back();
    free_.pop_back();
    return tile;
  }
  if (left_ == 0) {
    const size_t used = per_block_ * values_ * sizeof(uint16_t);
    const size_t bytes = (used + kSlabBytes - 1) / kSlabBytes * kSlabBytes;  // aligned_alloc: a multiple of the alignment
    auto* block = static_cast<uint16_t*>(std::aligned_alloc(kSlabBytes, bytes));
    if (!block) throw std::bad_alloc();
#ifdef MADV_HUGEPAGE
    madvise(block, bytes, MADV_HUGEPAGE);  // a hint: without it, small pages
#endif
    blocks_.emplace_back(block);
    left_ = per_block_;
  }
  return blocks_.back().get() + (per_block_ - left_--) * values_;
}

TileCache::TileCache(const Shape& shape)
    : tile_values_(size_t(shape.tile_px) * size_t(shape.tile_px)), levels_(int(shape.level_px.size())),
      tables_(shape.psfs * shape.level_px.size()), slabs_(tile_values_) {
  const int t = shape.tile_px;
  for (auto [w, h] : shape.level_px) tiles_xy_.push_back({(w + t - 1) / t, (h + t - 1) / t});
}
TileCache::~TileCache() = default;

void TileCache::add_room(uint64_t bytes) {
  std::lock_guard lock(mutex_);
  room_ += bytes;
}

size_t TileCache::pinned() const {
  std::lock_guard lock(mutex_);
  return pinned_;
}

uint64_t TileCache::bytes() const {
  std::lock_guard lock(mutex_);
  return bytes_;
}

uint64_t TileCache::peak_bytes() const {
  std::lock_guard lock(mutex_);
  return peak_;
}

void TileCache::account(int64_t delta) {
  bytes_ = uint64_t(int64_t(bytes_) + delta);
  peak_ = std::max(peak_, bytes_);
}

TileCache::Entry*& TileCache::slot(const Key& key) {
  const auto [psf, level, tx, ty] = key;
  const auto [nx, ny] = tiles_xy_.at(size_t(level));
  if (tx < 0 || ty < 0 || tx >= nx || ty >= ny) throw std::out_of_range("TileCache: no tile (" + std::to_string(tx) + ", " + std::to_string(ty) + ") on level " + std::to_string(level));
  auto& table = tables_.at(psf * size_t(levels_) + size_t(level));
  if (!table) table = std::make_unique<Entry*[]>(size_t(nx) * size_t(ny));  // all null
  return table[size_t(ty) * size_t(nx) + size_t(tx)];
}

bool TileCache::make_room(uint64_t need, Counts& counts) {
  // The clock: a tile looked up since the hand last passed it is passed
  // over once (its mark cleared), a pinned one always; the first other one
  // goes. Two turns without finding one: every tile is pinned.
  size_t looked = 0;
  while (bytes_ + need > room_ && !resident_.empty() && looked < 2 * resident_.size()) {
    if (hand_ >= resident_.size()) hand_ = 0;
    Entry& e = *resident_[hand_];
    ++looked;
    if (e.pins > 0 || e.used) {
      e.used = false;
      ++hand_;
      continue;
    }
    *e.slot = nullptr;
    slabs_.give(const_cast<uint16_t*>(e.bits));
    spare_.push_back(std::move(resident_[hand_]));
    resident_[hand_] = std::move(resident_.back());  // the hand looks at it next
    resident_.pop_back();
    account(-int64_t(tile_bytes()));
    ++counts.evictions;
    looked = 0;
  }
  return bytes_ + need <= room_;
}

bool TileCache::wait_for_room(std::unique_lock<std::mutex>& lock, uint64_t need, Counts& counts, bool wait,
                              const std::function<bool()>& found) {
  for (;;) {
    if ((found && found()) || make_room(need, counts)) return true;
    if (!wait || (pinned_ == 0 && reading_ == 0)) return false;
    ++waiting_;
    unpinned_.wait(lock);
    --waiting_;
  }
}

bool TileCache::take_room(uint64_t bytes, Counts& counts, bool wait) {
  std::unique_lock lock(mutex_);
  if (!wait_for_room(lock, bytes, counts, wait, nullptr)) return false;
  account(int64_t(bytes));
  return true;
}

void TileCache::give_room(uint64_t bytes) {
  std::lock_guard lock(mutex_);
  account(-int64_t(bytes));
  if (waiting_ > 0) unpinned_.notify_all();
}

const TileCache::Tile* TileCache::hit(Entry* e, Counts& counts) {
  ++counts.hits;
  e->used = true;
  ++e->pins, ++pinned_;
  return e;
}

const TileCache::Tile* TileCache::pin_cached(const Key& key, Counts& counts) {
  std::lock_guard lock(mutex_);
  Entry* e = slot(key);
  return e ? hit(e, counts) : nullptr;
}

const TileCache::Tile* TileCache::pin(const Key& key, const Reader& read, Counts& counts, bool wait) {
  uint16_t* bits = nullptr;
  {
    std::unique_lock lock(mutex_);
    Entry* e = nullptr;
    if (!wait_for_room(lock, tile_bytes(), counts, wait, [&] { return (e = slot(key)) != nullptr; })) return nullptr;
    if (e) return hit(e, counts);
    bits = slabs_.take();
    account(int64_t(tile_bytes()));  // reserved while it is read
    ++reading_;
  }
  auto give_back = [&] {
    slabs_.give(bits);
    account(-int64_t(tile_bytes()));
  };
  float scale = 0;
  try {
    scale = read(std::span<uint16_t>(bits, tile_values_));
  } catch (...) {
    std::lock_guard lock(mutex_);
    give_back();
    --reading_;
    if (waiting_ > 0) unpinned_.notify_all();
    throw;
  }
  std::lock_guard lock(mutex_);
  --reading_;
  if (waiting_ > 0) unpinned_.notify_all();
  ++counts.misses;
  Entry*& s = slot(key);
  if (s) {
    give_back();  // another caller read it meanwhile: theirs serves
  } else {
    std::unique_ptr<Entry> e;
    if (spare_.empty()) {
      e = std::make_unique<Entry>();
    } else {
      e = std::move(spare_.back());
      spare_.pop_back();
    }
    e->bits = bits;
    e->scale = scale;
    e->pins = 0;
    e->slot = &s;
    s = e.get();
    resident_.push_back(std::move(e));
  }
  s->used = true;
  ++s->pins, ++pinned_;
  return s;
}

void TileCache::unpin(std::span<const Tile* const> tiles) {
  std::lock_guard lock(mutex_);
  // Every tile pin() returns is an entry's; pinned, it is still cached.
  for (const Tile* t : tiles) --const_cast<Entry*>(static_cast<const Entry*>(t))->pins;
  pinned_ -= tiles.size();
  if (waiting_ > 0) unpinned_.notify_all();
}

}  // namespace prism
