// Continuous maximum-likelihood refinement of an event's vertices (issue 10):
// after the support search has put each vertex near a dictionary node, all K
// vertices, (x, y, depth, alpha) each, are fitted jointly on the binary
// sensor's sparse likelihood with the scene's own forward model, which gives
// the PSF and its derivatives at any position. The search's planes and
// lateral nodes stop mattering once it has found the right basin; what is
// left is the likelihood's own ambiguity, which the refinement meets by
// starting from the search's answer, its runners-up, the lenslet-lattice
// aliases and a ladder along the weakest direction, keeping the best, and by
// trying the aliases out to 2 pitches when the fit is still poor, and every
// site of the lattice the clicks vote for (click_geometry.h), those sites
// scored and first fitted with blurred images (near the face the search's
// wrong answer is an alias at another depth, and the source's own site lies
// a little off the lattice built from it; with few clicks the sharp images'
// cliffs hold a fit anywhere), and last refitting the estimate blurred, then
// sharp (the continuation). With K > 1 each vertex is also tried at every vertex's
// runners-up (the re-seed), and votes only with the clicks the others
// leave: a source the greedy search left unclaimed is found that way.
//
// The model of one vertex: P(theta) = b(theta) / sum(b(theta)), b the forward
// model's expected photons on the click grid, so P sums to 1 on the sensor
// (S = 1) and alpha is the expected photons detected, as in the search and in
// ForwardTruth (host/events/simulate.h). With rates
//   lambda_c = dark + sum_k alpha_k P_k(c),
// the NLL is sum_k alpha_k - sum_c [lambda_c + log(1 - exp(-lambda_c))] (sums
// over the clicks; reconstruct.h's convention, the dark sum left out). Steps
// are Levenberg-Marquardt on the expected (Fisher) information of the binary
// sensor, sum_pixels J J^T / (exp(lambda) - 1), whose inverse at the optimum
// is also each vertex's CRLB; parameters that sit on a bound with the
// gradient pushing outward are held there (projected LM).
//
// Goodness of fit: T = the NLL over every pixel at the estimate, against T
// of events drawn from the fitted model itself (Monte Carlo, seeded by the
// event id); fit_pvalue is the share of draws with T at least the event's.
// T at a fitted estimate is a little lower than at the truth, so the p-value
// is conservative for events the model explains.
#pragma once
#include <cstdint>
#include <memory>
#include <span>
#include <unordered_map>
#include <vector>

#include <glm/glm.hpp>

#include "engine/forward.h"
#include "host/dictionary/store.h"
#include "host/events/event_file.h"
#include "host/reconstruct/reconstruct.h"
#include "host/scene/scene.h"

namespace prism {

// One source's P = b / sum(b) on the click grid and dP/d(x, y, depth), at
// the pixels where b or a derivative is nonzero, sorted by pixel index
// (row * width + col).
struct ModelPixel {
  uint32_t index;
  double p;
  glm::dvec3 g;
};
struct SourceImage {
  std::vector<ModelPixel> pixels;
  double photons = 0;  // sum(b) at the scene's emitted photons (0: nothing lands on the sensor)
  // P and its gradient at `index` (zero where the image holds nothing).
  const ModelPixel* find(uint32_t index) const;
};
// `image` convolved with a Gaussian of `sigma_px` click-grid pixels (P and its
// gradient alike; what falls off the grid is lost); `image` itself for 0.
SourceImage blurred(const SourceImage& image, double sigma_px, const AnalysisGrid& grid);

// The continuous model: the scene's forward model on the click grid, on the
// device or the double CPU reference.
class SourceModel {
 public:
  virtual ~SourceModel() = default;
  std::vector<SourceImage> render(std::span<const glm::dvec3> theta);
  uint64_t renders() const { return renders_; }  // sources rendered so far
  // From here on render only the pixels within reach_px of these clicks (and
  // what the model's tiles round that to), where the model can (a masked
  // render, make_masked_scene_model); a model that cannot renders every pixel.
  virtual void focus(std::span<const uint32_t> /*clicks*/, int /*reach_px*/) {}

 protected:
  // b and db/d(x, y, depth) of one source at the pixels where any is nonzero, sorted.
  virtual std::vector<ModelPixel> render_raw(const glm::dvec3& theta) = 0;
  // The whole sensor's b and its gradient where render_raw's pixels are not
  // all of them (a focused render); false: their sum is.
  virtual bool sensor_photons(const glm::dvec3& /*theta*/, double& /*b*/, glm::dvec3& /*db*/) { return false; }

 private:
  uint64_t renders_ = 0;
};

// The device's forward model (ForwardVulkan) or the reference (ref::psf),
// at `settings` (binning: the clicks'; footprint splat by default).
std::unique_ptr<SourceModel> make_scene_model(const Scene& scene, const TraceSettings& settings,
                                              vk::Context* ctx /* nullptr: CPU reference */);
// The device's forward model at `settings`, focused (SourceModel::focus):
// each render covers the tiles (TileMask) around the clicks alone, and P is
// b over the whole sensor's light from a render of every pixel at
// `photons_settings` (coarser pixels, the same cells: the same light). The
// refinement's polish at the sensor's own pixels, where a render of every
// pixel costs a minute on lavapipe. Its images hold those tiles' pixels
// alone, so a refinement's Fisher information (its steps' metric, and the
// CRLB it reports) counts only them, and its p-value would not test the fit
// (Refinement reports the coarse level's instead).
// Clicks whose tiles outgrow one image buffer (ForwardVulkan::max_masked_tiles
// at `image_budget_bytes`) are rendered over every pixel instead.
std::unique_ptr<SourceModel> make_masked_scene_model(
    const Scene& scene, const TraceSettings& settings, const TraceSettings& photons_settings, vk::Context& ctx,
    uint64_t image_budget_bytes = ForwardVulkan::default_image_budget_bytes);

// The model from a dictionary alone, at click level `level`: the 8 PSFs
// around a position, moved by the magnification and blended (bilinear
// laterally, linear in depth); dictionary_model.cpp says how and what it
// cannot know.
std::unique_ptr<SourceModel> make_dictionary_model(const DictionaryReader& reader, int level);

// Which continuous model refines the search's answer.
enum class RefineModel { none, scene, dictionary };

// --model's value ("scene", "dictionary", "none"; "" for the default: scene
// for a dictionary synthesised from one or when a scene is given, dictionary
// for a calibrated one). Scene for a calibrated dictionary without a scene
// is an error that says what to give instead.
RefineModel choose_refine_model(const std::string& name, const DictionaryManifest& m, bool scene_given,
                                const std::string& dictionary_dir);
// The model for `choice` on click level `level` (nullptr for none), and a
// line saying what it is.
std::unique_ptr<SourceModel> make_refine_model(RefineModel choice, const Scene& scene,
                                               const DictionaryReader& dictionary, int level, vk::Context* ctx);
std::string describe(RefineModel choice, const Scene& scene);

// The refinement's trace settings: footprint cells per lenslet from
// defaults::refine_rays_per_lenslet at the clicks' binning.
TraceSettings refine_trace_settings(unsigned binning);

struct RefineSettings {
  int iterations = defaults::refine_iterations;  // LM steps per start
  bool aliases = true;                           // also start from the best vertex's lattice aliases
  int search_starts = defaults::refine_search_starts;  // the search's runners-up probed per vertex
  int alias_starts = defaults::refine_alias_starts;    // lattice aliases probed per vertex (best by first NLL)
  bool rescue = true;  // a poor fit also tries the aliases out to defaults::refine_rescue_alias_pitches
  bool lattice_scan = true;  // p < defaults::refine_lattice_scan_pvalue: also the sites the clicks vote for
  bool reseed = true;  // K > 1: each vertex also tried where the clicks the others leave vote for
  // A vertex shallower, or an event with fewer clicks, gets the lattice scan
  // whatever its fit (sites blurred) and the continuation (defaults.h).
  double always_scan_below_mm = defaults::refine_always_scan_below_mm;
  int always_scan_below_clicks = defaults::refine_always_scan_below_clicks;
  int ladder_starts = defaults::refine_ladder_starts;  // ladder points probed per vertex (0: no ladder)
  int ladder_reach_px = defaults::refine_ladder_reach_px;  // each rung's image also scored moved by up to this
                                                          // many click-grid pixels
  bool continuation = true;  // refit from the estimate with blurred images, then sharp (refine.cpp)
  double site_blur_px = defaults::refine_site_blur_px;  // the lattice scan's sites scored and first fitted with
                                                      // images blurred by this sigma (0: sharp)
  int pvalue_draws = defaults::fit_pvalue_draws; // Monte Carlo events per goodness-of-fit p-value
  double dark_rate = ReconstructionSettings{}.dark_rate;
  double alpha_max = ReconstructionSettings{}.alpha_max;
};

// The field the vertices are held in: the scene's volume.
struct RefineBounds {
  glm::dvec3 lo, hi;  // x, y, depth, mm
  static RefineBounds of(const Scene& scene);
};

struct RefineStats {
  uint64_t events = 0, starts = 0, iterations = 0;
  uint64_t rescues = 0;  // events whose poor fit sent them to the far aliases
  uint64_t lattice_scans = 0;   // events whose poor or marginal fit, or shallow vertex, had the clicks' votes counted
  uint64_t lattice_depths = 0;  // voted depths scanned
  uint64_t reseeds = 0;  // events (K > 1) whose vertices were re-seeded from the clicks the others leave
  uint64_t continuations = 0, continuations_kept = 0;  // blurred refits, and those that lowered the NLL
  double seconds = 0;
};

class Refiner {
 public:
  // `clicks`: the grid the events' clicks lie on (AnalysisGrid::of at their binning).
  Refiner(SourceModel& model, const Scene& scene, const AnalysisGrid& clicks, RefineSettings settings);
  // The search's vertices of `event` refined; rows keep their order. Rows
  // flagged no_clicks or alpha_zero are left as the search gave them (the
  // latter get no CRLB).
  std::vector<ReconstructedVertex> refine(const Event& event, std::vector<ReconstructedVertex> start);
  const RefineStats& stats() const { return stats_; }
  // One vertex fitted from `at` with weight `alpha` on `event`'s clicks and
  // followed to convergence, no other start tried: where it ends and its NLL
  // (refine()'s, ReconstructedVertex::nll; NaN without clicks). From the
  // truth it is the likelihood's own optimum there, which tells a search
  // that missed it from a likelihood that prefers the wrong answer
  // (evaluate's volume experiment). Leaves stats() alone.
  struct LocalFit {
    glm::dvec3 position_mm{NAN};
    double alpha = NAN, nll = NAN;
  };
  LocalFit local_fit(const Event& event, const glm::dvec3& at, double alpha);
  // The vertices of `rows` (another refinement's answer, on coarser pixels)
  // followed to convergence on these clicks, no other start tried: straight
  // from there and, with `blur_px`, also through the images blurred by each
  // of these sigmas (click-grid pixels) in turn, then sharp, the lower NLL
  // kept. Rows as refine() gives them, with this grid's CRLB and p-value.
  std::vector<ReconstructedVertex> polish(const Event& event, std::vector<ReconstructedVertex> rows,
                                          std::span<const double> blur_px);

 private:
  struct Fit;
  static std::vector<size_t> live_rows(const std::vector<ReconstructedVertex>& rows);
  // Vertices `live` of `rows` as a fit, not rendered; first_fit: rendered and
  // followed by Levenberg-Marquardt steps.
  Fit start_fit(const Event& event, const std::vector<ReconstructedVertex>& rows, const std::vector<size_t>& live) const;
  Fit first_fit(const Event& event, const std::vector<ReconstructedVertex>& rows, const std::vector<size_t>& live);
  // The continuation: `g` fitted with its images blurred by each of `blur_px`
  // in turn, then sharp; it replaces `f` where its NLL is lower (true then).
  bool continuation(Fit& f, Fit g, std::span<const double> blur_px);
  // Rows `live` of `rows` from fit `f`: positions, weights, CRLB, p-value, flags.
  void finish(const Fit& f, const std::vector<size_t>& live, std::vector<ReconstructedVertex>& rows, double pvalue) const;
  double fit_pvalue(const Fit& f, uint64_t event_id) const;
  SourceModel& model_;
  RefineSettings s_;
  RefineBounds bounds_;
  OpticalSystem optics_;
  AnalysisGrid grid_;
  std::vector<glm::dvec2> lattice_mm_;      // lenslet-lattice vectors (nearest neighbours)
  std::vector<glm::dvec2> rescue_lattice_mm_;  // those up to 2 pitches, for the rescue of a poor fit
  RefineStats stats_;
};

// The refinement as the commands run it, on the clicks' own level or, where
// rendering there costs too much, staged: every start, alias, lattice scan
// and continuation of Refiner::refine on the clicks binned to a coarser
// level (`refine_level`), then its answer fitted again on the clicks' own
// pixels from there (Refiner::polish: straight, and through images blurred
// by defaults::refine_polish_blur_refine_px of the coarser level's pixels,
// the better kept; from a coarser answer the clicks' own likelihood has
// cliffs a local step cannot see across). At the sensor's own
// 6.9 um pixels a render of every pixel of the prototype takes 7-18 s on
// lavapipe (50-110 s with the Airy square) and a refinement about 100 of
// them; on the device the polish's scene model renders only the tiles
// around the event's clicks (make_masked_scene_model), and the native
// pixels carry 5-6 times the position information of 110 um ones (docs/reconstruction.md
// "Refinement at the sensor's own pixels").
class Refinement {
 public:
  // `click_level`: the events' clicks' level of `dictionary`; `refine_level`
  // (>= click_level): where the refinement renders. `choice` is not none.
  Refinement(RefineModel choice, const Scene& scene, const DictionaryReader& dictionary, int click_level,
             int refine_level, vk::Context* ctx, const RefineSettings& settings);
  ~Refinement();
  std::vector<ReconstructedVertex> refine(const Event& event, std::vector<ReconstructedVertex> rows);
  // Refiner::local_fit on the clicks' own level.
  Refiner::LocalFit local_fit(const Event& event, const glm::dvec3& at, double alpha);
  uint64_t renders() const;  // sources rendered so far, both levels
  // The refinement's counts; its seconds include the polish's.
  RefineStats stats() const;
  int refine_level() const { return refine_level_; }
  bool staged() const { return polish_ != nullptr; }

 private:
  const int click_level_, refine_level_;
  uint32_t click_width_ = 0, refine_width_ = 0;
  std::unique_ptr<SourceModel> coarse_model_, fine_model_;
  std::unique_ptr<Refiner> coarse_, polish_;
  std::vector<double> polish_blur_px_;  // the polish's continuation, click-grid pixels
  int focus_reach_px_ = 0;  // the fine model renders the pixels this near the clicks (focus)
  bool fine_focused_ = false;  // the fine model is focused: the polish's p-value is the coarse level's
};

// The refine_level for clicks on `click_level`: `requested` where >= 0, else
// the finest level whose pixels span at least
// defaults::refine_pixel_sensor_px sensor pixels per axis, or the clicks'
// own where coarser.
int refine_level(const DictionaryManifest& m, int click_level, int requested = -1);
// Throws, naming --refine-level and the levels to choose from, unless
// click_level <= refine_level < the dictionary's levels.
void check_refine_level(const DictionaryManifest& m, int click_level, int refine_level);

// The goodness of fit of an event on the binary sensor: T = the NLL over
// every pixel, observed (the clicks) against `draws` events drawn from the
// model itself with an RNG seeded by `seed`; returns (1 + the draws with T at
// least the event's) / (1 + draws). `rates`: lambda (dark included) at each
// pixel the model lights, by index; the rest of the grid's `pixels` have
// lambda = `dark` (their clicks drawn as one Poisson count). Each lit pixel's
// clicks are placed by geometric gaps between the draws where it clicks,
// so that a pixel costs 1 + draws x P(click), not draws.
double binary_fit_pvalue(const std::unordered_map<uint32_t, double>& rates, std::span<const uint32_t> clicks,
                         double dark, double pixels, int draws, uint64_t seed);

// The lenslet lattice's vectors at most `max_pitches` times the
// nearest-neighbour distance, each once (a vector and its negative both).
// The default, the nearest neighbours: for the prototype's hex array six
// vectors of the 4 mm pitch; 2 adds the six of sqrt(3) and the six of 2 pitches.
std::vector<glm::dvec2> lattice_vectors(const OpticalSystem& sys, double max_pitches = 1.0);

// The unit eigenvector of the largest eigenvalue of symmetric `c` (power
// iteration from the depth axis, where the prototype's weakest direction
// lies): for a position covariance, the direction the position is worst
// determined in.
glm::dvec3 largest_eigenvector(const glm::dmat3& c);

}  // namespace prism
