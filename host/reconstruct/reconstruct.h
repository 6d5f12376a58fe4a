// The paper's ADCG-inspired reconstruction (Sec. IV.B, eqs. 12-19;
// DESIGN.md "Reconstruction") on the sparse likelihood: every score is a sum
// over the event's clicks plus summed-area look-ups for the on-sensor mass S,
// never a sum over all pixels.
//
// Per event: (1) gradient g = 1 - y / (1 - exp(-lambda)) of the current model;
// (2) support search: every dictionary PSF at its best whole-pixel lateral
// shift within tau, on a coarse level; (3) projected Newton weights;
// (4) pruning: the best candidates carried down to the click level, the
// lowest NLL kept; (5) parabolic depth refinement through neighbouring
// planes, lateral offset rescaled by the magnification at the refined depth;
// (6) K passes, each followed by a joint local descent of all vertices.
//
// Step (2) over every PSF is where the time goes, and where the three
// backends differ: `cpu` is the double-precision reference
// (engine/ref/support_scan_ref.h); `vulkan` runs shaders/support_scan.comp over
// a batch of events per dispatch (sums over clicks); `dense`
// shaders/support_scan_dense.comp (sums over every pixel of the scan level:
// the paper's way, the baseline). Everything after the scan is the same
// double-precision host code for all three (event_fit.h says where each step
// lives), so they differ only where the scan does.
#pragma once
#include <cmath>
#include <cstdint>
#include <memory>
#include <span>
#include <string>
#include <vector>

#include <glm/glm.hpp>

#include "engine/defaults.h"
#include "engine/support_scan.h"
#include "host/dictionary/service.h"
#include "host/events/event_file.h"

namespace prism {

struct ReconstructionSettings {
  int vertices = 1;              // K: vertices sought per event, 1..8
  int search_level = -1;         // dictionary level of the scan over all PSFs; -1: the service's coarse level
  double tau_mm = 2.5;           // lateral search half-width around each grid node, source mm (half a 5 mm pitch)
  double dark_rate = 1e-6;       // background expected counts per click-level pixel: keeps the NLL finite at
                                 // clicks no PSF reaches and is the gradient floor at lambda = 0 (see .cpp)
  // The floor with which the search chooses among the dictionary's PSFs (scan,
  // carry, selection), expected counts per *sensor* pixel (a click pixel of
  // b x b sensor pixels holds b^2 of it; never below dark_rate there); the
  // weights, the descent and the depth keep dark_rate, so the photon count is
  // not biased by it. 0: dark_rate alone. A PSF at a grid node misses clicks
  // of an off-grid source: a higher floor makes such a click cost the search
  // less (docs/reconstruction.md "The floor with the refinement"). The default is 1e-4 per
  // 110 um click pixel (16 x 16 sensor pixels).
  double search_dark_rate = defaults::search_dark_rate_per_sensor_pixel;
  int refine_candidates = 8;     // PSFs carried from the coarse scan (ranked by coarse NLL) to the click level
  // Coarse to fine: with the scan on a level coarser than select_level, every
  // PSF within carry_margin_nll of the scan's best NLL (at least
  // refine_candidates, at most carry_max) is carried down to select_level
  // (+-1 pixel re-searched per level) and ranked again there by its NLL; the
  // refine_candidates best go on to the clicks. -1: select_level()'s default
  // (441.6 um pixels, or the clicks' level + 2 where coarser).
  int select_level = -1;
  // The refine_candidates go down from select_level to rank_level and are
  // ranked there by their NLL; only the best goes on to the clicks (the
  // others' shifts scaled to the clicks' level, as runners-up). -1:
  // rank_level()'s default (27.6 um pixels, or the clicks' level where
  // coarser).
  int rank_level = -1;
  double carry_margin_nll = 50;  // measured: docs/reconstruction.md, coarse to fine
  // The carry margin at every level of the descent, not at the scan's alone:
  // between the scan and select_level the carried PSFs are ranked again at
  // each level and those beyond the margin dropped; of the refine_candidates
  // only those within it of the best at select_level go on towards
  // rank_level, ranked again the same way at each level between (the
  // dropped stay runners-up). false: every carried PSF goes down to
  // select_level and all refine_candidates to rank_level (before).
  bool staged_carry = true;
  int carry_max = 512;
  int newton_iterations = 60;    // cap per weight solve (projected Newton with backtracking)
  int descent_rounds = 12;       // cap on rounds of the joint local descent after each new vertex
  double alpha_max = 1e6;        // upper bound on a weight, expected photons; reaching it sets alpha_at_bound
  int min_clicks = 3;            // fewer clicks than this in the event sets few_clicks (3D needs more)
  int scan_step_px = 1;          // the scan tries shifts on multiples of this (search-level pixels); the
                                 // candidates are then re-searched +-(step - 1) around their best
  ScanLayout scan_layout = ScanLayout::automatic;  // device layout of the scan's weight fits (engine/support_scan.h);
                                              // the same results either way
  ScanLoads scan_loads = ScanLoads::texel;    // how the sparse kernel reads its look-ups (engine/support_scan.h);
                                              // the same results either way
  // Device backends: each pass's events go to the device this many at a
  // time; with overlap_scans the host descends one chunk (tiles, weights,
  // depth) while the device scans the next, else each chunk is scanned,
  // then descended. The same results either way (each event is scored alone).
  int scan_chunk_events = defaults::scan_chunk_events;
  bool overlap_scans = true;
  // The device scan fits the weights only of PSFs whose NLL bound shows they
  // can still be carried or selected (engine/support_scan.h, ScanSettings);
  // true: of every PSF, as before the bound (the same vertices; benchmarks
  // compare the two).
  bool fit_all_weights = false;
};

enum class ReconstructionBackend { cpu, vulkan, dense };
const char* to_string(ReconstructionBackend b);
ReconstructionBackend backend_from_string(const std::string& s);  // throws naming the choices

// Why a vertex's numbers should not be trusted; several may be set.
enum VertexFlag : uint32_t {
  vertex_ok = 0,
  no_clicks = 1u << 0,       // the event has no clicks: nothing to fit, the row only keeps the count of K
  few_clicks = 1u << 1,      // fewer than min_clicks clicks
  alpha_zero = 1u << 2,      // weight 0: the vertex explains nothing (fewer sources than K)
  alpha_at_bound = 1u << 3,  // weight reached alpha_max: the likelihood has no finite optimum
  edge = 1u << 4,            // optimum on the dictionary's outer boundary (refined: within one CRLB of the
                             // scene's volume): the vertex may be outside the field
  merged = 1u << 5,          // same PSF and shift as another vertex (refined: closer than either's
                             // 3D CRLB): the two are not separable
  poor_fit = 1u << 6,        // refined: fit_pvalue below defaults::fit_pvalue_flag; the event is not
                             // explained by K vertices in the field (one more, one outside, background)
};
std::string flags_to_string(uint32_t flags);  // "a|b", or "" when vertex_ok

struct ReconstructedVertex {
  double x_mm = 0, y_mm = 0, depth_mm = 0;  // depth from the scintillator face
  double alpha = 0;         // expected photons (paper convention: alpha P with P summing to 1 on-sensor)
  double nll = 0;           // NLL of the whole event's final model (eq. 12, minus sum_i dark_rate)
  uint32_t clicks = 0;      // clicks where this vertex's rate is the largest term (and above dark_rate)
  uint32_t flags = vertex_ok;
  size_t psf = 0;           // dictionary entry of the model used (diagnostic)
  glm::ivec2 shift_px{};    // its whole-pixel shift on the click grid (columns, rows)
  // Continuous refinement only (host/reconstruct/refine.h); NaN without it.
  double crlb_x_mm = NAN, crlb_y_mm = NAN, crlb_z_mm = NAN, crlb_3d_mm = NAN;  // binary sensor, at the estimate
  double fit_pvalue = NAN;  // the event's goodness of fit (the same on every row of the event)
  bool refined = false;
  // The search's runners-up for this vertex (x, y, depth on their plane,
  // alpha), best first: further starts for the refinement.
  std::vector<glm::dvec4> runners_up;
};

// The dictionary level the clicks lie on: the event binning must be
// base_binning * 2^level and the grids must match; throws naming both files.
int click_level(const DictionaryManifest& m, const EventFileHeader& h, const std::string& events_path,
                const std::string& dictionary_dir);

// The default level of the support scan: the finest from the clicks' level
// + 2 up whose shift lattices, summed over the PSFs, hold at
// most defaults::search_shifts_per_click shifts (scan_shifts); a level
// coarser than select_level() is searched coarse to fine. Capped at the
// coarsest stored. Every command and benchmark that picks a search level for
// the user takes it from here.
int default_search_level(const DictionaryManifest& m, int click_level, double tau_mm);
// The shifts one event's scan scores per click on `level`: every PSF's
// lattice within +-tau_mm (times its depth's magnification) summed.
double scan_shifts(const DictionaryManifest& m, int level, double tau_mm);
// A scan with more shifts per click than this is refused before it starts
// (the default level holds at most defaults::search_shifts_per_click).
inline constexpr double max_scan_shifts = 1e9;
// The level a coarse-to-fine search ranks its carried PSFs on:
// settings.select_level, or when it is -1 the finest from the clicks' level
// + 2 up whose pixels span defaults::select_pixel_sensor_px sensor pixels
// (capped at the coarsest stored).
int select_level(const ReconstructionSettings& s, const DictionaryManifest& m, int click_level);
// The level the candidates from select_level are ranked on before the best
// goes on to the clicks: settings.rank_level, or when it is -1 the finest
// from the clicks' level up whose pixels span defaults::rank_pixel_sensor_px
// sensor pixels.
int rank_level(const ReconstructionSettings& s, const DictionaryManifest& m, int click_level);

// Where the time of a batch went.
struct ReconstructionTimings {
  double scan_s = 0;         // the support scans over every PSF (device: dispatch to results on the host)
  double scan_wait_s = 0;    // of which the host spent waiting (device backends: the rest ran beside host work)
  double scan_kernel_ms = 0; // of which the kernels themselves (GPU timestamps), device backends
  double host_s = 0;         // everything else: gradients, refinement, weights, descent, depth
  uint64_t scans = 0;        // events x passes scanned
  uint64_t scan_device_bytes = 0;  // peak event/result buffers of one scan call
  uint64_t scan_fallbacks = 0;     // device rounds of weight fits whose serial fits ran out of loop budget
  uint64_t scan_fits = 0;          // weights the scans fitted ...
  uint64_t scan_candidates = 0;    // ... of (event, PSF) candidates scanned
};

// Reconstructs batches of events with one backend. The events of a batch go
// through the K passes in lockstep, so each pass scans the whole batch in one
// call (one dispatch per dictionary chunk on the device). Device backends need
// a service made with a device (and its coarse level is the scan level).
class Reconstructor {
 public:
  // `host_helpers`: more services of the same dictionary and coarse level
  // (made without a device), one per extra host thread: with a device
  // backend, the events of a chunk are descended on 1 + their count threads,
  // event i on service i mod (1 + count), so that no service is shared
  // between threads.
  Reconstructor(DictionaryService& dictionary, int click_level, ReconstructionSettings settings,
                ReconstructionBackend backend = ReconstructionBackend::cpu, vk::Context* ctx = nullptr,
                std::vector<DictionaryService*> host_helpers = {});
  ~Reconstructor();
  // Per event, K rows (fewer never; rows with alpha 0 are flagged). Bounded
  // work: every loop has a cap in settings.
  std::vector<std::vector<ReconstructedVertex>> run(std::span<const Event> events);
  // The first pass's support scan alone, per event one score per PSF (tests
  // compare the backends with it; events without clicks give none).
  std::vector<std::vector<SupportScore>> first_scan(std::span<const Event> events);
  const ReconstructionTimings& timings() const { return timings_; }
  const ReconstructionSettings& settings() const { return s_; }

 private:
  DictionaryService& d_;
  std::vector<DictionaryService*> services_;  // d_, then the host helpers
  int level_;
  ReconstructionSettings s_;
  ReconstructionBackend backend_;
  std::unique_ptr<SupportScanVulkan> device_;
  ScanLevel scan_level_;
  ReconstructionTimings timings_;
  void check_clicks(std::span<const Event> events) const;
};

// One event on the CPU reference. `level` is the click level from click_level().
std::vector<ReconstructedVertex> reconstruct(const Event& event, int level, DictionaryService& dictionary,
                                             const ReconstructionSettings& settings);

}  // namespace prism
