#include "host/dictionary_service.h"

#include <algorithm>

namespace prism {

namespace {
std::string mib(uint64_t b) { return std::to_string((b + (1 << 20) - 1) >> 20) + " MiB"; }
}  // namespace

DictionaryService::DictionaryService(const DictionaryReader& reader, vk::Context* ctx, int coarse_level,
                                     ServiceBudget budget)
    : reader_(reader), coarse_level_(coarse_level), budget_(budget) {
  const DictionaryManifest& m = reader.manifest();
  if (coarse_level < 0 || coarse_level >= m.levels)
    throw DictionaryError(reader.dir() + ": no level " + std::to_string(coarse_level) + " (levels 0.." +
                          std::to_string(m.levels - 1) + ")");
  const uint64_t psf_floats = uint64_t(m.level_width(coarse_level)) * m.level_height(coarse_level);
  const uint64_t psf_bytes = psf_floats * sizeof(float);
  const uint64_t sat_bytes = uint64_t(m.level_width(coarse_level) + 1) * (m.level_height(coarse_level) + 1) * sizeof(double);
  const size_t n = m.grid.size();
  auto finer_hint = [&] {
    return coarse_level + 1 < m.levels ? "; level " + std::to_string(coarse_level + 1) + " needs a quarter of it" : "";
  };
  if (sat_bytes * n > budget.host_bytes)
    throw DictionaryError(reader.dir() + ": the summed-area tables of level " + std::to_string(coarse_level) + " need " +
                          mib(sat_bytes * n) + ", more than the host budget of " + mib(budget.host_bytes) + finer_hint());
  if (ctx && psf_bytes * n > budget.device_bytes)
    throw DictionaryError(reader.dir() + ": level " + std::to_string(coarse_level) + " needs " + mib(psf_bytes * n) +
                          " on the device, more than the device budget of " + mib(budget.device_bytes) + finer_hint());

  // Pack the coarse level into chunks no larger than one storage buffer may be.
  uint64_t chunk_cap = ctx ? std::min<uint64_t>(ctx->max_storage_buffer_bytes(), 128ull << 20) : 0;
  uint64_t per_chunk = ctx ? std::max<uint64_t>(1, chunk_cap / psf_bytes) : 0;
  std::vector<float> staging;
  for (size_t i = 0; i < n; ++i) {
    PsfLevel lv = reader.has(i) ? reader.read_level(i, coarse_level)
                                : throw DictionaryError(reader.path_of(i) + ": missing; finish `prism dictionary build`");
    sats_.emplace_back(lv);
    account(int64_t(sats_.back().bytes()));
    if (!ctx) continue;
    uint32_t chunk = uint32_t(i / per_chunk);
    uint64_t in_chunk = i % per_chunk;
    if (in_chunk == 0) {
      uint64_t count = std::min<uint64_t>(per_chunk, n - i);
      chunks_.push_back(std::make_unique<vk::Buffer>(*ctx, count * psf_bytes));
      stats_.device_bytes += count * psf_bytes;
    }
    chunks_[chunk]->upload(lv.p.data(), psf_bytes, in_chunk * psf_bytes);
    slots_.push_back({chunk, in_chunk * psf_floats});
  }
}

void DictionaryService::account(int64_t delta) {
  stats_.host_bytes = uint64_t(int64_t(stats_.host_bytes) + delta);
  stats_.host_peak_bytes = std::max(stats_.host_peak_bytes, stats_.host_bytes);
}

const std::vector<float>& DictionaryService::tile(size_t i, int level, int tx, int ty) {
  TileKey key{i, level, tx, ty};
  auto it = tiles_.find(key);
  if (it != tiles_.end()) {
    ++stats_.tile_hits;
    lru_.splice(lru_.begin(), lru_, it->second.lru);
    return it->second.p;
  }
  ++stats_.tile_misses;
  int t = reader_.manifest().tile_px;
  uint64_t bytes = uint64_t(t) * t * sizeof(float);
  if (stats_.host_bytes + bytes > budget_.host_bytes && lru_.empty())
    throw DictionaryError(reader_.dir() + ": the host budget of " + mib(budget_.host_bytes) +
                          " leaves no room for one tile; raise it");
  // Make room first, so the budget holds at every moment.
  while (stats_.host_bytes + bytes > budget_.host_bytes && !lru_.empty()) {
    tiles_.erase(lru_.back());
    lru_.pop_back();
    account(-int64_t(bytes));
    ++stats_.evictions;
  }
  PsfWindow w = reader_.read_window(i, level, tx * t, ty * t, t, t);
  std::vector<float> p(size_t(t) * t, 0.0f);  // tiles at the level's edge are padded with zeros
  for (int y = 0; y < w.height; ++y)
    std::copy_n(&w.p[size_t(y) * w.width], w.width, &p[size_t(y) * t]);
  stats_.bytes_read += bytes;
  lru_.push_front(key);
  account(int64_t(bytes));
  return tiles_.emplace(key, Tile{std::move(p), lru_.begin()}).first->second.p;
}

std::vector<float> DictionaryService::values(size_t i, int level, std::span<const glm::ivec2> pixels) {
  const DictionaryManifest& m = reader_.manifest();
  int t = m.tile_px, w = m.level_width(level), h = m.level_height(level);
  std::vector<float> out(pixels.size(), 0.0f);
  for (size_t k = 0; k < pixels.size(); ++k) {
    glm::ivec2 px = pixels[k];
    if (px.x < 0 || px.y < 0 || px.x >= w || px.y >= h) continue;  // off the sensor: no light
    const auto& tl = tile(i, level, px.x / t, px.y / t);
    out[k] = tl[size_t(px.y % t) * t + px.x % t];
  }
  return out;
}

}  // namespace prism
