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
#include <optional>
#include <stdexcept>

#include "engine/defaults.h"
#include "host/dictionary/service.h"
#include "host/events/simulate.h"
#include "host/reconstruct/event_fit.h"
#include "host/reconstruct/match.h"
#include "host/scene/crlb_study.h"
#include "host/util/format.h"
#include "host/util/image_io.h"
#include "host/util/journal.h"
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
  const bool centre_inside = c.x >= x0 && c.x <= x1 && c.y >= y0 && c.y <= y1 && c.z >= z0 && c.z <= z1;
  auto pick = [&](double lo, double hi, double through, double step) {
    return o.quick ? quick_line(lo, hi, through) : line(lo, hi, through, step);
  };
  std::vector<Point> points;
  for (const auto& e : o.experiments) {
    if (e != "volume" && !centre_inside)
      throw std::runtime_error(e + ": the dictionary's grid does not contain the protocol's centre (1, 1, 31) mm; "
                               "use a dictionary that does, or the volume experiment alone");
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
    }
  }
  return points;
}

// A uniform double in [0, 1) from the event's own stream.
double uniform01(EventRng& rng) { return double(rng() >> 11) * 0x1.0p-53; }

// The volume experiment's field: the options' bounds, NaN ones from the grid.
struct Field {
  glm::dvec2 x, y, depth;
};
Field volume_field(const DictionaryGrid& g, const EvaluationOptions& o) {
  auto extent = [](const std::vector<double>& a, glm::dvec2 chosen, const char* name) {
    glm::dvec2 e{*std::min_element(a.begin(), a.end()), *std::max_element(a.begin(), a.end())};
    if (!std::isnan(chosen.x)) e = chosen;
    if (!(e.x < e.y))
      throw std::runtime_error(std::string("volume: the ") + name + " range " + format_number(e.x) + ".." +
                               format_number(e.y) + " mm is empty; give lo < hi");
    return e;
  };
  return {extent(g.x_mm, o.volume_x_mm, "x"), extent(g.y_mm, o.volume_y_mm, "y"),
          extent(g.depth_mm, o.volume_depth_mm, "depth")};
}

// Depth bands: edges at multiples of band_mm, clipped to [lo, hi].
std::vector<glm::dvec2> depth_bands(glm::dvec2 depth, double band_mm) {
  if (!(band_mm > 0)) throw std::runtime_error("--band-mm must be > 0");
  std::vector<glm::dvec2> bands;
  for (double lo = depth.x; lo < depth.y - 1e-9;) {
    double hi = std::min(depth.y, (std::floor(lo / band_mm + 1e-9) + 1) * band_mm);
    bands.push_back({lo, hi});
    lo = hi;
  }
  return bands;
}

glm::dvec3 error_mm(const ReconstructedVertex& v, const glm::dvec3& truth) {
  return glm::dvec3(v.x_mm, v.y_mm, v.depth_mm) - truth;
}

}  // namespace

AxisStats axis_stats(const std::vector<glm::dvec3>& err_mm, const std::vector<glm::dvec3>& crlb_mm) {
  if (err_mm.size() != crlb_mm.size()) throw std::invalid_argument("axis_stats: one CRLB per error");
  AxisStats a;
  a.events = int(err_mm.size());
  std::vector<glm::dvec3> e, c;
  for (size_t i = 0; i < err_mm.size(); ++i)
    if (glm::length(err_mm[i]) <= defaults::catastrophic_error_mm) {
      e.push_back(err_mm[i]);
      c.push_back(crlb_mm[i]);
    }
  if (a.events) a.catastrophic_rate = 1.0 - double(e.size()) / double(a.events);
  if (e.empty()) return a;
  const double n = double(e.size());
  for (int k = 0; k < 3; ++k) {
    double se = 0, sc = 0, sr = 0;
    std::vector<double> ratio;
    for (size_t i = 0; i < e.size(); ++i) {
      se += e[i][k] * e[i][k];
      sc += c[i][k] * c[i][k];
      sr += (e[i][k] / c[i][k]) * (e[i][k] / c[i][k]);
      ratio.push_back(std::abs(e[i][k]) / c[i][k]);
    }
    a.rmse_mm[k] = std::sqrt(se / n);
    a.crlb_mm[k] = std::sqrt(sc / n);
    a.efficiency[k] = std::sqrt(sr / n);
    std::sort(ratio.begin(), ratio.end());
    const size_t m = ratio.size() / 2;
    a.median_ratio[k] = ratio.size() % 2 ? ratio[m] : 0.5 * (ratio[m - 1] + ratio[m]);
  }
  return a;
}

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

namespace {

using json = nlohmann::json;

// JSON has no NaN: null stands for it (an unrefined vertex's CRLB and p-value).
json number_or_null(double x) { return std::isnan(x) ? json(nullptr) : json(x); }
double number_of(const json& j) { return j.is_null() ? NAN : j.get<double>(); }

// A vertex as JSON, and back (journal records).
json to_json(const ReconstructedVertex& e) {
  return {{"x_mm", e.x_mm}, {"y_mm", e.y_mm}, {"depth_mm", e.depth_mm}, {"alpha", e.alpha}, {"nll", e.nll},
          {"clicks", e.clicks}, {"flags", e.flags}, {"refined", e.refined},
          {"crlb_mm", {number_or_null(e.crlb_x_mm), number_or_null(e.crlb_y_mm), number_or_null(e.crlb_z_mm),
                       number_or_null(e.crlb_3d_mm)}},
          {"fit_pvalue", number_or_null(e.fit_pvalue)}};
}

ReconstructedVertex vertex_from_json(const json& e) {
  ReconstructedVertex r;
  r.x_mm = e.at("x_mm").get<double>();
  r.y_mm = e.at("y_mm").get<double>();
  r.depth_mm = e.at("depth_mm").get<double>();
  r.alpha = e.at("alpha").get<double>();
  r.nll = e.at("nll").get<double>();
  r.clicks = e.at("clicks").get<uint32_t>();
  r.flags = e.at("flags").get<uint32_t>();
  r.refined = e.at("refined").get<bool>();
  const json& c = e.at("crlb_mm");
  r.crlb_x_mm = number_of(c.at(0));
  r.crlb_y_mm = number_of(c.at(1));
  r.crlb_z_mm = number_of(c.at(2));
  r.crlb_3d_mm = number_of(c.at(3));
  r.fit_pvalue = number_of(e.at("fit_pvalue"));
  return r;
}

// A journal record read with `read`; a record without what it needs names
// the file.
template <class F>
auto read_record(const json& j, const std::string& path, F&& read) {
  try {
    return read(j);
  } catch (const json::exception& err) {
    throw JournalError(path + ": a record without what it needs (" + err.what() + "); remove the file to start over");
  }
}

// An evaluation's journal, <dir>/<stem>.jsonl. When several processes share
// the events (EvaluationOptions::share), the leader appends to it and every
// other process r to its own <stem>.part<r>.jsonl until the leader has its
// events; a stopped job leaves the parts, which the next run merges in with
// --resume (and drops without it), and a report reads beside the journal.
struct EventJournal {
  std::string path;            // the journal itself
  std::vector<json> records;   // what was done before this run
  std::optional<Journal> out;  // where this process appends: the journal, or its part

  void append(const json& record) const { out->append(record); }
  // The leader holds this process's events: its part goes.
  void drop_part() {
    if (out && out->path() != path) {
      std::filesystem::remove(out->path());
      out.reset();
    }
  }
};

std::string part_path(const std::string& dir, const std::string& stem, size_t process) {
  return dir + "/" + stem + ".part" + std::to_string(process) + ".jsonl";
}

// The parts of <dir>/<stem>.jsonl there are, whatever the job that left them.
std::vector<std::string> part_paths(const std::string& dir, const std::string& stem) {
  std::vector<std::string> parts;
  std::error_code missing;
  for (const auto& f : std::filesystem::directory_iterator(dir, missing)) {
    const std::string name = f.path().filename().string();
    const std::string prefix = stem + ".part", suffix = ".jsonl";
    if (name.size() > prefix.size() + suffix.size() && name.starts_with(prefix) && name.ends_with(suffix) &&
        name.find_first_not_of("0123456789", prefix.size()) == name.size() - suffix.size())
      parts.push_back(f.path().string());
  }
  std::sort(parts.begin(), parts.end());
  return parts;
}

// Opens the journal `stem` in o.journal_dir for this run: started afresh, or
// with o.resume kept (a stopped job's parts merged in first); read only with
// o.journal_only, where the events (seed, truth, scene, points) must be this
// run's and the estimator is whatever made the journal (added to
// `estimators`).
EventJournal open_event_journal(const EvaluationOptions& o, const std::string& stem, const json& header,
                                const std::string& on_mismatch, std::vector<std::string>& estimators) {
  EventJournal j;
  j.path = o.journal_dir + "/" + stem + ".jsonl";
  const WorkShare& share = o.share;
  if (!o.journal_only) {
    if (share.leads()) {
      std::filesystem::create_directories(o.journal_dir);
      if (!o.resume) {
        std::filesystem::remove(j.path);
        for (const auto& part : part_paths(o.journal_dir, stem)) std::filesystem::remove(part);
      }
      j.out.emplace(j.path, header, on_mismatch);
      j.records = j.out->records();
      for (const auto& path : part_paths(o.journal_dir, stem)) {
        const Journal part(path, header, on_mismatch, /*read_only=*/true);
        for (const json& record : part.records()) {
          j.out->append(record);
          j.records.push_back(record);
        }
        std::filesystem::remove(path);
      }
    }
    share.wait_for_all();  // the leader's journal is whole
    if (!share.leads()) {
      j.records = Journal(j.path, header, on_mismatch, /*read_only=*/true).records();
      j.out.emplace(part_path(o.journal_dir, stem, share.index), header, on_mismatch);
    }
    return j;
  }
  if (!std::filesystem::exists(j.path))
    throw std::runtime_error(j.path + ": no journal to report from; run prism evaluate with the same options "
                             "and without --journal-only first");
  json events = header;
  events.erase("search");
  events.erase("refine");
  const std::string mismatch =
      "give --journal-only the options of the run that made it (--seed, --experiments, --trials, the truth's --rays "
      "and splat, the scene and dictionary)";
  const Journal journal(j.path, events, mismatch, /*read_only=*/true);
  j.records = journal.records();
  // A running job's other processes keep their events in parts until its end.
  for (const auto& path : part_paths(o.journal_dir, stem)) {
    const Journal part(path, events, mismatch, /*read_only=*/true);
    j.records.insert(j.records.end(), part.records().begin(), part.records().end());
  }
  const json& made = journal.header();
  estimators.push_back(j.path + ": search " + (made.contains("search") ? made["search"].dump() : "?") +
                       ", refine " + (made.contains("refine") ? made["refine"].dump() : "?"));
  return j;
}

// A volume event as one journal record, and back.
json to_json(const VolumeEvent& v) {
  json j = {{"index", v.index},
          {"truth_mm", {v.truth_mm.x, v.truth_mm.y, v.truth_mm.z}},
          {"crlb_mm", {v.crlb_mm.x, v.crlb_mm.y, v.crlb_mm.z}},
          {"estimate", to_json(v.estimate)},
          {"seconds", number_or_null(v.seconds)},
          {"renders", number_or_null(v.renders)}};
  if (!std::isnan(v.p_confusion))
    j["ambiguity"] = {{"alias_kl", number_or_null(v.alias_kl)},
                      {"alias_mm", {number_or_null(v.alias_mm.x), number_or_null(v.alias_mm.y),
                                    number_or_null(v.alias_mm.z)}},
                      {"p_confusion", v.p_confusion}};
  if (!std::isnan(v.truth_fit_nll))
    j["truth_fit"] = {{"mm", {v.truth_fit_mm.x, v.truth_fit_mm.y, v.truth_fit_mm.z}}, {"nll", v.truth_fit_nll}};
  return j;
}

VolumeEvent volume_event_from_json(const json& j) {
  VolumeEvent v;
  v.index = j.at("index").get<uint64_t>();
  for (int k = 0; k < 3; ++k) {
    v.truth_mm[k] = j.at("truth_mm").at(size_t(k)).get<double>();
    v.crlb_mm[k] = number_of(j.at("crlb_mm").at(size_t(k)));
  }
  v.estimate = vertex_from_json(j.at("estimate"));
  v.seconds = number_of(j.value("seconds", json()));  // absent in journals of 30abc7b and before
  v.renders = number_of(j.value("renders", json()));
  if (j.contains("ambiguity")) {
    const json& a = j.at("ambiguity");
    v.alias_kl = number_of(a.at("alias_kl"));
    for (int k = 0; k < 3; ++k) v.alias_mm[k] = number_of(a.at("alias_mm").at(size_t(k)));
    v.p_confusion = a.at("p_confusion").get<double>();
  }
  if (j.contains("truth_fit")) {  // absent in journals before 2026-11-29
    const json& t = j.at("truth_fit");
    for (int k = 0; k < 3; ++k) v.truth_fit_mm[k] = t.at("mm").at(size_t(k)).get<double>();
    v.truth_fit_nll = t.at("nll").get<double>();
  }
  return v;
}

}  // namespace

bool VolumeEvent::search_failure() const {
  return error_3d_mm(estimate, truth_mm) > defaults::catastrophic_error_mm &&
         glm::length(truth_fit_mm - truth_mm) <= defaults::catastrophic_error_mm && estimate.nll > truth_fit_nll;
}

const std::vector<std::string>& evaluation_experiments() {
  static const std::vector<std::string> names{"single-lines", "photons", "double", "volume"};
  return names;
}

void check_experiments(const std::vector<std::string>& names) {
  const auto& known = evaluation_experiments();
  for (const auto& e : names)
    if (std::find(known.begin(), known.end(), e) == known.end()) {
      throw std::invalid_argument("unknown experiment '" + e + "': choose from " + join(known));
    }
}

Evaluation evaluate(vk::Context& ctx, const Scene& scene, const DictionaryReader& dictionary,
                    const EvaluationOptions& o, const std::function<void(size_t, size_t)>& progress) {
  if (o.trials < 3) throw std::invalid_argument("--trials: at least 3 (the best and the worst are dropped)");
  if (o.journal_only && o.share.count > 1)
    throw std::invalid_argument("journal_only: a report reconstructs nothing; run it as one process");
  if (o.journal_only && o.journal_dir.empty())
    throw std::invalid_argument("journal_only: name the directory whose journals to report (journal_dir)");
  check_experiments(o.experiments);
  const auto& m = dictionary.manifest();
  if (o.level < 0 || o.level >= m.levels)
    throw std::invalid_argument("click level " + std::to_string(o.level) + " is not stored in the dictionary");
  const bool volume = std::find(o.experiments.begin(), o.experiments.end(), "volume") != o.experiments.end();
  if (o.volume_ambiguity && !volume)
    throw std::invalid_argument("--ambiguity: only with the volume experiment (--experiments volume)");
  const auto points = plan(m.grid, o);
  if (volume && o.volume_events < 1) throw std::invalid_argument("--volume-events: at least 1");
  if (volume && !(o.volume_photons > 0 && std::isfinite(o.volume_photons)))
    throw std::invalid_argument("--volume-photons: a finite number above 0");

  // The system the events come from; `scene` is the refinement's model.
  const Scene& physical = o.truth_scene ? *o.truth_scene : scene;
  if (o.truth_scene) {
    const OpticalSystem &a = physical.optics, &b = m.scene.optics;
    if (a.sensor_width_px != b.sensor_width_px || a.sensor_height_px != b.sensor_height_px || a.pixel_um != b.pixel_um)
      throw std::invalid_argument("the truth scene " + physical.name + " has another sensor than the dictionary's (" +
                                  std::to_string(b.sensor_width_px) + " x " + std::to_string(b.sensor_height_px) +
                                  " px of " + std::to_string(b.pixel_um) + " um): events must be clicks on its pixels");
  }
  const unsigned binning = unsigned(m.base_binning << o.level);
  const TraceSettings model_settings = refine_trace_settings(binning);
  const bool refining = o.model != RefineModel::none;
  TraceSettings t;
  t.binning = binning;
  t.rays_per_lenslet = o.rays ? o.rays : (m.rays_per_lenslet ? m.rays_per_lenslet : TraceSettings::default_rays(o.splat));
  if (!o.rays && o.model == RefineModel::scene) t.rays_per_lenslet = std::max(t.rays_per_lenslet, 4 * model_settings.rays_per_lenslet);
  t.photons_emitted = physical.photons_emitted;
  t.splat = o.splat;
  t.estimator = TraceSettings::default_estimator(o.splat);
  t.stratification = o.stratification;

  // The volume's events: positions from each event's own random stream.
  Field field{};
  std::vector<glm::dvec3> volume_positions;
  std::vector<EventRng> volume_rngs;  // each event's stream, past its position's draws
  const uint64_t volume_first_id = uint64_t(1) << 40;  // ids apart from the paper's points'
  if (volume) {
    field = volume_field(m.grid, o);
    for (int i = 0; i < o.volume_events; ++i) {
      auto rng = event_rng(o.seed, volume_first_id + uint64_t(i));
      glm::dvec3 p;
      p.x = field.x.x + (field.x.y - field.x.x) * uniform01(rng);
      p.y = field.y.x + (field.y.y - field.y.x) * uniform01(rng);
      p.z = field.depth.x + (field.depth.y - field.depth.x) * uniform01(rng);
      volume_positions.push_back(p);
      volume_rngs.push_back(rng);
    }
  }

  ReconstructionSettings s = o.settings;
  if (s.search_level < 0) s.search_level = default_search_level(m, o.level, s.tau_mm);
  const bool on_device = o.backend != ReconstructionBackend::cpu;
  // What renders and reconstructs events; a report from the journals alone
  // needs none of it (and skips the dictionary's coarse level and the models).
  std::optional<ForwardTruth> truth;
  std::unique_ptr<DictionaryService> service;
  if (!o.journal_only) {
    truth.emplace(ctx, physical, t, 64);
    service = std::make_unique<DictionaryService>(dictionary, on_device ? &ctx : nullptr, s.search_level,
                                                  ServiceBudget{}, o.device_half);
  }
  std::map<int, std::unique_ptr<Reconstructor>> reconstructors;  // per K
  std::unique_ptr<Refinement> refiner;
  // Its own model (not the refinement's), so that the refinement's renders
  // per event stay its own.
  std::unique_ptr<SourceModel> ambiguity_model;
  if (o.volume_ambiguity && !o.journal_only) ambiguity_model = make_scene_model(physical, model_settings, &ctx);
  const int refine_level = prism::refine_level(m, o.level, o.refine_level);
  if (refining && !o.journal_only) {
    RefineSettings rs = o.refine;
    rs.dark_rate = s.dark_rate;
    rs.alpha_max = s.alpha_max;
    refiner = std::make_unique<Refinement>(o.model, scene, dictionary, o.level, refine_level, &ctx, rs);
  }

  Evaluation result;
  // What decides an event's outcome, besides the experiment's own choices:
  // the journals' common header.
  const RefineSettings& rs = o.refine;
  json run = {
      {"seed", o.seed},
      {"truth", {{"rays_per_lenslet", t.rays_per_lenslet}, {"splat", to_string(t.splat)},
                 {"stratification", t.stratification}, {"binning", t.binning}}},
      {"scene", to_json(scene)},
      {"dictionary", std::filesystem::weakly_canonical(dictionary.dir()).string()},
      {"search", {{"level", s.search_level}, {"backend", to_string(o.backend)}, {"half", o.device_half},
                  {"tau_mm", s.tau_mm}, {"dark_rate", s.dark_rate},
                  {"search_dark_rate", s.search_dark_rate}, {"candidates", s.refine_candidates},
                  {"newton_iterations", s.newton_iterations}, {"descent_rounds", s.descent_rounds},
                  {"alpha_max", s.alpha_max}, {"min_clicks", s.min_clicks}, {"scan_step_px", s.scan_step_px}}},
      {"refine", {{"model", describe(o.model, scene)}, {"iterations", rs.iterations}, {"aliases", rs.aliases},
                  {"search_starts", rs.search_starts}, {"alias_starts", rs.alias_starts}, {"rescue", rs.rescue},
                  {"lattice_scan", rs.lattice_scan}, {"reseed", rs.reseed}, {"always_scan_below_mm", rs.always_scan_below_mm}, {"always_scan_below_clicks", rs.always_scan_below_clicks},
                  {"ladder_starts", rs.ladder_starts},
                  {"ladder_reach_px", rs.ladder_reach_px}, {"continuation", rs.continuation}, {"site_blur_px", rs.site_blur_px},
                  {"pvalue_draws", rs.pvalue_draws}}}};
  // A journal of events from the model's own scene keeps its header.
  if (o.truth_scene) run["truth"]["scene"] = to_json(physical);
  // Coarse to fine only where the scan is coarser than the select level (a
  // journal of the exhaustive scan keeps its header).
  if (s.search_level > select_level(s, m, o.level))
    run["search"]["carry"] = {{"select_level", select_level(s, m, o.level)}, {"margin_nll", s.carry_margin_nll},
                              {"max", s.carry_max}};
  // The candidates ranked above the clicks only where these are finer than
  // its pixels (a journal of 110 um clicks keeps its header).
  const int ranked_on = detail::rank_level_of(detail::select_level_of(s.search_level, s, m, o.level), s, m, o.level);
  if (ranked_on > o.level) run["search"]["rank_level"] = ranked_on;
  // The refinement staged only where the clicks are finer than its level (a
  // journal of 110 um clicks keeps its header).
  if (refining && refine_level > o.level) run["refine"]["level"] = refine_level;
  const std::string on_mismatch = "rerun with the same options, or without --resume to start over";
  const WorkShare& share = o.share;
  // The protocol's trials done: point -> trial -> estimate. A record of a
  // journal or of another process goes in unless its trial is there already.
  std::optional<EventJournal> points_journal;
  std::vector<std::map<int, std::vector<ReconstructedVertex>>> trials_done(points.size());
  auto take_trial = [&](const json& j, const std::string& from) {
    return read_record(j, from, [&](const json& r) {
      const size_t p = r.at("point").get<size_t>();
      const int trial = r.at("trial").get<int>();
      std::vector<ReconstructedVertex> est;
      for (const json& v : r.at("estimate")) est.push_back(vertex_from_json(v));
      if (p >= points.size() || trial >= o.trials || trials_done[p].count(trial)) return false;
      trials_done[p].emplace(trial, std::move(est));
      return true;
    });
  };
  if (!points.empty() && !o.journal_dir.empty()) {
    json header = run;
    header["prism_evaluate_protocol"] = 1;
    std::vector<std::string> protocol;  // the volume's events are in their own journal
    for (const auto& e : o.experiments)
      if (e != "volume") protocol.push_back(e);
    header["experiments"] = protocol;
    header["quick"] = o.quick;
    header["trials"] = o.trials;  // event ids are point * trials + trial
    points_journal = open_event_journal(o, "protocol-journal", header, on_mismatch, result.journal_estimators);
    for (const json& j : points_journal->records) result.resumed += take_trial(j, points_journal->path);
  }
  // The volume's events done; a later record of an event replaces an earlier.
  std::optional<EventJournal> volume_journal;
  std::vector<std::optional<VolumeEvent>> volume_done(volume_positions.size());
  auto take_volume_event = [&](const json& j, const std::string& from) {
    VolumeEvent v = read_record(j, from, volume_event_from_json);
    if (!o.volume_ambiguity) v.alias_kl = v.p_confusion = v.truth_fit_nll = NAN, v.alias_mm = v.truth_fit_mm = glm::dvec3(NAN);  // not asked for
    if (v.index >= volume_done.size()) return false;
    const bool first = !volume_done[v.index];
    volume_done[v.index] = v;
    return first;
  };
  if (volume && !o.journal_dir.empty()) {
    json header = run;
    header["prism_evaluate_volume"] = 1;
    header["photons"] = o.volume_photons;
    // Only when asked for, so that journals made before the option resume.
    if (o.volume_ambiguity)
      header["ambiguity"] = {{"min_separation_mm", o.ambiguity.min_separation_mm},
                             {"refined", o.ambiguity.refined}, {"iterations", o.ambiguity.iterations},
                             {"p_confusion", confusion_model}};
    header["field_mm"] = {{field.x.x, field.x.y}, {field.y.x, field.y.y}, {field.depth.x, field.depth.y}};
    volume_journal = open_event_journal(
        o, "volume-journal", header,
        "rerun with the same options (--volume-events may differ), or without --resume to start over",
        result.journal_estimators);
    for (const json& j : volume_journal->records) result.resumed += take_volume_event(j, volume_journal->path);
  }

  // This process's events: of those the journals lack, in the order every
  // process enumerates them (the protocol's points and trials, then the
  // volume's events), the ones its share takes.
  std::vector<std::vector<int>> my_trials(points.size());
  std::vector<size_t> my_volume;
  size_t pending = 0;
  if (!o.journal_only) {
    for (size_t pi = 0; pi < points.size(); ++pi)
      for (int trial = 0; trial < o.trials; ++trial)
        if (!trials_done[pi].count(trial) && share.takes(pending++)) my_trials[pi].push_back(trial);
    for (size_t i = 0; i < volume_positions.size(); ++i)
      if (!volume_done[i] && share.takes(pending++)) my_volume.push_back(i);
  }
  size_t total = my_volume.size();
  for (const auto& trials : my_trials) total += trials.size();

  // The CRLB of every vertex position in one study, scaled to its photon
  // count. Every process makes the whole study, as one process would: the
  // device's float sums group a position's with its batch's, so a study of
  // other positions would differ from one process's in the last bits.
  std::vector<glm::dvec3> positions;
  for (const auto& p : points)
    for (const auto& v : p.vertices) positions.push_back(v.position);
  const size_t volume_bounds = positions.size();
  positions.insert(positions.end(), volume_positions.begin(), volume_positions.end());
  const auto bounds = crlb_study(physical, positions, t, Backend::vulkan, SensorModel::poisson, &ctx);
  auto crlb_at = [&](size_t i, double photons) {
    const auto& b = bounds.at(i);
    const double scale = b.photons > 0 ? std::sqrt(b.photons / photons) : INFINITY;
    return std::pair(glm::dvec3(b.crlb.x_mm, b.crlb.y_mm, b.crlb.depth_mm) * scale, b.crlb.r3_mm * scale);
  };

  EvaluationCost& spent = result.cost;
  size_t done = 0;
  uint64_t truth_fit_renders = 0;  // the refinement model's renders of the fits from the truth (not the estimator's)
  // The search, then the refinement, of a batch of K-vertex events.
  // `each(i, estimate, seconds, renders)` is called as event i is done, with
  // its share of the batch's search and its own refinement.
  using EachEvent = std::function<void(size_t, const std::vector<ReconstructedVertex>&, double, uint64_t)>;
  auto reconstruct = [&](const std::vector<Event>& events, int k, const EachEvent& each) {
    ReconstructionSettings ks = s;
    ks.vertices = k;
    auto& r = reconstructors[k];
    if (!r) r = std::make_unique<Reconstructor>(*service, o.level, ks, o.backend, &ctx);
    const auto before = r->timings();
    auto start = std::chrono::steady_clock::now();
    auto estimates = r->run(events);
    spent.scan_s += r->timings().scan_s - before.scan_s;
    const auto searched = std::chrono::steady_clock::now();
    const double search_share = std::chrono::duration<double>(searched - start).count() / double(events.size());
    double each_s = 0;  // what the callbacks take is not the reconstruction's
    for (size_t i = 0; i < events.size(); ++i) {
      const auto refine_start = std::chrono::steady_clock::now();
      const uint64_t renders_before = refiner ? refiner->renders() : 0;
      if (refiner) estimates[i] = refiner->refine(events[i], std::move(estimates[i]));
      const double seconds =
          search_share + std::chrono::duration<double>(std::chrono::steady_clock::now() - refine_start).count();
      const auto each_start = std::chrono::steady_clock::now();
      each(i, estimates[i], seconds, refiner ? refiner->renders() - renders_before : 0);
      each_s += std::chrono::duration<double>(std::chrono::steady_clock::now() - each_start).count();
      if (progress) progress(++done, total);
    }
    const auto end = std::chrono::steady_clock::now();
    spent.reconstruct_s += std::chrono::duration<double>(end - start).count() - each_s;
    spent.refine_s += std::chrono::duration<double>(end - searched).count() - each_s;
    spent.events += events.size();
    if (refiner) spent.renders = refiner->renders() - truth_fit_renders;
  };
  // What this process did, for the leader when there are others.
  json my_trial_records = json::array(), my_volume_records = json::array();

  // The protocol's trials, a point's together: event ids pi * trials + trial.
  for (size_t pi = 0; pi < points.size(); ++pi) {
    if (my_trials[pi].empty()) continue;
    const Point& p = points[pi];
    std::vector<std::shared_ptr<const PsfSampler>> held;
    std::vector<ClickSource> sources;
    for (const auto& v : p.vertices) {
      held.push_back(truth->psf(v.position));
      sources.push_back({held.back().get(), v.photons});
    }
    std::vector<Event> events;
    for (int trial : my_trials[pi]) {
      Event& e = events.emplace_back();
      e.id = uint64_t(pi) * uint64_t(o.trials) + uint64_t(trial);
      auto rng = event_rng(o.seed, e.id);
      sample_clicks(sources, rng, e.clicks);
    }
    reconstruct(events, int(p.vertices.size()),
                [&](size_t i, const std::vector<ReconstructedVertex>& estimate, double, uint64_t) {
                  const int trial = my_trials[pi][i];
                  json rows = json::array();
                  for (const auto& v : estimate) rows.push_back(to_json(v));
                  const json record = {{"point", pi}, {"trial", trial}, {"estimate", rows}};
                  if (points_journal) points_journal->append(record);
                  if (share.count > 1) my_trial_records.push_back(record);
                  trials_done[pi][trial] = estimate;
                });
  }

  // The volume's events, in batches.
  const size_t batch = 32;
  for (size_t first = 0; first < my_volume.size(); first += batch) {
    const size_t n = std::min(batch, my_volume.size() - first);
    std::vector<Event> events(n);
    for (size_t i = 0; i < n; ++i) {
      const size_t index = my_volume[first + i];
      auto& e = events[i];
      e.id = volume_first_id + index;
      auto psf = truth->psf(volume_positions[index]);
      const ClickSource source{psf.get(), o.volume_photons};
      sample_clicks(std::span(&source, 1), volume_rngs[index], e.clicks);
    }
    reconstruct(events, 1, [&](size_t i, const std::vector<ReconstructedVertex>& estimate, double seconds,
                               uint64_t renders) {
      const size_t index = my_volume[first + i];
      VolumeEvent v;
      v.seconds = seconds;
      v.renders = double(renders);
      v.index = index;
      v.truth_mm = volume_positions[index];
      v.estimate = estimate.at(0);
      v.crlb_mm = crlb_at(volume_bounds + index, o.volume_photons).first;
      if (ambiguity_model) {
        const auto ambiguity_start = std::chrono::steady_clock::now();
        AmbiguitySettings as = o.ambiguity;
        as.dark_rate = s.dark_rate;
        const Ambiguity a = ambiguity(*ambiguity_model, physical, v.truth_mm, o.volume_photons, as);
        v.alias_kl = a.kl;
        v.alias_mm = a.impostor_mm;
        v.p_confusion = a.p_confusion;
        spent.ambiguity_s += std::chrono::duration<double>(std::chrono::steady_clock::now() - ambiguity_start).count();
        spent.ambiguity_renders = ambiguity_model->renders();
        if (refiner) {
          const uint64_t before = refiner->renders();
          const Refiner::LocalFit fit = refiner->local_fit(events[i], v.truth_mm, o.volume_photons);
          v.truth_fit_mm = fit.position_mm;
          v.truth_fit_nll = fit.nll;
          truth_fit_renders += refiner->renders() - before;
        }
      }
      const json record = to_json(v);
      if (volume_journal) volume_journal->append(record);
      if (share.count > 1) my_volume_records.push_back(record);
      volume_done[index] = v;
    });
  }

  // Several processes: every one's events to the leader, which keeps them in
  // its journals and makes the figures from all of them; the others are done.
  if (share.count > 1) {
    const auto all = share.all_gather(json{{"protocol", my_trial_records}, {"volume", my_volume_records}}.dump());
    if (share.leads())
      for (size_t r = 1; r < all.size(); ++r) {
        const json theirs = json::parse(all[r]);
        const std::string from = "the events of process " + std::to_string(r);
        for (const json& j : theirs.at("protocol")) {
          take_trial(j, from);
          if (points_journal) points_journal->append(j);
        }
        for (const json& j : theirs.at("volume")) {
          take_volume_event(j, from);
          if (volume_journal) volume_journal->append(j);
        }
      }
    share.wait_for_all();  // the leader's journals hold every event now
    for (auto* j : {&points_journal, &volume_journal})
      if (*j) (*j)->drop_part();
    if (!share.leads()) return result;
  }

  // The protocol's figures: per point, its trials with the best and the
  // worst dropped.
  size_t bound = 0;
  for (size_t pi = 0; pi < points.size(); ++pi) {
    const Point& p = points[pi];
    const size_t n = p.vertices.size();
    std::vector<std::vector<double>> err(n), alpha_err(n);
    std::vector<std::vector<glm::dvec3>> axis_err(n);
    std::vector<int> flagged(n, 0);
    std::vector<std::vector<ReconstructedVertex>> estimates;
    for (auto& [trial, estimate] : trials_done[pi]) estimates.push_back(std::move(estimate));
    if (estimates.size() < 3) {  // only from a journal of a stopped run: too few trials to trim
      bound += n;
      continue;
    }
    std::vector<glm::dvec3> truth_mm;
    for (const auto& v : p.vertices) truth_mm.push_back(v.position);
    for (const auto& est : estimates) {
      auto which = match_vertices(est, truth_mm);
      for (size_t k = 0; k < n; ++k) {
        const auto& v = est.at(which[k]);
        err[k].push_back(error_3d_mm(v, p.vertices[k].position));
        axis_err[k].push_back(error_mm(v, p.vertices[k].position));
        alpha_err[k].push_back(std::abs(v.alpha - p.vertices[k].photons));
        flagged[k] += v.flags != vertex_ok;
      }
    }
    for (size_t k = 0; k < n; ++k, ++bound) {
      EvaluationRow r;
      r.experiment = p.experiment;
      r.series = p.vertices[k].series;
      r.varied = p.vertices[k].varied;
      r.position_mm = p.vertices[k].position;
      r.photons = p.vertices[k].photons;
      r.stats = trimmed_stats(err[k], alpha_err[k]);
      r.flagged = flagged[k];
      auto [crlb, crlb_3d] = crlb_at(bound, r.photons);
      r.crlb_3d_mm = crlb_3d;
      r.axes = axis_stats(axis_err[k], std::vector<glm::dvec3>(axis_err[k].size(), crlb));
      result.rows.push_back(r);
    }
  }

  if (volume) {
    for (const auto& v : volume_done)
      if (v) result.volume.push_back(*v);  // all of them unless journal_only
    // By depth band, then the whole field.
    auto bands = depth_bands(field.depth, o.band_mm);
    bands.push_back(field.depth);
    for (size_t b = 0; b < bands.size(); ++b) {
      const bool whole = b + 1 == bands.size();
      std::vector<double> err, alpha_err, p_confusion;
      std::vector<glm::dvec3> axis_err, crlb;
      EvaluationRow r;
      double crlb3_sq = 0;
      for (const auto& v : result.volume) {
        const double z = v.truth_mm.z;
        const bool last = bands[b].y == field.depth.y;
        if (!whole && !(z >= bands[b].x && (z < bands[b].y || (last && z <= bands[b].y)))) continue;
        err.push_back(error_3d_mm(v.estimate, v.truth_mm));
        axis_err.push_back(error_mm(v.estimate, v.truth_mm));
        alpha_err.push_back(std::abs(v.estimate.alpha - o.volume_photons));
        p_confusion.push_back(v.p_confusion);
        crlb.push_back(v.crlb_mm);
        crlb3_sq += glm::dot(v.crlb_mm, v.crlb_mm);
        r.flagged += v.estimate.flags != vertex_ok;
        if (error_3d_mm(v.estimate, v.truth_mm) > defaults::catastrophic_error_mm && !std::isnan(v.truth_fit_nll)) {
          ++r.catastrophic_classified;
          r.search_failures += v.search_failure();
        }
      }
      r.experiment = "volume";
      r.series = whole ? "all" : "";
      r.depth_lo_mm = bands[b].x;
      r.depth_hi_mm = bands[b].y;
      r.varied = 0.5 * (bands[b].x + bands[b].y);
      r.position_mm = glm::dvec3(NAN);
      r.photons = o.volume_photons;
      // The predicted rate: the mean of p_confusion (NaN when any event lacks it).
      if (!p_confusion.empty()) {
        double sum = 0;
        for (double p : p_confusion) sum += p;
        r.p_confusion_mean = sum / double(p_confusion.size());
      }
      r.stats.trials_used = int(err.size());
      auto me = mean_std(err), ma = mean_std(alpha_err);
      r.stats.err3d_mean = err.empty() ? NAN : me.mean;
      r.stats.err3d_std = err.empty() ? NAN : me.std;
      r.stats.alpha_err_mean = err.empty() ? NAN : ma.mean;
      r.stats.alpha_err_std = err.empty() ? NAN : ma.std;
      r.axes = axis_stats(axis_err, crlb);
      r.crlb_3d_mm = err.empty() ? NAN : std::sqrt(crlb3_sq / double(err.size()));
      result.rows.push_back(r);
    }
  }
  return result;
}

namespace {

std::string csv_number(double x) { return std::isnan(x) ? "" : format_number(x); }

// The columns every experiment shares, after its own.
const char* kStatsHeader =
    "trials_used,err3d_mean_mm,err3d_std_mm,alpha_err_mean,alpha_err_std,flagged,catastrophic_rate,rmse_x_mm,"
    "rmse_y_mm,rmse_z_mm,crlb_x_mm,crlb_y_mm,crlb_z_mm,crlb_3d_mm,efficiency_x,efficiency_y,efficiency_z,"
    "median_ratio_x,median_ratio_y,median_ratio_z";
void write_stats(std::ostream& out, const EvaluationRow& r) {
  out << r.stats.trials_used;
  for (double x : {r.stats.err3d_mean, r.stats.err3d_std, r.stats.alpha_err_mean, r.stats.alpha_err_std})
    out << ',' << csv_number(x);
  out << ',' << r.flagged << ',' << csv_number(r.axes.catastrophic_rate);
  for (const glm::dvec3* v : {&r.axes.rmse_mm, &r.axes.crlb_mm})
    for (int k = 0; k < 3; ++k) out << ',' << csv_number((*v)[k]);
  out << ',' << csv_number(r.crlb_3d_mm);
  for (const glm::dvec3* v : {&r.axes.efficiency, &r.axes.median_ratio})
    for (int k = 0; k < 3; ++k) out << ',' << csv_number((*v)[k]);
}

void write_csv(const std::string& path, const std::function<void(std::ostream&)>& body) {
  write_atomically(path, [&](const std::string& tmp) {
    std::ofstream out(tmp);
    body(out);
    if (!out) throw std::runtime_error("cannot write " + path);
  });
}

// volume-events.csv: one row per event, truth beside estimate.
void write_volume_events(const std::string& path, const std::vector<VolumeEvent>& events) {
  write_csv(path, [&](std::ostream& out) {
    out << "event,x_mm,y_mm,depth_mm,est_x_mm,est_y_mm,est_depth_mm,alpha,err3d_mm,crlb_x_mm,crlb_y_mm,crlb_z_mm,"
           "flags,fit_pvalue,seconds,renders,alias_kl,alias_x_mm,alias_y_mm,alias_depth_mm,p_confusion,nll,truth_fit_x_mm,"
           "truth_fit_y_mm,truth_fit_depth_mm,truth_fit_nll,search_failure\n";
    for (const auto& v : events) {
      const auto& e = v.estimate;
      out << v.index << ',' << format_number(v.truth_mm.x) << ',' << format_number(v.truth_mm.y) << ','
          << format_number(v.truth_mm.z) << ',' << format_number(e.x_mm) << ',' << format_number(e.y_mm) << ','
          << format_number(e.depth_mm) << ',' << format_number(e.alpha) << ','
          << format_number(error_3d_mm(e, v.truth_mm)) << ',' << format_number(v.crlb_mm.x) << ','
          << format_number(v.crlb_mm.y) << ',' << format_number(v.crlb_mm.z) << ',' << flags_to_string(e.flags) << ','
          << csv_number(e.fit_pvalue) << ',' << csv_number(v.seconds) << ',' << csv_number(v.renders);
      for (double x : {v.alias_kl, v.alias_mm.x, v.alias_mm.y, v.alias_mm.z, v.p_confusion}) out << ',' << csv_number(x);
      for (double x : {e.nll, v.truth_fit_mm.x, v.truth_fit_mm.y, v.truth_fit_mm.z, v.truth_fit_nll})
        out << ',' << csv_number(x);
      out << ','
          << (std::isnan(v.truth_fit_nll) ? "" : v.search_failure() ? "1" : "0") << '\n';
    }
  });
}

// volume.png (errors and CRLB per axis by depth band) and volume-catastrophic.png.
void plot_volume(const std::string& dir, const std::vector<const EvaluationRow*>& rows) {
  const char* axis[] = {"x", "y", "depth"};
  std::vector<Series> errors;
  Series mean{"3D error (mean)", {}, {}, false, true}, catastrophic{"measured: events > 3 mm", {}, {}, false, true};
  Series predicted{"predicted: mean p_confusion", {}, {}, true, true};
  // The likelihood's share: catastrophic events less the search's failures
  // (only where every catastrophic event was classified).
  Series confused{"measured, the likelihood's: search failures left out", {}, {}, false, true};
  bool any_classified = false;
  std::vector<Series> rmse(3), crlb(3);
  for (int k = 0; k < 3; ++k) {
    rmse[k] = {std::string("RMSE ") + axis[k], {}, {}, false, true};
    crlb[k] = {std::string("CRLB ") + axis[k], {}, {}, true, false};
  }
  for (const auto* r : rows) {
    if (r->series == "all" || r->axes.events == 0) continue;
    mean.x.push_back(r->varied);
    mean.y.push_back(r->stats.err3d_mean);
    catastrophic.x.push_back(r->varied);
    catastrophic.y.push_back(100 * r->axes.catastrophic_rate);
    if (!std::isnan(r->p_confusion_mean)) {
      predicted.x.push_back(r->varied);
      predicted.y.push_back(100 * r->p_confusion_mean);
    }
    const int catastrophic_events = int(std::lround(r->axes.catastrophic_rate * r->axes.events));
    any_classified = any_classified || r->catastrophic_classified > 0;
    if (r->catastrophic_classified == catastrophic_events) {
      confused.x.push_back(r->varied);
      confused.y.push_back(100.0 * (catastrophic_events - r->search_failures) / r->axes.events);
    }
    for (int k = 0; k < 3; ++k)
      if (!std::isnan(r->axes.rmse_mm[k])) {
        rmse[k].x.push_back(r->varied);
        rmse[k].y.push_back(r->axes.rmse_mm[k]);
        crlb[k].x.push_back(r->varied);
        crlb[k].y.push_back(r->axes.crlb_mm[k]);
      }
  }
  errors.push_back(mean);
  for (int k = 0; k < 3; ++k) errors.push_back(rmse[k]);
  for (int k = 0; k < 3; ++k) errors.push_back(crlb[k]);
  plot_lines(dir + "/volume.png",
             {"volume: errors by depth band (RMSE without events > 3 mm) and CRLB", "depth (mm, band centre)",
              "error (mm)", true},
             errors);
  plot_lines(dir + "/volume-catastrophic.png",
             {"volume: catastrophic estimates (3D error > 3 mm) by depth band", "depth (mm, band centre)",
              "events > 3 mm (%)", false},
             predicted.x.empty()                    ? std::vector<Series>{catastrophic}
             : confused.x.empty() || !any_classified ? std::vector<Series>{catastrophic, predicted}
                                  : std::vector<Series>{catastrophic, confused, predicted});
}

}  // namespace

std::vector<std::string> write_evaluation(const std::string& dir, const Evaluation& evaluation) {
  std::filesystem::create_directories(dir);
  std::vector<std::string> written;
  for (const auto& name : evaluation_experiments()) {
    std::vector<const EvaluationRow*> mine;
    for (const auto& r : evaluation.rows)
      if (r.experiment == name) mine.push_back(&r);
    if (mine.empty()) continue;
    const std::string csv = dir + "/" + name + ".csv", png = dir + "/" + name + ".png";
    if (name == "volume") {
      write_csv(csv, [&](std::ostream& out) {
        out << "experiment,series,depth_lo_mm,depth_hi_mm,photons," << kStatsHeader
            << ",p_confusion_mean,catastrophic_classified,search_failures\n";
        for (const auto* r : mine) {
          out << r->experiment << ',' << r->series << ',' << format_number(r->depth_lo_mm) << ','
              << format_number(r->depth_hi_mm) << ',' << format_number(r->photons) << ',';
          write_stats(out, *r);
          out << ',' << csv_number(r->p_confusion_mean) << ',' << r->catastrophic_classified << ','
              << r->search_failures << '\n';
        }
      });
      write_volume_events(dir + "/volume-events.csv", evaluation.volume);
      plot_volume(dir, mine);
      for (const char* f : {"volume.csv", "volume-events.csv", "volume.png", "volume-catastrophic.png"})
        written.push_back(dir + "/" + f);
      continue;
    }
    write_csv(csv, [&](std::ostream& out) {
      out << "experiment,series,varied,x_mm,y_mm,depth_mm,photons," << kStatsHeader << '\n';
      for (const auto* r : mine) {
        out << r->experiment << ',' << r->series << ',' << format_number(r->varied) << ','
            << format_number(r->position_mm.x) << ',' << format_number(r->position_mm.y) << ','
            << format_number(r->position_mm.z) << ',' << format_number(r->photons) << ',';
        write_stats(out, *r);
        out << '\n';
      }
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
