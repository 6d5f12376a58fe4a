// What a design is scored by (`prism sweep`; host/sweep/SWEEP.md): source
// positions sampled over the volume, figures of merit from the CRLB there,
// and bounds on them.
#pragma once
#include <cmath>
#include <stdexcept>
#include <string>
#include <vector>

#include <glm/glm.hpp>

#include <nlohmann/json.hpp>

#include "host/reconstruct/ambiguity.h"
#include "host/reconstruct/evaluate.h"
#include "host/scene/crlb_study.h"
#include "host/scene/scene.h"

namespace prism {

// A space, bound or state file that cannot be used; the message names the field.
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
  // Global ambiguity over the space's ambiguity samples (host/reconstruct/
  // ambiguity.h); NaN where not computed (see AmbiguityScoring).
  double mean_p_confusion = NAN;   // predicted probability per event of an estimate r or more away: a catastrophic rate
  double worst_p_confusion = NAN;  // largest over the samples
  double min_alias_kl = NAN;       // nats, the closest impostor over the samples (maximised)
};

// How the global ambiguity is scored. It costs about 60 renders of the
// scene's model per sample (the CRLB: one batched dispatch for all samples),
// so it has its own, smaller sample grid (DesignSpace::ambiguity_samples)
// and is computed only when an objective or a bound names it, or when asked.
struct AmbiguityScoring {
  // Detected photons per event and the clicks' pixels of the volume
  // experiment, so that mean_p_confusion predicts the catastrophic rate that
  // `prism evaluate --experiments volume` measures.
  double photons = volume_protocol::photons;
  unsigned binning = defaults::analysis_binning;
  AmbiguitySettings settings;
  nlohmann::json to_json() const;  // for the sweep's state header
};

const std::vector<std::string>& objective_names();
bool objective_is_maximised(const std::string& name);
// p_confusion, worst_p_confusion, alias_kl: needs AmbiguityScoring.
bool objective_is_ambiguity(const std::string& name);
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

// Score one scene at the grid's positions (one batched dispatch on Vulkan).
Objectives score(const Scene& scene, const SampleGrid& grid, const TraceSettings& settings, Backend backend,
                 vk::Context* ctx);

// Objectives as JSON (a sweep's state file, the scores its processes
// exchange), and back, every double exactly; the ambiguity's only when scored.
nlohmann::json to_json(const Objectives& o);
Objectives objectives_from_json(const nlohmann::json& j);

// Adds the ambiguity objectives of one scene at `samples`, with the scene's
// model on the device (`ctx`) or the double reference (nullptr).
void score_ambiguity(const Scene& scene, const SampleGrid& samples, const AmbiguityScoring& scoring, vk::Context* ctx,
                     Objectives& o);

// Several scenes at the grid's positions in one multi-design dispatch; throws
// std::invalid_argument when they differ in more than their lenslets.
std::vector<Objectives> score_together(const std::vector<Scene>& scenes, const SampleGrid& grid,
                                       const TraceSettings& settings, vk::Context& ctx);

}  // namespace prism
