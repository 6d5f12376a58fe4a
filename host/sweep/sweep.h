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
#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <unordered_map>
#include <unordered_set>
#include <vector>

#include <nlohmann/json.hpp>

#include "host/sweep/objectives.h"
#include "host/sweep/space.h"
#include "host/util/journal.h"
#include "host/util/work_share.h"

namespace prism {

struct SweepSettings {
  TraceSettings trace;
  Backend backend = Backend::vulkan;
  std::string objective = "mean_crlb_3d";
  std::vector<Bound> bounds;
  size_t budget = 100;  // designs in the state file, rejected ones included
  uint64_t seed = 1;
  size_t batch = 8;  // candidates generated and scored together (one dispatch on Vulkan)
  // The global ambiguity objectives: scored when set, and set by the Sweep
  // (with the defaults) when the objective or a bound names one of them.
  std::optional<AmbiguityScoring> ambiguity;
  bool names_ambiguity() const;  // the objective or a bound needs it
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
  // Under several processes (`share`; prism sweep under MPI) every one runs
  // the same search from the seed; each batch's candidates are scored by the
  // processes their share gives them to, every one gets all the scores, and
  // the leader alone writes the state file. The sweep equals one process's.
  Sweep(const DesignSpace& space, SweepSettings settings, std::string state_path, WorkShare share = {});

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
  // Validates and scores fresh candidates (this process's share of them).
  std::vector<Evaluated> score(const std::vector<Design>& fresh, vk::Context* ctx) const;
  bool better(const Evaluated& a, const Evaluated& b) const;
  void append(const Evaluated& e) const;
  nlohmann::json header() const;

  const DesignSpace& space_;
  SweepSettings settings_;
  std::string state_path_;
  WorkShare share_;
  std::optional<Journal> journal_;  // the state file
  std::vector<Evaluated> done_;           // in state-file order
  std::unordered_map<std::string, Evaluated> stored_;  // read from the state file, not yet replayed
  std::unordered_set<std::string> seen_;                // keys consumed by this run
  size_t replayed_ = 0;
  bool exhausted_ = false;
};

// Validate and score designs, the valid ones together (one multi-design
// dispatch when they differ only in their lenslets); a design validate()
// refuses is returned with valid = false and the reason.
// With `ambiguity`, also the ambiguity objectives at space.ambiguity_samples.
std::vector<Evaluated> evaluate_designs(const DesignSpace& space, const std::vector<Design>& designs,
                                        const TraceSettings& settings, Backend backend, vk::Context* ctx,
                                        const AmbiguityScoring* ambiguity = nullptr);
Evaluated evaluate_design(const DesignSpace& space, const Design& d, const TraceSettings& settings, Backend backend,
                          vk::Context* ctx, const AmbiguityScoring* ambiguity = nullptr);

}  // namespace prism
