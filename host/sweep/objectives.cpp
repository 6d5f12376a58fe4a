// The sample grid, the objectives a design is scored by, bounds on them, and
// the scoring itself (Fisher information at the grid's positions).
#include "host/sweep/objectives.h"

#include <algorithm>
#include <cmath>

#include "engine/forward.h"
#include "host/util/format.h"

namespace prism {

namespace {

using json = nlohmann::json;

// JSON has no infinity: a design with no light somewhere scores "inf"; nor
// NaN (not scored), which is null.
json num(double v) {
  if (std::isnan(v)) return nullptr;
  return std::isfinite(v) ? json(v) : json(v > 0 ? "inf" : "-inf");
}
double num(const json& j) {
  if (j.is_null()) return NAN;
  if (j.is_string()) return j == "inf" ? INFINITY : -INFINITY;
  return j.get<double>();
}

}  // namespace

nlohmann::json to_json(const Objectives& o) {
  nlohmann::json by_depth = nlohmann::json::array();
  for (double v : o.crlb_3d_by_depth_mm) by_depth.push_back(num(v));
  nlohmann::json j = {{"mean_crlb_3d_mm", num(o.mean_crlb_3d_mm)}, {"worst_crlb_3d_mm", num(o.worst_crlb_3d_mm)},
                      {"mean_crlb_x_mm", num(o.mean_crlb_x_mm)},   {"mean_crlb_y_mm", num(o.mean_crlb_y_mm)},
                      {"mean_crlb_z_mm", num(o.mean_crlb_z_mm)},   {"mean_photons", num(o.mean_photons)},
                      {"depth_ratio", num(o.depth_ratio)},         {"crlb_3d_by_depth_mm", by_depth}};
  if (!std::isnan(o.mean_p_confusion))
    j.update({{"mean_p_confusion", num(o.mean_p_confusion)},
              {"worst_p_confusion", num(o.worst_p_confusion)},
              {"min_alias_kl", num(o.min_alias_kl)}});
  return j;
}

Objectives objectives_from_json(const nlohmann::json& o) {
  Objectives b;
  b.mean_crlb_3d_mm = num(o.at("mean_crlb_3d_mm"));
  b.worst_crlb_3d_mm = num(o.at("worst_crlb_3d_mm"));
  b.mean_crlb_x_mm = num(o.at("mean_crlb_x_mm"));
  b.mean_crlb_y_mm = num(o.at("mean_crlb_y_mm"));
  b.mean_crlb_z_mm = num(o.at("mean_crlb_z_mm"));
  b.mean_photons = num(o.at("mean_photons"));
  b.depth_ratio = num(o.at("depth_ratio"));
  for (const auto& v : o.at("crlb_3d_by_depth_mm")) b.crlb_3d_by_depth_mm.push_back(num(v));
  if (o.contains("mean_p_confusion")) {
    b.mean_p_confusion = num(o.at("mean_p_confusion"));
    b.worst_p_confusion = num(o.at("worst_p_confusion"));
    b.min_alias_kl = num(o.at("min_alias_kl"));
  }
  return b;
}

// ---- Sample grid

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

// ---- Objectives and bounds

const std::vector<std::string>& objective_names() {
  static const std::vector<std::string> names{"mean_crlb_3d", "worst_crlb_3d", "mean_crlb_x",      "mean_crlb_y",
                                              "mean_crlb_z",  "photons",       "depth_ratio",      "p_confusion",
                                              "worst_p_confusion", "alias_kl"};
  return names;
}

bool objective_is_maximised(const std::string& name) { return name == "photons" || name == "alias_kl"; }

bool objective_is_ambiguity(const std::string& name) {
  return name == "p_confusion" || name == "worst_p_confusion" || name == "alias_kl";
}

double objective_value(const Objectives& o, const std::string& name) {
  if (name == "mean_crlb_3d") return o.mean_crlb_3d_mm;
  if (name == "worst_crlb_3d") return o.worst_crlb_3d_mm;
  if (name == "mean_crlb_x") return o.mean_crlb_x_mm;
  if (name == "mean_crlb_y") return o.mean_crlb_y_mm;
  if (name == "mean_crlb_z") return o.mean_crlb_z_mm;
  if (name == "photons") return o.mean_photons;
  if (name == "depth_ratio") return o.depth_ratio;
  if (name == "p_confusion") return o.mean_p_confusion;
  if (name == "worst_p_confusion") return o.worst_p_confusion;
  if (name == "alias_kl") return o.min_alias_kl;
  throw SweepError("unknown objective '" + name + "' (known: " + join(objective_names()) + ")");
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
  try {
    objective_value(Objectives{}, b.objective);  // throws, listing the names
  } catch (const SweepError& e) {
    throw SweepError("--bound '" + text + "': " + e.what());
  }
  try {
    size_t used = 0;
    b.value = std::stod(text.substr(at + 2), &used);
    if (used != text.size() - at - 2) throw std::invalid_argument(text);
  } catch (const std::exception&) {
    throw SweepError("--bound '" + text + "': '" + text.substr(at + 2) + "' is not a number");
  }
  // NaN would reject every design (no comparison with it holds).
  if (!std::isfinite(b.value))
    throw SweepError("--bound '" + text + "': '" + text.substr(at + 2) + "' is not a finite number");
  return b;
}

nlohmann::json AmbiguityScoring::to_json() const {
  return {{"photons", photons},
          {"binning", binning},
          {"min_separation_mm", settings.min_separation_mm},
          {"dark_rate", settings.dark_rate},
          {"refined", settings.refined},
          {"iterations", settings.iterations},
          {"p_confusion", confusion_model},
          {"rays_per_lenslet", refine_trace_settings(binning).rays()}};
}

// ---- Scoring

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

}  // namespace

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

Objectives score(const Scene& scene, const SampleGrid& grid, const TraceSettings& settings, Backend backend,
                 vk::Context* ctx) {
  return objectives_of(crlb_study(scene, grid.positions(), settings, backend, SensorModel::poisson, ctx), grid);
}

void score_ambiguity(const Scene& scene, const SampleGrid& samples, const AmbiguityScoring& scoring, vk::Context* ctx,
                     Objectives& o) {
  auto model = make_scene_model(scene, refine_trace_settings(scoring.binning), ctx);
  double sum = 0, worst = 0, kl = INFINITY;
  const auto positions = samples.positions();
  for (const auto& theta : positions) {
    const Ambiguity a = ambiguity(*model, scene, theta, scoring.photons, scoring.settings);
    sum += a.p_confusion;
    worst = std::max(worst, a.p_confusion);
    kl = std::min(kl, a.kl);
  }
  o.mean_p_confusion = sum / double(positions.size());
  o.worst_p_confusion = worst;
  o.min_alias_kl = kl;
}

}  // namespace prism
