// The sweep: candidates from the seed, scored in batches, every result
// appended to the state file as it exists so a stopped sweep resumes.
#include "host/sweep/sweep.h"

#include <algorithm>
#include <chrono>
#include <cmath>

#include "host/util/journal.h"

namespace prism {

using json = nlohmann::json;

bool SweepSettings::names_ambiguity() const {
  bool named = objective_is_ambiguity(objective);
  for (const auto& b : bounds) named = named || objective_is_ambiguity(b.objective);
  return named;
}

std::vector<Evaluated> evaluate_designs(const DesignSpace& space, const std::vector<Design>& designs,
                                        const TraceSettings& settings, Backend backend, vk::Context* ctx,
                                        const AmbiguityScoring* ambiguity) {
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
  if (ambiguity)
    for (size_t k = 0; k < scenes.size(); ++k)
      score_ambiguity(scenes[k], space.ambiguity_samples, *ambiguity, backend == Backend::vulkan ? ctx : nullptr,
                      scores[k]);
  double per_design = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count() / double(scenes.size());
  for (size_t k = 0; k < valid.size(); ++k) {
    out[valid[k]].objectives = scores[k];
    out[valid[k]].seconds = per_design;
  }
  return out;
}

Evaluated evaluate_design(const DesignSpace& space, const Design& d, const TraceSettings& settings, Backend backend,
                          vk::Context* ctx, const AmbiguityScoring* ambiguity) {
  return evaluate_designs(space, {d}, settings, backend, ctx, ambiguity).front();
}


namespace {

json to_json(const Evaluated& e) {
  json j = {{"key", e.key}, {"design", e.design.to_json()}, {"origin", e.origin}, {"valid", e.valid}};
  if (!e.valid) {
    j["reason"] = e.reason;
    return j;
  }
  j["objectives"] = to_json(e.objectives);
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
  e.objectives = objectives_from_json(j.at("objectives"));
  e.seconds = j.value("seconds", 0.0);
  return e;
}

}  // namespace

json Sweep::header() const {
  const TraceSettings& t = settings_.trace;
  json h = {{"prism_sweep", 1},
          {"space", space_.source},
          {"rays_per_lenslet", t.rays()},
          {"binning", t.binning},
          {"estimator", to_string(t.estimator)},
          {"splat", to_string(t.splat)},
          {"stratification", t.stratification},
          {"photons_emitted", t.photons_emitted},
          {"backend", settings_.backend == Backend::cpu ? "cpu" : "vulkan"},
          {"batch", settings_.batch},
          {"samples", {{"x_mm", space_.samples.x_mm}, {"y_mm", space_.samples.y_mm}, {"depth_mm", space_.samples.depth_mm}}}};
  if (settings_.ambiguity) {  // absent otherwise, so that sweeps without it resume from older state files
    const SampleGrid& g = space_.ambiguity_samples;
    h["ambiguity"] = settings_.ambiguity->to_json();
    h["ambiguity"]["samples"] = {{"x_mm", g.x_mm}, {"y_mm", g.y_mm}, {"depth_mm", g.depth_mm}};
  }
  return h;
}

Sweep::Sweep(const DesignSpace& space, SweepSettings settings, std::string state_path, WorkShare share)
    : space_(space), settings_(std::move(settings)), state_path_(std::move(state_path)), share_(std::move(share)) {
  objective_value(Objectives{}, settings_.objective);  // an unknown name fails before any work
  if (settings_.budget == 0) throw SweepError("--budget must be at least 1");
  if (settings_.names_ambiguity() && !settings_.ambiguity) settings_.ambiguity.emplace();
  try {
    const std::string on_mismatch =
        "rerun with the same space and --rays/--binning/--device kind (and the ambiguity's options, when the "
        "objective or a bound names it), or use a new --out";
    // The leader makes (or checks) the state file; the others read it.
    if (share_.leads()) journal_.emplace(state_path_, header(), on_mismatch);
    share_.wait_for_all();
    if (!share_.leads()) journal_.emplace(state_path_, header(), on_mismatch, /*read_only=*/true);
  } catch (const JournalError& e) {
    throw SweepError(e.what());
  }
  for (const json& j : journal_->records()) {
    Evaluated e = evaluated_from_json(j);
    stored_.emplace(e.key, e);
    done_.push_back(std::move(e));
  }
}

void Sweep::append(const Evaluated& e) const {
  if (!share_.leads()) return;
  try {
    journal_->append(to_json(e));
  } catch (const JournalError& err) {
    throw SweepError(err.what());
  }
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

std::vector<Evaluated> Sweep::score(const std::vector<Design>& fresh, vk::Context* ctx) const {
  const AmbiguityScoring* ambiguity = settings_.ambiguity ? &*settings_.ambiguity : nullptr;
  if (share_.count == 1) return evaluate_designs(space_, fresh, settings_.trace, settings_.backend, ctx, ambiguity);
  // Each process scores the candidates its share takes; every one gets all
  // the scores, in the candidates' order, as the state file holds them.
  std::vector<Design> mine;
  for (size_t i = 0; i < fresh.size(); ++i)
    if (share_.takes(i)) mine.push_back(fresh[i]);
  json scored = json::array();
  for (const auto& e : evaluate_designs(space_, mine, settings_.trace, settings_.backend, ctx, ambiguity))
    scored.push_back(to_json(e));
  std::vector<Evaluated> out;
  for (const json& e : share_.gather_items(fresh.size(), scored)) out.push_back(evaluated_from_json(e));
  return out;
}

void Sweep::consume(const std::vector<std::pair<Design, std::string>>& queue, vk::Context* ctx,
                    std::vector<size_t>& pool, const std::function<void(const Evaluated&, size_t)>& on_design) {
  // Score what the state file does not hold yet, all together.
  std::vector<Design> fresh;
  for (const auto& [d, origin] : queue)
    if (!stored_.count(d.key())) fresh.push_back(d);
  std::vector<Evaluated> scored = score(fresh, ctx);
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
      const Design& parent = done_[order[draw::index(rng, 4) == 0 ? draw::index(rng, top) : 0]].design;
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
