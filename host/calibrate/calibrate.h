// Calibration (issue 18): the as-built optics fitted to a measured PSF
// dictionary. The paper reconstructs with its measured PSFs alone because the
// built system is not its design; the continuous refinement needs a
// continuous model, and for a measured dictionary the honest one is the
// forward model with the scene's parameters fitted to those PSFs.
//
// The fit. PSF k, measured at the known source position theta_k, is a level
// of the dictionary: p_k, summing to ~1 over the sensor. Its model is
// s_k b_k(params), b_k the forward model's expected photons (footprint
// splat) and s_k a photon scale per PSF (emitted photons, detection
// efficiency and the merge's normalisation together). Weighted least squares:
//   chi2 = sum_k sum_i w_ki (p_ki - s_k b_ki)^2,  w_ki = 1 / (p_ki + floor_k),
// floor_k = defaults::calibration_weight_floor times the PSF's brightest
// pixel: an HDR pixel's variance grows with its signal (shot noise) above a
// floor. Pixels fainter than CalibrationOptions::reliable_over_faintest
// times the faintest value the HDR merge kept (near its threshold it keeps
// only upward fluctuations) are censored: all the fit knows of them is that
// they hold less than that value, so they count only where the model puts
// more light there, as a measurement at that value would. Each s_k has its optimum in
// closed form and is profiled out; the geometric parameters are found by
// Levenberg-Marquardt on the profiled chi2 with its Gauss-Newton matrix H
// (the scales' share removed by their Schur complement), a step taken
// further along its line where chi2 falls faster than H predicts, first on
// pixels 4x and 2x larger with the lens tilts held, then on the model's.
//
// Uncertainty: the sandwich H^-1 M H^-1, M = sum over pixels of (w r)^2 J J^T,
// right whatever the variance's true shape (the weights fix only a guess of
// it): a model that cannot explain the PSFs reports larger uncertainties,
// not smaller. It takes pixels as independent; with few PSFs, where the
// model's own errors run alike along an image's edges, it comes out about a
// third small (docs/calibration.md). chi2 / dof is the goodness of fit, per
// PSF and per lenslet in the result.
//
// The model's cells: a footprint of N cells per lenslet is itself an
// approximation, and where the images are large and curved (f = 3 mm near
// hemispheres) its error moves the optimum by more than the sandwich says
// (it errs alike along an image's edge, not pixel by pixel). After the fit
// the model is evaluated at the optimum with cells_check x N cells, and one
// Gauss-Newton step on it says where that finer model's optimum lies. The
// step's size is each parameter's uncertainty from the model's cells; the
// reported sigma adds it to the sandwich's in quadrature. The fitted values
// stay the N-cell model's: the one the refinement renders with.
//
// The bootstrap over the PSFs (CalibrationOptions::bootstrap, off by
// default: each replicate costs a few steps of the fit): the fit's end
// refitted on the model's pixels, replicate by replicate, to the PSFs drawn
// with replacement (a PSF drawn twice counts twice); the replicates' spread
// is each parameter's sigma_bootstrap. It assumes neither independent pixels
// nor chi2's Gauss-Newton curvature, which on the f = 3 mm lenslets' valley
// of position and tilt overstates chi2's own 4-5x (docs/calibration.md),
// but it sees only what differs between PSFs. The reported sigma takes the
// larger of it and the sandwich's, with the cells' term in quadrature.
//
// Derivatives: forward mode with respect to the scene's parameters
// (Tangents), each lenslet's image rendered alone so that its own
// parameters touch only its own pixels: on a device with the splat kernels'
// calibrate variants (CalibrationOptions::device), or with the
// double-precision CPU reference (engine/ref), which checks them.
#pragma once
#include <functional>
#include <limits>
#include <string>
#include <vector>

#include <glm/glm.hpp>

#include "engine/optical_system.h"
#include "engine/ref/forward_ref.h"

namespace prism {
namespace vk {
class Context;
}

// One free parameter: a scene parameter (SceneParam, not the source's), of
// one lenslet for the per-lenslet ones. Units: mm, degrees for tilts.
struct CalibrationParameter {
  SceneParam param;
  int lens = -1;  // per-lenslet parameters: which lenslet; -1 for global ones
  bool per_lens() const;
  std::string name() const;  // as in the scene file: "lenslets[3].x_mm", "lens_to_sensor_mm", "sensor.tilt_x_deg"
  double get(const OpticalSystem& s) const;
  void set(OpticalSystem& s, double value) const;
  // The range the fit may move it in around `nominal` (defaults.h).
  std::pair<double, double> bounds(const OpticalSystem& nominal) const;
};

// The groups `prism calibrate --fit` names, each a set of parameters:
// lens_xy, lens_focal, lens_tilt (every lenslet's own), lens_to_sensor,
// working_distance, sensor_offset, sensor_tilt, source_extent (the blur
// term: effect source_extent's sigma, source_blur.h).
std::vector<std::string> calibration_groups();
// Those `--fit` frees by default: all but source_extent (a point source,
// or the start scene's extent held, unless asked).
std::vector<std::string> calibration_default_groups();
// The parameters of `groups` for system `s`, in a fixed order (per-lenslet
// ones lenslet by lenslet, then the global ones). Throws
// std::invalid_argument naming an unknown group and the choices.
std::vector<CalibrationParameter> calibration_parameters(const OpticalSystem& s, const std::vector<std::string>& groups);

// One measured PSF: where its source was and its image on the model's grid
// (settings.binning), row-major, summing to ~1 over the sensor.
// A pixel of value 0 is one the HDR merge rejected as too faint; the fit
// censors those and the faint ones near them (calibrate.cpp, Noise).
struct MeasuredPsf {
  glm::dvec3 theta_mm{0.0};  // x, y, depth
  std::vector<float> p;
  std::string name;  // for messages: its file
  // Binned PSFs (calibrate's coarse levels): per pixel, the most light its
  // censored sub-pixels may hold (their count times the reliable value), 0
  // where every sub-pixel is measured; p holds the measured sub-pixels'
  // sum alone. Empty: decided from p.
  std::vector<float> unknown;
  // How many times it counts in chi2 (a bootstrap replicate draws some PSFs
  // more than once).
  unsigned count = 1;
};

// The PSFs `prism dictionary merge-hdr` wrote into `dir` (each <name>.json
// beside its <name>.exr; the JSON gives the source position), binned by
// `binning` (a power of two) from the sensor's pixels, sorted by name.
// Throws naming the file: a frame not of `sensor`'s size, a sidecar
// without its PSF or position, no PSF at all.
std::vector<MeasuredPsf> read_merged_psfs(const std::string& dir, const OpticalSystem& sensor, unsigned binning);

// The binning the fit uses by default on a sensor of `pixel_um` pixels:
// the smallest power of two that makes them defaults::calibration_pixel_um
// or more.
unsigned calibration_binning(double pixel_um);

// One accepted (or final rejected) step, for progress.
struct CalibrationStep {
  int step = 0;          // steps accepted so far
  double chi2 = 0;       // at the current parameters
  double damping = 0;    // Levenberg-Marquardt's mu
  // chi2's fall over this step and what Gauss-Newton's quadratic model
  // predicted for the step it solved (before a stretch or a pattern move):
  // their ratio near 1 where the model holds.
  double gain = 0, predicted = 0;
  double seconds = 0;    // since the start
  int level = 0;         // on pixels 2^level times the model's (coarse to fine)
  OpticalSystem reached;  // the scene at the current parameters: a fit stopped here resumes from it
};

struct CalibrationResult;

struct CalibrationOptions {
  TraceSettings settings;  // the model: splat, cells per lenslet, binning of the measured grid
  int max_steps = defaults::calibration_max_steps;  // per level
  int coarse_levels = defaults::calibration_coarse_levels;  // fitted first on pixels 2^k larger, k = this .. 1
  double weight_floor = defaults::calibration_weight_floor;  // relative to each PSF's brightest pixel; > 0
  // Pixels below this times the faintest value a PSF holds are censored (above); >= 1.
  double reliable_over_faintest = defaults::calibration_reliable_over_faintest;
  unsigned threads = 2;                                      // PSFs rendered at once (CPU reference)
  // With an extended source (source_extent): each lenslet's image is
  // rendered on pixels this many times finer (a power of two, at most the
  // binning), blurred there and binned (source_blur.h, defaults.h).
  unsigned blur_supersample = defaults::calibration_blur_supersample;
  // After the fit: the model with this many times the cells, for the
  // uncertainty its cells leave (above); 1: not checked.
  unsigned cells_check = defaults::calibration_cells_check_factor;
  // After the fit (and the cells' check): this many bootstrap replicates
  // over the PSFs (above), each at most bootstrap_steps steps; 0 or 1: none.
  unsigned bootstrap = 0;
  int bootstrap_steps = defaults::calibration_bootstrap_steps;
  uint64_t bootstrap_seed = 1;  // replicate r draws its PSFs from (seed, r) alone
  // After each accepted step, a point along the line through the point two
  // steps back and the new one, values only, taken where chi2 is lower
  // (calibrate.cpp, pattern_move): a fit that zig-zags down a narrow valley
  // goes along it.
  bool pattern_moves = false;
  // The calibrate kernels on this device (engine/forward.h,
  // Derivatives::scene); null: the double-precision CPU reference.
  vk::Context* device = nullptr;
  std::function<void(const CalibrationStep&)> progress;      // after each accepted step
  // After each bootstrap replicate: its number from 1, its fit.
  std::function<void(unsigned, const CalibrationResult&)> bootstrap_progress;
};

struct ParameterEstimate {
  CalibrationParameter parameter;
  double start = 0, value = 0;
  // One standard deviation; infinite when no PSF constrains it or the fit
  // ended on one of its bounds (at_bound: the data pushed it to the edge of
  // the range CalibrationParameter::bounds allows, so no interior optimum
  // exists to take an uncertainty at; the others' sigmas hold it fixed).
  double sigma = 0;
  // Its parts: the sandwich's (the residuals), the model's cells' (how far
  // the check's finer model moves it; 0 when not checked) and the bootstrap
  // replicates' standard deviation (0 when not run). sigma is
  // hypot(max(sigma_residuals, sigma_bootstrap), sigma_cells).
  double sigma_residuals = 0, sigma_cells = 0, sigma_bootstrap = 0;
  bool at_bound = false;
};

struct PsfFit {
  double scale = 0;   // s_k
  double chi2 = 0;    // its share of chi2
  size_t pixels = 0;  // pixels it weighs (lit in the PSF or the model)
};

struct LensFit {
  double chi2 = 0;    // chi2 of the pixels where this lenslet's light is the most
  size_t pixels = 0;
};

struct CalibrationResult {
  OpticalSystem fitted;
  std::vector<ParameterEstimate> estimates;
  std::vector<PsfFit> psfs;
  std::vector<LensFit> lenses;
  double chi2_start = 0;  // at the start
  double chi2 = 0;        // at the fit
  size_t pixels = 0;      // weighed, all PSFs
  size_t dof = 0;         // pixels - parameters - scales
  int steps = 0;          // accepted, all levels
  int stretched = 0;      // of those, taken further along their line where chi2 fell faster than predicted
  int pattern_moves = 0;  // points taken along the last two steps' line (CalibrationOptions::pattern_moves)
  bool converged = false; // at the finest level: the last step gained less than 1e-3 of chi2 / dof, or no step could
  // Converged because no step of any damping lowered chi2: what the smallest
  // step tried raised it by, over chi2 / dof (near 0 at an optimum; far
  // above 1 a jump in the model; infinite: a system it cannot trace). NaN
  // when a step gained.
  double no_gain_rise = std::numeric_limits<double>::quiet_NaN();
  double seconds = 0;
  unsigned check_cells = 0;    // cells per 3 mm lenslet of the check's model (0: not checked, or no step found)
  double check_seconds = 0;    // of seconds, the check's
  unsigned bootstrap_replicates = 0;  // run (0: none)
  double bootstrap_seconds = 0;       // of seconds, the replicates'
  double reduced_chi2() const { return dof ? chi2 / double(dof) : 0.0; }
};

// Fits `free` of `start` to `psfs`. Throws std::invalid_argument when there
// is nothing to fit or a PSF's image is not of the model's grid.
CalibrationResult calibrate(const OpticalSystem& start, const std::vector<MeasuredPsf>& psfs,
                            const std::vector<CalibrationParameter>& free, const CalibrationOptions& options);

// The normalised residual (p - s b) sqrt(w) of each PSF under `sys` with its
// best scale, row-major on the model's grid (residual maps): each(k, map)
// for PSF k in turn.
void calibration_residuals(const OpticalSystem& sys, const std::vector<MeasuredPsf>& psfs,
                           const CalibrationOptions& options,
                           const std::function<void(size_t, const std::vector<float>&)>& each);

}  // namespace prism
