// `prism evaluate`: the paper's evaluation protocol (issue 4, point 5) with a
// reconstruction backend of host/reconstruct/reconstruct.h (the trials of a point go
// through it as one batch) on forward-model events (host/events/simulate.h,
// ForwardTruth at the dictionary's click binning).
//
// Per point: `trials` events, each reconstructed; the best and the worst trial
// by 3D error are dropped and the mean and sample standard deviation of the
// rest are reported, for the 3D error and for the photon-count error
// |alpha - alpha_true| (alpha: expected detected photons; ForwardTruth has
// S = 1). Flagged vertices are kept (the protocol drops only best and worst);
// their count is reported beside the statistics.
//
// CRLB beside each error: crlb_study (the scene, Poisson sensor, the point,
// the same binning and rays) gives the bound at the scene's emitted photons,
// i.e. at row.photons expected detected photons; the Fisher information is
// linear in the photon count, so the bound at the target detected count N is
// crlb_3d * sqrt(row.photons / N). For the double experiment each vertex gets
// its own single-source bound at its own 125 photons (the interaction of the
// two sources is not in it: a lower bound on the two-source bound).
#pragma once
#include <cstdint>
#include <functional>
#include <string>
#include <vector>

#include <glm/glm.hpp>

#include "engine/vk/context.h"
#include "host/dictionary/store.h"
#include "host/reconstruct/reconstruct.h"
#include "host/scene/scene.h"

namespace prism {

// The paper's fixed numbers.
namespace paper_protocol {
inline constexpr glm::dvec3 centre_mm{1, 1, 31};  // the lines pass through it
inline constexpr double line_photons = 100;
inline const std::vector<double> photon_counts{50, 100, 200, 400};
inline constexpr double double_photons = 250;  // split 50/50
inline constexpr double double_fixed_depth_mm = 7.5;
inline constexpr int trials = 25;
}  // namespace paper_protocol

// Mean and sample standard deviation after dropping the best and the worst
// trial by 3D error (alpha errors of the same trials). Needs >= 3 trials.
struct TrimmedStats {
  int trials_used = 0;
  double err3d_mean = 0, err3d_std = 0, alpha_err_mean = 0, alpha_err_std = 0;
};
TrimmedStats trimmed_stats(const std::vector<double>& err3d_mm, const std::vector<double>& alpha_err);

struct EvaluationOptions {
  std::vector<std::string> experiments{"single-lines", "photons", "double"};
  int trials = paper_protocol::trials;
  int level = 0;               // click level: binning = base_binning * 2^level
  unsigned rays = 0;           // forward truth and CRLB; 0: the dictionary's own (or the default)
  Splat splat = TraceSettings{}.splat;  // forward truth and CRLB
  unsigned stratification = 1;  // forward truth: other strata than the dictionary's (0) by default
  uint64_t seed = 1;
  bool quick = false;          // few points per experiment (use with few trials)
  ReconstructionSettings settings;  // search_level -1: level + 2, capped at the coarsest
  ReconstructionBackend backend = ReconstructionBackend::vulkan;
  bool device_half = false;    // device backends: the scan level as half floats
};

// What the reconstructions of an evaluation cost.
struct EvaluationCost {
  uint64_t events = 0;
  double reconstruct_s = 0;  // wall time inside the reconstructions
  double scan_s = 0;         // of which the support scans
};

struct EvaluationRow {
  std::string experiment;  // single-lines, photons or double: the file the row goes to
  std::string series;      // the curve within it: x, y, depth (lines), moving, fixed (double); "" (photons)
  double varied = 0;       // the plot's x value
  glm::dvec3 position_mm{};
  double photons = 0;      // expected detected photons of this vertex
  TrimmedStats stats;
  int flagged = 0;         // trials whose vertex carried a flag
  double crlb_3d_mm = 0;
};

// Valid experiment names, in the order they run.
const std::vector<std::string>& evaluation_experiments();

// Runs the chosen experiments; progress(done, total) after each trial.
std::vector<EvaluationRow> evaluate(vk::Context& ctx, const Scene& scene, const DictionaryReader& dictionary,
                                    const EvaluationOptions& options,
                                    const std::function<void(size_t, size_t)>& progress = {},
                                    EvaluationCost* cost = nullptr);

// <dir>/<experiment>.csv and .png for every experiment present in rows.
// Returns the paths written.
std::vector<std::string> write_evaluation(const std::string& dir, const std::vector<EvaluationRow>& rows);

}  // namespace prism
