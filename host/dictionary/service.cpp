#include "host/dictionary/service.h"

#include <sys/mman.h>

#include <algorithm>
#include <array>
#include <cstdlib>
#include <cstring>
#include <new>

#include <Imath/half.h>

namespace prism {

namespace {
std::string mib(uint64_t b) { return std::to_string((b + (1 << 20) - 1) >> 20) + " MiB"; }
// What a service's budget leaves the tile cache (and the open files, which
// take their room from it): the rest after its tables.
uint64_t tile_room(const ServiceBudget& b, uint64_t tables) { return b.host_bytes > tables ? b.host_bytes - tables : 0; }
TileCache::Shape tile_shape(const DictionaryManifest& m) {
  TileCache::Shape s{m.grid.size(), m.tile_px, {}};
  for (int l = 0; l < m.levels; ++l) s.level_px.push_back({m.level_width(l), m.level_height(l)});
  return s;
}
}  // namespace

namespace {
uint64_t next_multiple_of_4(uint64_t words) { return (words + 3) / 4 * 4; }
// Words of one PSF's coarse level on the device: values (two halves per word,
// or one float), then its float summed-area table; with rows, from the next
// multiple of 4 words, its row table of (w + 3) x h texels of 4 floats
// (ScanLevel::rows; the next PSF starts at a multiple of 4 words too).
uint64_t device_words(const DictionaryManifest& m, int level, bool device_half, bool rows) {
  const uint64_t w = uint64_t(m.level_width(level)), h = uint64_t(m.level_height(level));
  const uint64_t head = (device_half ? (w * h + 1) / 2 : w * h) + (w + 1) * (h + 1);
  return rows ? next_multiple_of_4(head) + (w + 3) * h * 4 : head;
}
}  // namespace

uint64_t DictionaryService::device_bytes(const DictionaryManifest& m, int coarse_level, bool device_half, bool rows) {
  return device_words(m, coarse_level, device_half, rows) * 4 * m.grid.size();
}

bool DictionaryService::device_rows(const DictionaryManifest& m, int coarse_level, const vk::Context* ctx,
                                    bool device_half, uint64_t device_budget_bytes) {
  return ctx && ctx->is_cpu() && !device_half && device_bytes(m, coarse_level, false, true) <= device_budget_bytes;
}

DictionaryService::DictionaryService(const DictionaryReader& reader, vk::Context* ctx, int coarse_level,
                                     ServiceBudget budget, bool device_half)
    : reader_(reader), coarse_level_(coarse_level), budget_(budget), device_half_(device_half),
      device_rows_(device_rows(reader.manifest(), coarse_level, ctx, device_half, budget.device_bytes)),
      tables_(std::make_shared<CoarseTables>()),
      tiles_(std::make_shared<TileCache>(tile_shape(reader.manifest()))),
      owns_tiles_(true) {
  const DictionaryManifest& m = reader.manifest();
  if (coarse_level < 0 || coarse_level >= m.levels)
    throw DictionaryError(reader.dir() + ": no level " + std::to_string(coarse_level) + " (levels 0.." +
                          std::to_string(m.levels - 1) + ")");
  const uint64_t w = uint64_t(m.level_width(coarse_level)), h = uint64_t(m.level_height(coarse_level));
  const uint64_t sat_words = (w + 1) * (h + 1);
  const uint64_t p_words = device_words(m, coarse_level, device_half, false) - sat_words;
  const uint64_t row_word = next_multiple_of_4(p_words + sat_words);  // where the row table starts (device_rows_)
  // On the device: values, then the float table, then the row table.
  const uint64_t psf_bytes = device_words(m, coarse_level, device_half, device_rows_) * 4;
  const uint64_t sat_bytes = (w + 1) * (h + 1) * sizeof(double);
  const size_t n = m.grid.size();
  auto finer_hint = [&] {
    return coarse_level + 1 < m.levels ? "; level " + std::to_string(coarse_level + 1) + " needs a quarter of it" : "";
  };
  const uint64_t lit_bytes = (w + 1) * (h + 1) * sizeof(uint32_t);
  if ((sat_bytes + lit_bytes) * n > budget.host_bytes)
    throw DictionaryError(reader.dir() + ": the summed-area tables of level " + std::to_string(coarse_level) + " need " +
                          mib((sat_bytes + lit_bytes) * n) + ", more than the host budget of " + mib(budget.host_bytes) + finer_hint());
  if (ctx && psf_bytes * n > budget.device_bytes)
    throw DictionaryError(reader.dir() + ": level " + std::to_string(coarse_level) + " needs " + mib(psf_bytes * n) +
                          " on the device (values and summed-area tables), more than the device budget of " +
                          mib(budget.device_bytes) + finer_hint());

  // Pack the coarse level into chunks no larger than one storage buffer may
  // be, nor than the scan kernel's texel view of its values may span
  // (maxTexelBufferElements floats or half floats: support_scan.comp).
  uint64_t chunk_cap = 0;
  if (ctx) {
    const uint64_t texel_cap = uint64_t(ctx->properties().limits.maxTexelBufferElements) * (device_half ? 2 : 4);
    chunk_cap = std::min<uint64_t>({ctx->max_storage_buffer_bytes(), 128ull << 20, texel_cap});
  }
  uint64_t per_chunk = ctx ? std::max<uint64_t>(1, chunk_cap / psf_bytes) : 0;
  std::vector<uint32_t> words(psf_bytes / 4);
  for (size_t i = 0; i < n; ++i) {
    PsfLevel lv = reader.has(i) ? reader.read_level(i, coarse_level)
                                : throw DictionaryError(reader.path_of(i) + ": missing; finish `prism dictionary build`");
    tables_->mass.emplace_back(lv);
    tables_->lit.emplace_back(lv);
    account(int64_t(tables_->mass.back().bytes() + tables_->lit.back().bytes()));
    if (!ctx) continue;
    uint32_t chunk = uint32_t(i / per_chunk);
    uint64_t in_chunk = i % per_chunk;
    if (in_chunk == 0) {
      uint64_t count = std::min<uint64_t>(per_chunk, n - i);
      chunks_.push_back(std::make_unique<vk::Buffer>(*ctx, count * psf_bytes));
      stats_.device_bytes += count * psf_bytes;
    }
    std::fill(words.begin(), words.end(), 0u);
    if (device_half) {
      for (size_t k = 0; k < lv.p.size(); ++k) {
        uint32_t half = glm::packHalf2x16(glm::vec2(lv.p[k] * device_half_scale, 0.0f)) & 0xffffu;
        words[k / 2] |= half << (16 * (k % 2));
      }
    } else {
      std::memcpy(words.data(), lv.p.data(), lv.p.size() * 4);
    }
    const auto& table = tables_->mass.back().table();
    for (size_t k = 0; k < table.size(); ++k) {
      float v = float(table[k]);
      std::memcpy(&words[p_words + k], &v, 4);
    }
    if (device_rows_) {
      // Texel (x, y) = P(x - k, y), k = 0..3, zero off the sensor.
      for (uint64_t y = 0; y < h; ++y)
        for (uint64_t x = 0; x < w + 3; ++x)
          for (uint64_t k = 0; k < 4; ++k) {
            const float v = x >= k && x - k < w ? lv.p[y * w + x - k] : 0.0f;
            std::memcpy(&words[row_word + (y * (w + 3) + x) * 4 + k], &v, 4);
          }
    }
    chunks_[chunk]->upload(words.data(), psf_bytes, in_chunk * psf_bytes);
    const uint64_t first = in_chunk * psf_bytes / 4;
    slots_.push_back({chunk, first, first + p_words});
  }
  tiles_->add_room(tile_room(budget, stats_.host_bytes));
}

DictionaryService::DictionaryService(const DictionaryService& first, ServiceBudget budget)
    : reader_(first.reader_), coarse_level_(first.coarse_level_), budget_(budget), tables_(first.tables_),
      tiles_(first.tiles_), owns_tiles_(false) {
  tiles_->add_room(tile_room(budget, 0));
}

ServiceStats DictionaryService::stats() const {
  ServiceStats s = stats_;
  s.tile_hits = tile_counts_.hits;
  s.tile_misses = tile_counts_.misses;
  s.evictions = tile_counts_.evictions;
  if (owns_tiles_) {
    // Own peak and the cache's, each at its own moment: a bound on the sum's.
    s.host_bytes += tiles_->bytes();
    s.host_peak_bytes += tiles_->peak_bytes();
  }
  return s;
}

ScanLevel DictionaryService::scan_level() const {
  if (chunks_.empty())
    throw DictionaryError(reader_.dir() + ": the dictionary service was made without a device; the Vulkan "
                          "reconstruction needs one");
  const DictionaryManifest& m = reader_.manifest();
  ScanLevel s;
  s.width = m.level_width(coarse_level_);
  s.height = m.level_height(coarse_level_);
  s.half = device_half_;
  s.half_scale = device_half_ ? device_half_scale : 1.0f;
  s.rows = device_rows_;
  for (const auto& c : chunks_) s.chunks.push_back(c.get());
  for (const Slot& slot : slots_) {
    if (slot.sat_offset > 0xffffffffull) throw DictionaryError("scan level: a chunk offset exceeds 32 bits");
    s.psfs.push_back({slot.chunk, uint32_t(slot.offset), uint32_t(slot.sat_offset), 0});
  }
  return s;
}

ServiceStats& ServiceStats::operator+=(const ServiceStats& o) {
  for (auto [a, b] : {std::pair{&host_bytes, o.host_bytes}, {&host_peak_bytes, o.host_peak_bytes},
                      {&device_bytes, o.device_bytes}, {&tile_hits, o.tile_hits}, {&tile_misses, o.tile_misses},
                      {&evictions, o.evictions}, {&bytes_read, o.bytes_read}, {&file_opens, o.file_opens},
                      {&dark_pixels, o.dark_pixels}})
    *a += b;
  return *this;
}

void DictionaryService::account(int64_t delta) {
  stats_.host_bytes = uint64_t(int64_t(stats_.host_bytes) + delta);
  stats_.host_peak_bytes = std::max(stats_.host_peak_bytes, stats_.host_bytes);
}

PsfFile* DictionaryService::open_file(size_t i, bool wait) {
  auto it = std::find_if(files_.begin(), files_.end(), [&](const PsfFile& f) { return f.index() == i; });
  if (it != files_.end()) {
    files_.splice(files_.begin(), files_, it);
    return &files_.front();
  }
  // An open file's room is the tile cache's: unpinned tiles make way for it.
  const uint64_t bytes = PsfFile::bytes(reader_.manifest());
  if (int(files_.size()) >= std::max(1, budget_.open_files)) {
    files_.pop_back();
    tiles_->give_room(bytes);
  }
  if (!tiles_->take_room(bytes, tile_counts_, wait)) return nullptr;
  try {
    files_.emplace_front(reader_, i);
  } catch (...) {
    tiles_->give_room(bytes);
    throw;
  }
  ++stats_.file_opens;
  return &files_.front();
}

DictionaryService::~DictionaryService() {
  tiles_->give_room(files_.size() * PsfFile::bytes(reader_.manifest()));  // the open files' room
}

std::vector<float> DictionaryService::values(size_t i, int level, std::span<const glm::ivec2> pixels) {
  const DictionaryManifest& m = reader_.manifest();
  const int t = m.tile_px, w = m.level_width(level), h = m.level_height(level);
  std::vector<float> out(pixels.size(), 0.0f);
  // Where pixel k's tile is and its place in the tile, or false off the sensor.
  auto tile_of = [&](size_t k, int& tx, int& ty, uint32_t& in_tile) {
    const glm::ivec2 px = pixels[k];
    if (px.x < 0 || px.y < 0 || px.x >= w || px.y >= h) return false;
    tx = px.x / t, ty = px.y / t;
    in_tile = uint32_t((px.y - ty * t) * t + (px.x - tx * t));
    return true;
  };
  // Whether pixel k is dark on the coarse level: no light in it, no tile to
  // read for it. Asked where its tile is not already at hand.
  auto dark = [&](size_t k) {
    if (level >= coarse_level_) return false;
    const int d = coarse_level_ - level, cx = pixels[k].x >> d, cy = pixels[k].y >> d;
    if (tables_->lit[i].count(cx, cy, cx + 1, cy + 1) > 0) return false;
    ++stats_.dark_pixels;
    return true;
  };
  // Tile (tx, ty) pinned; on a miss its file opened first, while this
  // thread holds no reservation of the cache's (TileCache: a read takes no
  // room). Null where the room holds neither.
  auto pin = [&](int tx, int ty, bool wait) -> const TileCache::Tile* {
    const TileCache::Key key{i, level, tx, ty};
    if (const TileCache::Tile* hit = tiles_->pin_cached(key, tile_counts_)) return hit;
    PsfFile* file = open_file(i, wait);
    if (!file) return nullptr;
    auto read = [&](std::span<uint16_t> bits) {
      file->read_tile(level, tx, ty, bits);
      stats_.bytes_read += bits.size() * sizeof(uint16_t);
      return file->value_scale();
    };
    return tiles_->pin(key, read, tile_counts_, wait);
  };
  auto at = [&](const TileCache::Tile* tile, uint32_t in_tile) {
    half v;
    v.setBits(tile->bits[in_tile]);
    return float(v) * tile->scale;
  };
  // The tiles this call holds pinned, unpinned however it ends.
  struct Pins {
    TileCache& cache;
    std::vector<const TileCache::Tile*> held;
    void release() {
      if (!held.empty()) cache.unpin(held);
      held.clear();
    }
    ~Pins() { release(); }
  } pins{*tiles_, {}};

  // The tiles' lines are mostly not in the processor's caches (the search
  // visits hundreds of PSFs per event): every pixel's tile is found and its
  // line requested first, and the values read after, so that the misses
  // overlap. The tiles found are pinned until the end, each once: a table
  // direct-mapped by tile coordinates spares most look-ups (an event's
  // clicks fall in a few tiles).
  struct Seen {
    int tx = -1, ty = -1;
    const TileCache::Tile* tile = nullptr;
  };
  std::array<Seen, 32> seen{};
  std::vector<const TileCache::Tile*> found(pixels.size(), nullptr);
  std::vector<uint32_t> in_tile(pixels.size());
  const uint64_t dark_before = stats_.dark_pixels;
  bool all_pinned = true;
  for (size_t k = 0; k < pixels.size() && all_pinned; ++k) {
    int tx, ty;
    if (!tile_of(k, tx, ty, in_tile[k])) continue;
    Seen& slot = seen[size_t(tx * 7 + ty) % seen.size()];
    if (slot.tx != tx || slot.ty != ty) {
      if (dark(k)) continue;
      const TileCache::Tile* tile = pin(tx, ty, false);  // a tile met again after its slot was taken: pinned twice
      if (!tile) {
        all_pinned = false;
        break;
      }
      pins.held.push_back(tile);
      slot = {tx, ty, tile};
    }
    found[k] = slot.tile;
    __builtin_prefetch(&slot.tile->bits[in_tile[k]]);
  }
  if (all_pinned) {
    for (size_t k = 0; k < pixels.size(); ++k) out[k] = found[k] ? at(found[k], in_tile[k]) : 0.0f;
    return out;
  }
  // The room holds fewer tiles than the call needs beside those pinned: one
  // tile at a time, waiting for other threads' pins where they hold it all.
  pins.release();
  stats_.dark_pixels = dark_before;  // counted again below
  int held_x = -1, held_y = -1;
  for (size_t k = 0; k < pixels.size(); ++k) {
    int tx, ty;
    uint32_t place;
    if (!tile_of(k, tx, ty, place)) continue;
    if (tx != held_x || ty != held_y) {
      if (dark(k)) continue;
      pins.release();
      const TileCache::Tile* tile = pin(tx, ty, true);
      if (!tile)
        throw DictionaryError(reader_.dir() + ": the host budget of " + mib(budget_.host_bytes) +
                              " leaves no room for one tile and its open file; raise it");
      pins.held.push_back(tile);
      held_x = tx, held_y = ty;
    }
    out[k] = at(pins.held.back(), place);
  }
  return out;
}

}  // namespace prism
