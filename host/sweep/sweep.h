// Design sweeps: search a space of lenslet arrays for the lowest CRLB over a
// sample of the volume (`prism sweep`; user documentation in host/sweep/SWEEP.md).
//
// A space file names the free parameters (focal lengths and their assignment
// to positions, diameters, hex layout, distances, lens model, effects); the
// rest comes from a base scene. A design is a vector of choices (indices into
// the space's lists). Every design is scored from batched Fisher information
// at the same sample positions, and each result is appended to a state file
// as soon as it exists, so a stopped sweep resumes where it was.
#pragma once
#include <cmath>
#include <cstdint>
#include <functional>
#include <optional>
#include <random>
#include <stdexcept>
#include <string>
#include <unordered_map>
#include <unordered_set>
#include <vector>

#include <glm/glm.hpp>
#include <nlohmann/json.hpp>

#include "host/scene/crlb_study.h"
#include "host/scene/scene.h"

namespace prism {

// A space or state file that cannot be used; the message names the field.
struct SweepError : std::runtime_error {
  using std::runtime_error::runtime_error;
};

// Source positions every design is scored at: the product of the three lists.
struct SampleGrid {
  std::vector<double> x_mm, y_mm, depth_mm;
  std::vector<glm::dvec3> positions() const;  // depth outermost, then y, then x
  std::string describe() const;
  // `lateral` points per axis evenly over the middle 40% of the volume's width
  // (the centre included when odd), `depth` slice midpoints over its depth.
  static SampleGrid of(const Volume& v, int lateral, int depth);
};

// Figures of merit of one design over the sample grid. All are minimised
// except mean_photons, which is maximised.
struct Objectives {
  double mean_crlb_3d_mm = INFINITY;   // mean over the samples of sqrt(trace I^-1)
  double worst_crlb_3d_mm = INFINITY;  // largest over the samples
  double mean_crlb_x_mm = INFINITY, mean_crlb_y_mm = INFINITY, mean_crlb_z_mm = INFINITY;
  double mean_photons = 0;             // expected detected photons, mean over the samples
  double depth_ratio = INFINITY;       // worst / best depth plane of the mean 3D CRLB (1 = uniform)
  std::vector<double> crlb_3d_by_depth_mm;  // mean over the lateral samples, per depth plane
};

const std::vector<std::string>& objective_names();
bool objective_is_maximised(const std::string& name);
// The named objective's value; throws SweepError listing the names when unknown.
double objective_value(const Objectives& o, const std::string& name);

// "photons>=100", "worst_crlb_3d<=0.5": a constraint on one objective.
struct Bound {
  std::string objective;
  bool at_least = true;
  double value = 0;
  bool holds(const Objectives& o) const;
  std::string text() const;
};
Bound parse_bound(const std::string& text);

// One point of the space: indices into the space's lists.
struct Design {
  size_t layout = 0;
  std::vector<int> focal;     // per position, into DesignSpace::focal_mm
  std::vector<int> diameter;  // per position, into DesignSpace::diameter_mm
  size_t lens_to_sensor = 0, working_distance = 0, lens_model = 0, effects = 0;
  std::string key() const;  // unique text of the choices
  nlohmann::json to_json() const;
  static Design from_json(const nlohmann::json& j);
};

struct HexLayout {
  int rows = 0, columns = 0;  // 0: the base scene's own positions
  double pitch_mm = 0;
};

class DesignSpace {
 public:
  // `dir` resolves a relative base scene path (the space file's folder).
  static DesignSpace parse(const nlohmann::json& j, const std::string& origin, const std::string& dir = ".");
  static DesignSpace load(const std::string& path);

  // The scene of a design, not validated (see evaluate_design).
  Scene scene_of(const Design& d, const std::string& name) const;
  // The design of a scene when the space holds it (the base, usually).
  std::optional<Design> encode(const Scene& s) const;
  double size() const;                  // number of designs; may be huge
  std::vector<Design> enumerate() const;  // every design; only when size() is small
  Design random(std::mt19937_64& rng) const;
  Design neighbour(const Design& d, std::mt19937_64& rng) const;  // one or two moves
  // Parameters of a design as CSV columns (header names in parameter_columns).
  static std::vector<std::string> parameter_columns();
  std::vector<std::string> parameters(const Design& d) const;

  std::string name;
  nlohmann::json source;  // the space file as read, kept in the state file
  Scene base;
  std::vector<HexLayout> layouts;
  std::vector<double> focal_mm;
  bool focal_free = false;     // true: any focal length per position; false: balanced
  bool focal_fixed = false;    // the base scene's focal lengths, unchanged
  std::vector<double> diameter_mm;
  bool diameter_fixed = false;
  std::vector<double> lens_to_sensor_mm, working_distance_mm;
  std::vector<LensModel> lens_models;
  std::vector<Effects> effects;
  std::vector<std::string> effects_labels;
  SampleGrid samples;

  std::vector<LensletGeometry> positions(size_t layout) const;  // centres only
 private:
  Design random_at(size_t layout, std::mt19937_64& rng) const;
  std::vector<int> base_genes(const std::vector<double>& values, const std::vector<double>& set) const;
};

// Score one scene at the grid's positions (one batched dispatch on Vulkan).
Objectives score(const Scene& scene, const SampleGrid& grid, const TraceSettings& settings, Backend backend,
                 vk::Context* ctx);

struct SweepSettings {
  TraceSettings trace;
  Backend backend = Backend::vulkan;
  std::string objective = "mean_crlb_3d";
  std::vector<Bound> bounds;
  size_t budget = 100;  // designs in the state file, rejected ones included
  uint64_t seed = 1;
  size_t batch = 8;  // candidates generated and scored together (one dispatch on Vulkan)
};

struct Evaluated {
  Design design;
  std::string key;
  std::string origin;  // base, enumerated, start, search
  bool valid = true;
  std::string reason;  // why validate() rejected it
  Objectives objectives;
  double seconds = 0;  // time to score it
};

class Sweep {
 public:
  // Reads `state_path` when it exists (a sweep to resume); it must have been
  // made with the same space and trace settings.
  Sweep(const DesignSpace& space, SweepSettings settings, std::string state_path);

  // Generates candidates from the seed until the budget is met or stop()
  // returns true. Designs already in the state are replayed, not scored, so
  // the same seed gives the same sequence after a restart.
  void run(vk::Context* ctx, const std::function<bool()>& stop = {},
           const std::function<void(const Evaluated&, size_t done)>& on_design = {});

  // Feasible (all bounds hold) by objective, then infeasible, then rejected.
  std::vector<const Evaluated*> ranked() const;
  const std::vector<Evaluated>& evaluated() const { return done_; }
  const DesignSpace& space() const { return space_; }
  const SweepSettings& settings() const { return settings_; }
  bool exhausted() const { return exhausted_; }  // every design of the space is in the state
  size_t replayed() const { return replayed_; }

 private:
  // Scores the queued candidates together (replaying those already stored)
  // and appends each to the state file.
  void consume(const std::vector<std::pair<Design, std::string>>& queue, vk::Context* ctx, std::vector<size_t>& pool,
               const std::function<void(const Evaluated&, size_t)>& on_design);
  bool better(const Evaluated& a, const Evaluated& b) const;
  void append(const Evaluated& e) const;
  nlohmann::json header() const;

  const DesignSpace& space_;
  SweepSettings settings_;
  std::string state_path_;
  std::vector<Evaluated> done_;           // in state-file order
  std::unordered_map<std::string, Evaluated> stored_;  // read from the state file, not yet replayed
  std::unordered_set<std::string> seen_;                // keys consumed by this run
  size_t replayed_ = 0;
  bool exhausted_ = false;
};

// Validate and score designs, the valid ones together (one multi-design
// dispatch when they differ only in their lenslets); a design validate()
// refuses is returned with valid = false and the reason.
std::vector<Evaluated> evaluate_designs(const DesignSpace& space, const std::vector<Design>& designs,
                                        const TraceSettings& settings, Backend backend, vk::Context* ctx);
Evaluated evaluate_design(const DesignSpace& space, const Design& d, const TraceSettings& settings, Backend backend,
                          vk::Context* ctx);

}  // namespace prism
