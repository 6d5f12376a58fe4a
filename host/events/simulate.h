// Simulated events with the binary sensor model (paper eq. 5, DESIGN.md
// "Sensor and events"): lambda_i = sum_k alpha_k P_i(theta_k) and
// y_i ~ Bernoulli(1 - exp(-lambda_i)), drawn without touching every pixel:
// photons ~ Poisson(alpha_k S_k) per vertex land on pixels drawn from P / S,
// and a pixel clicks once however many photons hit it. For Poisson arrivals
// this is exactly the per-pixel Bernoulli model (EVENTS.md, "Sampling").
// Two truth models give P: the ray-traced forward model at the exact position,
// or a dictionary PSF shifted by the magnification rule (the paper's protocol).
#pragma once
#include <cstdint>
#include <list>
#include <memory>
#include <random>
#include <span>
#include <string>
#include <utility>
#include <vector>

#include <glm/glm.hpp>

#include "engine/forward.h"
#include "host/dictionary/placement.h"
#include "host/dictionary/store.h"
#include "host/events/event_file.h"
#include "host/scene/scene.h"

namespace prism {

// A PSF ready for drawing photon arrivals: the pixels with P > 0 and a Walker
// alias table over them, so a draw is O(1) (two memory reads; a binary search
// over a full-resolution CDF was ~20 cache misses per photon).
class EventRng;

class PsfSampler {
 public:
  // p: P_i on a width x height row-major grid; the PSF is moved by
  // (shift_cols, shift_rows) whole pixels and what leaves the grid is lost.
  PsfSampler(std::span<const float> p, int width, int height, int shift_cols = 0, int shift_rows = 0);

  // S = sum_i P_i: the fraction of alpha that lands on the sensor.
  double sensor_fraction() const { return mass_; }
  // The pixel hit by one photon, with probability P_i / S; u uniform in [0, 1).
  uint32_t draw(double u) const;
  size_t support_pixels() const { return pixel_.size(); }
  size_t bytes() const { return pixel_.size() * (2 * sizeof(uint32_t) + 2 * sizeof(double)); }
  // lambda_i += alpha P_i over the support (dense; for tests and references).
  void add_rates(double alpha, std::vector<double>& lambda) const;
  // Each pixel of the support clicks with probability 1 - exp(-alpha P_i):
  // appended to `clicks`, unsorted.
  void click_each(double alpha, EventRng& rng, std::vector<uint32_t>& clicks) const;
  // Mean (col, row) of P / S, in pixels of the grid.
  glm::dvec2 centroid_px(int width) const;

 private:
  std::vector<uint32_t> pixel_;
  std::vector<double> p_;         // P at pixel_[j]
  std::vector<double> keep_;      // alias table: keep entry j with this probability,
  std::vector<uint32_t> alias_;   // else take entry alias_[j]
  double mass_ = 0;
};

struct ClickSource {
  const PsfSampler* psf;
  double alpha;  // expected photons (see EVENTS.md, "alpha and P")
};

// xoshiro256** (Blackman and Vigna): a fast generator with a 32-byte state,
// so that seeding one per event costs nothing (mt19937_64 seeding took a
// third of the sampling time).
class EventRng {
 public:
  using result_type = uint64_t;
  static constexpr uint64_t min() { return 0; }
  static constexpr uint64_t max() { return ~uint64_t(0); }
  explicit EventRng(uint64_t seed);
  uint64_t operator()();

 private:
  uint64_t s_[4];
};

// One event's clicks, sorted and unique: Poisson(alpha_k S_k) photons per
// source, each on a pixel drawn from P_k / S_k, duplicates merged. A source
// whose mean photons exceed per_pixel_photons_per_support times its PSF's
// support clicks pixel by pixel instead, with probability 1 - exp(-alpha_k
// P_i) each (the same distribution, by Poisson thinning): time and memory
// then grow with the PSF's pixels, not the photons (alpha 1e9 is an event,
// not 4 GB of photons).
inline constexpr double per_pixel_photons_per_support = 64;
void sample_clicks(std::span<const ClickSource> sources, EventRng& rng, std::vector<uint32_t>& clicks);

// Independent random stream of one event: the same (seed, event id) gives the
// same event whatever else the run does.
EventRng event_rng(uint64_t seed, uint64_t event_id);

// Gives the PSF of a source at a position on the click grid, with a small
// cache so a repeated position is rendered or read once. The cache holds at
// most cache_entries PSFs and cache_share of the memory limit (the newest PSF
// is kept whatever its size): full-resolution PSFs lit nearly everywhere take
// 24 bytes per pixel, 0.8 GB at the prototype's 6696 x 4764.
class EventTruth {
 public:
  static constexpr double cache_share = 0.25;
  explicit EventTruth(size_t cache_entries) : cache_entries_(cache_entries) {}
  virtual ~EventTruth() = default;
  std::shared_ptr<const PsfSampler> psf(const glm::dvec3& position_mm);
  virtual int binning() const = 0;      // of the click grid, in sensor pixels
  virtual std::string provenance() const = 0;
  virtual TruthModel model() const = 0;
  size_t renders() const { return renders_; }  // cache misses
  double render_seconds() const { return render_seconds_; }  // spent rendering or reading PSFs

 protected:
  virtual std::shared_ptr<const PsfSampler> make(const glm::dvec3& position_mm) = 0;

 private:
  size_t cache_entries_;
  size_t renders_ = 0;
  double render_seconds_ = 0;
  std::list<std::pair<glm::dvec3, std::shared_ptr<const PsfSampler>>> cache_;  // front: most recent
  size_t cache_bytes_ = 0;
};

// The ray-traced forward model at the exact position: P = b / sum(b), so
// S = 1 and alpha is the expected photons detected on the sensor.
class ForwardTruth : public EventTruth {
 public:
  ForwardTruth(vk::Context& ctx, const Scene& scene, const TraceSettings& settings, size_t cache_entries = 64);
  int binning() const override { return int(settings_.binning); }
  std::string provenance() const override;
  TruthModel model() const override { return TruthModel::forward; }

 private:
  std::shared_ptr<const PsfSampler> make(const glm::dvec3& position_mm) override;
  TraceSettings settings_;
  ForwardVulkan fw_;
};


class DictionaryTruth : public EventTruth {
 public:
  // level: clicks are on level `level` (binning base_binning * 2^level).
  DictionaryTruth(const DictionaryReader& reader, int level, size_t cache_entries = 64);
  int binning() const override { return reader_.manifest().base_binning << level_; }
  std::string provenance() const override;
  TruthModel model() const override { return TruthModel::dictionary; }

 private:
  std::shared_ptr<const PsfSampler> make(const glm::dvec3& position_mm) override;
  const DictionaryReader& reader_;
  int level_;
  std::list<std::pair<size_t, std::shared_ptr<const PsfLevel>>> levels_;  // a few unshifted PSFs, most recent first
};

// The level of a dictionary whose clicks have this binning (its base
// binning x 2^level); throws naming `option` for any other.
int stored_level_of_binning(const DictionaryManifest& m, unsigned binning, const std::string& option);

// One run of `prism simulate` (and the Python module's simulate()): the
// vertices every event starts from, each moved per event uniformly within
// +-jitter_mm in x, y and depth.
struct SimulationRun {
  std::vector<EventVertex> vertices;  // x, y, depth and alpha; sensor_fraction is filled per event
  double jitter_mm = 0;
  uint64_t seed = 1;
};

// Throws naming `option` unless every vertex lies in the scene's volume and,
// jittered by the most, in front of its lenses; and unless jitter_mm >= 0.
// `option` names the vertices and `jitter_option` the jitter in messages.
void check_simulation(const Scene& scene, const SimulationRun& run, const std::string& option,
                      const std::string& jitter_option);
// The event file's header for a run of `truth` on `scene`.
EventFileHeader simulation_header(const Scene& scene, const EventTruth& truth, const SimulationRun& run);
// Event `id` of the run: depends only on (seed, id) and the truth.
void simulate_event(EventTruth& truth, const SimulationRun& run, uint64_t id, Event& e);

}  // namespace prism
