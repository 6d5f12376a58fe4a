#include "host/sweep/sweep.h"

#include <fcntl.h>
#include <unistd.h>

#include <algorithm>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <sstream>

#include "engine/forward.h"
#include "host/util/image_io.h"
#include "host/util/format.h"

namespace prism {

using json = nlohmann::json;

namespace {

// Portable draws: std::uniform_int_distribution and std::shuffle differ
// between standard libraries, and the same seed must give the same sweep.
size_t pick(std::mt19937_64& rng, size_t n) { return size_t(rng() % n); }
template <class T> void shuffle(std::vector<T>& v, std::mt19937_64& rng) {
  for (size_t i = v.size(); i > 1; --i) std::swap(v[i - 1], v[pick(rng, i)]);
}


// Which values get one extra use when n positions share k values unevenly.
std::vector<int> balanced_counts(size_t n, size_t k, const std::vector<size_t>& extra) {
  std::vector<int> c(k, int(n / k));
  for (size_t e : extra) ++c[e];
  return c;
}

std::vector<int> multiset(const std::vector<int>& counts) {
  std::vector<int> v;
  for (size_t i = 0; i < counts.size(); ++i) v.insert(v.end(), size_t(counts[i]), int(i));
  return v;
}

bool is_balanced(const std::vector<int>& genes, size_t k) {
  std::vector<int> c(k, 0);
  for (int g : genes) ++c[size_t(g)];
  auto [lo, hi] = std::minmax_element(c.begin(), c.end());
  return *hi - *lo <= 1;
}

// Mixed-radix counter: false once it wraps around.
bool next_odometer(std::vector<int>& v, int radix) {
  for (auto& d : v) {
    if (++d < radix) return true;
    d = 0;
  }
  return false;
}

bool same_effects(const Effects& a, const Effects& b) {
  return a.scintillator_refraction == b.scintillator_refraction && a.scintillator_index == b.scintillator_index &&
         a.holder_vignetting == b.holder_vignetting && a.holder_bore_mm == b.holder_bore_mm &&
         a.detection_efficiency == b.detection_efficiency && a.dark_counts_per_pixel == b.dark_counts_per_pixel;
}

std::string effects_label(const Effects& e) {
  std::string s;
  auto add = [&](bool on, const std::string& n) {
    if (on) s += (s.empty() ? "" : "+") + n;
  };
  add(e.scintillator_refraction, "scintillator_refraction");
  add(e.holder_vignetting, "holder_vignetting");
  add(e.detection_efficiency != 1.0, "detection_efficiency=" + format_number(e.detection_efficiency));
  add(e.dark_counts_per_pixel != 0.0, "dark_counts=" + format_number(e.dark_counts_per_pixel));
  return s.empty() ? "none" : s;
}

int find_index(const std::vector<double>& set, double v) {
  for (size_t i = 0; i < set.size(); ++i)
    if (std::abs(set[i] - v) <= 1e-9 * std::max(1.0, std::abs(v))) return int(i);
  return -1;
}

// Field readers for the space file; errors name the file and the field.
struct SpaceReader {
  const std::string& origin;
  [[noreturn]] void fail(const std::string& field, const std::string& why) const {
    throw SweepError("space " + origin + ": " + field + ": " + why);
  }
  // A number or a non-empty list of numbers, each > 0 (>= 0 when zero_ok).
  std::vector<double> numbers(const json& j, const std::string& field, bool zero_ok = false) const {
    json list = j.is_array() ? j : json::array({j});
    if (list.empty()) fail(field, "must list at least one value");
    std::vector<double> out;
    for (const auto& v : list) {
      if (!v.is_number()) fail(field, "must be a number or a list of numbers, got " + v.dump());
      double x = v.get<double>();
      if (!std::isfinite(x) || x < 0 || (!zero_ok && x == 0)) fail(field, std::string("values must be ") + (zero_ok ? ">= 0" : "> 0") + ", got " + v.dump());
      if (find_index(out, x) >= 0) fail(field, "lists " + v.dump() + " twice");
      out.push_back(x);
    }
    return out;
  }
  int count(const json& j, const std::string& field) const {
    if (!j.is_number_integer() || j.get<int>() < 1) fail(field, "must be a whole number >= 1, got " + j.dump());
    return j.get<int>();
  }
  void keys(const json& j, const std::string& path, std::initializer_list<const char*> allowed) const {
    for (auto it = j.begin(); it != j.end(); ++it) {
      if (std::none_of(allowed.begin(), allowed.end(), [&](const char* a) { return it.key() == a; })) {
        std::string list;
        for (const char* a : allowed) list += std::string(list.empty() ? "" : ", ") + a;
        fail(path + it.key(), "unknown field (expected one of: " + list + ")");
      }
    }
  }
};

double log_factorial(double n) { return std::lgamma(n + 1.0); }

}  // namespace

// ---- Sample grid -------------------------------------------------------------

std::vector<glm::dvec3> SampleGrid::positions() const {
  std::vector<glm::dvec3> p;
  for (double d : depth_mm)
    for (double y : y_mm)
      for (double x : x_mm) p.push_back({x, y, d});
  return p;
}

std::string SampleGrid::describe() const {
  auto list = [](const std::vector<double>& v) {
    std::string s;
    for (double x : v) s += (s.empty() ? "" : ",") + format_number(x);
    return s;
  };
  return std::to_string(x_mm.size() * y_mm.size() * depth_mm.size()) + " sources: x_mm {" + list(x_mm) + "} x y_mm {" +
         list(y_mm) + "} x depth_mm {" + list(depth_mm) + "}";
}

SampleGrid SampleGrid::of(const Volume& v, int lateral, int depth) {
  // Lateral: evenly over the middle 40% of the width (x, y in [-10, 10] mm for
  // the prototype's volume). Nearer the edge, near sources image through few
  // lenses onto the sensor and the prototype's Fisher matrix is singular at
  // 4096 rays (x = y = 15 mm, depth 2.5 and 7.5 mm): every design would score inf.
  auto inner = [](double lo, double hi, int n) {
    std::vector<double> out;
    for (int i = 0; i < n; ++i) out.push_back(n == 1 ? 0.5 * (lo + hi) : lo + (hi - lo) * (0.3 + 0.4 * i / (n - 1)));
    return out;
  };
  SampleGrid g;
  g.x_mm = inner(v.x_min_mm, v.x_max_mm, lateral);
  g.y_mm = inner(v.y_min_mm, v.y_max_mm, lateral);
  for (int i = 0; i < depth; ++i)
    g.depth_mm.push_back(v.depth_min_mm + (v.depth_max_mm - v.depth_min_mm) * (i + 0.5) / depth);
  return g;
}

// ---- Objectives and bounds --------------------------------------------------

const std::vector<std::string>& objective_names() {
  static const std::vector<std::string> names{"mean_crlb_3d", "worst_crlb_3d", "mean_crlb_x", "mean_crlb_y",
                                              "mean_crlb_z",  "photons",       "depth_ratio"};
  return names;
}

bool objective_is_maximised(const std::string& name) { return name == "photons"; }

double objective_value(const Objectives& o, const std::string& name) {
  if (name == "mean_crlb_3d") return o.mean_crlb_3d_mm;
  if (name == "worst_crlb_3d") return o.worst_crlb_3d_mm;
  if (name == "mean_crlb_x") return o.mean_crlb_x_mm;
  if (name == "mean_crlb_y") return o.mean_crlb_y_mm;
  if (name == "mean_crlb_z") return o.mean_crlb_z_mm;
  if (name == "photons") return o.mean_photons;
  if (name == "depth_ratio") return o.depth_ratio;
  std::string list;
  for (const auto& n : objective_names()) list += (list.empty() ? "" : ", ") + n;
  throw SweepError("unknown objective '" + name + "' (known: " + list + ")");
}

bool Bound::holds(const Objectives& o) const {
  double v = objective_value(o, objective);
  return at_least ? v >= value : v <= value;
}

std::string Bound::text() const { return objective + (at_least ? ">=" : "<=") + format_number(value); }

Bound parse_bound(const std::string& text) {
  size_t at = text.find(">=");
  bool at_least = at != std::string::npos;
  if (!at_least) at = text.find("<=");
  if (at == std::string::npos) throw SweepError("--bound '" + text + "': write NAME>=VALUE or NAME<=VALUE, e.g. photons>=100");
  Bound b{text.substr(0, at), at_least, 0};
  objective_value(Objectives{}, b.objective);  // throws, listing the names
  try {
    size_t used = 0;
    b.value = std::stod(text.substr(at + 2), &used);
    if (used != text.size() - at - 2) throw std::invalid_argument(text);
  } catch (const std::exception&) {
    throw SweepError("--bound '" + text + "': '" + text.substr(at + 2) + "' is not a number");
  }
  return b;
}

// ---- Designs ----------------------------------------------------------------

std::string Design::key() const {
  // One character per gene: '0' + index (the space's lists are short).
  std::string k = "L" + std::to_string(layout) + " f";
  for (int g : focal) k += char('0' + g);
  k += " d";
  for (int g : diameter) k += char('0' + g);
  k += " s" + std::to_string(lens_to_sensor) + " w" + std::to_string(working_distance) + " m" +
       std::to_string(lens_model) + " e" + std::to_string(effects);
  return k;
}

json Design::to_json() const {
  return {{"layout", layout}, {"focal", focal}, {"diameter", diameter}, {"lens_to_sensor", lens_to_sensor},
          {"working_distance", working_distance}, {"lens_model", lens_model}, {"effects", effects}};
}

Design Design::from_json(const json& j) {
  Design d;
  d.layout = j.at("layout");
  d.focal = j.at("focal").get<std::vector<int>>();
  d.diameter = j.at("diameter").get<std::vector<int>>();
  d.lens_to_sensor = j.at("lens_to_sensor");
  d.working_distance = j.at("working_distance");
  d.lens_model = j.at("lens_model");
  d.effects = j.at("effects");
  return d;
}

// ---- Design space -----------------------------------------------------------

DesignSpace DesignSpace::load(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw SweepError("space " + path + ": cannot read the file");
  json j;
  try {
    j = json::parse(in);
  } catch (const json::parse_error& e) {
    throw SweepError("space " + path + ": not valid JSON (" + e.what() + ")");
  }
  return parse(j, path, std::filesystem::path(path).parent_path().string());
}

DesignSpace DesignSpace::parse(const json& j, const std::string& origin, const std::string& dir) {
  SpaceReader rd{origin};
  if (!j.is_object()) rd.fail("(top level)", "a design space is a JSON object");
  rd.keys(j, "", {"name", "base", "layout", "focal_mm", "assignment", "diameter_mm", "lens_to_sensor_mm",
                  "working_distance_mm", "lens_model", "effects", "samples"});
  DesignSpace s;
  s.source = j;
  s.name = j.value("name", std::filesystem::path(origin).stem().string());

  // Base scene: a built-in, or a scene file relative to the space file.
  std::string base = "prototype";
  if (j.contains("base")) {
    if (!j["base"].is_string()) rd.fail("base", "must be a built-in scene name or a scene file path");
    base = j["base"];
  }
  std::string base_path = base;
  if (!std::filesystem::path(base).is_absolute() && std::filesystem::exists(std::filesystem::path(dir) / base))
    base_path = (std::filesystem::path(dir) / base).string();
  try {
    s.base = load_scene(base_path);
  } catch (const SceneError& e) {
    rd.fail("base", e.what());
  }
  const auto& base_lenses = s.base.optics.lenslets;

  if (j.contains("layout")) {
    const json& l = j["layout"];
    if (!l.is_object()) rd.fail("layout", "must be {\"rows\": [...], \"columns\": [...], \"pitch_mm\": [...]}");
    rd.keys(l, "layout.", {"rows", "columns", "pitch_mm"});
    for (const char* k : {"rows", "columns", "pitch_mm"})
      if (!l.contains(k)) rd.fail(std::string("layout.") + k, "is required when layout is given");
    auto rows = rd.numbers(l["rows"], "layout.rows"), cols = rd.numbers(l["columns"], "layout.columns");
    for (double r : rows)
      for (double c : cols) {
        if (r != std::floor(r) || c != std::floor(c)) rd.fail("layout", "rows and columns must be whole numbers");
        for (double p : rd.numbers(l["pitch_mm"], "layout.pitch_mm")) s.layouts.push_back({int(r), int(c), p});
      }
  } else {
    s.layouts.push_back({0, 0, 0});
  }

  if (j.contains("focal_mm")) {
    s.focal_mm = rd.numbers(j["focal_mm"], "focal_mm");
  } else {
    if (j.contains("layout")) rd.fail("focal_mm", "is required when layout is given (the base's focal lengths belong to its own positions)");
    for (const auto& l : base_lenses)
      if (find_index(s.focal_mm, l.focal_mm) < 0) s.focal_mm.push_back(l.focal_mm);
    s.focal_fixed = true;
  }
  std::string assignment = j.value("assignment", std::string("balanced"));
  if (assignment != "balanced" && assignment != "free")
    rd.fail("assignment", "must be \"balanced\" (each focal length equally often, +-1) or \"free\", got " + j["assignment"].dump());
  s.focal_free = assignment == "free";

  if (j.contains("diameter_mm")) {
    s.diameter_mm = rd.numbers(j["diameter_mm"], "diameter_mm");
  } else if (j.contains("layout")) {
    s.diameter_mm = {base_lenses.front().diameter_mm};
  } else {
    for (const auto& l : base_lenses)
      if (find_index(s.diameter_mm, l.diameter_mm) < 0) s.diameter_mm.push_back(l.diameter_mm);
    s.diameter_fixed = true;
  }

  const OpticalSystem& bo = s.base.optics;
  s.lens_to_sensor_mm = j.contains("lens_to_sensor_mm") ? rd.numbers(j["lens_to_sensor_mm"], "lens_to_sensor_mm")
                                                        : std::vector<double>{bo.lens_to_sensor_mm};
  s.working_distance_mm = j.contains("working_distance_mm")
                              ? rd.numbers(j["working_distance_mm"], "working_distance_mm", true)
                              : std::vector<double>{bo.working_distance_mm};
  if (j.contains("lens_model")) {
    json list = j["lens_model"].is_array() ? j["lens_model"] : json::array({j["lens_model"]});
    if (list.empty()) rd.fail("lens_model", "must list at least one of \"thin\", \"real\"");
    for (const auto& m : list) {
      if (m != "thin" && m != "real") rd.fail("lens_model", "must be \"thin\" or \"real\" (or a list of them), got " + m.dump());
      s.lens_models.push_back(m == "thin" ? LensModel::thin : LensModel::real);
    }
  } else {
    s.lens_models = {bo.lens_model};
  }
  if (j.contains("effects")) {
    const json& es = j["effects"];
    if (!es.is_array() || es.empty())
      rd.fail("effects", "must be a list of choices, each a scene's effects list, e.g. [[], [\"scintillator_refraction\"]]");
    for (size_t i = 0; i < es.size(); ++i) {
      if (!es[i].is_array()) rd.fail("effects[" + std::to_string(i) + "]", "must be a list of effects as in a scene file");
      // Parse through the scene reader, so effects mean the same here and in scenes.
      json probe = {{"lens_model", "thin"}, {"lenslets", {{{"x_mm", 0}, {"y_mm", 0}, {"focal_mm", 9}}}}, {"effects", es[i]}};
      try {
        s.effects.push_back(parse_scene(probe, "effects").optics.effects);
      } catch (const SceneError& e) {
        rd.fail("effects[" + std::to_string(i) + "]", e.what());
      }
    }
  } else {
    s.effects = {bo.effects};
  }
  for (const auto& e : s.effects) s.effects_labels.push_back(effects_label(e));

  int lateral = 3, depth = 6;
  s.samples = SampleGrid::of(s.base.volume, lateral, depth);
  if (j.contains("samples")) {
    const json& sj = j["samples"];
    if (!sj.is_object()) rd.fail("samples", "must be {\"lateral\": N, \"depth\": N} and/or explicit x_mm, y_mm, depth_mm lists");
    rd.keys(sj, "samples.", {"lateral", "depth", "x_mm", "y_mm", "depth_mm"});
    if (sj.contains("lateral")) lateral = rd.count(sj["lateral"], "samples.lateral");
    if (sj.contains("depth")) depth = rd.count(sj["depth"], "samples.depth");
    s.samples = SampleGrid::of(s.base.volume, lateral, depth);
    auto coords = [&](const char* k, std::vector<double>& out) {
      if (!sj.contains(k)) return;
      json list = sj[k].is_array() ? sj[k] : json::array({sj[k]});
      out.clear();
      for (const auto& v : list) {
        if (!v.is_number()) rd.fail(std::string("samples.") + k, "must be numbers in mm, got " + v.dump());
        out.push_back(v.get<double>());
      }
      if (out.empty()) rd.fail(std::string("samples.") + k, "must list at least one position");
    };
    coords("x_mm", s.samples.x_mm);
    coords("y_mm", s.samples.y_mm);
    coords("depth_mm", s.samples.depth_mm);
  }

  if (s.focal_fixed || s.diameter_fixed)
    for (size_t l = 0; l < s.layouts.size(); ++l)
      if (s.positions(l).size() != base_lenses.size())
        rd.fail("layout", "has lenses the base does not; give focal_mm and diameter_mm");
  if (!s.focal_fixed && !s.focal_free)
    for (size_t l = 0; l < s.layouts.size(); ++l)
      if (s.positions(l).size() < s.focal_mm.size())
        rd.fail("focal_mm", "a balanced assignment needs at least one lens per focal length (" +
                                std::to_string(s.positions(l).size()) + " positions); use \"assignment\": \"free\"");
  return s;
}

std::vector<LensletGeometry> DesignSpace::positions(size_t layout) const {
  const HexLayout& h = layouts.at(layout);
  if (h.rows == 0) return base.optics.lenslets;
  return hex_positions(h.rows, h.columns, h.pitch_mm);
}

std::vector<int> DesignSpace::base_genes(const std::vector<double>& values, const std::vector<double>& set) const {
  std::vector<int> g;
  for (double v : values) g.push_back(find_index(set, v));
  return g;
}

Scene DesignSpace::scene_of(const Design& d, const std::string& scene_name) const {
  Scene s = base;
  s.name = scene_name;
  OpticalSystem& o = s.optics;
  o.lenslets = positions(d.layout);
  for (size_t i = 0; i < o.lenslets.size(); ++i) {
    o.lenslets[i].focal_mm = focal_mm.at(size_t(d.focal.at(i)));
    o.lenslets[i].diameter_mm = diameter_mm.at(size_t(d.diameter.at(i)));
  }
  o.lens_to_sensor_mm = lens_to_sensor_mm.at(d.lens_to_sensor);
  o.working_distance_mm = working_distance_mm.at(d.working_distance);
  o.lens_model = lens_models.at(d.lens_model);
  o.effects = effects.at(d.effects);
  return s;
}

std::optional<Design> DesignSpace::encode(const Scene& s) const {
  const OpticalSystem& o = s.optics;
  Design d;
  bool found = false;
  for (size_t l = 0; l < layouts.size() && !found; ++l) {
    auto p = positions(l);
    if (p.size() != o.lenslets.size()) continue;
    found = true;
    for (size_t i = 0; i < p.size(); ++i)
      found = found && std::hypot(p[i].x_mm - o.lenslets[i].x_mm, p[i].y_mm - o.lenslets[i].y_mm) < 1e-6;
    if (found) d.layout = l;
  }
  if (!found) return std::nullopt;
  std::vector<double> f, dia;
  for (const auto& l : o.lenslets) {
    f.push_back(l.focal_mm);
    dia.push_back(l.diameter_mm);
  }
  d.focal = base_genes(f, focal_mm);
  d.diameter = base_genes(dia, diameter_mm);
  if (std::count(d.focal.begin(), d.focal.end(), -1) || std::count(d.diameter.begin(), d.diameter.end(), -1))
    return std::nullopt;
  if (!focal_fixed && !focal_free && !is_balanced(d.focal, focal_mm.size())) return std::nullopt;
  int s_i = find_index(lens_to_sensor_mm, o.lens_to_sensor_mm), w_i = find_index(working_distance_mm, o.working_distance_mm);
  auto m = std::find(lens_models.begin(), lens_models.end(), o.lens_model);
  auto e = std::find_if(effects.begin(), effects.end(), [&](const Effects& x) { return same_effects(x, o.effects); });
  if (s_i < 0 || w_i < 0 || m == lens_models.end() || e == effects.end()) return std::nullopt;
  d.lens_to_sensor = size_t(s_i);
  d.working_distance = size_t(w_i);
  d.lens_model = size_t(m - lens_models.begin());
  d.effects = size_t(e - effects.begin());
  return d;
}

double DesignSpace::size() const {
  double scalars = double(lens_to_sensor_mm.size() * working_distance_mm.size() * lens_models.size() * effects.size());
  double total = 0;
  for (size_t l = 0; l < layouts.size(); ++l) {
    double n = double(positions(l).size()), k = double(focal_mm.size());
    double focal = 1;
    if (!focal_fixed && focal_free) focal = std::pow(k, n);
    if (!focal_fixed && !focal_free) {
      // Choose which r values get one extra use, then arrange the multiset.
      double q = std::floor(n / k), r = n - q * k;
      focal = std::exp(log_factorial(k) - log_factorial(r) - log_factorial(k - r) + log_factorial(n) -
                       (k - r) * log_factorial(q) - r * log_factorial(q + 1));
    }
    double dia = diameter_fixed ? 1 : std::pow(double(diameter_mm.size()), n);
    total += focal * dia;
  }
  return std::round(total * scalars);
}

std::vector<Design> DesignSpace::enumerate() const {
  if (size() > 1e6) throw SweepError("space " + name + ": too many designs (" + format_number(size()) + ") to list them all");
  std::vector<Design> out;
  for (size_t l = 0; l < layouts.size(); ++l) {
    size_t n = positions(l).size(), k = focal_mm.size();
    std::vector<std::vector<int>> focals, diameters;
    if (focal_fixed) {
      std::vector<double> f;
      for (const auto& x : base.optics.lenslets) f.push_back(x.focal_mm);
      focals.push_back(base_genes(f, focal_mm));
    } else if (focal_free) {
      std::vector<int> g(n, 0);
      do focals.push_back(g);
      while (next_odometer(g, int(k)));
    } else {
      // Every choice of the r values used once more, then every distinct arrangement.
      size_t r = n % k;
      std::vector<int> chosen(k, 0);
      std::fill(chosen.end() - long(r), chosen.end(), 1);
      do {
        std::vector<size_t> extra;
        for (size_t i = 0; i < k; ++i)
          if (chosen[i]) extra.push_back(i);
        auto g = multiset(balanced_counts(n, k, extra));
        do focals.push_back(g);
        while (std::next_permutation(g.begin(), g.end()));
      } while (std::next_permutation(chosen.begin(), chosen.end()));
    }
    if (diameter_fixed) {
      std::vector<double> dv;
      for (const auto& x : base.optics.lenslets) dv.push_back(x.diameter_mm);
      diameters.push_back(base_genes(dv, diameter_mm));
    } else {
      std::vector<int> g(n, 0);
      do diameters.push_back(g);
      while (next_odometer(g, int(diameter_mm.size())));
    }
    for (const auto& f : focals)
      for (const auto& dia : diameters)
        for (size_t s = 0; s < lens_to_sensor_mm.size(); ++s)
          for (size_t w = 0; w < working_distance_mm.size(); ++w)
            for (size_t m = 0; m < lens_models.size(); ++m)
              for (size_t e = 0; e < effects.size(); ++e) out.push_back({l, f, dia, s, w, m, e});
  }
  return out;
}

Design DesignSpace::random(std::mt19937_64& rng) const { return random_at(pick(rng, layouts.size()), rng); }

Design DesignSpace::random_at(size_t layout, std::mt19937_64& rng) const {
  Design d;
  d.layout = layout;
  size_t n = positions(d.layout).size(), k = focal_mm.size();
  if (focal_fixed) {
    std::vector<double> f;
    for (const auto& x : base.optics.lenslets) f.push_back(x.focal_mm);
    d.focal = base_genes(f, focal_mm);
  } else if (focal_free) {
    for (size_t i = 0; i < n; ++i) d.focal.push_back(int(pick(rng, k)));
  } else {
    std::vector<size_t> values(k);
    for (size_t i = 0; i < k; ++i) values[i] = i;
    shuffle(values, rng);
    values.resize(n % k);
    d.focal = multiset(balanced_counts(n, k, values));
    shuffle(d.focal, rng);
  }
  if (diameter_fixed) {
    std::vector<double> dv;
    for (const auto& x : base.optics.lenslets) dv.push_back(x.diameter_mm);
    d.diameter = base_genes(dv, diameter_mm);
  } else {
    for (size_t i = 0; i < n; ++i) d.diameter.push_back(int(pick(rng, diameter_mm.size())));
  }
  d.lens_to_sensor = pick(rng, lens_to_sensor_mm.size());
  d.working_distance = pick(rng, working_distance_mm.size());
  d.lens_model = pick(rng, lens_models.size());
  d.effects = pick(rng, effects.size());
  return d;
}

Design DesignSpace::neighbour(const Design& parent, std::mt19937_64& rng) const {
  enum Move { focal, diameter, layout, lts, wd, model, fx };
  std::vector<Move> moves;
  if (!focal_fixed && focal_mm.size() > 1) moves.push_back(focal);
  if (!diameter_fixed && diameter_mm.size() > 1) moves.push_back(diameter);
  if (layouts.size() > 1) moves.push_back(layout);
  if (lens_to_sensor_mm.size() > 1) moves.push_back(lts);
  if (working_distance_mm.size() > 1) moves.push_back(wd);
  if (lens_models.size() > 1) moves.push_back(model);
  if (effects.size() > 1) moves.push_back(fx);
  Design d = parent;
  if (moves.empty()) return d;
  auto other = [&](size_t current, size_t n) { return (current + 1 + pick(rng, n - 1)) % n; };
  int count = pick(rng, 3) == 0 ? 2 : 1;  // mostly single moves; pairs to step over a ridge
  for (int m = 0; m < count; ++m) {
    size_t n = d.focal.size();
    switch (moves[pick(rng, moves.size())]) {
      case focal: {
        size_t i = pick(rng, n), j = pick(rng, n);
        if (d.focal[i] != d.focal[j] && pick(rng, 2) == 0) {
          std::swap(d.focal[i], d.focal[j]);  // a swap keeps the balance
        } else {
          int old = d.focal[i];
          d.focal[i] = int(other(size_t(old), focal_mm.size()));
          if (!focal_free && !is_balanced(d.focal, focal_mm.size())) {
            // Changing one value would unbalance the array: swap instead.
            d.focal[i] = old;
            for (int tries = 0; d.focal[i] == d.focal[j] && tries < 64; ++tries) j = pick(rng, n);
            std::swap(d.focal[i], d.focal[j]);
          }
        }
        break;
      }
      case diameter: {
        size_t i = pick(rng, n);
        d.diameter[i] = int(other(size_t(d.diameter[i]), diameter_mm.size()));
        break;
      }
      case layout: {
        // Other positions: keep the genes when the count allows, draw the rest.
        d.layout = other(d.layout, layouts.size());
        Design drawn = random_at(d.layout, rng);
        if (drawn.focal.size() != n) {
          d.focal = drawn.focal;
          d.diameter = drawn.diameter;
        }
        break;
      }
      case lts: d.lens_to_sensor = other(d.lens_to_sensor, lens_to_sensor_mm.size()); break;
      case wd: d.working_distance = other(d.working_distance, working_distance_mm.size()); break;
      case model: d.lens_model = other(d.lens_model, lens_models.size()); break;
      case fx: d.effects = other(d.effects, effects.size()); break;
    }
  }
  return d;
}

std::vector<std::string> DesignSpace::parameter_columns() {
  return {"layout", "lenses", "focal_mm", "diameter_mm", "lens_to_sensor_mm", "working_distance_mm", "lens_model", "effects"};
}

std::vector<std::string> DesignSpace::parameters(const Design& d) const {
  const HexLayout& h = layouts.at(d.layout);
  auto genes = [](const std::vector<int>& g, const std::vector<double>& set) {
    bool uniform = std::adjacent_find(g.begin(), g.end(), std::not_equal_to<>()) == g.end();
    if (uniform && !g.empty()) return format_number(set[size_t(g[0])]);
    std::string s;
    for (int x : g) s += (s.empty() ? "" : ";") + format_number(set[size_t(x)]);
    return s;
  };
  return {h.rows == 0 ? "base" : std::to_string(h.rows) + "x" + std::to_string(h.columns) + "@" + format_number(h.pitch_mm) + "mm",
          std::to_string(d.focal.size()),
          genes(d.focal, focal_mm),
          genes(d.diameter, diameter_mm),
          format_number(lens_to_sensor_mm.at(d.lens_to_sensor)),
          format_number(working_distance_mm.at(d.working_distance)),
          to_string(lens_models.at(d.lens_model)),
          effects_labels.at(d.effects)};
}

// ---- Scoring ----------------------------------------------------------------

namespace {

// The objectives of one design from its CRLB at the grid's positions.
Objectives objectives_of(const std::vector<CrlbRow>& rows, const SampleGrid& grid) {
  Objectives o;
  double n = double(rows.size()), sum3 = 0, sx = 0, sy = 0, sz = 0, photons = 0, worst = 0;
  for (const auto& r : rows) {
    sum3 += r.crlb.r3_mm;
    sx += r.crlb.x_mm;
    sy += r.crlb.y_mm;
    sz += r.crlb.depth_mm;
    photons += r.photons;
    worst = std::max(worst, r.crlb.r3_mm);
  }
  o.mean_crlb_3d_mm = sum3 / n;
  o.worst_crlb_3d_mm = worst;
  o.mean_crlb_x_mm = sx / n;
  o.mean_crlb_y_mm = sy / n;
  o.mean_crlb_z_mm = sz / n;
  o.mean_photons = photons / n;
  size_t per_plane = grid.x_mm.size() * grid.y_mm.size();  // positions() puts depth outermost
  for (size_t p = 0; p < grid.depth_mm.size(); ++p) {
    double s = 0;
    for (size_t i = 0; i < per_plane; ++i) s += rows[p * per_plane + i].crlb.r3_mm;
    o.crlb_3d_by_depth_mm.push_back(s / double(per_plane));
  }
  auto [lo, hi] = std::minmax_element(o.crlb_3d_by_depth_mm.begin(), o.crlb_3d_by_depth_mm.end());
  o.depth_ratio = std::isfinite(*hi) ? *hi / *lo : INFINITY;
  return o;
}

// All scenes at all the grid's positions in one multi-design dispatch.
std::vector<Objectives> score_together(const std::vector<Scene>& scenes, const SampleGrid& grid,
                                       const TraceSettings& settings, vk::Context& ctx) {
  std::vector<OpticalSystem> systems;
  for (const auto& s : scenes) systems.push_back(s.optics);
  ForwardVulkan fw(ctx, systems, settings);
  auto positions = grid.positions();
  std::vector<glm::dvec3> theta;
  std::vector<uint32_t> design_of;
  for (uint32_t d = 0; d < scenes.size(); ++d)
    for (const auto& p : positions) {
      theta.push_back(p);
      design_of.push_back(d);
    }
  auto fisher = fw.fisher(theta, design_of);
  std::vector<Objectives> out;
  for (size_t d = 0; d < scenes.size(); ++d) {
    std::vector<CrlbRow> rows;
    for (size_t i = 0; i < positions.size(); ++i) {
      const FisherResult& f = fisher[d * positions.size() + i];
      rows.push_back({scenes[d].name, scenes[d].optics.lens_model, positions[i], f.photons,
                      crlb_from_fisher(f.poisson, f.photons), settings.rays()});
    }
    out.push_back(objectives_of(rows, grid));
  }
  return out;
}

}  // namespace

Objectives score(const Scene& scene, const SampleGrid& grid, const TraceSettings& settings, Backend backend,
                 vk::Context* ctx) {
  return objectives_of(crlb_study(scene, grid.positions(), settings, backend, SensorModel::poisson, ctx), grid);
}

std::vector<Evaluated> evaluate_designs(const DesignSpace& space, const std::vector<Design>& designs,
                                        const TraceSettings& settings, Backend backend, vk::Context* ctx) {
  std::vector<Evaluated> out(designs.size());
  std::vector<size_t> valid;
  std::vector<Scene> scenes;
  for (size_t i = 0; i < designs.size(); ++i) {
    Evaluated& e = out[i];
    e.design = designs[i];
    e.key = designs[i].key();
    Scene scene = space.scene_of(designs[i], space.name);
    try {
      validate(scene.optics);
    } catch (const std::invalid_argument& err) {
      e.valid = false;
      e.reason = err.what();
      continue;
    }
    valid.push_back(i);
    scenes.push_back(std::move(scene));
  }
  if (valid.empty()) return out;
  auto start = std::chrono::steady_clock::now();
  std::vector<Objectives> scores;
  bool together = backend == Backend::vulkan && scenes.size() > 1;
  if (together) {
    try {
      scores = score_together(scenes, space.samples, settings, *ctx);
    } catch (const std::invalid_argument&) {
      together = false;  // designs that differ in more than their lenslets: one dispatch each
    }
  }
  if (!together)
    for (const auto& scene : scenes) scores.push_back(score(scene, space.samples, settings, backend, ctx));
  double per_design = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count() / double(scenes.size());
  for (size_t k = 0; k < valid.size(); ++k) {
    out[valid[k]].objectives = scores[k];
    out[valid[k]].seconds = per_design;
  }
  return out;
}

Evaluated evaluate_design(const DesignSpace& space, const Design& d, const TraceSettings& settings, Backend backend,
                          vk::Context* ctx) {
  return evaluate_designs(space, {d}, settings, backend, ctx).front();
}

// ---- Sweep ------------------------------------------------------------------

namespace {

// JSON has no infinity: a design with no light somewhere scores "inf".
json num(double v) { return std::isfinite(v) ? json(v) : json(v > 0 ? "inf" : "-inf"); }
double num(const json& j) {
  if (j.is_string()) return j == "inf" ? INFINITY : -INFINITY;
  return j.get<double>();
}

json to_json(const Evaluated& e) {
  json j = {{"key", e.key}, {"design", e.design.to_json()}, {"origin", e.origin}, {"valid", e.valid}};
  if (!e.valid) {
    j["reason"] = e.reason;
    return j;
  }
  const Objectives& o = e.objectives;
  json by_depth = json::array();
  for (double v : o.crlb_3d_by_depth_mm) by_depth.push_back(num(v));
  j["objectives"] = {{"mean_crlb_3d_mm", num(o.mean_crlb_3d_mm)}, {"worst_crlb_3d_mm", num(o.worst_crlb_3d_mm)},
                     {"mean_crlb_x_mm", num(o.mean_crlb_x_mm)},   {"mean_crlb_y_mm", num(o.mean_crlb_y_mm)},
                     {"mean_crlb_z_mm", num(o.mean_crlb_z_mm)},   {"mean_photons", num(o.mean_photons)},
                     {"depth_ratio", num(o.depth_ratio)},         {"crlb_3d_by_depth_mm", by_depth}};
  j["seconds"] = e.seconds;
  return j;
}

Evaluated evaluated_from_json(const json& j) {
  Evaluated e;
  e.key = j.at("key");
  e.design = Design::from_json(j.at("design"));
  e.origin = j.at("origin");
  e.valid = j.at("valid");
  if (!e.valid) {
    e.reason = j.at("reason");
    return e;
  }
  const json& o = j.at("objectives");
  Objectives& b = e.objectives;
  b.mean_crlb_3d_mm = num(o.at("mean_crlb_3d_mm"));
  b.worst_crlb_3d_mm = num(o.at("worst_crlb_3d_mm"));
  b.mean_crlb_x_mm = num(o.at("mean_crlb_x_mm"));
  b.mean_crlb_y_mm = num(o.at("mean_crlb_y_mm"));
  b.mean_crlb_z_mm = num(o.at("mean_crlb_z_mm"));
  b.mean_photons = num(o.at("mean_photons"));
  b.depth_ratio = num(o.at("depth_ratio"));
  for (const auto& v : o.at("crlb_3d_by_depth_mm")) b.crlb_3d_by_depth_mm.push_back(num(v));
  e.seconds = j.value("seconds", 0.0);
  return e;
}

}  // namespace

json Sweep::header() const {
  const TraceSettings& t = settings_.trace;
  return {{"prism_sweep", 1},
          {"space", space_.source},
          {"rays_per_lenslet", t.rays()},
          {"binning", t.binning},
          {"estimator", to_string(t.estimator)},
          {"photons_emitted", t.photons_emitted},
          {"backend", settings_.backend == Backend::cpu ? "cpu" : "vulkan"},
          {"batch", settings_.batch},
          {"samples", {{"x_mm", space_.samples.x_mm}, {"y_mm", space_.samples.y_mm}, {"depth_mm", space_.samples.depth_mm}}}};
}

Sweep::Sweep(const DesignSpace& space, SweepSettings settings, std::string state_path)
    : space_(space), settings_(std::move(settings)), state_path_(std::move(state_path)) {
  objective_value(Objectives{}, settings_.objective);  // an unknown name fails before any work
  if (settings_.budget == 0) throw SweepError("--budget must be at least 1");
  json want = header();
  std::ifstream in(state_path_);
  if (!in) {
    write_atomically(state_path_, [&](const std::string& tmp) {
      std::ofstream out(tmp);
      out << want.dump() << '\n';
      if (!out) throw SweepError("cannot write " + state_path_);
    });
    return;
  }
  std::string line;
  std::vector<std::string> good;
  bool torn = false;
  size_t line_no = 0;
  while (std::getline(in, line)) {
    ++line_no;
    json j;
    try {
      j = json::parse(line);
    } catch (const json::parse_error&) {
      // Only a design cut short by a kill can be half written: the last line.
      if (in.peek() != EOF) throw SweepError(state_path_ + ":" + std::to_string(line_no) + ": not a sweep record; remove the file to start over");
      torn = true;
      break;
    }
    if (line_no == 1) {
      for (auto it = want.begin(); it != want.end(); ++it)
        if (!j.contains(it.key()) || j[it.key()] != it.value())
          throw SweepError(state_path_ + " was made with a different " + it.key() + " (" +
                           (j.contains(it.key()) ? j[it.key()].dump() : "none") + ", this run: " + it.value().dump() +
                           "); rerun with the same space and --rays/--binning/--device kind, or use a new --out");
    } else {
      Evaluated e = evaluated_from_json(j);
      stored_.emplace(e.key, e);
      done_.push_back(std::move(e));
    }
    good.push_back(line);
  }
  if (torn) {
    write_atomically(state_path_, [&](const std::string& tmp) {
      std::ofstream out(tmp);
      for (const auto& g : good) out << g << '\n';
    });
  }
}

void Sweep::append(const Evaluated& e) const {
  // One write() of a whole line with O_APPEND, then fsync: a kill leaves
  // either the line or (at worst) a torn last line, which the reader drops.
  std::string line = to_json(e).dump() + "\n";
  int fd = ::open(state_path_.c_str(), O_WRONLY | O_APPEND);
  if (fd < 0) throw SweepError("cannot append to " + state_path_);
  ssize_t n = ::write(fd, line.data(), line.size());
  ::fsync(fd);
  ::close(fd);
  if (n != ssize_t(line.size())) throw SweepError("cannot append to " + state_path_ + " (disk full?)");
}

bool Sweep::better(const Evaluated& a, const Evaluated& b) const {
  auto tier = [&](const Evaluated& e) {
    if (!e.valid) return 2;
    for (const auto& bound : settings_.bounds)
      if (!bound.holds(e.objectives)) return 1;
    return 0;
  };
  auto value = [&](const Evaluated& e) -> double {
    if (!e.valid) return INFINITY;
    double v = objective_value(e.objectives, settings_.objective);
    v = objective_is_maximised(settings_.objective) ? -v : v;
    return std::isnan(v) ? INFINITY : v;
  };
  int ta = tier(a), tb = tier(b);
  if (ta != tb) return ta < tb;
  double va = value(a), vb = value(b);
  if (va != vb) return va < vb;
  return a.key < b.key;  // a total order: ties rank the same way every run
}

std::vector<const Evaluated*> Sweep::ranked() const {
  std::vector<const Evaluated*> r;
  for (const auto& e : done_) r.push_back(&e);
  std::sort(r.begin(), r.end(), [&](const Evaluated* a, const Evaluated* b) { return better(*a, *b); });
  return r;
}

void Sweep::consume(const std::vector<std::pair<Design, std::string>>& queue, vk::Context* ctx,
                    std::vector<size_t>& pool, const std::function<void(const Evaluated&, size_t)>& on_design) {
  // Score what the state file does not hold yet, all together.
  std::vector<Design> fresh;
  for (const auto& [d, origin] : queue)
    if (!stored_.count(d.key())) fresh.push_back(d);
  std::vector<Evaluated> scored = evaluate_designs(space_, fresh, settings_.trace, settings_.backend, ctx);
  size_t next = 0;
  size_t consumed = seen_.size() - queue.size();
  for (const auto& [d, origin] : queue) {
    std::string key = d.key();
    size_t index = done_.size();
    if (stored_.count(key)) {
      ++replayed_;
      for (size_t i = 0; i < done_.size(); ++i)
        if (done_[i].key == key) index = i;
    } else {
      Evaluated e = std::move(scored[next++]);
      e.origin = origin;
      append(e);
      done_.push_back(std::move(e));
    }
    pool.push_back(index);
    if (on_design) on_design(done_[index], ++consumed);
  }
}

void Sweep::run(vk::Context* ctx, const std::function<bool()>& stop, const std::function<void(const Evaluated&, size_t)>& on_design) {
  std::mt19937_64 rng(settings_.seed);
  seen_.clear();
  replayed_ = 0;
  exhausted_ = false;
  std::vector<size_t> pool;  // indices into done_ of the designs this run consumed, in order
  auto more = [&] { return seen_.size() < settings_.budget && !(stop && stop()); };
  // Candidates queue up and are scored a batch at a time (one dispatch).
  std::vector<std::pair<Design, std::string>> queue;
  auto flush = [&] {
    if (queue.empty()) return;
    consume(queue, ctx, pool, on_design);
    queue.clear();
  };
  auto take = [&](const Design& d, const std::string& origin) {
    seen_.insert(d.key());
    queue.emplace_back(d, origin);
    if (queue.size() >= std::max<size_t>(1, settings_.batch)) flush();
  };

  // The base scene first when the space holds it: the sweep reports it beside
  // whatever it finds, and never does worse.
  if (auto base = space_.encode(space_.base); base && more()) take(*base, "base");
  flush();  // the base design alone: the local search may start from it

  if (space_.size() <= double(settings_.budget)) {
    for (const auto& d : space_.enumerate())
      if (!seen_.count(d.key()) && more()) take(d, "enumerated");
    flush();
    exhausted_ = seen_.size() >= size_t(space_.size());
    return;
  }

  // Seeded random start over an eighth of the budget, then local search (a
  // random arrangement is rarely near the best one; most of the budget goes
  // to improving the best designs found).
  size_t start = std::max<size_t>(1, settings_.budget / 8);
  for (size_t i = 0; i < start && more(); ++i) {
    Design d = space_.random(rng);
    for (int tries = 0; seen_.count(d.key()) && tries < 100; ++tries) d = space_.random(rng);
    if (!seen_.count(d.key())) take(d, "start");
  }
  flush();
  while (more()) {
    std::vector<size_t> order;
    for (size_t i : pool)
      if (done_[i].valid) order.push_back(i);
    std::sort(order.begin(), order.end(), [&](size_t a, size_t b) { return better(done_[a], done_[b]); });
    std::optional<Design> child;
    if (!order.empty()) {
      // Mostly from the best; sometimes from one of the next few, so one
      // local optimum does not hold the whole search.
      size_t top = std::min<size_t>(8, order.size());
      const Design& parent = done_[order[pick(rng, 4) == 0 ? pick(rng, top) : 0]].design;
      for (int tries = 0; tries < 200 && !child; ++tries) {
        Design d = space_.neighbour(parent, rng);
        if (!seen_.count(d.key())) child = d;
      }
    }
    for (int tries = 0; tries < 200 && !child; ++tries) {
      Design d = space_.random(rng);
      if (!seen_.count(d.key())) child = d;
    }
    if (!child) {
      flush();
      exhausted_ = true;  // nothing new near the best nor at random
      return;
    }
    take(*child, "search");
  }
  flush();
}

}  // namespace prism
