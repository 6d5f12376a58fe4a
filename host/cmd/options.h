// Options and parsing shared by several subcommands.
#pragma once
#include <optional>
#include <span>
#include <string>
#include <vector>

#include <CLI/CLI.hpp>

#include "engine/optical_system.h"
#include "engine/vk/context.h"
#include "host/scene/crlb_study.h"

namespace prism::cmd {

// --device, --rays, --binning, --lens-model, --photons, --backend,
// --fisher-estimator, --splat, --stratification: the forward model's knobs,
// with the same names and defaults everywhere.
// --splat and --stratification (TraceSettings): how rays become pixel values,
// on every command that traces, with the same names and defaults.
struct SplatOptions {
  std::string splat = to_string(TraceSettings{}.splat);
  unsigned stratification = 0;
  // `stratification_use`: what the command does with it, added to its help.
  void add_to(CLI::App* app, const std::string& stratification_use = "");
  Splat kind() const { return splat_from_string(splat); }
  void apply(TraceSettings& t) const;  // splat and stratification
};

// What --rays becomes, said in each command's help: the aperture is cut
// into n x n strata, n even, so 128 runs as 144.
inline constexpr const char* rays_rounding = "rounded up to an even square of strata (128 runs as 144)";
// capture-hdr's and simulate-hdr's --darks (engine/hdr_times.h).
inline constexpr const char* darks_help =
    "number of dark frames, at the longest, the shortest and exposure times between, so that the merge fits each "
    "pixel's dark current (one: at the longest, its level subtracted from every exposure)";
// What --device takes, said alike in every command's help.
inline constexpr const char* device_help =
    "Vulkan device: auto (GPU if present), gpu, cpu (lavapipe), an index or part of a name (prism devices); "
    "default $PRISM_DEVICE or auto";

// What --dark-rate sets, said alike by reconstruct and evaluate.
inline constexpr const char* dark_rate_help =
    "the likelihood's background, expected counts per click-level pixel and event: the NLL's floor at clicks no "
    "PSF reaches, for the weights and the refinement, and for the search where --search-dark-rate gives less "
    "(docs/reconstruction.md \"Clicks at the sensor's own pixels\": it sets how much a click the model misses costs)";

// What --search-dark-rate sets, said alike by reconstruct and evaluate.
inline constexpr const char* search_dark_rate_help =
    "the floor with which the search chooses among the dictionary's PSFs, expected counts per sensor pixel (a click "
    "pixel of b x b sensor pixels holds b^2 of it, and never less than --dark-rate; 0: --dark-rate alone); the "
    "weights, the descent and the refinement keep --dark-rate. Higher makes a click the nearest PSF misses cost the "
    "search less without biasing the photon count (docs/reconstruction.md \"The floor with the refinement\")";

struct ForwardOptions {
  std::string device;
  unsigned rays = 0;  // 0: the splat's converged default (TraceSettings::default_rays)
  unsigned binning = defaults::analysis_binning;
  std::string lens_model;  // empty: the scene's own
  double photons = 0;      // 0: the scene's own
  std::string backend = "vulkan";
  std::string estimator = "auto";  // split for point rays, naive for footprints
  SplatOptions splat;

  void add_to(CLI::App* app, unsigned default_binning);
  TraceSettings settings(const Scene& scene) const;
  void apply(Scene& scene) const;  // lens model override
  Backend backend_kind() const { return backend == "cpu" ? Backend::cpu : Backend::vulkan; }
};

// After a parse that failed: where a command must stand (prism, prism
// dictionary, prism camera) and a word names none or none is given, what to
// say instead of CLI11's "A subcommand is required"; nothing otherwise.
std::optional<std::string> missing_command(const CLI::App& app, const CLI::ParseError& error);

// Comma-separated numbers and FIRST:LAST:STEP ranges: "5,10,25", "0:50:2.5",
// "0:10:1,12.5,15:50:5"; at most max_list_values, counted before expanding.
inline constexpr size_t max_list_values = 100000;
std::vector<double> parse_list(const std::string& text, const std::string& option);
// Values as parse_list reads them back (A,B,C with %g).
std::string format_list(std::span<const double> values);
// Comma-separated numbers, no ranges: min_count to max_count of them, as
// `form` says ("X,Y,DEPTH[,ALPHA] (mm, mm, mm, photons)"), which errors quote.
std::vector<double> parse_numbers(const std::string& text, const std::string& option, const std::string& form,
                                  size_t min_count, size_t max_count);
// "X,Y,DEPTH".
glm::dvec3 parse_point(const std::string& text, const std::string& option);

// Checks for number options that say what is wrong in words ("--photons: 0
// must be > 0"), where CLI11's PositiveNumber and NonNegativeNumber print a
// range up to the largest double; both refuse NaN and infinities.
extern const CLI::Validator positive_number;
extern const CLI::Validator non_negative_number;
// --always-scan-below-mm and --always-scan-below-clicks (RefineSettings'),
// for the commands that refine.
void add_always_scan_options(CLI::App* c, double& below_mm, int& below_clicks);
// --refine-level (Refinement's refine_level; -1 leaves the default).
void add_refine_level_option(CLI::App* c, int& refine_level);
// A number no larger than `limit` ("'1e300' is more than 1e+12 photons").
CLI::Validator at_most(double limit, const std::string& unit);

// Every number option of `app` and its subcommands (CLI11 type FLOAT) refuses
// NaN and infinities, and every unsigned one (UINT) a negative value, naming
// the option: call once, after every subcommand has added its options.
void require_finite_numbers(CLI::App& app);

// --max-memory SIZE (or PRISM_MAX_MEMORY) on `command`: the limit memory
// estimates are checked against
// (host/util/memory.h), set while the arguments are read, before any
// command runs.
void add_memory_limit(CLI::App& command);

}  // namespace prism::cmd
