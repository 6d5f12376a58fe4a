#include "host/events/simulate.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <sstream>

#include "host/util/memory.h"

namespace prism {

PsfSampler::PsfSampler(std::span<const float> p, int width, int height, int shift_cols, int shift_rows) {
  if (p.size() != size_t(width) * size_t(height))
    throw std::invalid_argument("PsfSampler: " + std::to_string(p.size()) + " values for a " + std::to_string(width) +
                                " x " + std::to_string(height) + " grid");
  // Destination rows/columns that stay on the grid after the shift.
  int row0 = std::max(0, shift_rows), row1 = std::min(height, height + shift_rows);
  int col0 = std::max(0, shift_cols), col1 = std::min(width, width + shift_cols);
  for (int r = row0; r < row1; ++r) {
    const float* src = p.data() + size_t(r - shift_rows) * width - shift_cols;
    for (int c = col0; c < col1; ++c) {
      if (!(src[c] > 0.0f)) continue;  // also skips NaN
      mass_ += src[c];
      pixel_.push_back(uint32_t(size_t(r) * width + c));
      p_.push_back(src[c]);
    }
  }
  // Vose's alias method: scale P to mean 1, pair each under-full entry with
  // an over-full one that tops it up.
  const size_t n = p_.size();
  keep_.assign(n, 1.0);
  alias_.resize(n);
  std::vector<uint32_t> small, large;
  std::vector<double> q(n);
  for (size_t j = 0; j < n; ++j) {
    alias_[j] = uint32_t(j);
    q[j] = p_[j] * double(n) / mass_;
    (q[j] < 1.0 ? small : large).push_back(uint32_t(j));
  }
  while (!small.empty() && !large.empty()) {
    uint32_t s = small.back(), l = large.back();
    small.pop_back();
    keep_[s] = q[s];
    alias_[s] = l;
    q[l] -= 1.0 - q[s];
    if (q[l] < 1.0) {
      large.pop_back();
      small.push_back(l);
    }
  }
  // Whatever is left is 1 up to rounding: kept with probability 1 (the default).
}

uint32_t PsfSampler::draw(double u) const {
  // One uniform gives the entry (integer part) and the coin (fraction).
  double x = u * double(pixel_.size());
  size_t j = std::min(size_t(x), pixel_.size() - 1);
  return pixel_[x - double(j) < keep_[j] ? j : alias_[j]];
}

void PsfSampler::add_rates(double alpha, std::vector<double>& lambda) const {
  for (size_t j = 0; j < pixel_.size(); ++j) lambda.at(pixel_[j]) += alpha * p_[j];
}

void PsfSampler::click_each(double alpha, EventRng& rng, std::vector<uint32_t>& clicks) const {
  std::uniform_real_distribution<double> uniform(0.0, 1.0);
  for (size_t j = 0; j < pixel_.size(); ++j)
    if (uniform(rng) < -std::expm1(-alpha * p_[j])) clicks.push_back(pixel_[j]);
}

glm::dvec2 PsfSampler::centroid_px(int width) const {
  glm::dvec2 m{0, 0};
  for (size_t j = 0; j < pixel_.size(); ++j)
    m += p_[j] * glm::dvec2(pixel_[j] % uint32_t(width), pixel_[j] / uint32_t(width));
  return m / sensor_fraction();
}

namespace {
uint64_t splitmix64(uint64_t& state) {
  uint64_t z = (state += 0x9E3779B97F4A7C15ull);
  z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ull;
  z = (z ^ (z >> 27)) * 0x94D049BB133111EBull;
  return z ^ (z >> 31);
}
uint64_t rotl(uint64_t x, int k) { return (x << k) | (x >> (64 - k)); }
}  // namespace

EventRng::EventRng(uint64_t seed) {
  // splitmix64 fills the state, as the xoshiro authors recommend: never all zero.
  for (auto& w : s_) w = splitmix64(seed);
}

uint64_t EventRng::operator()() {
  uint64_t result = rotl(s_[1] * 5, 7) * 9;
  uint64_t t = s_[1] << 17;
  s_[2] ^= s_[0];
  s_[3] ^= s_[1];
  s_[1] ^= s_[2];
  s_[0] ^= s_[3];
  s_[2] ^= t;
  s_[3] = rotl(s_[3], 45);
  return result;
}

void sample_clicks(std::span<const ClickSource> sources, EventRng& rng, std::vector<uint32_t>& clicks) {
  clicks.clear();
  std::uniform_real_distribution<double> uniform(0.0, 1.0);
  for (const auto& s : sources) {
    double mean = s.alpha * s.psf->sensor_fraction();
    if (!(mean > 0)) continue;
    if (mean > per_pixel_photons_per_support * double(s.psf->support_pixels())) {
      s.psf->click_each(s.alpha, rng, clicks);
      continue;
    }
    // Superposed Poisson processes: each vertex's photons are independent.
    uint64_t photons = std::poisson_distribution<uint64_t>(mean)(rng);
    for (uint64_t n = 0; n < photons; ++n) clicks.push_back(s.psf->draw(uniform(rng)));
  }
  // A pixel hit by one or more photons clicks once: P(click) = 1 - exp(-lambda).
  std::sort(clicks.begin(), clicks.end());
  clicks.erase(std::unique(clicks.begin(), clicks.end()), clicks.end());
}

EventRng event_rng(uint64_t seed, uint64_t event_id) {
  // Hash (seed, id) into one well-mixed 64-bit seed; neighbouring ids differ.
  uint64_t state = seed;
  uint64_t mixed = splitmix64(state) ^ event_id;
  return EventRng(splitmix64(mixed));
}

std::shared_ptr<const PsfSampler> EventTruth::psf(const glm::dvec3& position_mm) {
  for (auto it = cache_.begin(); it != cache_.end(); ++it)
    if (it->first == position_mm) {
      cache_.splice(cache_.begin(), cache_, it);
      return cache_.front().second;
    }
  auto t0 = std::chrono::steady_clock::now();
  auto s = make(position_mm);
  render_seconds_ += std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  ++renders_;
  cache_.emplace_front(position_mm, s);
  cache_bytes_ += s->bytes();
  const double budget = cache_share * double(memory_limit_bytes());
  while (cache_.size() > 1 && (cache_.size() > cache_entries_ || double(cache_bytes_) > budget)) {
    cache_bytes_ -= cache_.back().second->bytes();
    cache_.pop_back();
  }
  return s;
}

namespace {

// Checked before the forward model is made: one PSF rendered on the device,
// read back and made into a sampler (up to every pixel lit).
TraceSettings within_memory(vk::Context& ctx, const Scene& scene, const TraceSettings& settings) {
  const AnalysisGrid grid = AnalysisGrid::of(scene.optics, settings.binning);
  const double px = double(grid.width) * grid.height;
  MemoryEstimate memory("the forward model's events at binning " + std::to_string(settings.binning) + " (" +
                        std::to_string(grid.width) + " x " + std::to_string(grid.height) + " px)");
  memory.add("a PSF read back from the device", 4 * px).add("its sampler, up to every pixel lit", 24 * px);
  memory.add_device_buffers(double(ForwardVulkan::device_bytes_at_most(grid, settings.splat)), ctx.is_cpu());
  memory.require_within_limit("Use a coarser --binning");
  return settings;
}

}  // namespace

ForwardTruth::ForwardTruth(vk::Context& ctx, const Scene& scene, const TraceSettings& settings, size_t cache_entries)
    : EventTruth(cache_entries), settings_(settings), fw_(ctx, scene.optics, within_memory(ctx, scene, settings)) {}

std::string ForwardTruth::provenance() const {
  return "forward model, " + std::string(to_string(settings_.splat)) + " splat, " + std::to_string(settings_.rays()) +
         " rays per 3 mm lenslet, stratification " + std::to_string(settings_.stratification) + ", binning " +
         std::to_string(settings_.binning);
}

std::shared_ptr<const PsfSampler> ForwardTruth::make(const glm::dvec3& position_mm) {
  std::vector<float> b = fw_.psf_values(position_mm);
  double total = 0;
  for (float v : b) total += v;
  // alpha = expected photons detected on the sensor: P = b / sum(b), S = 1.
  // A position that puts no light on the sensor gets S = 0 (no clicks).
  float scale = total > 0 ? float(1.0 / total) : 0.0f;
  for (float& v : b) v *= scale;
  return std::make_shared<PsfSampler>(b, fw_.grid().width, fw_.grid().height);
}

DictionaryTruth::DictionaryTruth(const DictionaryReader& reader, int level, size_t cache_entries)
    : EventTruth(cache_entries), reader_(reader), level_(level) {
  if (level < 0 || level >= reader.manifest().levels)
    throw DictionaryError(reader.dir() + ": level " + std::to_string(level) + " does not exist (the dictionary has " +
                          std::to_string(reader.manifest().levels) + " levels)");
}

std::string DictionaryTruth::provenance() const {
  std::ostringstream s;
  s << "dictionary " << reader_.dir() << ", level " << level_ << " (binning " << binning()
    << "), nearest depth plane and node, shifted by -d * " << reader_.manifest().scene.optics.lens_to_sensor_mm
    << " / (z + " << reader_.manifest().scene.optics.working_distance_mm << ")";
  return s.str();
}

std::shared_ptr<const PsfSampler> DictionaryTruth::make(const glm::dvec3& position_mm) {
  auto place = place_in_dictionary(reader_.manifest(), level_, position_mm);
  std::shared_ptr<const PsfLevel> level;
  for (auto it = levels_.begin(); it != levels_.end(); ++it)
    if (it->first == place.index) {
      levels_.splice(levels_.begin(), levels_, it);
      level = it->second;
      break;
    }
  if (!level) {
    if (!reader_.has(place.index))
      throw DictionaryError(reader_.path_of(place.index) + ": missing; the dictionary is incomplete (resume its build)");
    level = std::make_shared<PsfLevel>(reader_.read_level(place.index, level_));
    levels_.emplace_front(place.index, level);
    if (levels_.size() > 8) levels_.pop_back();  // jittered positions revisit a few nodes
  }
  return std::make_shared<PsfSampler>(level->p, level->width, level->height, place.shift_px.x, place.shift_px.y);
}

int stored_level_of_binning(const DictionaryManifest& m, unsigned binning, const std::string& option) {
  int level = 0;
  while (level < m.levels && (m.base_binning << level) < int(binning)) ++level;
  if (level == m.levels || (m.base_binning << level) != int(binning))
    throw std::runtime_error(option + " " + std::to_string(binning) + ": the dictionary stores binnings " +
                             std::to_string(m.base_binning) + " x 2^k only; choose one of those");
  return level;
}

void check_simulation(const Scene& scene, const SimulationRun& run, const std::string& option,
                      const std::string& jitter_option) {
  if (!(run.jitter_mm >= 0)) throw std::runtime_error(jitter_option + " must be >= 0");
  for (const auto& v : run.vertices) {
    if (!(v.alpha >= 0) || !std::isfinite(v.alpha))
      throw std::runtime_error(option + ": alpha " + std::to_string(v.alpha) + " must be a finite number >= 0 (expected photons)");
    require_in_volume(scene, v.x_mm, v.y_mm, v.depth_mm, option);
    require_in_front(scene, v.depth_mm - run.jitter_mm, run.jitter_mm > 0 ? option + " less " + jitter_option : option);
  }
}

EventFileHeader simulation_header(const Scene& scene, const EventTruth& truth, const SimulationRun& run) {
  EventFileHeader h;
  h.sensor_width_px = uint32_t(scene.optics.sensor_width_px);
  h.sensor_height_px = uint32_t(scene.optics.sensor_height_px);
  h.pixel_um = scene.optics.pixel_um;
  h.binning = uint32_t(truth.binning());
  h.scene = scene.name;
  h.truth = truth.model();
  h.seed = run.seed;
  h.provenance = truth.provenance() + (run.jitter_mm > 0 ? ", jitter +-" + std::to_string(run.jitter_mm) + " mm" : "");
  return h;
}

void simulate_event(EventTruth& truth, const SimulationRun& run, uint64_t id, Event& e) {
  auto rng = event_rng(run.seed, id);
  e.id = id;
  e.vertices = run.vertices;
  std::vector<ClickSource> sources;
  std::vector<std::shared_ptr<const PsfSampler>> held;  // alive until the clicks are drawn
  std::uniform_real_distribution<double> jitter(-run.jitter_mm, run.jitter_mm);
  for (auto& v : e.vertices) {
    if (run.jitter_mm > 0) {
      v.x_mm += jitter(rng);
      v.y_mm += jitter(rng);
      v.depth_mm += jitter(rng);
    }
    held.push_back(truth.psf({v.x_mm, v.y_mm, v.depth_mm}));
    v.sensor_fraction = held.back()->sensor_fraction();
    sources.push_back({held.back().get(), v.alpha});
  }
  sample_clicks(sources, rng, e.clicks);
}

}  // namespace prism
