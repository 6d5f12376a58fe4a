// prism sweep: search a design space for the lenslet array with the lowest
// CRLB over a sample of the volume (host/sweep/sweep.h; host/sweep/SWEEP.md).
#include <atomic>
#include <cmath>
#include <csignal>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <memory>

#include "host/cmd/commands.h"
#include "host/cmd/options.h"
#include "host/cmd/ranks.h"
#include "host/sweep/baselines.h"
#include "host/sweep/sweep.h"
#include "host/util/format.h"
#include "host/util/image_io.h"
#include "host/util/plot.h"
#include "host/util/progress.h"

namespace prism::cmd {

namespace {

struct SweepArgs {
  std::string space, objective = "mean_crlb_3d", out, device, backend = "vulkan";
  size_t budget = 100;
  uint64_t seed = 1;
  size_t batch = 8;
  unsigned rays = 0;  // 0: the splat's sweep default (defaults.h)
  unsigned binning = defaults::sweep_binning;
  SplatOptions splat;
  std::vector<std::string> bounds;
  unsigned keep = 3, confirm = 0;
  bool ambiguity = false;  // score it even when no objective or bound names it
  AmbiguityScoring ambiguity_scoring;
};

std::atomic<bool> interrupted{false};
extern "C" void on_sigint(int) {
  interrupted = true;
  // A second Ctrl-C stops at once (temporaries removed); the state file is safe either way.
  std::signal(SIGINT, remove_temporaries_and_die);
}



void write_csv(const std::string& path, const Sweep& sweep, const std::vector<const Evaluated*>& ranked) {
  write_atomically(path, [&](const std::string& tmp) {
    std::ofstream out(tmp);
    out << "rank,feasible,valid,origin";
    for (const auto& c : DesignSpace::parameter_columns()) out << ',' << c;
    out << ",mean_crlb_3d_mm,worst_crlb_3d_mm,mean_crlb_x_mm,mean_crlb_y_mm,mean_crlb_z_mm,mean_photons,depth_ratio,"
           "p_confusion,worst_p_confusion,alias_kl,seconds,reason,key\n";
    auto maybe = [](double v) { return std::isnan(v) ? std::string() : format_number(v); };  // empty: not scored
    size_t rank = 0;
    for (const Evaluated* e : ranked) {
      bool feasible = e->valid;
      for (const auto& b : sweep.settings().bounds) feasible = feasible && b.holds(e->objectives);
      out << ++rank << ',' << feasible << ',' << e->valid << ',' << e->origin;
      for (const auto& p : sweep.space().parameters(e->design)) out << ',' << csv_field(p);
      const Objectives& o = e->objectives;
      if (e->valid)
        out << ',' << format_number(o.mean_crlb_3d_mm) << ',' << format_number(o.worst_crlb_3d_mm) << ',' << format_number(o.mean_crlb_x_mm) << ','
            << format_number(o.mean_crlb_y_mm) << ',' << format_number(o.mean_crlb_z_mm) << ',' << format_number(o.mean_photons) << ','
            << format_number(o.depth_ratio) << ',' << maybe(o.mean_p_confusion) << ',' << maybe(o.worst_p_confusion)
            << ',' << maybe(o.min_alias_kl) << ',' << format_number(e->seconds) << ',';
      else
        out << ",,,,,,,,,,,," << csv_field(e->reason);
      out << ',' << e->key << '\n';
    }
    if (!out) throw std::runtime_error("cannot write " + path);
  });
}

// A small X at (x, y) drawn as one line series (plot_lines draws lines only).
Series marker(const std::string& label, double x, double y, double dx) {
  return {label, {x - dx, x + dx, x, x - dx, x + dx}, {y * 0.93, y * 1.07, y, y * 1.07, y * 0.93}};
}

// The staircase of the lowest y so far along `pts` (in the order given: best x first).
Series pareto_front(const std::vector<std::pair<double, double>>& pts) {
  Series front{"Pareto front (" + std::to_string(pts.size()) + " designs)", {}, {}};
  double best = INFINITY;
  for (const auto& [x, y] : pts)
    if (y < best && std::isfinite(y)) {
      if (!front.x.empty()) {  // staircase
        front.x.push_back(x);
        front.y.push_back(best);
      }
      best = y;
      front.x.push_back(x);
      front.y.push_back(y);
    }
  return front;
}

void write_plots(const SweepArgs& a, const Sweep& sweep, const std::vector<const Evaluated*>& ranked,
                 const std::vector<Baseline>& baselines, const std::string& stated) {
  // Pareto front: the best objective among designs with at least x photons.
  std::string y_name = objective_is_maximised(a.objective) || objective_is_ambiguity(a.objective) ? "mean_crlb_3d" : a.objective;
  std::vector<std::pair<double, double>> pts;
  for (const Evaluated* e : ranked)
    if (e->valid) pts.push_back({e->objectives.mean_photons, objective_value(e->objectives, y_name)});
  if (pts.empty()) return;
  std::sort(pts.begin(), pts.end(), [](auto& p, auto& q) { return p.first > q.first || (p.first == q.first && p.second < q.second); });
  Series front = pareto_front(pts);
  double dx = 0.01 * std::max(1.0, pts.front().first - pts.back().first);
  std::vector<Series> series{front};
  const Evaluated& top = *ranked.front();
  series.push_back(marker("best-1", top.objectives.mean_photons, objective_value(top.objectives, y_name), dx));
  for (const auto& b : baselines)
    series.push_back(marker(b.name, b.objectives.mean_photons, objective_value(b.objectives, y_name), dx));
  plot_lines(a.out + "/pareto.png",
             {y_name + " vs detected photons, " + stated, "mean detected photons over the samples", y_name + " (mm)", true},
             series);

  std::vector<Series> depth;
  const auto& z = sweep.space().samples.depth_mm;
  for (size_t k = 0; k < ranked.size() && k < a.keep; ++k)
    if (ranked[k]->valid) depth.push_back({"best-" + std::to_string(k + 1), z, ranked[k]->objectives.crlb_3d_by_depth_mm});
  for (const auto& b : baselines) depth.push_back({b.name, z, b.objectives.crlb_3d_by_depth_mm, true});
  plot_lines(a.out + "/crlb-depth.png",
             {"3D CRLB (lateral mean) vs depth, " + stated, "depth from scintillator face (mm)",
              "3D CRLB (mm)", true},
             depth);
}

// The trade-off the ambiguity objectives exist for: the lowest predicted
// confusion rate among designs with at most a given mean 3D CRLB.
void write_ambiguity_plot(const std::string& path, const std::vector<const Evaluated*>& ranked,
                          const std::vector<Baseline>& baselines, const AmbiguityScoring& scoring,
                          const std::string& stated) {
  constexpr double floor = 1e-6;  // the Gaussian tail is not a figure below ~1e-4 (host/reconstruct/ambiguity.h)
  auto p = [&](const Objectives& o) { return std::max(floor, o.mean_p_confusion); };
  std::vector<std::pair<double, double>> pts;
  for (const Evaluated* e : ranked)
    if (e->valid && std::isfinite(e->objectives.mean_crlb_3d_mm) && !std::isnan(e->objectives.mean_p_confusion))
      pts.push_back({e->objectives.mean_crlb_3d_mm, p(e->objectives)});
  if (pts.empty()) return;
  std::sort(pts.begin(), pts.end());
  Series front = pareto_front(pts);
  front.markers = true;
  std::vector<Series> series{front};
  for (const auto& b : baselines)
    if (std::isfinite(b.objectives.mean_crlb_3d_mm))
      series.push_back({b.name, {b.objectives.mean_crlb_3d_mm}, {p(b.objectives)}, false, true});
  plot_lines(path,
             {"confusion vs CRLB: " + format_number(scoring.photons) + " photons, >= " +
                  format_number(scoring.settings.min_separation_mm) + " mm",
              "mean 3D CRLB (mm; " + stated + ")", "mean p_confusion per event (floor 1e-6)", true, true},
             series);
}

void run(const SweepArgs& a) {
  DesignSpace space = DesignSpace::load(a.space);
  SweepSettings s;
  s.trace.rays_per_lenslet = a.rays;
  s.trace.binning = a.binning;
  s.trace.photons_emitted = space.base.photons_emitted;
  a.splat.apply(s.trace);
  if (a.rays == 0)
    s.trace.rays_per_lenslet = s.trace.splat == Splat::point ? defaults::sweep_rays_per_lenslet_point
                                                             : defaults::sweep_rays_per_lenslet;
  s.trace.estimator = TraceSettings::default_estimator(s.trace.splat);
  s.backend = a.backend == "cpu" ? Backend::cpu : Backend::vulkan;
  s.objective = a.objective;
  s.budget = a.budget;
  s.seed = a.seed;
  s.batch = a.batch;
  for (const auto& b : a.bounds) s.bounds.push_back(parse_bound(b));
  if (a.ambiguity || s.names_ambiguity()) s.ambiguity = a.ambiguity_scoring;
  std::filesystem::create_directories(a.out);
  // Under mpirun every rank runs the same search; a batch's candidates are
  // shared out and every rank gets all the scores (host/sweep/sweep.h). Rank
  // 0 writes the state and every output.
  Sweep sweep(space, s, a.out + "/evaluated.jsonl", ranks::work_share());

  std::unique_ptr<vk::Context> ctx;
  std::string device = "CPU reference (double precision)";
  if (s.backend == Backend::vulkan) {
    ctx = std::make_unique<vk::Context>(vk::ContextOptions{a.device});
    device = ctx->describe();
  }
  AnalysisGrid g = AnalysisGrid::of(space.base.optics, a.binning);
  std::string stated = std::to_string(s.trace.rays()) + " rays/lenslet, " + format_number(g.pixel_mm * 1e3) + " um pixels";
  if (ranks::root()) {
    if (ranks::size() > 1)
      std::printf("# %d MPI ranks, each on its own device, share each batch; rank 0's device:\n", ranks::size());
    std::printf("# space: %s (%s designs), objective: minimise %s%s\n", a.space.c_str(), format_number(space.size()).c_str(),
                objective_is_maximised(a.objective) ? ("-" + a.objective).c_str() : a.objective.c_str(),
                s.bounds.empty() ? "" : ", bounds:");
    for (const auto& b : s.bounds) std::printf("#   %s\n", b.text().c_str());
    std::printf("# device: %s\n# rays per 3 mm lenslet: %u, analysis pixel: %u x %u binned = %.1f um, %s splat, %s "
                "Fisher estimator, poisson sensor, %s photons emitted\n",
                device.c_str(), s.trace.rays(), a.binning, a.binning, g.pixel_mm * 1e3, to_string(s.trace.splat),
                to_string(s.trace.estimator), format_number(s.trace.photons_emitted).c_str());
    std::printf("# volume samples: %s\n", space.samples.describe().c_str());
    if (s.ambiguity)
      std::printf("# ambiguity: %s (host/reconstruct/ambiguity.h): %s detected photons, impostors >= %s mm away, "
                  "binary sensor at %u x %u binned pixels, scene model at %u cells per lenslet\n",
                  space.ambiguity_samples.describe().c_str(), format_number(s.ambiguity->photons).c_str(),
                  format_number(s.ambiguity->settings.min_separation_mm).c_str(), s.ambiguity->binning,
                  s.ambiguity->binning, refine_trace_settings(s.ambiguity->binning).rays());
    std::printf("# state: %s/evaluated.jsonl (%zu designs already scored), seed %llu, budget %zu\n", a.out.c_str(),
                sweep.evaluated().size(), static_cast<unsigned long long>(a.seed), a.budget);
    std::fflush(stdout);
  }
  interrupted = false;
  auto previous = std::signal(SIGINT, on_sigint);
  if (previous == SIG_IGN) std::signal(SIGINT, SIG_IGN);  // ignored by who started us: stays so
  Progress progress("prism sweep: designs", a.budget, ranks::root());
  size_t fresh = 0;
  // Every rank stops at the same candidate: the flag is shared (a sum).
  sweep.run(
      ctx.get(), [] { return ranks::size() > 1 ? ranks::sum(uint64_t(interrupted.load())) > 0 : interrupted.load(); },
      [&](const Evaluated&, size_t done) {
        ++fresh;
        progress.update(done);
      });
  progress.finish();
  std::signal(SIGINT, previous);
  // Baselines at the same settings and samples: the prototype and the
  // unifocal arrays, shared out like a batch.
  auto baselines = score_baselines(space, s, ctx.get(), ranks::work_share());
  if (!ranks::root()) return;

  auto ranked = sweep.ranked();
  write_csv(a.out + "/ranked.csv", sweep, ranked);
  for (size_t k = 0; k < ranked.size() && k < a.keep && ranked[k]->valid; ++k) {
    Scene best = space.scene_of(ranked[k]->design, space.name + "-best-" + std::to_string(k + 1));
    std::string path = a.out + "/best-" + std::to_string(k + 1) + ".json";
    write_atomically(path, [&](const std::string& tmp) {
      std::ofstream out(tmp);
      out << to_json(best).dump(2) << '\n';
      if (!out) throw std::runtime_error("cannot write " + path);
    });
  }

  write_plots(a, sweep, ranked, baselines, stated);
  if (s.ambiguity) write_ambiguity_plot(a.out + "/ambiguity.png", ranked, baselines, *s.ambiguity, stated);

  const bool amb = s.ambiguity.has_value();
  std::printf("%-4s %-12s %12s %12s %10s %8s%s  %s\n", "rank", "origin", "mean_3d_mm", "worst_3d_mm", "photons",
              "d_ratio", amb ? "  p_confusion    alias_kl" : "", "focal_mm");
  auto row = [&](const std::string& rank, const std::string& origin, const Objectives& o, const std::string& focal) {
    char extra[64] = "";
    if (amb)
      std::snprintf(extra, sizeof extra, " %12s %11s", format_number(o.mean_p_confusion).c_str(),
                    format_number(o.min_alias_kl).c_str());
    std::printf("%-4s %-12s %12s %12s %10s %8s%s  %s\n", rank.c_str(), origin.c_str(),
                format_number(o.mean_crlb_3d_mm).c_str(), format_number(o.worst_crlb_3d_mm).c_str(),
                format_number(o.mean_photons).c_str(), format_number(o.depth_ratio).c_str(), extra, focal.c_str());
  };
  for (size_t k = 0; k < ranked.size() && k < 5; ++k)
    row(std::to_string(k + 1), ranked[k]->origin, ranked[k]->objectives,
        ranked[k]->valid ? space.parameters(ranked[k]->design)[2] : ranked[k]->reason);
  for (const auto& b : baselines) row("-", b.name, b.objectives, "");
  if (!ranked.empty() && ranked.front()->valid) {
    double best = objective_value(ranked.front()->objectives, a.objective);
    double proto = objective_value(baselines.front().objectives, a.objective);
    // --keep 0 writes no design file: then none is named.
    const std::string file = a.keep > 0 ? " (" + a.out + "/best-1.json)" : "";
    std::printf("# best-1%s: %s = %s vs prototype %s (%+.2f%%); %zu designs scored this run, %zu replayed%s\n",
                file.c_str(), a.objective.c_str(), format_number(best).c_str(), format_number(proto).c_str(), 100 * (best / proto - 1), fresh - sweep.replayed(),
                sweep.replayed(), sweep.exhausted() ? ", space exhausted" : "");
  }

  // The double-precision reference re-scores the top designs: does it rank them the same way?
  if (a.confirm > 0) {
    std::printf("# CPU reference check of the top %u designs (same rays, binning and samples):\n", a.confirm);
    std::printf("%-4s %14s %14s %8s\n", "rank", "device_value", "cpu_value", "cpu_rank");
    for (const auto& c : confirm_with_reference(sweep, ranked, a.confirm))
      std::printf("%-4zu %14s %14s %8zu\n", c.rank, format_number(c.device_value).c_str(),
                  format_number(c.reference_value).c_str(), c.reference_rank);
  }
  std::fprintf(stderr, "prism sweep: wrote %s/ranked.csv, best-*.json, pareto.png, crlb-depth.png%s\n", a.out.c_str(),
               amb ? ", ambiguity.png" : "");
  if (interrupted)
    throw Interrupted("sweep interrupted; " + std::to_string(sweep.evaluated().size()) + " designs kept in " + a.out +
                      "/evaluated.jsonl and ranked above; rerun the same command to resume");
}

}  // namespace

void add_sweep(CLI::App& app) {
  auto a = std::make_shared<SweepArgs>();
  CLI::App* c = app.add_subcommand("sweep", "search a design space of lenslet arrays for the lowest CRLB (host/sweep/SWEEP.md)");
  c->add_option("--space", a->space, "design space JSON file (host/sweep/spaces/*.json)")->required();
  c->add_option("--objective", a->objective, "what to minimise (photons and alias_kl are maximised): " + join(objective_names()))
      ->capture_default_str()->check(CLI::IsMember(objective_names()));
  c->add_option("--budget", a->budget, "designs to score (rejected ones count); the whole space when it is smaller")
      ->capture_default_str()->check(CLI::Range(size_t(1), size_t(1) << 30));
  c->add_option("--out", a->out, "output folder; holds the state to resume from")->required();
  c->add_option("--seed", a->seed, "random start and local search; the same seed gives the same sweep")->capture_default_str();
  c->add_option("--batch", a->batch, "candidates generated and scored together, in one dispatch")
      ->capture_default_str()->check(CLI::Range(size_t(1), size_t(4096)));
  c->add_option("--rays", a->rays,
                std::string("rays (cells) per 3 mm lenslet per source, ") + rays_rounding +
                    "; other sizes: the same per mm^2; default " +
                    std::to_string(defaults::sweep_rays_per_lenslet) + " footprint cells, " +
                    std::to_string(defaults::sweep_rays_per_lenslet_point) + " point rays")
      ->check(CLI::Range(1u, 1u << 24));
  c->add_option("--binning", a->binning, "analyse on B x B binned sensor pixels")
      ->capture_default_str()->check(CLI::Range(1u, 1024u));
  a->splat.add_to(c);
  c->add_option("--device", a->device, device_help);
  c->add_option("--backend", a->backend, "vulkan, or cpu (double-precision reference; slow)")
      ->capture_default_str()->check(CLI::IsMember({"vulkan", "cpu"}));
  c->add_option("--bound", a->bounds, "constraint NAME>=X or NAME<=X, e.g. photons>=100; repeatable");
  c->add_flag("--ambiguity", a->ambiguity,
              "also score the global ambiguity (p_confusion, worst_p_confusion, alias_kl; host/reconstruct/ambiguity.h) "
              "at the space's ambiguity_samples: on by itself when the objective or a bound names one; ~60 renders "
              "per sample and design");
  c->add_option("--ambiguity-photons", a->ambiguity_scoring.photons,
                "ambiguity: detected photons per event (the volume experiment's)")
      ->capture_default_str()->check(CLI::Range(1e-3, 1e9));
  c->add_option("--separation-mm", a->ambiguity_scoring.settings.min_separation_mm,
                "ambiguity: the least distance of an impostor (3D; the catastrophic threshold of prism evaluate)")
      ->capture_default_str()->check(CLI::Range(1e-3, 1e3));
  c->add_option("--keep", a->keep, "write the best K designs as best-1.json ... best-K.json")->capture_default_str();
  c->add_option("--confirm", a->confirm, "re-score the top K designs with the CPU reference and show its ranking");
  c->callback([a] { run(*a); });
}

}  // namespace prism::cmd
