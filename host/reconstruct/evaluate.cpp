#include "host/reconstruct/evaluate.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <map>
#include <memory>
#include <numeric>
#include <stdexcept>

#include "host/dictionary/service.h"
#include "host/events/simulate.h"
#include "host/reconstruct/match.h"
#include "host/scene/crlb_study.h"
#include "host/util/format.h"
#include "host/util/image_io.h"
#include "host/util/plot.h"

namespace prism {

namespace {

struct MeanStd {
  double mean = 0, std = 0;
};
MeanStd mean_std(const std::vector<double>& v) {
  MeanStd r;
  if (v.empty()) return r;
  r.mean = std::accumulate(v.begin(), v.end(), 0.0) / double(v.size());
  double ss = 0;
  for (double e : v) ss += (e - r.mean) * (e - r.mean);
  r.std = v.size() > 1 ? std::sqrt(ss / double(v.size() - 1)) : 0.0;
  return r;
}

// One vertex of a point: its truth, photons and the curve it belongs to.
struct Target {
  glm::dvec3 position;
  double photons;
  std::string series;
  double varied;
};
// A point of an experiment: one or two vertices in the same events.
struct Point {
  std::string experiment;
  std::vector<Target> vertices;
};

// first..last in `step` steps, clipped to [lo, hi], always containing `through`.
std::vector<double> line(double lo, double hi, double through, double step) {
  std::vector<double> v;
  for (double x = through; x >= lo - 1e-9; x -= step) v.push_back(x);
  for (double x = through + step; x <= hi + 1e-9; x += step) v.push_back(x);
  std::sort(v.begin(), v.end());
  return v;
}

std::vector<double> quick_line(double lo, double hi, double through) {
  std::vector<double> v;
  for (double x : {through - 2.0, through + 2.0})
    if (x >= lo && x <= hi) v.push_back(x);
  return v;
}

std::vector<Point> plan(const DictionaryGrid& g, const EvaluationOptions& o) {
  using namespace paper_protocol;
  auto range = [](const std::vector<double>& a) { return std::pair(*std::min_element(a.begin(), a.end()), *std::max_element(a.begin(), a.end())); };
  auto [x0, x1] = range(g.x_mm);
  auto [y0, y1] = range(g.y_mm);
  auto [z0, z1] = range(g.depth_mm);
  const glm::dvec3 c = centre_mm;
  if (c.x < x0 || c.x > x1 || c.y < y0 || c.y > y1 || c.z < z0 || c.z > z1)
    throw std::runtime_error("the dictionary's grid does not contain the protocol's centre (1, 1, 31) mm");
  auto pick = [&](double lo, double hi, double through, double step) {
    return o.quick ? quick_line(lo, hi, through) : line(lo, hi, through, step);
  };
  std::vector<Point> points;
  for (const auto& e : o.experiments) {
    if (e == "single-lines") {
      for (double x : pick(x0, x1, c.x, 2.5)) points.push_back({e, {{{x, c.y, c.z}, line_photons, "x", x}}});
      for (double y : pick(y0, y1, c.y, 2.5)) points.push_back({e, {{{c.x, y, c.z}, line_photons, "y", y}}});
      for (double z : pick(z0, z1, c.z, 2.5)) points.push_back({e, {{{c.x, c.y, z}, line_photons, "depth", z}}});
    } else if (e == "photons") {
      std::vector<double> counts = photon_counts;
      if (o.quick) counts = {counts.front(), counts.back()};
      for (double n : counts) points.push_back({e, {{c, n, "", n}}});
    } else if (e == "double") {
      if (double_fixed_depth_mm < z0 || double_fixed_depth_mm > z1)
        throw std::runtime_error("double: the dictionary's depths " + std::to_string(z0) + ".." + std::to_string(z1) +
                                 " mm do not contain the fixed vertex's 7.5 mm; use a dictionary that does, or drop "
                                 "'double' from --experiments");
      std::vector<double> depths = o.quick ? std::vector<double>{c.z} : line(z0, z1, c.z, 2.5);
      const double half = double_photons / 2;
      for (double z : depths)
        points.push_back({e,
                          {{{c.x, c.y, z}, half, "moving", z},
                           {{c.x, c.y, double_fixed_depth_mm}, half, "fixed", z}}});
    } else {
      throw std::runtime_error("unknown experiment '" + e + "': choose from single-lines, photons, double");
    }
  }
  return points;
}

}  // namespace

TrimmedStats trimmed_stats(const std::vector<double>& err3d_mm, const std::vector<double>& alpha_err) {
  if (err3d_mm.size() < 3 || alpha_err.size() != err3d_mm.size())
    throw std::invalid_argument("trimmed_stats: needs >= 3 trials and one alpha error per 3D error");
  std::vector<size_t> order(err3d_mm.size());
  std::iota(order.begin(), order.end(), size_t(0));
  std::stable_sort(order.begin(), order.end(), [&](size_t a, size_t b) { return err3d_mm[a] < err3d_mm[b]; });
  std::vector<double> e, a;
  for (size_t i = 1; i + 1 < order.size(); ++i) {
    e.push_back(err3d_mm[order[i]]);
    a.push_back(alpha_err[order[i]]);
  }
  TrimmedStats s;
  s.trials_used = int(e.size());
  auto me = mean_std(e), ma = mean_std(a);
  s.err3d_mean = me.mean;
  s.err3d_std = me.std;
  s.alpha_err_mean = ma.mean;
  s.alpha_err_std = ma.std;
  return s;
}

const std::vector<std::string>& evaluation_experiments() {
  static const std::vector<std::string> names{"single-lines", "photons", "double"};
  return names;
}

std::vector<EvaluationRow> evaluate(vk::Context& ctx, const Scene& scene, const DictionaryReader& dictionary,
                                    const EvaluationOptions& o, const std::function<void(size_t, size_t)>& progress,
                                    EvaluationCost* cost) {
  if (o.trials < 3) throw std::invalid_argument("--trials: at least 3 (the best and the worst are dropped)");
  const auto& m = dictionary.manifest();
  if (o.level < 0 || o.level >= m.levels)
    throw std::invalid_argument("click level " + std::to_string(o.level) + " is not stored in the dictionary");
  const auto points = plan(m.grid, o);

  TraceSettings t;
  t.binning = unsigned(m.base_binning << o.level);
  t.rays_per_lenslet = o.rays ? o.rays : (m.rays_per_lenslet ? m.rays_per_lenslet : TraceSettings::default_rays(o.splat));
  t.photons_emitted = scene.photons_emitted;
  t.splat = o.splat;
  t.estimator = TraceSettings::default_estimator(o.splat);
  t.stratification = o.stratification;

  // CRLB of every vertex position in one study, scaled to its photon count.
  std::vector<glm::dvec3> positions;
  for (const auto& p : points)
    for (const auto& v : p.vertices) positions.push_back(v.position);
  auto bounds = crlb_study(scene, positions, t, Backend::vulkan, SensorModel::poisson, &ctx);

  ForwardTruth truth(ctx, scene, t, 64);
  ReconstructionSettings s = o.settings;
  if (s.search_level < 0) s.search_level = default_search_level(m, o.level);
  const bool on_device = o.backend != ReconstructionBackend::cpu;
  DictionaryService service(dictionary, on_device ? &ctx : nullptr, s.search_level, {}, o.device_half);
  std::map<int, std::unique_ptr<Reconstructor>> reconstructors;  // per K
  EvaluationCost spent;

  std::vector<EvaluationRow> rows;
  const size_t total = points.size() * size_t(o.trials);
  size_t done = 0, bound = 0;
  uint64_t event_id = 0;
  for (const auto& p : points) {
    ReconstructionSettings ps = s;
    ps.vertices = int(p.vertices.size());
    std::vector<std::shared_ptr<const PsfSampler>> held;
    std::vector<ClickSource> sources;
    for (const auto& v : p.vertices) {
      held.push_back(truth.psf(v.position));
      sources.push_back({held.back().get(), v.photons});
    }
    const size_t n = p.vertices.size();
    std::vector<std::vector<double>> err(n), alpha_err(n);
    std::vector<int> flagged(n, 0);
    std::vector<Event> events(size_t(o.trials));
    for (auto& e : events) {
      e.id = event_id++;
      auto rng = event_rng(o.seed, e.id);
      sample_clicks(sources, rng, e.clicks);
    }
    auto& r = reconstructors[ps.vertices];
    if (!r) r = std::make_unique<Reconstructor>(service, o.level, ps, o.backend, &ctx);
    const auto before = r->timings();
    auto start = std::chrono::steady_clock::now();
    auto estimates = r->run(events);
    spent.reconstruct_s += std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    spent.scan_s += r->timings().scan_s - before.scan_s;
    spent.events += events.size();
    std::vector<glm::dvec3> truth_mm;
    for (const auto& v : p.vertices) truth_mm.push_back(v.position);
    for (const auto& est : estimates) {
      auto which = match_vertices(est, truth_mm);
      for (size_t k = 0; k < n; ++k) {
        const auto& v = est.at(which[k]);
        err[k].push_back(error_3d_mm(v, p.vertices[k].position));
        alpha_err[k].push_back(std::abs(v.alpha - p.vertices[k].photons));
        flagged[k] += v.flags != vertex_ok;
      }
      if (progress) progress(++done, total);
    }
    for (size_t k = 0; k < n; ++k, ++bound) {
      const auto& b = bounds.at(bound);
      EvaluationRow r;
      r.experiment = p.experiment;
      r.series = p.vertices[k].series;
      r.varied = p.vertices[k].varied;
      r.position_mm = p.vertices[k].position;
      r.photons = p.vertices[k].photons;
      r.stats = trimmed_stats(err[k], alpha_err[k]);
      r.flagged = flagged[k];
      r.crlb_3d_mm = b.photons > 0 ? b.crlb.r3_mm * std::sqrt(b.photons / r.photons) : INFINITY;
      rows.push_back(r);
    }
  }
  if (cost) *cost = spent;
  return rows;
}

std::vector<std::string> write_evaluation(const std::string& dir, const std::vector<EvaluationRow>& rows) {
  std::filesystem::create_directories(dir);
  std::vector<std::string> written;
  for (const auto& name : evaluation_experiments()) {
    std::vector<const EvaluationRow*> mine;
    for (const auto& r : rows)
      if (r.experiment == name) mine.push_back(&r);
    if (mine.empty()) continue;
    const std::string csv = dir + "/" + name + ".csv", png = dir + "/" + name + ".png";
    write_atomically(csv, [&](const std::string& tmp) {
      std::ofstream out(tmp);
      out << "experiment,x_mm,y_mm,depth_mm,photons,trials_used,err3d_mean_mm,err3d_std_mm,alpha_err_mean,"
             "alpha_err_std,crlb_3d_mm\n";
      for (const auto* r : mine)
        out << r->experiment << (r->series.empty() ? "" : ":" + r->series) << ',' << format_number(r->position_mm.x) << ','
            << format_number(r->position_mm.y) << ',' << format_number(r->position_mm.z) << ',' << format_number(r->photons) << ','
            << r->stats.trials_used << ',' << format_number(r->stats.err3d_mean) << ',' << format_number(r->stats.err3d_std) << ','
            << format_number(r->stats.alpha_err_mean) << ',' << format_number(r->stats.alpha_err_std) << ',' << format_number(r->crlb_3d_mm)
            << '\n';
      if (!out) throw std::runtime_error("cannot write " + csv);
    });
    // Per curve: the trimmed mean, mean + 1 std, and the CRLB dashed.
    std::vector<std::string> order;
    std::map<std::string, std::vector<const EvaluationRow*>> curves;
    for (const auto* r : mine) {
      if (!curves.count(r->series)) order.push_back(r->series);
      curves[r->series].push_back(r);
    }
    std::vector<Series> series;
    for (const auto& c : order) {
      std::string label = c.empty() ? "" : c + ": ";
      Series mean{label + "3D error (mean)", {}, {}, false}, upper{label + "mean + 1 std", {}, {}, false},
          crlb{label + "CRLB", {}, {}, true};
      for (const auto* r : curves[c]) {
        for (Series* s : {&mean, &upper, &crlb}) s->x.push_back(r->varied);
        mean.y.push_back(r->stats.err3d_mean);
        upper.y.push_back(r->stats.err3d_mean + r->stats.err3d_std);
        crlb.y.push_back(r->crlb_3d_mm);
      }
      series.push_back(mean);
      series.push_back(upper);
      series.push_back(crlb);
    }
    const char* x_label = name == "single-lines" ? "position along the line: x, y or depth (mm)"
                          : name == "photons"    ? "expected detected photons"
                                                 : "depth of the moving vertex (mm); the other at 7.5 mm";
    plot_lines(png, {name + ": 3D error (best and worst of each point dropped) and CRLB", x_label, "3D error (mm)", true},
               series);
    written.push_back(csv);
    written.push_back(png);
  }
  return written;
}

}  // namespace prism
