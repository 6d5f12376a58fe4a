// What the engine needs to know of an optical design: lenslets, lens model,
// sensor, distances and the effects to simulate. Scenes (host/scene/scene.h) are
// parsed into this; the engine never reads files.
#pragma once
#include <array>
#include <string>
#include <vector>

#include "engine/defaults.h"

namespace prism {

enum class LensModel { thin, real };
const char* to_string(LensModel m);

struct LensletGeometry {
  double x_mm = 0;           // centre on the lens plane
  double y_mm = 0;
  double diameter_mm = defaults::lenslet_diameter_mm;
  double focal_mm = 0;
  // As built: the lens turned about its centre on the lens plane, about the
  // x axis by tilt_x, then about the y axis by tilt_y (tilt_matrix).
  double tilt_x_deg = 0;
  double tilt_y_deg = 0;
};

// As built: the sensor moved within its plane and turned about its centre
// (about x by tilt_x, then about y by tilt_y, as a lenslet's tilt). Pixel
// coordinates run along the turned sensor's own axes.
struct SensorPose {
  double offset_x_mm = 0;
  double offset_y_mm = 0;
  double tilt_x_deg = 0;
  double tilt_y_deg = 0;
  bool operator==(const SensorPose&) const = default;
  bool nominal() const { return *this == SensorPose{}; }
};

// Effects beyond the plain model. Each is off unless a scene names it, and an
// effect that is off is compiled out of the kernels (specialisation constants).
struct Effects {
  bool scintillator_refraction = false;
  double scintillator_index = defaults::scintillator_index;
  bool holder_vignetting = false;
  double holder_bore_mm = defaults::holder_bore_mm;
  double detection_efficiency = defaults::detection_efficiency;
  double dark_counts_per_pixel = defaults::dark_counts_per_pixel;
  bool source_extent = false;  // Gaussian source instead of a point
  double source_sigma_mm = defaults::source_sigma_mm;
  bool diffraction = false;    // each lenslet's image blurred by its Airy core (a uniform square, blur.glsl)
  double wavelength_nm = defaults::wavelength_nm;
};

struct OpticalSystem {
  std::vector<LensletGeometry> lenslets;
  LensModel lens_model = LensModel::real;
  double glass_index = defaults::glass_index_nbk7;
  double edge_thickness_mm = defaults::edge_thickness_mm;
  // Real model: which face is curved. DESIGN.md: toward the scintillator.
  bool curved_toward_sensor = false;
  int sensor_width_px = defaults::sensor_width_px;
  int sensor_height_px = defaults::sensor_height_px;
  double pixel_um = defaults::pixel_um;
  double lens_to_sensor_mm = defaults::lens_to_sensor_mm;
  double working_distance_mm = defaults::working_distance_mm;
  SensorPose sensor_pose;
  Effects effects;

  // Whether a lenslet is tilted or the sensor is off its nominal pose: the
  // kernels then trace through each lens's own frame and onto the turned
  // sensor (specialisation constant AS_BUILT); a nominal system compiles that
  // out.
  bool as_built() const;

  // Plano-convex geometry of lenslet i (real model): R = f (n - 1), the sag of
  // the front face at the rim, and centre thickness = sag + edge thickness.
  double curvature_radius_mm(size_t i) const { return lenslets[i].focal_mm * (glass_index - 1.0); }
  double sag_mm(size_t i) const;
  double center_thickness_mm(size_t i) const { return sag_mm(i) + edge_thickness_mm; }
  // The shortest focal length lenslet i can have as a real lens: validate
  // refuses a radius f (n - 1) below the aperture's radius (which the sag's
  // square root needs). Rounding may put this very value just beyond.
  double shortest_focal_mm(size_t i) const { return 0.5 * lenslets[i].diameter_mm / (glass_index - 1.0); }
  // Lateral magnification of a source at depth d (from the scintillator face)
  // through a lenslet's centre: a lateral source shift s moves every lenslet
  // image by -s * magnification(d) on the sensor (the images are inverted).
  double magnification(double depth_mm) const { return lens_to_sensor_mm / (depth_mm + working_distance_mm); }
  // A source at this depth (from the scintillator face) lies in front of the
  // lenses, which are working_distance_mm before the face (false for NaN).
  bool in_front(double depth_mm) const { return depth_mm > -working_distance_mm; }
  // A source at depth d moved by a lenslet-lattice vector times this puts
  // every lenslet image where its neighbour's was (a lattice alias):
  // (D + L) / L = 1 + 1 / magnification(d), D = d + working distance.
  double alias_scale(double depth_mm) const { return 1.0 + 1.0 / magnification(depth_mm); }
  // Effect diffraction: the half side of the uniform square that stands for a
  // lenslet's Airy core on the sensor is this over the lenslet's diameter
  // (mm^2; defaults.h).
  double airy_half_side_mm_times_diameter() const {
    return defaults::airy_square_half_side_per_sigma * defaults::airy_gaussian_factor * effects.wavelength_nm * 1e-6 *
           lens_to_sensor_mm;
  }
  double airy_half_side_mm(size_t i) const { return airy_half_side_mm_times_diameter() / lenslets[i].diameter_mm; }
  double sensor_width_mm() const { return sensor_width_px * pixel_um * 1e-3; }
  double sensor_height_mm() const { return sensor_height_px * pixel_um * 1e-3; }
};

// How Fisher information is estimated from splatted rays (see fisher_terms in
// shaders/common/optics.glsl): `split` pairs two independent halves of the rays
// and has no noise bias in the numerator; `naive` is the plug-in estimate.
enum class FisherEstimator { naive, split };
const char* to_string(FisherEstimator e);

// How a traced ray becomes pixel values (shaders/common/footprint.glsl):
// `point` splats each ray bilinearly into the 4 nearest pixel centres (the
// paper's way: the box pixel blurred once more by a one-pixel tent, and shot
// noise at fine pixels); `footprint` traces the aperture strata's corners and
// gives each box pixel the exact area of every cell image inside it.
enum class Splat { point, footprint };
const char* to_string(Splat s);
Splat splat_from_string(const std::string& s);  // throws naming the choices

// What the three derivatives of a forward model are taken with respect to:
// the source position (the default), or parameters of the scene
// (calibration, issue 18). Units: mm for positions and distances, degrees
// for tilts. A lens parameter names its lenslet; lens = -1 takes every
// lenslet's own (the image's derivative is then the sum of each lenslet's).
// The kernels' PARAM_* (shaders/common/optics.glsl) follow this order.
enum class SceneParam {
  source_x, source_y, source_depth,
  lens_x, lens_y, lens_focal, lens_tilt_x, lens_tilt_y,
  lens_to_sensor, working_distance, sensor_offset_x, sensor_offset_y, sensor_tilt_x, sensor_tilt_y,
  source_sigma  // effect source_extent's sigma (mm): the calibration's blur term
};
struct Tangent {
  SceneParam param;
  int lens = -1;
  bool operator==(const Tangent&) const = default;
};
using Tangents = std::array<Tangent, 3>;
inline constexpr Tangents source_tangents{{{SceneParam::source_x}, {SceneParam::source_y}, {SceneParam::source_depth}}};

// Analysis settings of one forward-model run.
struct TraceSettings {
  // Rays through a lenslet of the prototype's 3 mm diameter, rounded up to an
  // even square of strata. Other lenses get the same density of rays per
  // aperture area, so designs with lenses of different sizes compare fairly.
  unsigned rays_per_lenslet = defaults::rays_per_lenslet;
  unsigned binning = defaults::analysis_binning;           // analyse on binning x binning sensor pixels
  double photons_emitted = defaults::photons_emitted;
  // The footprint's Fisher terms carry no sampling noise: the plug-in
  // estimate is exact for them (the split one pairs cells of the two halves
  // and under-counts where a pixel sees cells of one half only).
  FisherEstimator estimator = FisherEstimator::naive;
  Splat splat = Splat::footprint;
  // 0: the default strata; another value gives another stratification of the
  // same apertures (other jitter for point rays, cells turned for footprints):
  // truth rendered apart from the model that fits it.
  unsigned stratification = 0;

  // The converged default rays (cells) per lenslet of a splat (defaults.h),
  // its Fisher estimator (the point splat's plug-in estimate is biased by ray
  // noise, docs/model.md "Convergence"; the footprint's pixels are smooth), and
  // settings with a splat's defaults.
  static unsigned default_rays(Splat s) {
    return s == Splat::point ? defaults::rays_per_lenslet_point : defaults::rays_per_lenslet;
  }
  static FisherEstimator default_estimator(Splat s) {
    return s == Splat::point ? FisherEstimator::split : FisherEstimator::naive;
  }
  static TraceSettings defaults_for(Splat s) {
    TraceSettings t;
    t.splat = s;
    t.rays_per_lenslet = default_rays(s);
    t.estimator = default_estimator(s);
    return t;
  }

  unsigned strata() const { return strata_for(defaults::lenslet_diameter_mm); }
  unsigned rays() const { return strata() * strata(); }  // through a 3 mm lenslet
  unsigned strata_for(double diameter_mm) const;          // even, >= 2
};

// The analysis grid: the sensor binned B x B (the last column/row may hang
// over the sensor edge; hits beyond the physical sensor are dropped).
struct AnalysisGrid {
  int width = 0;
  int height = 0;
  double pixel_mm = 0;
  static AnalysisGrid of(const OpticalSystem& sys, unsigned binning);
};

// Throws prism::SceneError-like std::invalid_argument naming the field when the
// system cannot be traced (overlapping lenslets, impossible real lens, ...).
void validate(const OpticalSystem& sys);

}  // namespace prism
