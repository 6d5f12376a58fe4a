// The design space: its file, and the designs in it (enumerated, drawn at
// random, or a neighbour of another).
#include "host/sweep/space.h"

#include <algorithm>
#include <cmath>
#include <fstream>
#include <sstream>

#include "host/util/format.h"
#include "host/util/json_file.h"

namespace prism {

using json = nlohmann::json;

namespace {

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
    // Read as a double first: get<int> would wrap 2^32 + 1 to 1.
    if (!j.is_number_integer() || j.get<double>() < 1 || j.get<double>() > 1e6)
      fail(field, "must be a whole number from 1 to 1000000, got " + j.dump());
    return j.get<int>();
  }
  std::string text(const json& j, const std::string& key, const std::string& fallback) const {
    if (!j.contains(key)) return fallback;
    if (!j[key].is_string()) fail(key, "must be a string, got " + j[key].dump());
    return j[key].get<std::string>();
  }
  void keys(const json& j, const std::string& path, std::initializer_list<const char*> allowed) const {
    for (auto it = j.begin(); it != j.end(); ++it) {
      if (std::none_of(allowed.begin(), allowed.end(), [&](const char* a) { return it.key() == a; })) {
        fail(path + it.key(), "unknown field (expected one of: " + join(allowed) + ")");
      }
    }
  }
};

double log_factorial(double n) { return std::lgamma(n + 1.0); }

}  // namespace

// ---- Designs

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

// ---- Design space

DesignSpace DesignSpace::load(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw SweepError("space " + path + ": cannot read the file");
  json j;
  try {
    j = parse_json_file(in);
  } catch (const JsonDuplicateKey& e) {
    throw SweepError("space " + path + ": " + e.what());
  } catch (const JsonSyntaxError& e) {
    throw SweepError("space " + path + ": not valid JSON (" + e.what() + ")");
  }
  return parse(j, path, std::filesystem::path(path).parent_path().string());
}

DesignSpace DesignSpace::parse(const json& j, const std::string& origin, const std::string& dir) {
  SpaceReader rd{origin};
  if (!j.is_object()) rd.fail("(top level)", "a design space is a JSON object");
  rd.keys(j, "", {"name", "base", "layout", "focal_mm", "assignment", "diameter_mm", "lens_to_sensor_mm",
                  "working_distance_mm", "lens_model", "effects", "samples", "ambiguity_samples"});
  DesignSpace s;
  s.source = j;
  s.name = rd.text(j, "name", std::filesystem::path(origin).stem().string());

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
        if (r != std::floor(r) || c != std::floor(c) || r > 1000 || c > 1000)
          rd.fail("layout", "rows and columns must be whole numbers up to 1000");
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
  std::string assignment = rd.text(j, "assignment", "balanced");
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

  // Volume samples: {"lateral": N, "depth": N} (SampleGrid::of) and/or explicit lists.
  auto sample_grid = [&](const char* key, int lateral, int depth) {
    const std::string k = key;
    if (!j.contains(key)) return SampleGrid::of(s.base.volume, lateral, depth);
    const json& sj = j[key];
    if (!sj.is_object()) rd.fail(k, "must be {\"lateral\": N, \"depth\": N} and/or explicit x_mm, y_mm, depth_mm lists");
    rd.keys(sj, k + ".", {"lateral", "depth", "x_mm", "y_mm", "depth_mm"});
    if (sj.contains("lateral")) lateral = rd.count(sj["lateral"], k + ".lateral");
    if (sj.contains("depth")) depth = rd.count(sj["depth"], k + ".depth");
    SampleGrid g = SampleGrid::of(s.base.volume, lateral, depth);
    auto coords = [&](const char* c, std::vector<double>& out) {
      if (!sj.contains(c)) return;
      json list = sj[c].is_array() ? sj[c] : json::array({sj[c]});
      out.clear();
      for (const auto& v : list) {
        if (!v.is_number()) rd.fail(k + "." + c, "must be numbers in mm, got " + v.dump());
        out.push_back(v.get<double>());
      }
      if (out.empty()) rd.fail(k + "." + c, "must list at least one position");
    };
    coords("x_mm", g.x_mm);
    coords("y_mm", g.y_mm);
    coords("depth_mm", g.depth_mm);
    return g;
  };
  s.samples = sample_grid("samples", 3, 6);
  // The global ambiguity costs ~60 renders per sample: by default the
  // volume's axis at six depths.
  s.ambiguity_samples = sample_grid("ambiguity_samples", 1, 6);

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

Design DesignSpace::random(std::mt19937_64& rng) const { return random_at(draw::index(rng, layouts.size()), rng); }

Design DesignSpace::random_at(size_t layout, std::mt19937_64& rng) const {
  Design d;
  d.layout = layout;
  size_t n = positions(d.layout).size(), k = focal_mm.size();
  if (focal_fixed) {
    std::vector<double> f;
    for (const auto& x : base.optics.lenslets) f.push_back(x.focal_mm);
    d.focal = base_genes(f, focal_mm);
  } else if (focal_free) {
    for (size_t i = 0; i < n; ++i) d.focal.push_back(int(draw::index(rng, k)));
  } else {
    std::vector<size_t> values(k);
    for (size_t i = 0; i < k; ++i) values[i] = i;
    draw::shuffle(values, rng);
    values.resize(n % k);
    d.focal = multiset(balanced_counts(n, k, values));
    draw::shuffle(d.focal, rng);
  }
  if (diameter_fixed) {
    std::vector<double> dv;
    for (const auto& x : base.optics.lenslets) dv.push_back(x.diameter_mm);
    d.diameter = base_genes(dv, diameter_mm);
  } else {
    for (size_t i = 0; i < n; ++i) d.diameter.push_back(int(draw::index(rng, diameter_mm.size())));
  }
  d.lens_to_sensor = draw::index(rng, lens_to_sensor_mm.size());
  d.working_distance = draw::index(rng, working_distance_mm.size());
  d.lens_model = draw::index(rng, lens_models.size());
  d.effects = draw::index(rng, effects.size());
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
  auto other = [&](size_t current, size_t n) { return (current + 1 + draw::index(rng, n - 1)) % n; };
  int count = draw::index(rng, 3) == 0 ? 2 : 1;  // mostly single moves; pairs to step over a ridge
  for (int m = 0; m < count; ++m) {
    size_t n = d.focal.size();
    switch (moves[draw::index(rng, moves.size())]) {
      case focal: {
        size_t i = draw::index(rng, n), j = draw::index(rng, n);
        if (d.focal[i] != d.focal[j] && draw::index(rng, 2) == 0) {
          std::swap(d.focal[i], d.focal[j]);  // a swap keeps the balance
        } else {
          int old = d.focal[i];
          d.focal[i] = int(other(size_t(old), focal_mm.size()));
          if (!focal_free && !is_balanced(d.focal, focal_mm.size())) {
            // Changing one value would unbalance the array: swap instead.
            d.focal[i] = old;
            for (int tries = 0; d.focal[i] == d.focal[j] && tries < 64; ++tries) j = draw::index(rng, n);
            std::swap(d.focal[i], d.focal[j]);
          }
        }
        break;
      }
      case diameter: {
        size_t i = draw::index(rng, n);
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

}  // namespace prism
