// prism calibrate: the scene's as-built parameters fitted to a measured PSF
// dictionary (host/calibrate/calibrate.h says how and what it assumes).
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <memory>
#include <thread>

#include "engine/vk/error.h"
#include "host/calibrate/calibrate.h"
#include "host/cmd/commands.h"
#include "host/cmd/options.h"
#include "host/dictionary/store.h"
#include "host/scene/scene.h"
#include "host/util/format.h"
#include "host/util/image_io.h"
#include "host/util/output_file.h"
#include "host/util/plot.h"

namespace fs = std::filesystem;

namespace prism::cmd {

namespace {

struct CalibrateArgs {
  std::string dictionary;
  std::string merged;
  std::string scene;  // empty: the dictionary's own
  std::string out;
  std::string fit = join(calibration_default_groups(), ",");
  int level = -1;
  unsigned rays = 0;
  unsigned every = 1;
  int max_steps = defaults::calibration_max_steps;
  bool pattern_moves = false;
  int coarse_levels = defaults::calibration_coarse_levels;
  double weight_floor = defaults::calibration_weight_floor;
  double reliable = defaults::calibration_reliable_over_faintest;
  unsigned threads = std::max(1u, std::thread::hardware_concurrency());
  unsigned blur_supersample = defaults::calibration_blur_supersample;
  unsigned cells_check = defaults::calibration_cells_check_factor;
  unsigned bootstrap = 0;
  int bootstrap_steps = defaults::calibration_bootstrap_steps;
  uint64_t seed = 1;
  std::string backend = "auto";
  std::string device;
  std::string csv;
  std::string residuals;
  std::string checkpoint;
};

std::vector<std::string> split_commas(const std::string& text) {
  std::vector<std::string> out;
  size_t start = 0;
  while (start <= text.size()) {
    const size_t end = std::min(text.find(',', start), text.size());
    if (end > start) out.push_back(text.substr(start, end - start));
    start = end + 1;
  }
  return out;
}

// The finest level whose pixels are at least defaults::calibration_pixel_um.
int default_level(const DictionaryManifest& m) {
  for (int k = 0; k < m.levels; ++k)
    if (m.pixel_mm(k) * 1e3 >= defaults::calibration_pixel_um * (1 - 1e-9)) return k;
  return m.levels - 1;
}

void write_text(const std::string& path, const std::string& text) {
  write_atomically(path, [&](const std::string& tmp) {
    std::ofstream out(tmp);
    out << text;
    if (!out) throw std::runtime_error("cannot write " + path);
  });
}

// Whether the fit found a source extent the start scene lacked: the
// calibration source's (an LED's die), not the optics'. Events are point
// sources, so the scene written keeps the start's effects.
bool extent_is_the_source_only(const Scene& start, const OpticalSystem& optics) {
  return optics.effects.source_extent && !start.optics.effects.source_extent;
}

// The scene a command writes for fitted optics: the start's, its optics
// replaced (but for a source-only extent, above), named "<start>-calibrated".
Scene fitted_scene(const Scene& start, const OpticalSystem& optics) {
  Scene fitted = start;
  fitted.optics = optics;
  // Once: a fit resumed from a checkpoint or refined from a fitted scene
  // keeps the name it had.
  fitted.name = start.name.ends_with("-calibrated") ? start.name : start.name + "-calibrated";
  if (extent_is_the_source_only(start, optics)) fitted.optics.effects = start.optics.effects;
  return fitted;
}

// The measured PSFs, the scene they are fitted with and the model's binning.
struct Inputs {
  Scene scene;
  std::vector<MeasuredPsf> psfs;
  unsigned binning = 1;
  std::string what;  // for the first line: where the PSFs came from
};

Inputs from_dictionary(const CalibrateArgs& a) {
  DictionaryReader reader(a.dictionary);
  const DictionaryManifest& m = reader.manifest();
  Inputs in;
  in.scene = a.scene.empty() ? m.scene : load_scene(a.scene);
  const int level = a.level < 0 ? default_level(m) : a.level;
  if (level >= m.levels)
    throw std::invalid_argument("--level: " + std::to_string(level) + " is beyond the dictionary's levels 0.." +
                                std::to_string(m.levels - 1) + " (" + a.dictionary + "/manifest.json)");
  in.binning = unsigned(m.base_binning) << level;
  const AnalysisGrid grid = AnalysisGrid::of(in.scene.optics, in.binning);
  if (grid.width != m.level_width(level) || grid.height != m.level_height(level))
    throw std::invalid_argument("the dictionary's level " + std::to_string(level) + " is " +
                                std::to_string(m.level_width(level)) + " x " + std::to_string(m.level_height(level)) +
                                " px (" + a.dictionary + "/manifest.json); the scene's sensor at binning " +
                                std::to_string(in.binning) + " is " + std::to_string(grid.width) + " x " +
                                std::to_string(grid.height) + ": give the scene of this sensor (--scene)");
  size_t taken = 0;
  for (size_t i = 0; i < m.grid.size(); ++i) {
    if (!reader.has(i)) continue;
    if (taken++ % a.every) continue;
    PsfLevel l = reader.read_level(i, level);
    in.psfs.push_back({m.grid.position(i), std::move(l.p), reader.path_of(i), {}});
  }
  in.what = std::to_string(in.psfs.size()) + " of " + std::to_string(taken) + " PSFs present (every " +
            std::to_string(a.every) + ") at level " + std::to_string(level);
  return in;
}

Inputs from_merged(const CalibrateArgs& a) {
  if (a.scene.empty())
    throw std::invalid_argument("--merged: give --scene, the nominal scene of the camera (merged PSFs name none)");
  if (a.level >= 0) throw std::invalid_argument("--level: only with --dictionary (merged PSFs have one level)");
  Inputs in;
  in.scene = load_scene(a.scene);
  in.binning = calibration_binning(in.scene.optics.pixel_um);
  std::vector<MeasuredPsf> all = read_merged_psfs(a.merged, in.scene.optics, in.binning);
  for (const auto& p : all) require_in_front(in.scene, p.theta_mm.z, p.name + "'s source");
  for (size_t i = 0; i < all.size(); i += a.every) in.psfs.push_back(std::move(all[i]));
  in.what = std::to_string(in.psfs.size()) + " of " + std::to_string(all.size()) + " merged PSFs (every " +
            std::to_string(a.every) + ") binned " + std::to_string(in.binning) + " x " + std::to_string(in.binning);
  return in;
}

void run(const CalibrateArgs& a) {
  if (a.dictionary.empty() == a.merged.empty())
    throw std::invalid_argument("give the measured PSFs as --dictionary DIR or as --merged DIR (merge-hdr's output), "
                                "one of them");
  check_writable(a.out);
  const std::initializer_list<NamedInput> inputs{
      {"--dictionary", a.dictionary}, {"--merged", a.merged}, {"--scene", a.scene}};
  check_not_input(a.out, "--out", inputs);
  if (!a.csv.empty()) check_writable(a.csv), check_not_input(a.csv, "--csv", inputs);
  if (!a.residuals.empty()) check_not_input(a.residuals, "--residuals", inputs);
  if (!a.checkpoint.empty()) {
    check_writable(a.checkpoint), check_not_input(a.checkpoint, "--checkpoint", inputs);
    if (fs::weakly_canonical(a.checkpoint) == fs::weakly_canonical(a.out))
      throw std::invalid_argument("--checkpoint: " + a.checkpoint + " is also --out; give the checkpoint its own file");
  }
  Inputs in = a.dictionary.empty() ? from_merged(a) : from_dictionary(a);
  const Scene& scene = in.scene;
  std::vector<MeasuredPsf>& psfs = in.psfs;
  CalibrationOptions o;
  o.settings = TraceSettings::defaults_for(Splat::footprint);
  o.settings.rays_per_lenslet = a.rays ? a.rays : defaults::calibration_rays_per_lenslet;
  o.settings.binning = in.binning;
  o.settings.photons_emitted = scene.photons_emitted;
  o.max_steps = a.max_steps;
  o.pattern_moves = a.pattern_moves;
  o.coarse_levels = a.coarse_levels;
  o.weight_floor = a.weight_floor;
  o.reliable_over_faintest = a.reliable;
  o.threads = a.threads;
  o.blur_supersample = std::min(a.blur_supersample, in.binning);
  o.cells_check = a.cells_check;
  o.bootstrap = a.bootstrap;
  o.bootstrap_steps = a.bootstrap_steps;
  o.bootstrap_seed = a.seed;
  // auto: the calibrate kernels on a GPU; on a CPU device (lavapipe) the
  // reference on --threads cores is as fast (bench_calibrate, docs/calibration.md "Time").
  std::unique_ptr<vk::Context> ctx;
  std::string on = "the CPU reference with " + std::to_string(o.threads) + " threads";
  if (a.backend == "auto" && a.device.empty()) {
    try {  // no Vulkan at all: the reference, as the first line says
      ctx = std::make_unique<vk::Context>(vk::ContextOptions{a.device});
    } catch (const vk::Error& e) {
      on += " (auto: no Vulkan device: " + std::string(e.what()) + ")";
    }
  } else if (a.backend != "cpu") {
    ctx = std::make_unique<vk::Context>(vk::ContextOptions{a.device});
  }
  if (ctx) {
    if (a.backend == "vulkan" || !ctx->is_cpu()) {
      o.device = ctx.get();
      on = ctx->describe();
    } else {
      on += " (auto: the Vulkan device " + ctx->describe() + " is a CPU)";
    }
  }
  const AnalysisGrid grid = AnalysisGrid::of(scene.optics, o.settings.binning);
  const auto free = calibration_parameters(scene.optics, split_commas(a.fit));

  std::fprintf(stderr, "prism calibrate: %s (%.1f um pixels), %zu parameters, footprint at %u cells per lenslet, on %s\n",
               in.what.c_str(), grid.pixel_mm * 1e3, free.size(), o.settings.rays(), on.c_str());
  int checkpoint_level = -1;
  o.progress = [&](const CalibrationStep& s) {
    std::fprintf(stderr, "prism calibrate: step %d: chi2 %.6g (damping %.3g; gain %.3g, predicted %.3g), %.1f s\n",
                 s.step, s.chi2, s.damping, s.gain, s.predicted, s.seconds);
    if (a.checkpoint.empty()) return;
    write_text(a.checkpoint, to_json(fitted_scene(scene, s.reached)).dump(2) + "\n");
    if (s.level != checkpoint_level)
      std::fprintf(stderr,
                   "prism calibrate: on %.1f um pixels; %s holds the scene reached after each step (stopped, the fit "
                   "resumes with --scene %s --coarse-levels %d)\n",
                   grid.pixel_mm * 1e3 * double(1 << s.level), a.checkpoint.c_str(), a.checkpoint.c_str(), s.level);
    checkpoint_level = s.level;
  };
  o.bootstrap_progress = [&](unsigned rep, const CalibrationResult& f) {
    std::fprintf(stderr, "prism calibrate: bootstrap replicate %u of %u: chi2 %.6g, %d steps, %.1f s\n", rep,
                 o.bootstrap, f.chi2, f.steps, f.seconds);
  };
  const CalibrationResult r = calibrate(scene.optics, psfs, free, o);

  const bool source_only = extent_is_the_source_only(scene, r.fitted);
  write_text(a.out, to_json(fitted_scene(scene, r.fitted)).dump(2) + "\n");

  std::string table =
      "parameter,start,fitted,sigma,change_over_sigma,at_bound,sigma_residuals,sigma_cells,sigma_bootstrap\n";
  for (const auto& e : r.estimates)
    table += e.parameter.name() + "," + format_number(e.start, 12) + "," + format_number(e.value, 12) + "," +
             format_number(e.sigma) + "," + format_number((e.value - e.start) / e.sigma) + "," +
             (e.at_bound ? "1" : "0") + "," + format_number(e.sigma_residuals) + "," + format_number(e.sigma_cells) +
             "," + format_number(e.sigma_bootstrap) + "\n";
  if (!a.csv.empty()) write_text(a.csv, table);

  if (!a.residuals.empty()) {
    fs::create_directories(a.residuals);
    // Per PSF: its scale and chi2, and its map of (p - s b) / sigma; per
    // lenslet: the chi2 of the pixels its light dominates.
    const double sigma = std::sqrt(r.reduced_chi2());
    std::string per_psf = "psf,x_mm,y_mm,depth_mm,scale,chi2,pixels,chi2_per_pixel\n";
    for (size_t k = 0; k < psfs.size(); ++k) {
      const auto& f = r.psfs[k];
      per_psf += csv_field(psfs[k].name) + "," + format_number(psfs[k].theta_mm.x) + "," +
                 format_number(psfs[k].theta_mm.y) + "," + format_number(psfs[k].theta_mm.z) + "," +
                 format_number(f.scale) + "," + format_number(f.chi2) + "," + std::to_string(f.pixels) + "," +
                 format_number(f.pixels ? f.chi2 / double(f.pixels) : 0.0) + "\n";
    }
    calibration_residuals(r.fitted, psfs, o, [&](size_t k, const std::vector<float>& map) {
      char name[64];
      std::snprintf(name, sizeof name, "residual-%04zu.png", k);
      write_png_signed((fs::path(a.residuals) / name).string(), grid.width, grid.height, map.data(), 3 * sigma);
    });
    write_text((fs::path(a.residuals) / "psfs.csv").string(), per_psf);
    std::string per_lens = "lenslet,x_mm,y_mm,focal_mm,chi2,pixels,chi2_per_pixel\n";
    Series lens_series{"chi2 per pixel", {}, {}, false, true};
    for (size_t l = 0; l < r.lenses.size(); ++l) {
      const auto& f = r.lenses[l];
      const double per_pixel = f.pixels ? f.chi2 / double(f.pixels) : 0.0;
      per_lens += std::to_string(l) + "," + format_number(r.fitted.lenslets[l].x_mm) + "," +
                  format_number(r.fitted.lenslets[l].y_mm) + "," + format_number(r.fitted.lenslets[l].focal_mm) + "," +
                  format_number(f.chi2) + "," + std::to_string(f.pixels) + "," + format_number(per_pixel) + "\n";
      if (f.pixels) lens_series.x.push_back(double(l)), lens_series.y.push_back(per_pixel);
    }
    write_text((fs::path(a.residuals) / "lenslets.csv").string(), per_lens);
    plot_lines((fs::path(a.residuals) / "lenslets.png").string(),
               {"calibration residual per lenslet (chi2 / dof " + format_number(r.reduced_chi2()) + " overall)",
                "lenslet", "chi2 per pixel", true, false},
               {lens_series});
  }

  std::printf("%-28s %14s %14s %12s %10s %12s %12s %12s\n", "parameter", "start", "fitted", "sigma", "change/sd",
              "sd residuals", "sd cells", "sd bootstrap");
  std::string on_bounds;
  size_t n_on_bounds = 0;
  for (const auto& e : r.estimates) {
    std::printf("%-28s %14.6f %14.6f %12.3g %10.2f %12.3g %12.3g %12.3g%s\n", e.parameter.name().c_str(), e.start,
                e.value, e.sigma, (e.value - e.start) / e.sigma, e.sigma_residuals, e.sigma_cells, e.sigma_bootstrap,
                e.at_bound ? "  at its bound" : "");
    if (e.at_bound) on_bounds += (n_on_bounds++ ? ", " : "") + e.parameter.name();
  }
  if (n_on_bounds)
    std::printf("%zu parameter(s) ended on the bounds of their range (the PSFs do not hold them inside it; no "
                "sigma): %s. Add PSFs that show those lenslets (other positions, longer exposures) or leave their "
                "group out of --fit\n",
                n_on_bounds, on_bounds.c_str());
  // Where no step could gain, how the smallest one tried fared tells an
  // optimum from a cliff in the model (CalibrationResult::no_gain_rise).
  std::string stop = r.converged ? " (converged)" : " (step limit reached)";
  if (r.converged && std::isinf(r.no_gain_rise))
    stop = " (stopped: no step of any damping lowered chi2; the smallest one tried made a system the model cannot "
           "trace)";
  else if (r.converged && !std::isnan(r.no_gain_rise))
    stop = " (stopped: no step of any damping lowered chi2; the smallest one tried raised it by " +
           format_number(r.no_gain_rise, 3) +
           " x chi2 / dof: an optimum where that is below 1, a jump in the model where it is far above, "
           "docs/model.md \"Splatting\")";
  std::printf("chi2 %.6g -> %.6g over %zu pixels of %zu PSFs, chi2 / dof %.4g, %d steps (%d stretched, %d pattern "
              "moves)%s, %.1f s\n",
              r.chi2_start, r.chi2, r.pixels, psfs.size(), r.reduced_chi2(), r.steps, r.stretched, r.pattern_moves,
              stop.c_str(), r.seconds);
  // One line says what sigma is made of: the residuals' part (the sandwich,
  // or the bootstrap where larger) and the model's cells' part.
  const std::string residual_part =
      r.bootstrap_replicates
          ? "the larger of the residuals' (sandwich) and the bootstrap's (" + std::to_string(r.bootstrap_replicates) +
                " replicates over the PSFs drawn with replacement, each at most " +
                std::to_string(o.bootstrap_steps) + " steps from the fit's end, " +
                format_number(r.bootstrap_seconds) + " s)"
          : std::string("the residuals' (sandwich)");
  if (r.check_cells)
    std::printf("sigma = %s and the model's cells' in quadrature: the fit's %u cells per lenslet checked against %u "
                "(%.1f s of it)\n",
                residual_part.c_str(), o.settings.rays(), r.check_cells, r.check_seconds);
  else if (o.cells_check > 1)
    std::printf("sigma = %s alone: the model with %ux the cells gave no Gauss-Newton step (no parameter with a "
                "sigma, or its matrix singular)\n",
                residual_part.c_str(), o.cells_check);
  else
    std::printf("sigma = %s alone (--cells-check 1: the model's cells not checked)\n", residual_part.c_str());
  if (source_only)
    std::printf("The calibration source's extent (sigma %.4g mm) is in the table, not in %s: events are point "
                "sources. To simulate the calibration source, add the effect source_extent with that sigma.\n",
                r.fitted.effects.source_sigma_mm, a.out.c_str());
}

}  // namespace

void add_calibrate(CLI::App& app) {
  auto a = std::make_shared<CalibrateArgs>();
  CLI::App* c = app.add_subcommand(
      "calibrate",
      "fit the scene's as-built parameters (lenslet positions, focal lengths and tilts; lens-to-sensor and working "
      "distances; the sensor's offset and tilt) and a photon scale per PSF to measured PSFs (a dictionary, or what "
      "merge-hdr wrote), by weighted least squares; writes the fitted scene, which every command accepts");
  c->add_option("--dictionary", a->dictionary, "the measured (or synthesised) PSF dictionary's folder");
  c->add_option("--merged", a->merged,
                "instead of --dictionary: the folder of PSFs prism dictionary merge-hdr wrote (<name>.exr and "
                "<name>.json, the source position), at the camera's pixels; needs --scene");
  c->add_option("--scene", a->scene, "the nominal scene the fit starts from (built-in name or JSON file; default: the "
                                     "dictionary's own)");
  c->add_option("--out", a->out, "the fitted scene (JSON)")->required();
  c->add_option("--fit", a->fit,
                "comma-separated parameter groups to free: " + join(calibration_groups(), ", ") + " (per lenslet: "
                "lens_xy, lens_focal, lens_tilt; source_extent: the blur term, the calibration source's Gaussian sigma "
                "per axis, starting from the scene's or " + format_number(defaults::source_sigma_mm) + " mm)")
      ->capture_default_str();
  c->add_option("--level", a->level,
                "with --dictionary: the level to fit (default: the finest with pixels of at least " +
                    format_number(defaults::calibration_pixel_um) + " um)")
      ->check(CLI::Range(0, 30));
  c->add_option("--rays", a->rays,
                "the model's footprint cells per lenslet (default " + std::to_string(defaults::calibration_rays_per_lenslet) +
                    "), " + rays_rounding);
  c->add_option("--every", a->every, "fit every N-th PSF present (the model's time grows with the PSFs)")
      ->check(CLI::Range(1u, 1000000u))
      ->capture_default_str();
  c->add_flag("--pattern-moves", a->pattern_moves,
              "after each accepted step, try points along the line through the point two steps back and the new "
              "one (values only, about a fifth of a step each) and take the lowest: a fit zig-zagging down a narrow "
              "valley goes along it (docs/calibration.md: on the whole prototype's creeping fit 3.3x the fall "
              "over 8 steps, not beyond; on a fit that converges 1.27x the time)");
  c->add_option("--max-steps", a->max_steps,
                "Levenberg-Marquardt steps accepted at most on each pixel size (with the default --coarse-levels: "
                "4x, 2x, 1x the model's)")
      ->check(CLI::Range(1, 10000))
      ->capture_default_str();
  c->add_option("--coarse-levels", a->coarse_levels,
                "fit first on pixels 2^k times the model's, k = this .. 1 (the disc edges make chi2 a staircase at "
                "the pixel scale: from a nominal start the model's pixels alone land elsewhere); 0: the model's "
                "pixels only, to refine a scene already fitted (lens tilts are held on the coarser pixels)")
      ->check(CLI::Range(0, 4))
      ->capture_default_str();
  c->add_option("--weight-floor", a->weight_floor,
                "pixel weights are 1 / (value + floor), the floor this fraction of each PSF's brightest pixel")
      ->check(positive_number)
      ->capture_default_str();
  c->add_option("--reliable", a->reliable,
                "pixels fainter than this times the faintest value a PSF holds are censored: they say only that the "
                "light there is below that level (near the HDR merge's threshold it keeps only upward fluctuations)")
      ->check(CLI::Range(1.0, 1e6))
      ->capture_default_str();
  c->add_option("--backend", a->backend,
                "vulkan (the splat kernels' calibrate variants on the device), cpu (the double-precision reference "
                "on --threads cores) or auto: vulkan on a GPU, cpu where the Vulkan device is a CPU (lavapipe, where "
                "the reference is as fast)")
      ->check(CLI::IsMember({"auto", "vulkan", "cpu"}))
      ->capture_default_str();
  c->add_option("--device", a->device, device_help);
  c->add_option("--threads", a->threads, "CPU reference: PSFs rendered at once (default: the CPU's cores)")
      ->check(CLI::Range(1u, 1024u));
  c->add_option("--blur-supersample", a->blur_supersample,
                "with an extended source (source_extent fitted, or in the scene; a fitted one is the calibration "
                "source's and stays out of --out unless the scene had it): blur each lenslet's image on "
                "pixels this many times finer (1, 2, 4 or 8; at most the binning), at about its fourth power in time; "
                "on docs/calibration.md's test it gained little")
      ->check(CLI::IsMember({1u, 2u, 4u, 8u}))
      ->capture_default_str();
  c->add_option("--cells-check", a->cells_check,
                "after the fit, evaluate the model with this many times its cells (one evaluation with derivatives; "
                "at 16x about a step's time at 110 um pixels): how far that moves each parameter is its uncertainty "
                "from the model's cells, added to sigma; 1: no check")
      ->check(CLI::Range(1u, 64u))
      ->capture_default_str();
  c->add_option("--bootstrap", a->bootstrap,
                "after the fit, this many bootstrap replicates: the fit's end refitted to the PSFs drawn with "
                "replacement (each at most --bootstrap-steps steps on the model's pixels); their spread, where larger "
                "than the sandwich's, is sigma's residual part (docs/calibration.md: on the whole prototype fitted "
                "from the truth, 10 replicates put 215 of 216 parameters within 3 sigma, the sandwich 207; they cost "
                "5 times that fit). 0: none")
      ->check(CLI::Validator(
          [](std::string& v) {
            return v == "1" ? std::string("one replicate has no spread: give 0 (none) or at least 2") : std::string();
          },
          "0 or 2..10000"))
      ->check(CLI::Range(0u, 10000u))
      ->capture_default_str();
  c->add_option("--bootstrap-steps", a->bootstrap_steps, "Levenberg-Marquardt steps of a bootstrap replicate at most")
      ->check(CLI::Range(1, 10000))
      ->capture_default_str();
  c->add_option("--seed", a->seed, "the bootstrap's random seed: replicate r draws its PSFs from (seed, r) alone")
      ->capture_default_str();
  c->add_option("--csv", a->csv,
                "the parameters' table: start, fitted, sigma, change / sigma, at_bound, and sigma's parts "
                "(residuals, the model's cells, the bootstrap's)");
  c->add_option("--checkpoint", a->checkpoint,
                "after each accepted step, write the scene reached to this JSON file (replaced whole each time): a fit "
                "stopped resumes from it with the --coarse-levels its progress names");
  c->add_option("--residuals", a->residuals,
                "a folder for the residual maps (residual-NNNN.png: (p - s b) / sigma per PSF, red above the model, "
                "blue below, full at 3 sigma), psfs.csv, lenslets.csv and lenslets.png");
  c->footer(
      "The model's derivatives by the scene's parameters come from the splat kernels' calibrate variants or from the "
      "double-precision reference, as --backend says (docs/calibration.md gives the time per PSF and step); "
      "--every N fits a sample of the PSFs.");
  c->callback([a] { run(*a); });
}

}  // namespace prism::cmd
