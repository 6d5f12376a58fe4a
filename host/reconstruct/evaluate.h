// `prism evaluate`: the paper's evaluation protocol (issue 4, point 5) and a
// whole-volume experiment (issue 10) with a reconstruction backend of
// host/reconstruct/reconstruct.h (the trials of a point go through it as one
// batch), optionally followed by the continuous refinement
// (host/reconstruct/refine.h), on forward-model events (host/events/simulate.h,
// ForwardTruth at the dictionary's click binning). The truth is traced with
// other strata and at least 4x the rays of the refinement's model, so the
// estimator never sees its own model.
//
// Per point of the paper's experiments: `trials` events, each reconstructed;
// the best and the worst trial by 3D error are dropped and the mean and sample
// standard deviation of the rest are reported, for the 3D error and for the
// photon-count error |alpha - alpha_true| (alpha: expected detected photons;
// ForwardTruth has S = 1). Flagged vertices are kept (the protocol drops only
// best and worst); their count is reported beside the statistics. Beside them,
// over all trials: the catastrophic rate (3D error above
// defaults::catastrophic_error_mm) and, over the other trials, the RMSE per
// axis, the CRLB per axis and the efficiency RMSE / CRLB.
//
// The volume experiment: `volume_events` events, one vertex each at a position
// drawn uniformly from the field (x, y, depth), reported by depth band. Every
// event has its own CRLB, so a band's efficiency per axis is the RMS of
// err / CRLB over its non-catastrophic events (1 for an efficient estimator),
// its CRLB the RMS of the events' bounds; the median over events of
// |err| / CRLB is reported too (0.674 for an efficient, Gaussian estimator).
// With `volume_ambiguity`, each event also gets the global ambiguity of its
// true position (host/reconstruct/ambiguity.h, at the event's photons, on the
// scene's model as `prism crlb --ambiguity` computes it), and each band the
// mean of p_confusion: the catastrophic rate the figure predicts, beside the
// rate measured (issue 13's validation).
//
// EvaluationOptions::truth_scene sets the system the events come from apart
// from the refinement's model (a calibration's comparison, issue 18).
//
// CRLB beside each error: crlb_study (the truth's scene, Poisson sensor, the point,
// the truth's binning, rays and splat) gives the bound at the scene's emitted
// photons, i.e. at row.photons expected detected photons; the Fisher
// information is linear in the photon count, so the bound at the target
// detected count N is crlb * sqrt(photons / N). For the double experiment each
// vertex gets its own single-source bound at its own 125 photons (the
// interaction of the two sources is not in it: a lower bound on the two-source
// bound).
#pragma once
#include <cmath>
#include <cstdint>
#include <functional>
#include <optional>
#include <string>
#include <vector>

#include <glm/glm.hpp>

#include "engine/vk/context.h"
#include "host/dictionary/store.h"
#include "host/reconstruct/ambiguity.h"
#include "host/reconstruct/reconstruct.h"
#include "host/reconstruct/refine.h"
#include "host/scene/scene.h"
#include "host/util/work_share.h"

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

// The volume experiment's defaults (issue 10's acceptance run).
namespace volume_protocol {
inline constexpr int events = 500;
inline constexpr double photons = 100;
inline constexpr double band_mm = 5;  // depth bands [0, 5), [5, 10), ... clipped to the field
}  // namespace volume_protocol

// Mean and sample standard deviation after dropping the best and the worst
// trial by 3D error (alpha errors of the same trials). Needs >= 3 trials.
struct TrimmedStats {
  int trials_used = 0;
  double err3d_mean = 0, err3d_std = 0, alpha_err_mean = 0, alpha_err_std = 0;
};
TrimmedStats trimmed_stats(const std::vector<double>& err3d_mm, const std::vector<double>& alpha_err);

// Per-axis accuracy of a set of estimates (x, y, depth errors) against their
// CRLBs (one per estimate; equal within a point of the paper's protocol).
// Catastrophic estimates (3D error above defaults::catastrophic_error_mm) are
// counted and left out of everything else.
struct AxisStats {
  int events = 0;
  double catastrophic_rate = 0;  // share of events
  glm::dvec3 rmse_mm{NAN};        // over the other events
  glm::dvec3 crlb_mm{NAN};        // RMS of their CRLBs
  glm::dvec3 efficiency{NAN};     // sqrt(mean((err / crlb)^2)): RMSE / CRLB, 1 when efficient
  glm::dvec3 median_ratio{NAN};   // median |err| / crlb
};
AxisStats axis_stats(const std::vector<glm::dvec3>& err_mm, const std::vector<glm::dvec3>& crlb_mm);


struct EvaluationOptions {
  std::vector<std::string> experiments{"single-lines", "photons", "double"};
  int trials = paper_protocol::trials;
  int volume_events = volume_protocol::events;
  double volume_photons = volume_protocol::photons;  // expected detected photons per volume event
  bool volume_ambiguity = false;  // each volume event's predicted confusion beside its error
  AmbiguitySettings ambiguity;    // with volume_ambiguity (dark_rate: from `settings`)
  // The volume's field: NaN bounds take the dictionary grid's extent.
  glm::dvec2 volume_x_mm{NAN, NAN}, volume_y_mm{NAN, NAN}, volume_depth_mm{NAN, NAN};
  double band_mm = volume_protocol::band_mm;
  int level = 0;               // click level: binning = base_binning * 2^level
  int refine_level = -1;       // the level the refinement renders on (Refinement); -1: refine_level()'s default
  // Forward truth and CRLB; 0: the dictionary's own (or the default), and at
  // least 4x the refinement model's.
  unsigned rays = 0;
  Splat splat = TraceSettings{}.splat;  // forward truth and CRLB
  unsigned stratification = 1;  // forward truth: other strata than the dictionary's (0) by default
  // The system the events come from, when it is not the model's scene: an
  // as-built system (issue 18: truth from the as-built scene, refinement with
  // the nominal, the fitted or the as-built one). It gives the event truth,
  // the CRLB and the ambiguity (the real system's bounds); the scene passed
  // to evaluate() gives only the refinement's model. Its sensor must be the
  // dictionary's.
  std::optional<Scene> truth_scene;
  uint64_t seed = 1;
  bool quick = false;          // few points per experiment (use with few trials)
  ReconstructionSettings settings;  // search_level -1: default_search_level()
  ReconstructionBackend backend = ReconstructionBackend::vulkan;
  bool device_half = false;    // device backends: the scan level as half floats
  RefineModel model = RefineModel::scene;
  RefineSettings refine;       // dark_rate and alpha_max: from `settings`
  // Where the journals are kept (host/util/journal.h): protocol-journal.jsonl
  // (the paper's experiments) and volume-journal.jsonl. Each event is
  // appended as it is reconstructed. With `resume` the events already there
  // are not redone, so a stopped run resumes (a journal must have been made
  // with the same options; --volume-events may differ); without it they are
  // replaced. Empty: none.
  std::string journal_dir;
  bool resume = false;
  // The figures from what the journals hold, reconstructing nothing: a
  // stopped (or running) evaluation's results so far. Points with fewer than
  // 3 trials there are left out; the journals must exist and hold this run's
  // events (seed, truth, scene, points), made by any search and refinement
  // (Evaluation::journal_estimators says which).
  bool journal_only = false;
  // The processes that share the events (prism evaluate under MPI): each
  // reconstructs those its share takes of the events the journals lack, in
  // the order the protocol's points and the volume's events come, appending
  // them to its own part of each journal; the leader gathers them all and
  // alone makes the figures (the others' Evaluation holds only their cost).
  // The figures equal one process's. journal_only needs a single process.
  WorkShare share;
};

// What the reconstructions of an evaluation cost.
struct EvaluationCost {
  uint64_t events = 0;
  double reconstruct_s = 0;  // wall time inside the reconstructions
  double scan_s = 0;         // of which the support scans
  double refine_s = 0;       // the refinement, after the search
  uint64_t renders = 0;      // sources the refinement's model rendered (its main cost)
  double ambiguity_s = 0;    // the volume events' ambiguity (not in the times above)
  uint64_t ambiguity_renders = 0;
};

struct EvaluationRow {
  std::string experiment;  // single-lines, photons, double or volume: the file the row goes to
  std::string series;      // the curve within it: x, y, depth (lines), moving, fixed (double); "" (photons, volume)
  double varied = 0;       // the plot's x value (volume: the band's centre depth)
  glm::dvec3 position_mm{};  // volume: NaN
  double depth_lo_mm = NAN, depth_hi_mm = NAN;  // volume: the depth band
  double photons = 0;      // expected detected photons of this vertex
  TrimmedStats stats;      // volume: untrimmed
  AxisStats axes;
  int flagged = 0;         // trials whose vertex carried a flag
  double crlb_3d_mm = 0;   // volume: RMS over the band's events
  double p_confusion_mean = NAN;  // volume with ambiguity: the predicted catastrophic rate, mean over events
  // Volume with ambiguity and a refinement: catastrophic events whose truth
  // was fitted (VolumeEvent::truth_fit_nll), and of them the search's failures.
  int catastrophic_classified = 0, search_failures = 0;
};

// One event of the volume experiment.
struct VolumeEvent {
  uint64_t index = 0;  // 0..volume_events-1
  glm::dvec3 truth_mm{};
  ReconstructedVertex estimate;
  glm::dvec3 crlb_mm{};  // Poisson CRLB at the truth (x, y, depth)
  // Its cost: its share of its batch's search plus its refinement, and the
  // refinement's renders; NaN when not recorded (an older journal).
  double seconds = NAN, renders = NAN;
  // With EvaluationOptions::volume_ambiguity, the truth's global ambiguity
  // (NaN otherwise): the closest impostor's KL divergence (nats), its position
  // and the predicted probability of a confusion.
  double alias_kl = NAN, p_confusion = NAN;
  glm::dvec3 alias_mm{NAN};
  // With the ambiguity and a refinement: the refinement's model fitted from
  // the truth alone on the event's clicks (Refiner::local_fit), where it
  // ended and its NLL, beside the estimate's NLL; NaN when not recorded.
  // A catastrophic estimate is the search's failure when that fit stayed
  // within defaults::catastrophic_error_mm of the truth with a lower NLL
  // (the likelihood has a better optimum by the truth, which the search
  // missed), and otherwise the likelihood's own confusion, which is what
  // p_confusion predicts.
  glm::dvec3 truth_fit_mm{NAN};
  double truth_fit_nll = NAN;
  bool search_failure() const;
};

struct Evaluation {
  std::vector<EvaluationRow> rows;
  std::vector<VolumeEvent> volume;  // every event of the volume experiment
  size_t resumed = 0;               // events read from the journals (not in `cost`)
  EvaluationCost cost;              // what this run's reconstructions cost
  // journal_only: per journal read, the search and refinement settings that made it.
  std::vector<std::string> journal_estimators;
};

// Valid experiment names, in the order they run.
const std::vector<std::string>& evaluation_experiments();
// Throws std::invalid_argument naming the first name that is not one of them.
void check_experiments(const std::vector<std::string>& names);

// Runs the chosen experiments; progress(done, total) after each event.
Evaluation evaluate(vk::Context& ctx, const Scene& scene, const DictionaryReader& dictionary,
                    const EvaluationOptions& options, const std::function<void(size_t, size_t)>& progress = {});

// <dir>/<experiment>.csv and .png for every experiment present, and for the
// volume experiment volume-events.csv (one row per event) and
// volume-catastrophic.png. Returns the paths written.
std::vector<std::string> write_evaluation(const std::string& dir, const Evaluation& evaluation);

}  // namespace prism
