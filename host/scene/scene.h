// Scenes: an optical design plus the volume and the source, from a built-in
// name or a JSON file (schema in README.md, "Scene files").
#pragma once
#include <stdexcept>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "engine/optical_system.h"

namespace prism {

struct Volume {
  double x_min_mm = -defaults::volume_half_width_mm, x_max_mm = defaults::volume_half_width_mm;
  double y_min_mm = -defaults::volume_half_width_mm, y_max_mm = defaults::volume_half_width_mm;
  double depth_min_mm = 0, depth_max_mm = defaults::volume_depth_mm;
};

// A scene file's sensor is refused beyond these (checked before any image
// is allocated): the prototype's SVS-SHR661 has 6696 x 4764 = 3.2e7 pixels.
inline constexpr int max_sensor_side_px = 65536;
inline constexpr double max_sensor_pixels = 268435456;  // 2^28: 4 GiB as a full-resolution image

struct Scene {
  std::string name;
  OpticalSystem optics;
  Volume volume;
  double photons_emitted = defaults::photons_emitted;
};

// A scene that cannot be used; the message names the file and the field.
struct SceneError : std::runtime_error {
  using std::runtime_error::runtime_error;
};

// Lenslet centres on a hex grid as the prototype's (DESIGN.md): odd rows
// shifted by half a pitch, rows pitch sqrt(3)/2 apart, centroid on the axis.
// Focal lengths are left 0 for the caller to assign.
std::vector<LensletGeometry> hex_positions(int rows, int columns, double pitch_mm);

// `nominal` as built, by known amounts, for calibration's tests and the
// built-in "prototype-as-built" (issue 18): lenslet i (k = i + 1) moved by
// (40 sin 1.7k, 30 cos 2.3k) um, its focal length off by 2% sin(0.9k + 0.4),
// tilted (0.5 sin(1.3k + 1), -0.4 cos 0.7k) degrees; the sensor 0.15 mm
// farther, moved by (30, -20) um and tilted (0.3, -0.2) degrees; the
// scintillator face 0.1 mm nearer.
OpticalSystem synthetic_as_built(const OpticalSystem& nominal);

std::vector<std::string> builtin_scene_names();
Scene builtin_scene(const std::string& name);
// A built-in name, or the path of a JSON scene file.
Scene load_scene(const std::string& name_or_path);
Scene parse_scene(const nlohmann::json& j, const std::string& origin);
nlohmann::json to_json(const Scene& s);

// The forward model's settings from the knobs that `prism crlb`, `psf`, `simulate`
// and the Python module take by the same names: 0 rays, the splat's
// converged default; 0 photons, the scene's own; estimator "auto", the
// splat's default ("split" or "naive" otherwise).
TraceSettings trace_settings(const Scene& scene, unsigned binning, unsigned rays, double photons, Splat splat,
                             unsigned stratification, const std::string& estimator);
// The scene's lens model replaced by "thin" or "real" (empty: left as it is)
// and validated; an error names the scene and `option`.
void override_lens_model(Scene& scene, const std::string& lens_model, const std::string& option);

// A source must be in front of the lenses: depth (from the scintillator face)
// > -working distance. Throws naming the option and the scene's limit.
void require_in_front(const Scene& scene, double depth_mm, const std::string& option);
// Throws naming `option` unless (x, y, depth) lies in the scene's volume
// (the scintillator, where events happen).
void require_in_volume(const Scene& scene, double x_mm, double y_mm, double depth_mm, const std::string& option);

}  // namespace prism
