#include "engine/optical_system.h"

#include <cmath>
#include <sstream>
#include <stdexcept>

namespace prism {

const char* to_string(LensModel m) { return m == LensModel::real ? "real" : "thin"; }
const char* to_string(FisherEstimator e) { return e == FisherEstimator::split ? "split" : "naive"; }

const char* to_string(Splat s) { return s == Splat::footprint ? "footprint" : "point"; }

Splat splat_from_string(const std::string& s) {
  if (s == "point") return Splat::point;
  if (s == "footprint") return Splat::footprint;
  throw std::invalid_argument("splat '" + s + "': choose point or footprint");
}

bool OpticalSystem::as_built() const {
  for (const auto& l : lenslets)
    if (l.tilt_x_deg != 0 || l.tilt_y_deg != 0) return true;
  return !sensor_pose.nominal();
}

double OpticalSystem::sag_mm(size_t i) const {
  double r = curvature_radius_mm(i);
  double a = 0.5 * lenslets[i].diameter_mm;
  return r - std::sqrt(r * r - a * a);
}

// Even, so the checkerboard halves of the strata hold equally many rays.
unsigned TraceSettings::strata_for(double diameter_mm) const {
  double per_side = std::sqrt(double(rays_per_lenslet)) * diameter_mm / defaults::lenslet_diameter_mm;
  unsigned s = unsigned(std::ceil(per_side - 1e-9));
  s += s & 1u;
  return s < 2 ? 2 : s;
}

AnalysisGrid AnalysisGrid::of(const OpticalSystem& sys, unsigned binning) {
  if (binning < 1) throw std::invalid_argument("binning must be at least 1");
  AnalysisGrid g;
  g.width = int((sys.sensor_width_px + binning - 1) / binning);
  g.height = int((sys.sensor_height_px + binning - 1) / binning);
  g.pixel_mm = sys.pixel_um * binning * 1e-3;
  return g;
}

void validate(const OpticalSystem& sys) {
  auto fail = [](const std::string& field, const std::string& why) { throw std::invalid_argument(field + ": " + why); };
  auto check_tilt = [&](const std::string& field, double tilt_deg) {
    if (!(std::abs(tilt_deg) <= defaults::max_tilt_deg))
      fail(field, "must be within +-" + std::to_string(int(defaults::max_tilt_deg)) + " degrees (an as-built tilt), got " +
                      std::to_string(tilt_deg));
  };
  if (sys.lenslets.empty()) fail("lenslets", "at least one lenslet is needed");
  if (!(sys.glass_index > 1.0)) fail("glass.index", "must be > 1");
  if (!(sys.edge_thickness_mm >= 0)) fail("glass.edge_thickness_mm", "must be >= 0");
  if (sys.sensor_width_px < 1 || sys.sensor_height_px < 1) fail("sensor", "width_px and height_px must be >= 1");
  if (!(sys.pixel_um > 0)) fail("sensor.pixel_um", "must be > 0");
  if (!(sys.lens_to_sensor_mm > 0)) fail("lens_to_sensor_mm", "must be > 0");
  if (!(sys.working_distance_mm >= 0)) fail("working_distance_mm", "must be >= 0");
  for (size_t i = 0; i < sys.lenslets.size(); ++i) {
    const auto& l = sys.lenslets[i];
    std::string at = "lenslets[" + std::to_string(i) + "]";
    if (!(l.diameter_mm > 0)) fail(at + ".diameter_mm", "must be > 0");
    if (!(l.focal_mm > 0)) fail(at + ".focal_mm", "must be > 0");
    if (std::abs(l.x_mm) > 0.5 * sys.sensor_width_mm() || std::abs(l.y_mm) > 0.5 * sys.sensor_height_mm())
      fail(at, "centre (" + std::to_string(l.x_mm) + ", " + std::to_string(l.y_mm) + ") mm lies off the sensor");
    check_tilt(at + ".tilt_x_deg", l.tilt_x_deg);
    check_tilt(at + ".tilt_y_deg", l.tilt_y_deg);
    if (sys.lens_model == LensModel::real) {
      double r = sys.curvature_radius_mm(i);
      if (r < 0.5 * l.diameter_mm)
        fail(at, "a plano-convex lens of diameter " + std::to_string(l.diameter_mm) + " mm cannot have f = " +
                     std::to_string(l.focal_mm) + " mm with n = " + std::to_string(sys.glass_index) +
                     " (R = f (n - 1) = " + std::to_string(r) + " mm is smaller than the aperture radius); use lens_model thin");
      if (sys.center_thickness_mm(i) >= sys.lens_to_sensor_mm) fail(at, "lens is thicker than the lens-to-sensor distance");
    }
    for (size_t j = 0; j < i; ++j) {
      const auto& m = sys.lenslets[j];
      double d = std::hypot(l.x_mm - m.x_mm, l.y_mm - m.y_mm);
      if (d < 0.5 * (l.diameter_mm + m.diameter_mm) - 1e-9)
        fail(at, "overlaps lenslets[" + std::to_string(j) + "] (centres " + std::to_string(d) + " mm apart)");
    }
  }
  const SensorPose& pose = sys.sensor_pose;
  check_tilt("sensor.tilt_x_deg", pose.tilt_x_deg);
  check_tilt("sensor.tilt_y_deg", pose.tilt_y_deg);
  if (!(std::abs(pose.offset_x_mm) <= 0.5 * sys.sensor_width_mm()))
    fail("sensor.offset_x_mm", "must be within half the sensor's width, got " + std::to_string(pose.offset_x_mm));
  if (!(std::abs(pose.offset_y_mm) <= 0.5 * sys.sensor_height_mm()))
    fail("sensor.offset_y_mm", "must be within half the sensor's height, got " + std::to_string(pose.offset_y_mm));
  const Effects& e = sys.effects;
  if (e.scintillator_refraction && !(e.scintillator_index >= 1.0)) fail("effects.scintillator_refraction.index", "must be >= 1");
  if (e.holder_vignetting && !(e.holder_bore_mm >= 0 && e.holder_bore_mm <= sys.lens_to_sensor_mm))
    fail("effects.holder_vignetting.bore_mm",
         "must be in [0, lens_to_sensor_mm = " + (std::ostringstream() << sys.lens_to_sensor_mm).str() +
             " mm]: the holder ends at the sensor");
  if (!(e.detection_efficiency > 0 && e.detection_efficiency <= 1)) fail("effects.detection_efficiency.value", "must be in (0, 1]");
  if (!(e.dark_counts_per_pixel >= 0)) fail("effects.dark_counts.per_pixel", "must be >= 0");
  if (e.source_extent && !(e.source_sigma_mm > 0)) fail("effects.source_extent.sigma_mm", "must be > 0");
  if (e.diffraction && !(e.wavelength_nm > 0 && e.wavelength_nm < 1e5))
    fail("effects.diffraction.wavelength_nm", "must be in (0, 100000) nm");
}

}  // namespace prism
