#include "host/calibrate/calibrate.h"

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <bit>
#include <exception>
#include <functional>
#include <memory>
#include <filesystem>
#include <fstream>
#include <limits>
#include <mutex>
#include <optional>
#include <random>
#include <stdexcept>
#include <thread>

#include "engine/forward.h"
#include "engine/ref/pixel_map.h"
#include "host/calibrate/source_blur.h"
#include "host/dictionary/store.h"                  // bin_level
#include "host/util/format.h"
#include "host/util/image_io.h"
#include "host/util/json_file.h"
#include "host/reconstruct/levenberg_marquardt.h"  // solve_spd

namespace prism {

using Param = SceneParam;

bool CalibrationParameter::per_lens() const { return param >= Param::lens_x && param <= Param::lens_tilt_y; }

std::string CalibrationParameter::name() const {
  const std::string at = "lenslets[" + std::to_string(lens) + "].";
  switch (param) {
    case Param::lens_x: return at + "x_mm";
    case Param::lens_y: return at + "y_mm";
    case Param::lens_focal: return at + "focal_mm";
    case Param::lens_tilt_x: return at + "tilt_x_deg";
    case Param::lens_tilt_y: return at + "tilt_y_deg";
    case Param::lens_to_sensor: return "lens_to_sensor_mm";
    case Param::working_distance: return "working_distance_mm";
    case Param::sensor_offset_x: return "sensor.offset_x_mm";
    case Param::sensor_offset_y: return "sensor.offset_y_mm";
    case Param::sensor_tilt_x: return "sensor.tilt_x_deg";
    case Param::sensor_tilt_y: return "sensor.tilt_y_deg";
    case Param::source_sigma: return "effects.source_extent.sigma_mm";
    default: return "source";  // the source's position is never a calibration parameter
  }
}

namespace {
// The one home of which field a parameter is.
template <class System> auto& field(System& s, const CalibrationParameter& p) {
  switch (p.param) {
    case Param::lens_x: return s.lenslets[size_t(p.lens)].x_mm;
    case Param::lens_y: return s.lenslets[size_t(p.lens)].y_mm;
    case Param::lens_focal: return s.lenslets[size_t(p.lens)].focal_mm;
    case Param::lens_tilt_x: return s.lenslets[size_t(p.lens)].tilt_x_deg;
    case Param::lens_tilt_y: return s.lenslets[size_t(p.lens)].tilt_y_deg;
    case Param::lens_to_sensor: return s.lens_to_sensor_mm;
    case Param::working_distance: return s.working_distance_mm;
    case Param::sensor_offset_x: return s.sensor_pose.offset_x_mm;
    case Param::sensor_offset_y: return s.sensor_pose.offset_y_mm;
    case Param::sensor_tilt_x: return s.sensor_pose.tilt_x_deg;
    case Param::sensor_tilt_y: return s.sensor_pose.tilt_y_deg;
    case Param::source_sigma: return s.effects.source_sigma_mm;
    default: throw std::logic_error("calibration: the source's position is not a scene parameter");
  }
}
}  // namespace

double CalibrationParameter::get(const OpticalSystem& s) const { return field(s, *this); }
void CalibrationParameter::set(OpticalSystem& s, double value) const {
  field(s, *this) = value;
  if (param == Param::source_sigma) s.effects.source_extent = true;  // a fitted extent is one the scene has
}

std::pair<double, double> CalibrationParameter::bounds(const OpticalSystem& nominal) const {
  const double v = get(nominal);
  switch (param) {
    case Param::lens_x:
    case Param::lens_y:
    case Param::sensor_offset_x:
    case Param::sensor_offset_y: return {v - defaults::calibration_max_shift_mm, v + defaults::calibration_max_shift_mm};
    case Param::lens_focal: {
      double lo = v * (1 - defaults::calibration_max_focal_change);
      // A real lens cannot be shorter than the plano-convex limit validate
      // enforces. Without this bound a fit pulled toward shorter f stalled
      // at that wall as "converged", every trial beyond it untraceable and
      // every other parameter frozen with it; as a bound, the step is
      // clamped there and the parameter reported at_bound.
      if (nominal.lens_model == LensModel::real)
        lo = std::max(lo, nominal.shortest_focal_mm(size_t(lens)) * (1 + 1e-12));
      return {lo, v * (1 + defaults::calibration_max_focal_change)};
    }
    case Param::lens_tilt_x:
    case Param::lens_tilt_y:
    case Param::sensor_tilt_x:
    case Param::sensor_tilt_y: return {-defaults::max_tilt_deg, defaults::max_tilt_deg};
    case Param::source_sigma: return {defaults::calibration_min_source_sigma_mm, defaults::calibration_max_source_sigma_mm};
    default: return {v - defaults::calibration_max_distance_mm, v + defaults::calibration_max_distance_mm};
  }
}

namespace {
struct Group {
  const char* name;
  std::vector<Param> params;
};
const std::vector<Group>& groups() {
  static const std::vector<Group> g{
      {"lens_xy", {Param::lens_x, Param::lens_y}},
      {"lens_focal", {Param::lens_focal}},
      {"lens_tilt", {Param::lens_tilt_x, Param::lens_tilt_y}},
      {"lens_to_sensor", {Param::lens_to_sensor}},
      {"working_distance", {Param::working_distance}},
      {"sensor_offset", {Param::sensor_offset_x, Param::sensor_offset_y}},
      {"sensor_tilt", {Param::sensor_tilt_x, Param::sensor_tilt_y}},
      {"source_extent", {Param::source_sigma}},
  };
  return g;
}
}  // namespace

std::vector<std::string> calibration_groups() {
  std::vector<std::string> out;
  for (const auto& g : groups()) out.push_back(g.name);
  return out;
}

std::vector<std::string> calibration_default_groups() {
  std::vector<std::string> out = calibration_groups();
  out.erase(std::find(out.begin(), out.end(), "source_extent"));
  return out;
}

std::vector<CalibrationParameter> calibration_parameters(const OpticalSystem& s, const std::vector<std::string>& names) {
  std::vector<Param> chosen;
  for (const auto& name : names) {
    auto it = std::find_if(groups().begin(), groups().end(), [&](const Group& g) { return name == g.name; });
    if (it == groups().end())
      throw std::invalid_argument("calibration: no parameter group '" + name + "'; the groups are " +
                                  join(calibration_groups()));
    for (Param p : it->params)
      if (std::find(chosen.begin(), chosen.end(), p) == chosen.end()) chosen.push_back(p);
  }
  std::sort(chosen.begin(), chosen.end());
  std::vector<CalibrationParameter> out;
  for (size_t l = 0; l < s.lenslets.size(); ++l)
    for (Param p : chosen)
      if (CalibrationParameter{p}.per_lens()) out.push_back({p, int(l)});
  for (Param p : chosen)
    if (!CalibrationParameter{p}.per_lens()) out.push_back({p, -1});
  return out;
}

namespace {

// A model pixel: b, the lenslet whose light there is the most, and db/dparam
// for the free parameters that move it (sparse: a lenslet's own parameters
// touch only its own pixels).
struct Derivative {
  uint32_t param;
  double d;
};
struct ModelPixel {
  double b = 0;
  int lens = -1;
  double lens_b = 0;
  std::vector<Derivative> d;
  void add(uint32_t param, double value) {
    for (auto& e : d)
      if (e.param == param) {
        e.d += value;
        return;
      }
    d.push_back({param, value});
  }
};
using Model = ref::PixelMap<ModelPixel>;

// One render of a PSF: of lenslet `only_lens` (-1: every one), with or
// without derivatives by `tangents`; calls visit(key, {b, db/dslot 0..2})
// for each pixel it touches.
using PixelVisitor = std::function<void(int64_t, const std::array<double, 4>&)>;
using RenderPass = std::function<void(const Tangents&, int only_lens, bool derivatives, const PixelVisitor&)>;

// Effect source_extent in the model: each lenslet's point image, rendered
// on pixels `supersample` times finer than the model's, blurred smoothly
// (source_blur.h) and binned; off where sigma is 0.
struct SourceBlurModel {
  double sigma_mm = 0;
  int width = 0, height = 0;  // the grid rendered on
  unsigned supersample = 1;
  int model_width = 0, model_height = 0;
};

// Pixel `key`'s channels in `img`, a zeroed row appended on its first use;
// `row_of` holds 1 + each key's row (0: none yet).
double* values_of(LensImage& img, ref::PixelMap<size_t>& row_of, int64_t key) {
  size_t& at = row_of[key];
  if (at == 0) img.keys.push_back(key), img.values.resize(img.values.size() + img.channels, 0.0), at = img.keys.size();
  return &img.values[(at - 1) * img.channels];
}

// `img` summed over f x f pixels onto the width x height grid.
LensImage bin_lens_image(const LensImage& img, unsigned f, int width, int height) {
  if (f == 1) return img;
  LensImage out{width, height, img.channels, {}, {}};
  ref::PixelMap<size_t> row_of;
  for (size_t i = 0; i < img.keys.size(); ++i) {
    const int64_t col = img.keys[i] % img.width / f, row = img.keys[i] / img.width / f;
    if (col >= width || row >= height) continue;
    double* o = values_of(out, row_of, row * width + col);
    for (size_t c = 0; c < img.channels; ++c) o[c] += img.values[i * img.channels + c];
  }
  return out;
}

// Where a lenslet's image moves as the source does: J, pixels per mm of
// source x, y, depth (source_blur.h); nothing where it cannot say.
using ImageMotion = std::function<std::optional<std::array<double, 6>>(size_t lens)>;

// A PSF's model from `render`: the whole image at once when no derivative
// and no blur is wanted, else lenslet by lenslet with each one's own
// parameters and the global ones as tangents, three a pass; with the blur,
// each lenslet's image blurred by its motion (`motion`, or, where that says
// nothing, its centroid's from a pass by the source), and the derivative by
// sigma from the kernel.
Model assemble(size_t lenses, const std::vector<CalibrationParameter>& free, bool derivatives, const RenderPass& render,
               const SourceBlurModel& blur, const ImageMotion& motion) {
  Model model;
  const bool blurred = blur.sigma_mm > 0;
  if (!derivatives && !blurred) {
    render(source_tangents, -1, false, [&](int64_t key, const std::array<double, 4>& v) { model[key].b = v[0]; });
    return model;
  }
  int sigma_slot = -1;
  for (uint32_t j = 0; j < free.size() && derivatives; ++j)
    if (free[j].param == Param::source_sigma) sigma_slot = int(j);
  for (size_t l = 0; l < lenses; ++l) {
    std::vector<uint32_t> slots;  // rendered as tangents; sigma is the blur's
    for (uint32_t j = 0; j < free.size() && derivatives; ++j)
      if (free[j].param != Param::source_sigma && (!free[j].per_lens() || size_t(free[j].lens) == l))
        slots.push_back(j);
    // Channels: b, db/d(source x, y, depth) (a source pass's), then one per slot.
    LensImage img{blur.width, blur.height, 4 + slots.size(), {}, {}};
    ref::PixelMap<size_t> row_of;
    std::optional<std::array<double, 6>> J;
    if (blurred) J = motion(l);
    const bool source_pass = blurred && !J;
    if (source_pass)
      render(source_tangents, int(l), true, [&](int64_t key, const std::array<double, 4>& v) {
        std::copy(v.begin(), v.end(), values_of(img, row_of, key));
      });
    const size_t slot_passes = (slots.size() + 2) / 3;
    const size_t passes = source_pass ? slot_passes : std::max<size_t>(1, slot_passes);
    for (size_t pass = 0; pass < passes; ++pass) {
      Tangents tangents = source_tangents;  // slots left over: ignored
      const size_t first = 3 * pass, n = std::min<size_t>(3, slots.size() - std::min(slots.size(), first));
      for (size_t k = 0; k < n; ++k) tangents[k] = {free[slots[first + k]].param, free[slots[first + k]].lens};
      render(tangents, int(l), derivatives, [&](int64_t key, const std::array<double, 4>& v) {
        double* o = values_of(img, row_of, key);
        if (!source_pass && pass == 0) o[0] = v[0];
        for (size_t k = 0; k < n; ++k) o[4 + first + k] = v[1 + k];
      });
    }
    if (blurred) {
      if (!J) J = centroid_jacobian(img);
      img = prism::blur(img, source_blur_kernel(*J, blur.sigma_mm), sigma_slot >= 0);
      img = bin_lens_image(img, blur.supersample, blur.model_width, blur.model_height);
    }
    for (size_t i = 0; i < img.keys.size(); ++i) {
      const double* v = &img.values[i * img.channels];
      ModelPixel& m = model[img.keys[i]];
      m.b += v[0];
      if (v[0] > m.lens_b) m.lens_b = v[0], m.lens = int(l);
      if (m.d.empty()) m.d.reserve(slots.size() + 1);  // one allocation for its first lenslet
      for (size_t k = 0; k < slots.size(); ++k)
        if (v[4 + k] != 0) m.add(slots[k], v[4 + k]);
      if (blurred && sigma_slot >= 0 && v[4 + slots.size()] != 0) m.add(uint32_t(sigma_slot), v[4 + slots.size()]);
    }
  }
  return model;
}

// PSF models under one scene after another: with the calibrate kernels on
// options.device (one forward model, moved to each scene), or with the
// double-precision CPU reference (several PSFs at once, options.threads).
class Renderer {
 public:
  // `extended`: the scenes it renders may have a source_extent (the start
  // has one, or sigma is fitted): it renders on finer pixels.
  Renderer(const OpticalSystem& start, const CalibrationOptions& o, bool extended)
      : model_settings_(o.settings), settings_(o.settings) {
    if (extended) {
      supersample_ = std::min(o.blur_supersample, o.settings.binning);
      settings_.binning = o.settings.binning / supersample_;
    }
    if (o.device)
      fw_ = std::make_unique<ForwardVulkan>(*o.device, point_source(start), settings_,
                                            ForwardVulkan::default_image_budget_bytes, ForwardVulkan::Derivatives::scene);
  }
  // PSFs rendered at once: the device renders one at a time.
  unsigned threads(unsigned wanted) const { return fw_ ? 1u : std::max(1u, wanted); }
  // Every PSF until the next call is of `sys`.
  void set_scene(const OpticalSystem& sys) {
    sys_ = point_source(sys);
    const AnalysisGrid grid = AnalysisGrid::of(sys, settings_.binning),
                       model = AnalysisGrid::of(sys, model_settings_.binning);
    blur_ = {sys.effects.source_extent ? sys.effects.source_sigma_mm : 0.0, grid.width, grid.height, supersample_,
             model.width, model.height};
    if (!(blur_.sigma_mm > 0) && supersample_ > 1)
      throw std::logic_error("calibration: a renderer made for an extended source given a point source");
    if (fw_) fw_->set_scene(sys_);
  }
  Model operator()(const glm::dvec3& theta, const std::vector<CalibrationParameter>& free, bool derivatives) {
    return assemble(sys_.lenslets.size(), free, derivatives,
                    [&](const Tangents& tangents, int only, bool with_d, const PixelVisitor& visit) {
                      if (fw_) return device_pass(theta, tangents, only, with_d, visit);
                      // One lenslet alone is rendered as with derivatives (psf() without a
                      // tangent renders them all).
                      const ref::SparseImage img = with_d || only >= 0 ? ref::psf(sys_, settings_, theta, tangents, only)
                                                                       : ref::psf(sys_, settings_, theta);
                      for (const auto& [key, px] : img.pixels)
                        visit(key, with_d ? img.value(key) : std::array<double, 4>{px[0], 0, 0, 0});
                    }, blur_, [&](size_t lens) { return chief_ray_motion(sys_, settings_, theta, lens); });
  }

 private:
  void device_pass(const glm::dvec3& theta, const Tangents& tangents, int only, bool with_d,
                   const PixelVisitor& visit) {
    if (!with_d && only < 0) {  // the whole image; one lenslet alone as with derivatives
      const std::vector<float> b = fw_->psf_values(theta);
      for (size_t i = 0; i < b.size(); ++i)
        if (b[i] != 0) visit(int64_t(i), {b[i], 0, 0, 0});
      return;
    }
    const PixelImage img = fw_->psf(theta, tangents, only);
    for (size_t i = 0; i < img.data.size() / 4; ++i) {
      const float* q = &img.data[4 * i];
      if (q[0] != 0 || q[1] != 0 || q[2] != 0 || q[3] != 0) visit(int64_t(i), {q[0], q[1], q[2], q[3]});
    }
  }

  // The renders are of a point source, the blur (an extended source) the
  // model's own: the engine's source_extent samples it per footprint cell,
  // speckled at the pixel scale (source_blur.h).
  static OpticalSystem point_source(OpticalSystem s) {
    s.effects.source_extent = false;
    return s;
  }

  TraceSettings model_settings_;
  TraceSettings settings_;  // as rendered: the model's, or finer pixels for the blur
  unsigned supersample_ = 1;
  OpticalSystem sys_;  // as rendered: a point source
  SourceBlurModel blur_;
  std::unique_ptr<ForwardVulkan> fw_;
};

// What one PSF adds to the fit at the rendered parameters.
struct PsfTerms {
  PsfFit fit;
  std::vector<double> lens_chi2;
  std::vector<size_t> lens_pixels;
};

// The sums of all PSFs: chi2 and, with derivatives, Sums' three (below).
struct Evaluation {
  bool ok = false;  // false when the parameters make a system the model cannot trace
  double chi2 = std::numeric_limits<double>::infinity();
  size_t pixels = 0;
  std::vector<double> grad, gn, meat;
  std::vector<PsfFit> psfs;
  std::vector<LensFit> lenses;
};

// The Gauss-Newton matrix `gn` (P x P) over the parameters `act` (m x m,
// row-major).
std::vector<double> over(const std::vector<double>& gn, const std::vector<size_t>& act, size_t P) {
  const size_t m = act.size();
  std::vector<double> A(m * m);
  for (size_t a = 0; a < m; ++a)
    for (size_t b = 0; b < m; ++b) A[a * m + b] = gn[act[a] * P + act[b]];
  return A;
}

// The Levenberg-Marquardt step of `e` over `act`, damped by mu on the
// diagonal (mu = 0: Gauss-Newton): -(H + mu diag H)^-1 grad, entry a for
// parameter act[a]. False where that matrix is not positive definite.
bool damped_step(const Evaluation& e, const std::vector<size_t>& act, size_t P, double mu, std::vector<double>& step) {
  const size_t m = act.size();
  std::vector<double> A = over(e.gn, act, P);
  step.resize(m);
  for (size_t a = 0; a < m; ++a) {
    A[a * m + a] *= 1.0 + mu;
    step[a] = -e.grad[act[a]];
  }
  return solve_spd(A, step, m);
}

// What the fit knows of a measured PSF's noise: its weight floor, and the
// value below which its pixels are left out (unknown). The HDR merge stores 0
// for a pixel too faint to measure, and near its threshold it keeps a pixel
// only when noise pushed it up: fitted as they are, the faint pixels biased
// the images' faint edges (an f = 4.5 mm lenslet, its big near-face disc
// mostly below the threshold, fitted 2 degrees tilted against a true -0.3,
// both when the rejected pixels counted as 0 and as at most the faintest
// kept value). Pixels fainter than defaults::calibration_reliable_over_faintest
// times the faintest value kept are censored: they say only that the light
// there is below that value (upper_bound), and count where the model exceeds
// it: the likelihood of a censored measurement. Left out altogether, they
// would cost a lenslet nothing for light it puts where the camera saw none.
// Neither way finds lenslets whose images lie below what the merge keeps
// (docs/calibration.md: the whole prototype at 0.2 s and at 2 s exposures).
struct Noise {
  double floor = 0;     // weight floor (calibrate.h)
  double reliable = 0;  // the faintest value fitted
};
Noise noise_of(const MeasuredPsf& psf, const CalibrationOptions& o) {
  float peak = 0, faintest = std::numeric_limits<float>::infinity();
  for (float v : psf.p)
    if (v > 0) peak = std::max(peak, v), faintest = std::min(faintest, v);
  if (!(peak > 0)) throw std::invalid_argument("calibration: PSF " + psf.name + " has no light");
  return {o.weight_floor * double(peak), o.reliable_over_faintest * double(faintest)};
}

// A pixel's weight: the inverse of its variance's shape (calibrate.h).
double weight(double p, const Noise& n) { return 1.0 / (std::max(p, 0.0) + n.floor); }

// Whether pixel i is measured whole: above the reliable value (at a coarse
// level: every sub-pixel was, MeasuredPsf::unknown).
bool known(const MeasuredPsf& psf, size_t i, const Noise& n) {
  return psf.unknown.empty() ? psf.p[i] >= n.reliable : psf.unknown[i] == 0;
}

// The most light a censored pixel i may hold: the reliable value (at a coarse
// level: what its measured sub-pixels hold plus the censored ones' bound).
double upper_bound(const MeasuredPsf& psf, size_t i, const Noise& n) {
  return psf.unknown.empty() ? n.reliable : double(psf.p[i]) + double(psf.unknown[i]);
}

// The value pixel i is fitted to where the model gives it s b: its measured
// value; for a censored pixel, the nearer end of the interval it may lie in
// where s b is outside it (below: what its measured sub-pixels hold, 0 on
// the model's pixels; above: upper_bound); NaN where the pixel does not
// count. A coarse pixel with some sub-pixels censored still holds at least
// its measured ones' light: counted as a bound above only, such pixels
// pulled no light toward them, and on 441.6 um pixels the faint discs of
// an f = 3 mm corner lenslet were left 150 um of position and focal length
// from the truth (docs/calibration.md).
double target(const MeasuredPsf& psf, size_t i, double sb, const Noise& n) {
  if (known(psf, i, n)) return psf.p[i];
  const double lower = psf.unknown.empty() ? 0.0 : double(psf.p[i]), upper = upper_bound(psf, i, n);
  if (sb < lower) return lower;
  return sb > upper ? upper : std::numeric_limits<double>::quiet_NaN();
}

// The PSF's photon scale that minimises chi2 under `model`: over its measured
// pixels, and its censored ones where s b exceeds their bound (convex in s,
// quadratic between changes of that set: solved set by set); also returns
// sum w b^2 over the pixels that count (the scale's information). At this
// optimum the gradient by the other parameters needs no term through s.
std::pair<double, double> best_scale(const MeasuredPsf& psf, const Model& model, const Noise& n) {
  double s = 0, wbb = 0;  // s = 0 first: the measured pixels alone
  for (int pass = 0; pass < 32; ++pass) {
    double wpb = 0;
    wbb = 0;
    for (const auto& [key, m] : model) {
      const double p = target(psf, size_t(key), s * m.b, n);
      if (std::isnan(p)) continue;
      const double w = weight(p, n);
      wpb += w * p * m.b;
      wbb += w * m.b * m.b;
    }
    const double next = wbb > 0 ? wpb / wbb : 0.0;
    const bool settled = std::abs(next - s) <= 1e-12 * std::abs(next);
    s = next;
    if (settled) break;
  }
  return {s, wbb};
}

// The sums over pixels that derivatives give: the gradient of chi2 / 2, its
// Gauss-Newton matrix, and the sandwich's middle, sum (w r)^2 J J^T, each
// with the scales profiled out (P and P x P, row-major).
struct Sums {
  std::vector<double> grad, gn, meat;
  explicit Sums(size_t P) : grad(P, 0.0), gn(P * P, 0.0), meat(P * P, 0.0) {}
  void add(const Sums& o, double times = 1) {
    for (size_t i = 0; i < grad.size(); ++i) grad[i] += times * o.grad[i];
    for (size_t i = 0; i < gn.size(); ++i) gn[i] += times * o.gn[i], meat[i] += times * o.meat[i];
  }
};

// Runs of PSFs whose derivative sums are kept apart in an evaluation.
constexpr size_t kSumBlocks = 64;

// Adds PSF `psf`'s terms under `model` to `sums` (when non-null), once.
PsfTerms psf_terms_once(const MeasuredPsf& psf, const Model& model, const CalibrationOptions& o, size_t lenses,
                        size_t P, Sums* sums) {
  const Noise noise = noise_of(psf, o);
  const auto [s, wbb] = best_scale(psf, model, noise);
  PsfTerms out;
  out.lens_chi2.assign(lenses, 0.0);
  out.lens_pixels.assign(lenses, 0);
  out.fit.scale = s;
  // With J = s db: u = sum w J b (the scale's coupling to the parameters),
  // v = sum (w r)^2 J b and q = sum (w r)^2 b^2 (the same in the sandwich).
  std::vector<double> u(sums ? P : 0, 0.0), v(sums ? P : 0, 0.0);
  double q = 0;
  for (const auto& [key, m] : model) {
    const double p = target(psf, size_t(key), s * m.b, noise);
    if (std::isnan(p)) continue;
    const double w = weight(p, noise), r = p - s * m.b;
    out.fit.chi2 += w * r * r;
    ++out.fit.pixels;
    if (m.lens >= 0) out.lens_chi2[size_t(m.lens)] += w * r * r, ++out.lens_pixels[size_t(m.lens)];
    if (!sums) continue;
    const double wr2 = (w * r) * (w * r);
    q += wr2 * m.b * m.b;
    for (const auto& a : m.d) {
      sums->grad[a.param] -= w * r * s * a.d;
      u[a.param] += w * s * a.d * m.b;
      v[a.param] += wr2 * s * a.d * m.b;
      for (const auto& c : m.d) {
        sums->gn[size_t(a.param) * P + c.param] += w * s * s * a.d * c.d;
        sums->meat[size_t(a.param) * P + c.param] += wr2 * s * s * a.d * c.d;
      }
    }
  }
  // Lit pixels the model leaves dark: what it should at least hold is residual.
  for (size_t i = 0; i < psf.p.size(); ++i) {
    if (!(psf.p[i] > 0) || model.contains(int64_t(i))) continue;
    const double p = target(psf, i, 0.0, noise);
    if (!(p > 0)) continue;  // NaN too: a censored pixel may be dark
    out.fit.chi2 += weight(p, noise) * p * p;
    ++out.fit.pixels;
  }
  // The scale profiled out: J becomes J - b u / wbb (its part along the
  // scale's direction removed).
  if (sums && wbb > 0)
    for (size_t a = 0; a < P; ++a)
      for (size_t c = 0; c < P; ++c) {
        const double ca = u[a] / wbb, cc = u[c] / wbb;
        sums->gn[a * P + c] -= u[a] * cc;
        sums->meat[a * P + c] += -ca * v[c] - v[a] * cc + q * ca * cc;
      }
  return out;
}

// The same, counted psf.count times (a bootstrap replicate draws some PSFs
// more than once): its own sums, then added that many times.
PsfTerms psf_terms(const MeasuredPsf& psf, const Model& model, const CalibrationOptions& o, size_t lenses, size_t P,
                   Sums* sums) {
  if (psf.count == 1) return psf_terms_once(psf, model, o, lenses, P, sums);
  std::optional<Sums> own;
  if (sums) own.emplace(P);
  PsfTerms t = psf_terms_once(psf, model, o, lenses, P, own ? &*own : nullptr);
  if (sums) sums->add(*own, psf.count);
  t.fit.chi2 *= psf.count, t.fit.pixels *= psf.count;
  for (size_t l = 0; l < lenses; ++l) t.lens_chi2[l] *= psf.count, t.lens_pixels[l] *= psf.count;
  return t;
}

// Whether a fit's scenes have an extended source: the start's, or a fitted one.
bool extended(const OpticalSystem& start, const std::vector<CalibrationParameter>& free) {
  return start.effects.source_extent ||
         std::any_of(free.begin(), free.end(), [](const auto& p) { return p.param == Param::source_sigma; });
}

class Fitter {
 public:
  Fitter(const OpticalSystem& start, const std::vector<MeasuredPsf>& psfs, const std::vector<CalibrationParameter>& free,
         const CalibrationOptions& o)
      : start_(start), psfs_(psfs), free_(free), o_(o), render_(std::make_unique<Renderer>(start, o, extended(start, free))) {}

  OpticalSystem system(const std::vector<double>& x) const {
    OpticalSystem s = start_;
    for (size_t j = 0; j < free_.size(); ++j) free_[j].set(s, x[j]);
    return s;
  }

  Evaluation evaluate(const std::vector<double>& x, bool derivatives) const {
    Evaluation e;
    const OpticalSystem sys = system(x);
    try {
      validate(sys);
    } catch (const std::invalid_argument&) {
      return e;  // a trial beyond what the model can trace: rejected
    }
    const size_t P = free_.size(), L = sys.lenslets.size();
    e.psfs.resize(psfs_.size());
    std::vector<PsfTerms> terms(psfs_.size());
    render_->set_scene(sys);
    // The PSFs in at most kSumBlocks runs of consecutive ones, each run's
    // sums apart, added in order after the threads: the same parameters give
    // the same bits whichever thread took which run (the runs depend on the
    // PSFs' count alone), and the sums' memory stays kSumBlocks x 2 P^2.
    const size_t N = psfs_.size(), blocks = std::min(N, kSumBlocks);
    std::vector<Sums> per_block(derivatives ? blocks : 0, Sums(P));
    std::atomic<size_t> next{0};
    std::mutex failing;
    std::exception_ptr failure;
    auto work = [&] {
      try {
        for (size_t b; (b = next++) < blocks;)
          for (size_t k = b * N / blocks; k < (b + 1) * N / blocks; ++k) {
            const Model model = (*render_)(psfs_[k].theta_mm, free_, derivatives);
            terms[k] = psf_terms(psfs_[k], model, o_, L, P, derivatives ? &per_block[b] : nullptr);
          }
      } catch (...) {
        std::lock_guard lock(failing);
        failure = std::current_exception();
        next = blocks;
      }
    };
    std::vector<std::thread> threads;
    for (unsigned i = 1; i < render_->threads(o_.threads); ++i) threads.emplace_back(work);
    work();
    for (auto& t : threads) t.join();
    if (failure) std::rethrow_exception(failure);
    Sums total(derivatives ? P : 0);
    for (const Sums& s : per_block) total.add(s);
    e.grad = std::move(total.grad), e.gn = std::move(total.gn), e.meat = std::move(total.meat);
    e.ok = true;
    e.chi2 = 0;
    e.lenses.resize(L);
    for (size_t k = 0; k < psfs_.size(); ++k) {
      e.psfs[k] = terms[k].fit;
      e.chi2 += terms[k].fit.chi2;
      e.pixels += terms[k].fit.pixels;
      for (size_t l = 0; l < L; ++l)
        e.lenses[l].chi2 += terms[k].lens_chi2[l], e.lenses[l].pixels += terms[k].lens_pixels[l];
    }
    return e;
  }

 private:
  const OpticalSystem& start_;
  const std::vector<MeasuredPsf>& psfs_;
  const std::vector<CalibrationParameter>& free_;
  const CalibrationOptions& o_;
  std::unique_ptr<Renderer> render_;  // evaluate() is const: the renderer's scene is its working state
};

void check_inputs(const OpticalSystem& start, const std::vector<MeasuredPsf>& psfs,
                  const std::vector<CalibrationParameter>& free, const CalibrationOptions& o) {
  if (psfs.empty()) throw std::invalid_argument("calibration: no PSF to fit");
  if (free.empty()) throw std::invalid_argument("calibration: no parameter to fit (--fit names none)");
  if (!(o.weight_floor > 0)) throw std::invalid_argument("calibration: the weight floor must be > 0");
  if (!(o.reliable_over_faintest >= 1))
    throw std::invalid_argument("calibration: the reliable level must be at least the faintest value kept (--reliable >= 1)");
  if (!std::has_single_bit(o.blur_supersample))
    throw std::invalid_argument("calibration: the blur's supersampling " + std::to_string(o.blur_supersample) +
                                " is not a power of two");
  const AnalysisGrid grid = AnalysisGrid::of(start, o.settings.binning);
  for (const auto& p : psfs)
    if (p.p.size() != size_t(grid.width) * size_t(grid.height))
      throw std::invalid_argument("calibration: PSF " + p.name + " has " + std::to_string(p.p.size()) +
                                  " pixels; the model's grid at binning " + std::to_string(o.settings.binning) +
                                  " has " + std::to_string(grid.width) + " x " + std::to_string(grid.height));
  for (const auto& f : free)
    if (f.per_lens() && (f.lens < 0 || size_t(f.lens) >= start.lenslets.size()))
      throw std::invalid_argument("calibration: " + f.name() + ": the scene has " +
                                  std::to_string(start.lenslets.size()) + " lenslets");
}

}  // namespace

namespace {

// Levenberg-Marquardt on the profiled chi2 / 2 from x, the damping on the
// diagonal (scale-free across mm and degrees); parameters on a bound that the
// gradient pushes outward are held. `cur` enters and leaves evaluated with
// derivatives at x. Returns the steps accepted; `converged` when the last
// step gained less than 1e-3 of chi2 / dof (nothing next to the noise: an
// uncertainty is where chi2 rises by chi2 / dof) or less than kGainsOfNoise
// times what two evaluations of the same parameters differ by, or no step
// could gain. In that last case `no_gain_rise` is what the smallest step
// tried (the largest damping) raised chi2 by, over chi2 / dof (infinite if
// it was a system the model cannot trace; NaN otherwise): near 0 at an
// optimum of a smooth chi2, far above 1 where the model jumps (the
// footprint's discrete choices, docs/model.md "Splatting"): no step near
// the noise gets across such a cliff, and the fit stops at its low edge.
constexpr double kGainsOfNoise = 4;

// Gauss-Newton's matrix leaves out the residuals' own curvature (sum w r
// d2b). Where the model's misfit is large, as on the f = 3 mm lenslets' faint
// rims counted at --reliable 2, it overstates chi2's curvature: accepted
// steps gained 1.8-1.9 times what the quadratic model predicted (chi2 almost
// linear along them) and the fit crept to the step limit (docs/calibration.md). From chi2 at the start, its slope along the step and its
// value at the step's end, a parabola gives chi2's own curvature along the
// step; where its minimum lies beyond the end (by more than kStretchFrom),
// the point there (at most kStretchMost steps out, clamped to the bounds) is
// tried, values only, and taken (xt, trial) if chi2 is lower still; returns
// whether it was. (The refinement's optimiser meets the same and stretches
// its next step instead, levenberg_marquardt.h: its every render carries
// derivatives. Here values cost about a fifth of a step's evaluation, so the
// further point is tried at once.)
constexpr double kStretchFrom = 1.5, kStretchMost = 16;
bool stretch(const Fitter& fitter, const std::vector<double>& x, const std::vector<double>& lo,
             const std::vector<double>& hi, const std::vector<size_t>& act, const Evaluation& cur,
             std::vector<double>& xt, Evaluation& trial) {
  double slope = 0;  // d chi2 / dt at t = 0 along x + t (xt - x); cur.grad is that of chi2 / 2
  for (size_t j : act) slope += 2 * cur.grad[j] * (xt[j] - x[j]);
  const double curvature = 2 * (trial.chi2 - cur.chi2 - slope);
  if (!(slope < 0) || !(curvature > 0)) return false;
  const double t = std::min(-slope / curvature, kStretchMost);
  if (!(t > kStretchFrom)) return false;
  std::vector<double> xs = x;
  for (size_t j : act) xs[j] = std::clamp(x[j] + t * (xt[j] - x[j]), lo[j], hi[j]);
  Evaluation further = fitter.evaluate(xs, false);
  if (!(further.chi2 < trial.chi2)) return false;
  xt = std::move(xs), trial = std::move(further);
  return true;
}

// Where Gauss-Newton's curvature is wrong across a narrow valley, steps
// zig-zag from wall to wall and gain little each, while the line through the
// point two steps back and the new one runs along the valley (parallel
// tangents, PARTAN). On that line, t = 0 the point two steps back, t = 1 the
// new point: chi2 is tried at t = 2 (values only), and a parabola through the
// three gives a further point (at most t = kPatternMost) tried too; the lowest,
// if below the new point's chi2, is taken (xt, trial). Returns whether one
// was. Each try costs a values evaluation, about a fifth of a step.
constexpr double kPatternMost = 8;
bool pattern_move(const Fitter& fitter, const std::vector<double>& back2, double chi2_back2,
                  const std::vector<double>& lo, const std::vector<double>& hi, std::vector<double>& xt,
                  Evaluation& trial) {
  auto along = [&](double t) {
    std::vector<double> p(xt.size());
    for (size_t j = 0; j < p.size(); ++j) p[j] = std::clamp(back2[j] + t * (xt[j] - back2[j]), lo[j], hi[j]);
    return p;
  };
  std::vector<double> x2 = along(2.0);
  if (x2 == xt) return false;
  Evaluation e2 = fitter.evaluate(x2, false);
  if (!e2.ok) return false;
  const double f0 = chi2_back2, f1 = trial.chi2, f2 = e2.chi2;
  const double curvature = f0 - 2 * f1 + f2;  // second difference over unit spacing
  std::vector<double> best;
  Evaluation best_e;
  if (f2 < f1) best = std::move(x2), best_e = std::move(e2);
  // The parabola's minimum beyond t = 2 (or, chi2 concave there, the cap).
  const double vertex = curvature > 0 ? 1.0 + 0.5 * (f0 - f2) / curvature : kPatternMost;
  if (f2 < f1 && vertex > 2.5) {
    std::vector<double> xf = along(std::min(vertex, kPatternMost));
    Evaluation ef = fitter.evaluate(xf, false);
    if (ef.ok && ef.chi2 < best_e.chi2) best = std::move(xf), best_e = std::move(ef);
  }
  if (best.empty()) return false;
  xt = std::move(best), trial = std::move(best_e);
  return true;
}

int levenberg_marquardt(const Fitter& fitter, std::vector<double>& x, const std::vector<double>& lo,
                        const std::vector<double>& hi, const std::vector<bool>& hold, size_t scales,
                        const CalibrationOptions& o, int level, int first_step, double t0, Evaluation& cur,
                        bool& converged, double& no_gain_rise, int& stretched, int& pattern_moves) {
  const size_t P = x.size();
  auto dof_of = [&](const Evaluation& e) { return e.pixels > P + scales ? e.pixels - P - scales : size_t(1); };
  double mu = 1e-3;
  constexpr double kRejectedMu = 0.1, kMaxMu = 1e6;
  int steps = 0;
  converged = false;
  no_gain_rise = std::numeric_limits<double>::quiet_NaN();
  // The points (and chi2) one and two accepted steps back, for pattern moves.
  std::vector<double> back1, back2;
  double chi2_back1 = 0, chi2_back2 = 0;
  while (steps < o.max_steps && !converged) {
    std::vector<size_t> act;
    for (size_t j = 0; j < P; ++j) {
      const bool held = hold[j] || (x[j] <= lo[j] && cur.grad[j] > 0) || (x[j] >= hi[j] && cur.grad[j] < 0);
      if (!held && cur.gn[j * P + j] > 0) act.push_back(j);
    }
    const size_t m = act.size();
    bool accepted = false;
    double rise = std::numeric_limits<double>::quiet_NaN();  // of the last step rejected
    while (m && !accepted && mu <= kMaxMu) {
      std::vector<double> step;
      if (!damped_step(cur, act, P, mu, step)) {
        mu = std::max(mu * 4, kRejectedMu);
        continue;
      }
      std::vector<double> xt = x;
      bool moved = false;
      for (size_t a = 0; a < m; ++a) {
        const size_t j = act[a];
        xt[j] = std::clamp(x[j] + step[a], lo[j], hi[j]);
        moved = moved || xt[j] != x[j];
      }
      if (!moved) break;
      Evaluation trial = fitter.evaluate(xt, false);
      if (!(trial.chi2 < cur.chi2)) {
        // (chi2 0: the model is the measurement, an optimum whatever a step does.)
        rise = !trial.ok       ? std::numeric_limits<double>::infinity()
               : cur.chi2 > 0 ? (trial.chi2 - cur.chi2) / (cur.chi2 / double(dof_of(cur)))
                              : 0.0;
        mu = std::max(mu * 4, kRejectedMu);
        continue;
      }
      // The fall of chi2 Gauss-Newton's model predicts for the step taken
      // (clamped to the bounds): g and H are of chi2 / 2, so -2 (g.s + s.H s / 2).
      double predicted = 0;
      for (size_t a : act) {
        const double sa = xt[a] - x[a];
        double hs = 0;
        for (size_t b : act) hs += cur.gn[a * P + b] * (xt[b] - x[b]);
        predicted -= 2 * cur.grad[a] * sa + sa * hs;
      }
      stretched += stretch(fitter, x, lo, hi, act, cur, xt, trial);
      back2 = std::move(back1), chi2_back2 = chi2_back1;
      back1 = x, chi2_back1 = cur.chi2;
      if (o.pattern_moves && !back2.empty()) pattern_moves += pattern_move(fitter, back2, chi2_back2, lo, hi, xt, trial);
      const double gain = cur.chi2 - trial.chi2;
      x = xt;
      cur = fitter.evaluate(x, true);
      mu = std::max(mu / 4, 1e-7);
      ++steps;
      accepted = true;
      if (o.progress)
        o.progress({first_step + steps, cur.chi2, mu, gain, predicted,
                    std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count() - t0,
                    level, fitter.system(x)});
      // The device's model is a float sum in no fixed order: the same
      // parameters evaluated twice (the trial, then with derivatives) differ
      // a little, and a gain within a few times that is noise.
      const double repeat_noise = std::abs(cur.chi2 - trial.chi2);
      if (gain < std::max(1e-3 * cur.chi2 / double(dof_of(cur)), kGainsOfNoise * repeat_noise)) converged = true;
    }
    if (!accepted) converged = true, no_gain_rise = rise;  // no step of any damping gains
  }
  return steps;
}

// The PSFs binned by 2^k (each a sum over 2^k x 2^k pixels, as the
// dictionary's levels are): per pixel, the sum of its measured sub-pixels
// and the most its censored ones may add (their count times the reliable
// value). A pixel with a censored sub-pixel is censored to that interval.
std::vector<MeasuredPsf> binned(const std::vector<MeasuredPsf>& psfs, const AnalysisGrid& grid, int k,
                                const CalibrationOptions& o) {
  std::vector<MeasuredPsf> out;
  for (const auto& p : psfs) {
    const Noise n = noise_of(p, o);
    PsfLevel measured{0, grid.width, grid.height, p.p}, censored{0, grid.width, grid.height, p.p};
    for (size_t i = 0; i < p.p.size(); ++i) {
      const bool m = known(p, i, n);
      measured.p[i] = m ? p.p[i] : 0.0f;
      censored.p[i] = m ? 0.0f : float(n.reliable);
    }
    out.push_back({p.theta_mm, bin_level(measured, k).p, p.name, bin_level(censored, k).p, p.count});
  }
  return out;
}

// The model's cells (calibrate.h): the fit's parameters x evaluated again
// with options.cells_check times the cells, and one Gauss-Newton step on
// that model over the parameters `act` (those with an uncertainty): how far
// it moves each. Zeros when not checked or when the finer model's matrix is
// singular (then r.check_cells stays 0: the command says so); records the
// check's cells and time in r.
std::vector<double> cells_check(const OpticalSystem& start, const std::vector<MeasuredPsf>& psfs,
                                const std::vector<CalibrationParameter>& free, const CalibrationOptions& options,
                                const std::vector<double>& x, const std::vector<size_t>& act, CalibrationResult& r) {
  const size_t P = free.size(), m = act.size();
  std::vector<double> moved(P, 0.0);
  if (options.cells_check <= 1 || m == 0) return moved;
  const auto t0 = std::chrono::steady_clock::now();
  CalibrationOptions finer = options;
  finer.settings.rays_per_lenslet = options.settings.rays_per_lenslet * options.cells_check;
  const Evaluation e = Fitter(start, psfs, free, finer).evaluate(x, true);
  std::vector<double> step;
  if (e.ok && damped_step(e, act, P, 0.0, step)) {
    for (size_t a = 0; a < m; ++a) moved[act[a]] = std::abs(step[a]);
    r.check_cells = finer.settings.rays();
  }
  r.check_seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return moved;
}

// The bootstrap over the PSFs (calibrate.h): per parameter, the standard
// deviation of its value over options.bootstrap replicates, each the fit's
// end r.fitted refitted on the model's pixels to the PSFs drawn with
// replacement. Zeros when not asked for; records the count and time in r.
std::vector<double> bootstrap(const std::vector<MeasuredPsf>& psfs, const std::vector<CalibrationParameter>& free,
                              const CalibrationOptions& options, CalibrationResult& r) {
  const size_t P = free.size(), N = psfs.size();
  std::vector<double> spread(P, 0.0);
  if (options.bootstrap < 2) return spread;
  const auto t0 = std::chrono::steady_clock::now();
  CalibrationOptions o = options;
  o.coarse_levels = 0;  // from the fit's end: the replicate's optimum lies near it
  o.max_steps = options.bootstrap_steps;
  o.cells_check = 1, o.bootstrap = 0;
  o.progress = nullptr, o.bootstrap_progress = nullptr;
  std::vector<double> sum(P, 0.0), sum2(P, 0.0);
  for (unsigned rep = 1; rep <= options.bootstrap; ++rep) {
    std::seed_seq seq{options.bootstrap_seed, uint64_t(rep)};
    std::mt19937_64 rng(seq);
    std::uniform_int_distribution<size_t> draw(0, N - 1);
    std::vector<unsigned> drawn(N, 0);
    for (size_t i = 0; i < N; ++i) ++drawn[draw(rng)];
    std::vector<MeasuredPsf> sample;
    for (size_t k = 0; k < N; ++k)
      if (drawn[k]) sample.push_back(psfs[k]), sample.back().count = psfs[k].count * drawn[k];
    const CalibrationResult fit = calibrate(r.fitted, sample, free, o);
    for (size_t j = 0; j < P; ++j) {
      const double d = fit.estimates[j].value - fit.estimates[j].start;  // about the fit's end, for precision
      sum[j] += d, sum2[j] += d * d;
    }
    if (options.bootstrap_progress) options.bootstrap_progress(rep, fit);
  }
  const double R = options.bootstrap;
  for (size_t j = 0; j < P; ++j) spread[j] = std::sqrt(std::max(0.0, (sum2[j] - sum[j] * sum[j] / R) / (R - 1)));
  r.bootstrap_replicates = options.bootstrap;
  r.bootstrap_seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - t0).count();
  return spread;
}

}  // namespace

CalibrationResult calibrate(const OpticalSystem& start, const std::vector<MeasuredPsf>& psfs,
                            const std::vector<CalibrationParameter>& free, const CalibrationOptions& options) {
  check_inputs(start, psfs, free, options);
  const double t0 = std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count();
  const size_t P = free.size();
  std::vector<double> x(P), lo(P), hi(P);
  for (size_t j = 0; j < P; ++j) {
    x[j] = free[j].get(start);
    std::tie(lo[j], hi[j]) = free[j].bounds(start);
  }
  validate(start);  // throws naming the field
  CalibrationResult r;
  // Coarse to fine: the images' disc edges make chi2 a staircase at the
  // pixels' scale, far from quadratic once an edge is a pixel off; on pixels
  // 2^k times larger the start lies within the basin, and each finer level
  // starts from the coarser one's optimum.
  const AnalysisGrid grid = AnalysisGrid::of(start, options.settings.binning);
  // chi2 at the start on the model's pixels: the first level's own
  // evaluation when that level is the model's (a refit, a bootstrap
  // replicate), else one evaluation of its own.
  if (options.coarse_levels > 0) r.chi2_start = Fitter(start, psfs, free, options).evaluate(x, false).chi2;
  Evaluation cur;
  for (int k = std::max(0, options.coarse_levels); k >= 0; --k) {
    const std::vector<MeasuredPsf> level = k ? binned(psfs, grid, k, options) : std::vector<MeasuredPsf>{};
    CalibrationOptions at = options;
    at.settings.binning = options.settings.binning << k;
    const Fitter fitter(start, k ? level : psfs, free, at);
    // A lenslet's tilt moves its image much as its position does, and
    // changes its shape only at second order: on coarse pixels the two are
    // nearly one direction, along which the fit wandered (to a 10 degree
    // tilt of an f = 3 mm lens, balanced by 0.2 mm of position). Tilts are
    // held until the finest level.
    std::vector<bool> hold(P, false);
    for (size_t j = 0; j < P; ++j)
      hold[j] = k > 0 && (free[j].param == Param::lens_tilt_x || free[j].param == Param::lens_tilt_y);
    cur = fitter.evaluate(x, true);
    if (k == 0 && options.coarse_levels <= 0) r.chi2_start = cur.chi2;
    r.steps +=
        levenberg_marquardt(fitter, x, lo, hi, hold, psfs.size(), at, k, r.steps, t0, cur, r.converged,
                            r.no_gain_rise, r.stretched, r.pattern_moves);
    if (k == 0) r.fitted = fitter.system(x);
  }
  r.chi2 = cur.chi2;
  r.pixels = cur.pixels;
  r.dof = cur.pixels > P + psfs.size() ? cur.pixels - P - psfs.size() : 1;
  r.psfs = cur.psfs;
  r.lenses = cur.lenses;
  // Uncertainties: the sandwich H^-1 M H^-1 (H the Gauss-Newton matrix, M =
  // sum (w r)^2 J J^T) over the parameters some PSF constrains; the others
  // are reported as unconstrained. With weights of the right shape it equals
  // H^-1 chi2 / dof; where the weights' shape is wrong (an HDR pixel's
  // variance is only roughly a + b p) it stays right, which H^-1 chi2 / dof
  // did not: on the synthetic HDR test that put 7 of 31 parameters 3-9 of
  // their reported sigmas from the truth even with the model's own rays.
  std::vector<size_t> act;
  std::vector<bool> at_bound(P);
  for (size_t j = 0; j < P; ++j) {
    at_bound[j] = x[j] <= lo[j] || x[j] >= hi[j];
    if (cur.gn[j * P + j] > 0 && !at_bound[j]) act.push_back(j);
  }
  std::vector<double> sigma(P, std::numeric_limits<double>::infinity());
  const size_t m = act.size();
  const std::vector<double> A = over(cur.gn, act, P);  // H over act
  std::vector<double> inv(m * m);                      // and its inverse (column by column)
  bool invertible = true;
  for (size_t a = 0; a < m && invertible; ++a) {
    std::vector<double> e(m, 0.0);
    e[a] = 1;
    invertible = solve_spd(A, e, m);
    for (size_t b = 0; b < m; ++b) inv[b * m + a] = e[b];
  }
  if (invertible)
    for (size_t a = 0; a < m; ++a) {
      double var = 0;  // (inv M inv)_aa
      for (size_t b = 0; b < m; ++b)
        for (size_t c = 0; c < m; ++c) var += inv[a * m + b] * cur.meat[act[b] * P + act[c]] * inv[c * m + a];
      if (var > 0) sigma[act[a]] = std::sqrt(var);
    }
  const std::vector<double> cells = cells_check(start, psfs, free, options, x, act, r);
  const std::vector<double> spread = bootstrap(psfs, free, options, r);
  for (size_t j = 0; j < P; ++j) {
    ParameterEstimate e{free[j], free[j].get(start), x[j], sigma[j], sigma[j], cells[j], spread[j], at_bound[j]};
    // The sandwich and the bootstrap estimate the same spread, each missing
    // something (independent pixels and H's curvature; what all PSFs share):
    // the larger counts.
    if (std::isfinite(e.sigma))
      e.sigma = std::hypot(std::max(e.sigma_residuals, e.sigma_bootstrap), e.sigma_cells);
    r.estimates.push_back(e);
  }
  r.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now().time_since_epoch()).count() - t0;
  return r;
}

void calibration_residuals(const OpticalSystem& sys, const std::vector<MeasuredPsf>& psfs,
                           const CalibrationOptions& options,
                           const std::function<void(size_t, const std::vector<float>&)>& each) {
  Renderer render(sys, options, sys.effects.source_extent);
  render.set_scene(sys);
  for (size_t k = 0; k < psfs.size(); ++k) {
    const MeasuredPsf& psf = psfs[k];
    const Model model = render(psf.theta_mm, {}, false);
    const Noise noise = noise_of(psf, options);
    const double s = best_scale(psf, model, noise).first;
    std::vector<float> out(psf.p.size());
    for (size_t i = 0; i < out.size(); ++i) {
      const double p = psf.p[i];
      const ModelPixel* m = model.find(int64_t(i));
      const double b = m ? m->b : 0.0;
      out[i] = known(psf, i, noise) ? float((p - s * b) * std::sqrt(weight(p, noise))) : 0.0f;
    }
    each(k, out);
  }
}

unsigned calibration_binning(double pixel_um) {
  unsigned b = 1;
  while (pixel_um * b < defaults::calibration_pixel_um * (1 - 1e-9) && b < (1u << 20)) b *= 2;
  return b;
}

std::vector<MeasuredPsf> read_merged_psfs(const std::string& dir, const OpticalSystem& sensor, unsigned binning) {
  namespace fs = std::filesystem;
  if (!std::has_single_bit(binning)) throw std::invalid_argument("calibration: binning " + std::to_string(binning) +
                                                                  " is not a power of two");
  std::vector<fs::path> sidecars;
  std::error_code ec;
  for (const auto& e : fs::directory_iterator(dir, ec))
    if (e.path().extension() == ".json") sidecars.push_back(e.path());
  if (ec) throw std::runtime_error("cannot read " + dir + ": " + ec.message());
  std::sort(sidecars.begin(), sidecars.end());
  if (sidecars.empty())
    throw std::runtime_error(dir + ": no merged PSF (<name>.json beside <name>.exr, as prism dictionary merge-hdr "
                             "writes them)");
  std::vector<MeasuredPsf> out;
  for (const auto& json : sidecars) {
    const std::string name = json.string();
    nlohmann::json j;
    try {
      std::ifstream in(json);
      j = parse_json_file(in);
      const auto& src = j.at("source");
      MeasuredPsf m;
      m.theta_mm = {src.at("x_mm").get<double>(), src.at("y_mm").get<double>(), src.at("depth_mm").get<double>()};
      const fs::path exr = fs::path(json).replace_extension(".exr");
      int w = 0, h = 0;
      std::vector<float> y = read_exr_channel(exr.string(), "Y", w, h);
      if (w != sensor.sensor_width_px || h != sensor.sensor_height_px)
        throw std::runtime_error(exr.string() + " is " + std::to_string(w) + " x " + std::to_string(h) +
                                 " px; the scene's sensor is " + std::to_string(sensor.sensor_width_px) + " x " +
                                 std::to_string(sensor.sensor_height_px) + ": give the scene of this camera (--scene)");
      m.p = bin_level(PsfLevel{0, w, h, std::move(y)}, std::countr_zero(binning)).p;
      m.name = exr.string();
      out.push_back(std::move(m));
    } catch (const nlohmann::json::exception& e) {
      throw std::runtime_error(name + ": no source position (source.x_mm, y_mm, depth_mm): " + e.what());
    }
  }
  return out;
}

}  // namespace prism
