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
constexpr size_t kSlabBytes = size_t(2) << 20;  // a huge page on x86-64 and arm64
}  // namespace

void DictionaryService::TileSlabs::Free::operator()(uint16_t* p) const { std::free(p); }

DictionaryService::TileSlabs::TileSlabs(size_t values)
    : values_(values), per_block_(std::max<size_t>(1, kSlabBytes / (values * sizeof(uint16_t)))) {}

uint16_t* DictionaryService::TileSlabs::take() {
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
      slabs_(size_t(reader.manifest().tile_px) * size_t(reader.manifest().tile_px)) {
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
}

DictionaryService::DictionaryService(const DictionaryService& first, ServiceBudget budget)
    : reader_(first.reader_), coarse_level_(first.coarse_level_), budget_(budget), tables_(first.tables_),
      slabs_(size_t(first.reader_.manifest().tile_px) * size_t(first.reader_.manifest().tile_px)) {}

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

const DictionaryService::Tile& DictionaryService::tile(size_t i, int level, int tx, int ty) {
  const int t = reader_.manifest().tile_px;
  TileKey key{i, level, tx, ty};
  auto it = tiles_.find(key);
  if (it != tiles_.end()) {
    ++stats_.tile_hits;
    lru_.splice(lru_.begin(), lru_, it->second.lru);
    return it->second;
  }
  ++stats_.tile_misses;
  uint64_t bytes = uint64_t(t) * t * sizeof(uint16_t);
  // A file opened for the tile counts too, unless it takes a closed one's place.
  const bool file_open = std::any_of(files_.begin(), files_.end(), [&](const PsfFile& f) { return f.index() == i; });
  const bool file_added = !file_open && int(files_.size()) < std::max(1, budget_.open_files);
  const uint64_t need = bytes + (file_added ? PsfFile::bytes(reader_.manifest()) : 0);
  // Make room first, so the budget holds at every moment.
  while (stats_.host_bytes + need > budget_.host_bytes && !lru_.empty()) {
    auto evicted = tiles_.find(lru_.back());
    slabs_.give(evicted->second.bits);
    tiles_.erase(evicted);
    lru_.pop_back();
    account(-int64_t(bytes));
    ++stats_.evictions;
  }
  if (stats_.host_bytes + need > budget_.host_bytes)
    throw DictionaryError(reader_.dir() + ": the host budget of " + mib(budget_.host_bytes) +
                          " leaves no room for one tile and its open file; raise it");
  PsfFile& file = open_file(i);
  uint16_t* bits = slabs_.take();
  try {
    file.read_tile(level, tx, ty, std::span<uint16_t>(bits, size_t(t) * t));
  } catch (...) {
    slabs_.give(bits);
    throw;
  }
  stats_.bytes_read += bytes;
  lru_.push_front(key);
  account(int64_t(bytes));
  return tiles_.emplace(key, Tile{bits, file.value_scale(), lru_.begin()}).first->second;
}

PsfFile& DictionaryService::open_file(size_t i) {
  auto it = std::find_if(files_.begin(), files_.end(), [&](const PsfFile& f) { return f.index() == i; });
  if (it != files_.end()) {
    files_.splice(files_.begin(), files_, it);
    return files_.front();
  }
  const int64_t bytes = int64_t(PsfFile::bytes(reader_.manifest()));
  if (int(files_.size()) >= std::max(1, budget_.open_files)) {
    files_.pop_back();
    account(-bytes);
  }
  files_.emplace_front(reader_, i);
  account(bytes);
  ++stats_.file_opens;
  return files_.front();
}

std::vector<float> DictionaryService::values(size_t i, int level, std::span<const glm::ivec2> pixels) {
  const DictionaryManifest& m = reader_.manifest();
  int t = m.tile_px, w = m.level_width(level), h = m.level_height(level);
  std::vector<float> out(pixels.size(), 0.0f);
  // The tiles this call has touched, direct-mapped by tile coordinates, so
  // that a pixel in one of them costs no look-up in the cache (an event's
  // clicks fall in a few tiles). Valid until a fetch evicts: an evicted
  // tile's values are gone.
  struct Seen {
    int tx = -1, ty = -1;
    const Tile* tile = nullptr;
  };
  std::array<Seen, 32> seen{};
  // Pixel k's half in its tile, or null where no light reaches it.
  auto locate = [&](size_t k, float& scale) -> const uint16_t* {
    glm::ivec2 px = pixels[k];
    if (px.x < 0 || px.y < 0 || px.x >= w || px.y >= h) return nullptr;  // off the sensor: no light
    const int tx = px.x / t, ty = px.y / t;
    Seen& slot = seen[size_t(tx * 7 + ty) % seen.size()];
    if (slot.tx != tx || slot.ty != ty) {
      if (level < coarse_level_) {
        // Dark on the coarse level: no light in the pixel, no tile to read.
        const int d = coarse_level_ - level, cx = px.x >> d, cy = px.y >> d;
        if (tables_->lit[i].count(cx, cy, cx + 1, cy + 1) == 0) {
          ++stats_.dark_pixels;
          return nullptr;
        }
      }
      const uint64_t evictions = stats_.evictions;
      const Tile* tile_read = &tile(i, level, tx, ty);
      if (stats_.evictions != evictions) seen.fill(Seen{});
      slot = {tx, ty, tile_read};
    }
    scale = slot.tile->scale;
    return &slot.tile->bits[size_t(px.y - ty * t) * t + size_t(px.x - tx * t)];
  };
  auto read = [](const uint16_t* at, float scale) {
    half v;
    v.setBits(*at);
    return float(v) * scale;
  };
  // The tiles' lines are mostly not in the processor's caches (the search
  // visits hundreds of PSFs per event): every pixel's line is requested
  // first and read after, so that the misses overlap. Should a fetch evict
  // a tile, addresses found before it may be gone: then pixel by pixel.
  std::vector<const uint16_t*> at(pixels.size());
  const uint64_t evictions = stats_.evictions, dark = stats_.dark_pixels;
  for (size_t k = 0; k < pixels.size(); ++k) {
    at[k] = locate(k, out[k]);
    if (at[k]) __builtin_prefetch(at[k]);
  }
  if (stats_.evictions == evictions) {
    for (size_t k = 0; k < pixels.size(); ++k) out[k] = at[k] ? read(at[k], out[k]) : 0.0f;
  } else {
    seen.fill(Seen{});
    stats_.dark_pixels = dark;  // counted again below
    for (size_t k = 0; k < pixels.size(); ++k) {
      float scale = 0;
      const uint16_t* a = locate(k, scale);
      out[k] = a ? read(a, scale) : 0.0f;
    }
  }
  return out;
}

}  // namespace prism
