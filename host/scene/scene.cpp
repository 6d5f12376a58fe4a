#include "host/scene/scene.h"

#include <cmath>
#include <cstdlib>
#include <fstream>
#include <map>
#include <sstream>
#include <tuple>

#include "host/util/format.h"
#include "host/util/json_file.h"

namespace prism {

namespace {

using json = nlohmann::json;

// The prototype's 42 lenslets (DESIGN.md): focal index (column + 3 row) mod 7,
// or all of one focal length.
std::vector<LensletGeometry> hex_array(double focal_or_zero) {
  auto out = hex_positions(defaults::lenslet_rows, defaults::lenslet_columns, defaults::lenslet_pitch_mm);
  for (int row = 0; row < defaults::lenslet_rows; ++row)
    for (int col = 0; col < defaults::lenslet_columns; ++col)
      out[size_t(row * defaults::lenslet_columns + col)].focal_mm =
          focal_or_zero > 0 ? focal_or_zero : defaults::focal_lengths_mm[(col + 3 * row) % 7];
  return out;
}

Scene base_scene(std::string name) {
  Scene s;
  s.name = std::move(name);
  return s;
}

// Field readers that name the field on error.
struct Reader {
  const std::string& origin;
  [[noreturn]] void fail(const std::string& field, const std::string& why) const {
    throw SceneError("scene " + origin + ": " + field + ": " + why);
  }
  std::string text(const json& j, const std::string& key, const std::string& fallback) const {
    if (!j.contains(key)) return fallback;
    if (!j[key].is_string()) fail(key, "must be a string, got " + j[key].dump());
    return j[key].get<std::string>();
  }
  double number(const json& j, const std::string& key, const std::string& path, double fallback, bool required = false) const {
    if (!j.contains(key)) {
      if (required) fail(path + key, "is required");
      return fallback;
    }
    if (!j[key].is_number()) fail(path + key, "must be a number, got " + j[key].dump());
    double v = j[key].get<double>();
    if (!std::isfinite(v)) fail(path + key, "must be finite");
    return v;
  }
  std::pair<double, double> range(const json& j, const std::string& key, const std::string& path,
                                  std::pair<double, double> fallback) const {
    if (!j.contains(key)) return fallback;
    const json& r = j[key];
    if (!r.is_array() || r.size() != 2 || !r[0].is_number() || !r[1].is_number())
      fail(path + key, "must be [min, max] in mm, got " + r.dump());
    if (!(r[0].get<double>() < r[1].get<double>())) fail(path + key, "min must be below max");
    return {r[0].get<double>(), r[1].get<double>()};
  }
};

void check_keys(const Reader& rd, const json& j, const std::string& path, std::initializer_list<const char*> allowed) {
  const std::string list = join(allowed);
  if (!j.is_object()) {
    const std::string field = path.empty() ? "(top level)" : path.substr(0, path.size() - 1);  // "sensor." -> "sensor"
    rd.fail(field, "must be an object with the fields " + list + ", got " + j.dump());
  }
  for (auto it = j.begin(); it != j.end(); ++it) {
    bool ok = false;
    for (const char* a : allowed) ok = ok || it.key() == a;
    if (!ok) {
      rd.fail(path + it.key(), "unknown field (expected one of: " + list + ")");
    }
  }
}

LensModel parse_lens_model(const Reader& rd, const json& v, const std::string& field) {
  if (v == "thin") return LensModel::thin;
  if (v == "real") return LensModel::real;
  rd.fail(field, "must be \"thin\" or \"real\", got " + v.dump());
}

}  // namespace

std::vector<LensletGeometry> hex_positions(int rows, int columns, double pitch_mm) {
  std::vector<LensletGeometry> out;
  double cx = 0, cy = 0;
  for (int row = 0; row < rows; ++row)
    for (int col = 0; col < columns; ++col) {
      LensletGeometry l;
      l.x_mm = pitch_mm * (col + (row % 2 ? 0.5 : 0.0));
      l.y_mm = pitch_mm * std::sqrt(3.0) / 2.0 * row;
      l.focal_mm = 0;
      cx += l.x_mm;
      cy += l.y_mm;
      out.push_back(l);
    }
  for (auto& l : out) {
    l.x_mm -= cx / double(out.size());
    l.y_mm -= cy / double(out.size());
  }
  return out;
}

OpticalSystem synthetic_as_built(const OpticalSystem& nominal) {
  OpticalSystem s = nominal;
  for (size_t i = 0; i < s.lenslets.size(); ++i) {
    const double k = double(i) + 1;
    auto& l = s.lenslets[i];
    l.x_mm += 0.04 * std::sin(1.7 * k);
    l.y_mm += 0.03 * std::cos(2.3 * k);
    l.focal_mm *= 1 + 0.02 * std::sin(0.9 * k + 0.4);
    l.tilt_x_deg = 0.5 * std::sin(1.3 * k + 1);
    l.tilt_y_deg = -0.4 * std::cos(0.7 * k);
  }
  s.lens_to_sensor_mm += 0.15;
  s.working_distance_mm -= 0.1;
  s.sensor_pose = {0.03, -0.02, 0.3, -0.2};
  return s;
}

std::vector<std::string> builtin_scene_names() {
  return {"prototype", "prototype-as-built", "unifocal-f3", "unifocal-f9", "unifocal-f15", "single-f3", "single-f9", "single-f15"};
}

Scene builtin_scene(const std::string& name) {
  Scene s = base_scene(name);
  if (name == "prototype") {
    s.optics.lenslets = hex_array(0);
  } else if (name == "prototype-as-built") {
    s.optics.lenslets = hex_array(0);
    s.optics = synthetic_as_built(s.optics);
  } else if (name.rfind("unifocal-f", 0) == 0 || name.rfind("single-f", 0) == 0) {
    bool single = name[0] == 's';
    const std::string digits = name.substr(name.find("-f") + 2);
    char* end = nullptr;
    const double f = std::strtod(digits.c_str(), &end);
    if (digits.empty() || *end != '\0') throw SceneError("unknown built-in scene '" + name + "'");
    if (f != 3 && f != 9 && f != 15) throw SceneError("unknown built-in scene '" + name + "'");
    if (single) {
      // Ideal thin lens on the axis with the array's total aperture area:
      // diameter 3 sqrt(42) mm (paper Sec. II.A: a theoretical reference; no
      // plano-convex lens of that diameter reaches these focal lengths).
      LensletGeometry l;
      l.diameter_mm = defaults::lenslet_diameter_mm * std::sqrt(double(defaults::lenslet_rows * defaults::lenslet_columns));
      l.focal_mm = f;
      s.optics.lenslets = {l};
      s.optics.lens_model = LensModel::thin;
    } else {
      s.optics.lenslets = hex_array(f);
    }
  } else {
    throw SceneError("unknown scene '" + name + "': not a built-in (" + join(builtin_scene_names(), " ") + ") nor a readable file");
  }
  return s;
}

Scene parse_scene(const json& j, const std::string& origin) {
  Reader rd{origin};
  if (!j.is_object()) rd.fail("(top level)", "a scene is a JSON object");
  check_keys(rd, j, "", {"name", "base", "lens_model", "glass", "lenslets", "sensor", "lens_to_sensor_mm",
                         "working_distance_mm", "volume", "photons_emitted", "effects"});
  Scene s = j.contains("base") ? builtin_scene(j["base"].get<std::string>()) : base_scene("");
  s.name = rd.text(j, "name", s.name.empty() ? origin : s.name);
  OpticalSystem& o = s.optics;
  if (j.contains("lens_model")) o.lens_model = parse_lens_model(rd, j["lens_model"], "lens_model");
  if (j.contains("glass")) {
    check_keys(rd, j["glass"], "glass.", {"index", "edge_thickness_mm", "curved_face"});
    if (j["glass"].contains("curved_face")) {
      const json& cf = j["glass"]["curved_face"];
      if (cf != "source" && cf != "sensor") rd.fail("glass.curved_face", "must be \"source\" or \"sensor\", got " + cf.dump());
      o.curved_toward_sensor = cf == "sensor";
    }
    o.glass_index = rd.number(j["glass"], "index", "glass.", o.glass_index);
    o.edge_thickness_mm = rd.number(j["glass"], "edge_thickness_mm", "glass.", o.edge_thickness_mm);
  }
  if (j.contains("lenslets")) {
    const json& ls = j["lenslets"];
    if (!ls.is_array())
      rd.fail("lenslets", "must be an array of {x_mm, y_mm, diameter_mm, focal_mm} (as built also tilt_x_deg, tilt_y_deg)");
    o.lenslets.clear();
    for (size_t i = 0; i < ls.size(); ++i) {
      std::string path = "lenslets[" + std::to_string(i) + "].";
      if (!ls[i].is_object()) rd.fail(path.substr(0, path.size() - 1), "must be an object");
      check_keys(rd, ls[i], path, {"x_mm", "y_mm", "diameter_mm", "focal_mm", "tilt_x_deg", "tilt_y_deg"});
      LensletGeometry l;
      l.x_mm = rd.number(ls[i], "x_mm", path, 0, true);
      l.y_mm = rd.number(ls[i], "y_mm", path, 0, true);
      l.diameter_mm = rd.number(ls[i], "diameter_mm", path, defaults::lenslet_diameter_mm);
      l.focal_mm = rd.number(ls[i], "focal_mm", path, 0, true);
      l.tilt_x_deg = rd.number(ls[i], "tilt_x_deg", path, 0);
      l.tilt_y_deg = rd.number(ls[i], "tilt_y_deg", path, 0);
      o.lenslets.push_back(l);
    }
  }
  if (j.contains("sensor")) {
    const json& sj = j["sensor"];
    check_keys(rd, sj, "sensor.", {"width_px", "height_px", "pixel_um", "offset_x_mm", "offset_y_mm", "tilt_x_deg", "tilt_y_deg"});
    // Sizes bounded before anything is allocated for them: a full-resolution
    // image holds 16 bytes per pixel (value and three derivatives).
    auto side = [&](const char* key, int current) {
      const double v = rd.number(sj, key, "sensor.", current);
      if (!(v >= 1 && v <= max_sensor_side_px) || v != std::floor(v))
        rd.fail(std::string("sensor.") + key,
                "must be a whole number of pixels from 1 to " + std::to_string(max_sensor_side_px) + ", got " +
                    format_number(v));
      return int(v);
    };
    o.sensor_width_px = side("width_px", o.sensor_width_px);
    o.sensor_height_px = side("height_px", o.sensor_height_px);
    if (double(o.sensor_width_px) * o.sensor_height_px > double(max_sensor_pixels))
      rd.fail("sensor", std::to_string(o.sensor_width_px) + " x " + std::to_string(o.sensor_height_px) +
                            " px is more than " + format_number(double(max_sensor_pixels)) +
                            " pixels (the prototype's has 3.2e7); bin them, e.g. twice the pixel_um at half the size");
    o.pixel_um = rd.number(sj, "pixel_um", "sensor.", o.pixel_um);
    SensorPose& pose = o.sensor_pose;
    pose.offset_x_mm = rd.number(sj, "offset_x_mm", "sensor.", pose.offset_x_mm);
    pose.offset_y_mm = rd.number(sj, "offset_y_mm", "sensor.", pose.offset_y_mm);
    pose.tilt_x_deg = rd.number(sj, "tilt_x_deg", "sensor.", pose.tilt_x_deg);
    pose.tilt_y_deg = rd.number(sj, "tilt_y_deg", "sensor.", pose.tilt_y_deg);
  }
  o.lens_to_sensor_mm = rd.number(j, "lens_to_sensor_mm", "", o.lens_to_sensor_mm);
  o.working_distance_mm = rd.number(j, "working_distance_mm", "", o.working_distance_mm);
  s.photons_emitted = rd.number(j, "photons_emitted", "", s.photons_emitted);
  if (!(s.photons_emitted > 0 && s.photons_emitted <= defaults::max_photons_emitted))
    rd.fail("photons_emitted", "must be in (0, " + format_number(defaults::max_photons_emitted) + "]");
  if (j.contains("volume")) {
    const json& v = j["volume"];
    check_keys(rd, v, "volume.", {"x_mm", "y_mm", "depth_mm"});
    std::tie(s.volume.x_min_mm, s.volume.x_max_mm) = rd.range(v, "x_mm", "volume.", {s.volume.x_min_mm, s.volume.x_max_mm});
    std::tie(s.volume.y_min_mm, s.volume.y_max_mm) = rd.range(v, "y_mm", "volume.", {s.volume.y_min_mm, s.volume.y_max_mm});
    std::tie(s.volume.depth_min_mm, s.volume.depth_max_mm) =
        rd.range(v, "depth_mm", "volume.", {s.volume.depth_min_mm, s.volume.depth_max_mm});
  }
  if (!o.in_front(s.volume.depth_min_mm))
    rd.fail("volume.depth_mm", "starts at " + format_number(s.volume.depth_min_mm) +
                                   " mm, not in front of the lenses, which lie working_distance_mm = " +
                                   format_number(o.working_distance_mm) + " mm before the scintillator face");
  if (j.contains("effects")) {
    const json& es = j["effects"];
    if (!es.is_array()) rd.fail("effects", "must be a list of effect names or {\"name\": ..., parameters}");
    std::map<std::string, size_t> seen;  // each effect once: a second one's parameters would silently win
    for (size_t i = 0; i < es.size(); ++i) {
      std::string path = "effects[" + std::to_string(i) + "]";
      json e = es[i].is_string() ? json{{"name", es[i]}} : es[i];
      if (!e.is_object() || !e.contains("name") || !e["name"].is_string())
        rd.fail(path, "must be a name or an object with \"name\"");
      std::string name = e["name"];
      if (auto [first, fresh] = seen.emplace(name, i); !fresh)
        rd.fail(path + ".name", "'" + name + "' is given twice (also effects[" + std::to_string(first->second) +
                                    "]); give each effect once");
      path += "." ;
      Effects& fx = o.effects;
      if (name == "scintillator_refraction") {
        check_keys(rd, e, path, {"name", "index"});
        fx.scintillator_refraction = true;
        fx.scintillator_index = rd.number(e, "index", path, fx.scintillator_index);
      } else if (name == "holder_vignetting") {
        check_keys(rd, e, path, {"name", "bore_mm"});
        fx.holder_vignetting = true;
        fx.holder_bore_mm = rd.number(e, "bore_mm", path, fx.holder_bore_mm);
      } else if (name == "detection_efficiency") {
        check_keys(rd, e, path, {"name", "value"});
        fx.detection_efficiency = rd.number(e, "value", path, 0, true);
      } else if (name == "dark_counts") {
        check_keys(rd, e, path, {"name", "per_pixel"});
        fx.dark_counts_per_pixel = rd.number(e, "per_pixel", path, 0, true);
      } else if (name == "source_extent") {
        check_keys(rd, e, path, {"name", "sigma_mm"});
        fx.source_extent = true;
        fx.source_sigma_mm = rd.number(e, "sigma_mm", path, fx.source_sigma_mm);
      } else if (name == "diffraction") {
        check_keys(rd, e, path, {"name", "wavelength_nm"});
        fx.diffraction = true;
        fx.wavelength_nm = rd.number(e, "wavelength_nm", path, fx.wavelength_nm);
      } else {
        rd.fail(path + "name", "unknown effect '" + name +
                                   "' (known: scintillator_refraction, holder_vignetting, detection_efficiency, "
                                   "dark_counts, source_extent, diffraction)");
      }
    }
  }
  try {
    validate(o);
  } catch (const std::invalid_argument& e) {
    throw SceneError("scene " + origin + ": " + e.what());
  }
  return s;
}

Scene load_scene(const std::string& name_or_path) {
  for (const auto& n : builtin_scene_names())
    if (n == name_or_path) return builtin_scene(n);
  std::ifstream in(name_or_path);
  if (!in) return builtin_scene(name_or_path);  // throws, listing the built-ins
  json j;
  try {
    j = parse_json_file(in);
  } catch (const JsonDuplicateKey& e) {
    throw SceneError("scene " + name_or_path + ": " + e.what());
  } catch (const JsonSyntaxError& e) {
    // FILE:LINE first, as compilers write it, for editors to jump to.
    std::ifstream again(name_or_path);
    std::string text((std::istreambuf_iterator<char>(again)), {});
    size_t line = 1 + std::count(text.begin(), text.begin() + std::min(text.size(), e.byte), '\n');
    throw SceneError("scene " + name_or_path + ":" + std::to_string(line) + ": not valid JSON (" + e.what() + ")");
  }
  return parse_scene(j, name_or_path);
}

json to_json(const Scene& s) {
  const OpticalSystem& o = s.optics;
  json ls = json::array();
  for (const auto& l : o.lenslets) {
    ls.push_back({{"x_mm", l.x_mm}, {"y_mm", l.y_mm}, {"diameter_mm", l.diameter_mm}, {"focal_mm", l.focal_mm}});
    // As-built fields only where they are not nominal: a nominal scene's
    // JSON (and so a dictionary's manifest) is what it was before them.
    if (l.tilt_x_deg != 0 || l.tilt_y_deg != 0) ls.back()["tilt_x_deg"] = l.tilt_x_deg, ls.back()["tilt_y_deg"] = l.tilt_y_deg;
  }
  json sensor = {{"width_px", o.sensor_width_px}, {"height_px", o.sensor_height_px}, {"pixel_um", o.pixel_um}};
  if (!o.sensor_pose.nominal()) {
    sensor["offset_x_mm"] = o.sensor_pose.offset_x_mm;
    sensor["offset_y_mm"] = o.sensor_pose.offset_y_mm;
    sensor["tilt_x_deg"] = o.sensor_pose.tilt_x_deg;
    sensor["tilt_y_deg"] = o.sensor_pose.tilt_y_deg;
  }
  json fx = json::array();
  const Effects& e = o.effects;
  if (e.scintillator_refraction) fx.push_back({{"name", "scintillator_refraction"}, {"index", e.scintillator_index}});
  if (e.holder_vignetting) fx.push_back({{"name", "holder_vignetting"}, {"bore_mm", e.holder_bore_mm}});
  if (e.detection_efficiency != 1.0) fx.push_back({{"name", "detection_efficiency"}, {"value", e.detection_efficiency}});
  if (e.dark_counts_per_pixel != 0.0) fx.push_back({{"name", "dark_counts"}, {"per_pixel", e.dark_counts_per_pixel}});
  if (e.source_extent) fx.push_back({{"name", "source_extent"}, {"sigma_mm", e.source_sigma_mm}});
  if (e.diffraction) fx.push_back({{"name", "diffraction"}, {"wavelength_nm", e.wavelength_nm}});
  return {{"name", s.name},
          {"lens_model", to_string(o.lens_model)},
          {"glass",
           {{"index", o.glass_index},
            {"edge_thickness_mm", o.edge_thickness_mm},
            {"curved_face", o.curved_toward_sensor ? "sensor" : "source"}}},
          {"lenslets", ls},
          {"sensor", sensor},
          {"lens_to_sensor_mm", o.lens_to_sensor_mm},
          {"working_distance_mm", o.working_distance_mm},
          {"volume",
           {{"x_mm", {s.volume.x_min_mm, s.volume.x_max_mm}},
            {"y_mm", {s.volume.y_min_mm, s.volume.y_max_mm}},
            {"depth_mm", {s.volume.depth_min_mm, s.volume.depth_max_mm}}}},
          {"photons_emitted", s.photons_emitted},
          {"effects", fx}};
}

void require_in_front(const Scene& scene, double depth_mm, const std::string& option) {
  const double wd = scene.optics.working_distance_mm;
  if (!scene.optics.in_front(depth_mm))
    throw std::runtime_error(option + ": depth " + format_number(depth_mm) + " mm is not in front of " + scene.name +
                             "'s lenses, which lie " + format_number(wd) +
                             " mm before the scintillator face: give a depth > " + format_number(-wd) + " mm");
}

void require_in_volume(const Scene& scene, double x_mm, double y_mm, double depth_mm, const std::string& option) {
  const Volume& v = scene.volume;
  for (const auto& [name, value, lo, hi] : {std::tuple{"x", x_mm, v.x_min_mm, v.x_max_mm},
                                            {"y", y_mm, v.y_min_mm, v.y_max_mm},
                                            {"depth", depth_mm, v.depth_min_mm, v.depth_max_mm}})
    if (!(value >= lo && value <= hi))
      throw std::runtime_error(option + ": " + name + " " + format_number(value) + " mm lies outside " + scene.name +
                               "'s volume (" + name + " " + format_number(lo) + ".." + format_number(hi) +
                               " mm), where events happen; move the vertex or widen the scene file's \"volume\"");
}

TraceSettings trace_settings(const Scene& scene, unsigned binning, unsigned rays, double photons, Splat splat,
                             unsigned stratification, const std::string& estimator) {
  TraceSettings t;
  t.binning = binning;
  t.photons_emitted = photons > 0 ? photons : scene.photons_emitted;
  t.splat = splat;
  t.stratification = stratification;
  t.rays_per_lenslet = rays ? rays : TraceSettings::default_rays(splat);
  if (estimator == "auto") t.estimator = TraceSettings::default_estimator(splat);
  else if (estimator == "naive" || estimator == "split")
    t.estimator = estimator == "naive" ? FisherEstimator::naive : FisherEstimator::split;
  else throw std::invalid_argument("estimator '" + estimator + "': use auto, split or naive");
  return t;
}

void override_lens_model(Scene& scene, const std::string& lens_model, const std::string& option) {
  if (lens_model.empty()) return;
  if (lens_model != "thin" && lens_model != "real")
    throw std::invalid_argument(option + " '" + lens_model + "': use thin or real");
  scene.optics.lens_model = lens_model == "real" ? LensModel::real : LensModel::thin;
  try {
    validate(scene.optics);
  } catch (const std::invalid_argument& e) {
    throw std::runtime_error("scene " + scene.name + " with " + option + " " + lens_model + ": " + e.what());
  }
}

}  // namespace prism
