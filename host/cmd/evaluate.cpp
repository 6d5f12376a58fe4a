// prism evaluate: the paper's evaluation protocol and the whole-volume
// experiment (host/reconstruct/evaluate.h) on forward-model events with a
// reconstruction backend and, by default, the continuous refinement; a CSV
// and a PNG per experiment, a table and the reconstruction rate on stdout.
#include <cmath>
#include <cstdio>
#include <memory>

#include "host/cmd/commands.h"
#include "engine/defaults.h"
#include "host/cmd/options.h"
#include "host/cmd/ranks.h"
#include "host/util/output_file.h"
#include "host/reconstruct/evaluate.h"
#include "host/util/progress.h"

namespace prism::cmd {

namespace {

struct EvaluateArgs {
  std::string dictionary, scene, truth_scene, out = "evaluation", backend = "vulkan", experiments = "single-lines,photons,double";
  std::string device;
  std::string precision = "float";
  std::string model;  // scene | none; "": scene when the dictionary was synthesised from one (or --scene given)
  std::vector<double> volume_x, volume_y, volume_depth;
  unsigned binning = 0;  // 0: the dictionary's base binning
  bool quick = false;
  EvaluationOptions options;
  SplatOptions splat{.stratification = EvaluationOptions{}.stratification};
};

std::vector<std::string> split(const std::string& text) {
  std::vector<std::string> v;
  size_t start = 0;
  for (size_t comma; (comma = text.find(',', start)) != std::string::npos; start = comma + 1)
    v.push_back(text.substr(start, comma - start));
  v.push_back(text.substr(start));
  return v;
}

glm::dvec2 range_of(const std::vector<double>& v, const char* option) {
  if (v.empty()) return {NAN, NAN};
  if (v.size() != 2 || !(v[0] < v[1]))
    throw std::runtime_error(std::string(option) + ": give lo,hi in mm with lo < hi");
  return {v[0], v[1]};
}

void run(EvaluateArgs a) {
  check_not_input(a.out, "--out", {{"--dictionary", a.dictionary}, {"--scene", a.scene}, {"--truth-scene", a.truth_scene}});
  Scene scene;
  std::unique_ptr<DictionaryReader> reader;
  if (a.scene.empty()) {
    reader = std::make_unique<DictionaryReader>(a.dictionary);
    scene = reader->manifest().scene;
  } else {
    scene = load_scene(a.scene);
    reader = std::make_unique<DictionaryReader>(a.dictionary, &scene.optics);
  }
  const auto& m = reader->manifest();
  EvaluationOptions& o = a.options;
  if (!a.truth_scene.empty()) o.truth_scene = load_scene(a.truth_scene);
  o.experiments = split(a.experiments);
  o.quick = a.quick;
  o.splat = a.splat.kind();
  o.stratification = a.splat.stratification;
  if (a.quick && o.trials == paper_protocol::trials) o.trials = 5;
  const unsigned binning = a.binning ? a.binning : unsigned(m.base_binning);
  o.level = 0;
  while (o.level < m.levels && unsigned(m.base_binning << o.level) < binning) ++o.level;
  if (o.level == m.levels || unsigned(m.base_binning << o.level) != binning)
    throw std::runtime_error("--binning " + std::to_string(binning) + ": the dictionary stores binnings " +
                             std::to_string(m.base_binning) + " x 2^k only; choose one of those");

  if (o.settings.search_level >= 0 && (o.settings.search_level < o.level || o.settings.search_level >= m.levels))
    throw std::runtime_error("--level " + std::to_string(o.settings.search_level) + ": choose a level from " +
                             std::to_string(o.level) + " (the clicks' own) to " + std::to_string(m.levels - 1) +
                             " (the coarsest in " + a.dictionary + ")");
  if (o.refine_level >= 0) check_refine_level(m, o.level, o.refine_level);
  o.volume_x_mm = range_of(a.volume_x, "--volume-x-mm");
  o.volume_y_mm = range_of(a.volume_y, "--volume-y-mm");
  o.volume_depth_mm = range_of(a.volume_depth, "--volume-depth-mm");
  // The box must lie where events happen (the scene's volume), as simulate's --vertex must.
  {
    const Volume& v = scene.volume;
    const glm::dvec3 mid{(v.x_min_mm + v.x_max_mm) / 2, (v.y_min_mm + v.y_max_mm) / 2,
                         (v.depth_min_mm + v.depth_max_mm) / 2};
    for (int end = 0; end < 2; ++end) {
      if (!std::isnan(o.volume_x_mm.x)) require_in_volume(scene, o.volume_x_mm[end], mid.y, mid.z, "--volume-x-mm");
      if (!std::isnan(o.volume_y_mm.x)) require_in_volume(scene, mid.x, o.volume_y_mm[end], mid.z, "--volume-y-mm");
      if (!std::isnan(o.volume_depth_mm.x))
        require_in_volume(scene, mid.x, mid.y, o.volume_depth_mm[end], "--volume-depth-mm");
    }
  }
  o.model = choose_refine_model(a.model, m, !a.scene.empty(), a.dictionary);

  o.backend = backend_from_string(a.backend);
  o.device_half = a.precision == "half";
  o.share = ranks::work_share();
  if (o.journal_only && ranks::size() > 1)
    throw std::runtime_error("--journal-only reconstructs nothing: run it as one process, without mpirun");
  vk::Context ctx(vk::ContextOptions{a.device});
  o.journal_dir = a.out;
  // Under mpirun rank 0 speaks for the job and writes every output.
  if (ranks::root()) {
    if (ranks::size() > 1)
      std::printf("# %d MPI ranks, each on its own device; the events are shared, the times below summed; rank "
                  "0's device:\n",
                  ranks::size());
    if (o.backend == ReconstructionBackend::cpu)
      std::printf("# reconstruction: CPU reference (double precision, 1 thread); events and CRLB: %s\n",
                  ctx.describe().c_str());
    else
      std::printf("# reconstruction: %s scan (%s dictionary) and events and CRLB on %s\n", to_string(o.backend),
                  a.precision.c_str(), ctx.describe().c_str());
    std::printf("# scene %s, dictionary %s, clicks on %u x %u binned pixels, %d trials per point, seed %llu\n",
                scene.name.c_str(), a.dictionary.c_str(), binning, binning, o.trials, (unsigned long long)o.seed);
    if (o.truth_scene)
      std::printf("# events, CRLB%s from the truth scene %s (the refinement's model: scene %s)\n",
                  o.volume_ambiguity ? " and ambiguity" : "", o.truth_scene->name.c_str(), scene.name.c_str());
    std::printf("# refinement: %s\n", describe(o.model, scene).c_str());
    if (const int rl = refine_level(m, o.level, o.refine_level);
        o.model != RefineModel::none && rl > o.level)
      std::printf("# refinement on level %d (%u x %u binned pixels; --refine-level), then fitted again on the clicks' "
                  "pixels from its answer\n",
                  rl, m.base_binning << rl, m.base_binning << rl);
    std::printf("# best and worst trial (3D error) dropped; alpha error = |alpha - true photons|; CRLB: Poisson, "
                "Fisher information scaled to the point's detected photons; catastrophic: 3D error > %g mm, left "
                "out of RMSE and efficiency\n",
                defaults::catastrophic_error_mm);
    if (o.journal_only)
      std::printf("# from the journals in %s only: nothing reconstructed, points with fewer than 3 trials left out\n",
                  a.out.c_str());
    else
      std::printf("# events are kept in %s/*-journal.jsonl as they are done; %s\n", a.out.c_str(),
                  o.resume ? "resuming from what is there" : "a stopped run resumes from there with --resume");
  }
  std::unique_ptr<Progress> progress;
  auto result = evaluate(ctx, scene, *reader, o, [&](size_t done, size_t total) {
    if (!progress)
      progress = std::make_unique<Progress>(ranks::size() > 1 ? "evaluate (rank 0's share)" : "evaluate", total,
                                            ranks::root());
    progress->update(done);
  });
  if (progress) progress->finish();
  EvaluationCost& cost = result.cost;
  cost.events = ranks::sum(cost.events);
  cost.renders = ranks::sum(cost.renders);
  cost.ambiguity_renders = ranks::sum(cost.ambiguity_renders);
  for (double* x : {&cost.reconstruct_s, &cost.scan_s, &cost.refine_s, &cost.ambiguity_s}) *x = ranks::sum(*x);
  if (!ranks::root()) return;
  for (const auto& e : result.journal_estimators) std::printf("# made by %s\n", e.c_str());

  std::printf("%-20s %7s %7s %7s %8s %5s %9s %9s %9s %9s %8s %6s %6s %6s %7s\n", "experiment", "x_mm", "y_mm",
              "depth", "photons", "used", "err3d_mm", "std_mm", "alpha_err", "crlb_3d", "cat_%", "eff_x", "eff_y",
              "eff_z", "flagged");
  for (const auto& r : result.rows) {
    std::string name = r.experiment + (r.series.empty() ? "" : ":" + r.series);
    if (r.experiment == "volume")
      std::printf("%-20s %7s %7s %3.0f-%-3.0f %8.1f", name.c_str(), "", "", r.depth_lo_mm, r.depth_hi_mm, r.photons);
    else
      std::printf("%-20s %7.2f %7.2f %7.2f %8.1f", name.c_str(), r.position_mm.x, r.position_mm.y, r.position_mm.z,
                  r.photons);
    std::printf(" %5d %9.4f %9.4f %9.3f %9.4f %8.1f %6.2f %6.2f %6.2f %7d\n", r.stats.trials_used,
                r.stats.err3d_mean, r.stats.err3d_std, r.stats.alpha_err_mean, r.crlb_3d_mm,
                100 * r.axes.catastrophic_rate, r.axes.efficiency.x, r.axes.efficiency.y, r.axes.efficiency.z,
                r.flagged);
  }
  for (const auto& r : result.rows)
    if (r.experiment == "volume" && r.series == "all")
      std::printf("volume: %d events, %.1f%% catastrophic (> %g mm); median |err| / CRLB x %.2f, y %.2f, depth %.2f "
                  "(0.67 when efficient)\n",
                  r.axes.events, 100 * r.axes.catastrophic_rate, defaults::catastrophic_error_mm,
                  r.axes.median_ratio.x, r.axes.median_ratio.y, r.axes.median_ratio.z);
  for (const auto& r : result.rows)
    if (r.experiment == "volume" && !std::isnan(r.p_confusion_mean))
    {
      std::printf("volume %s %.0f-%.0f mm: predicted catastrophic rate (mean p_confusion) %.3g%%, measured %.3g%% "
                  "(%d events)",
                  r.series == "all" ? "all" : "band", r.depth_lo_mm, r.depth_hi_mm, 100 * r.p_confusion_mean,
                  100 * r.axes.catastrophic_rate, r.axes.events);
      // What p_confusion predicts is the likelihood's share.
      if (r.catastrophic_classified > 0)
        std::printf("; of %d catastrophic with the truth fitted, %d the search's (the fit from the truth stays "
                    "there and scores better), %d the likelihood's",
                    r.catastrophic_classified, r.search_failures, r.catastrophic_classified - r.search_failures);
      std::printf("\n");
    }
  if (result.resumed)
    std::printf("%zu events read from the journals in %s (reconstructed by an earlier run; not in the cost below)\n",
                result.resumed, a.out.c_str());
  {
    double seconds = 0, renders = 0;
    size_t costed = 0;
    for (const auto& v : result.volume)
      if (std::isfinite(v.seconds)) seconds += v.seconds, renders += v.renders, ++costed;
    if (costed)
      std::printf("volume: %.2f s and %.1f renders per event over the %zu of %zu events whose cost is recorded "
                  "(journal included)\n",
                  seconds / double(costed), renders / double(costed), costed, result.volume.size());
  }
  std::printf("reconstruction: %llu events in %.2f s, %.2f events/s, %.2f s per event (support scans %.2f s, "
              "refinement %.2f s of it, %.1f renders per event; %s backend)\n",
              (unsigned long long)cost.events, cost.reconstruct_s,
              cost.reconstruct_s > 0 ? double(cost.events) / cost.reconstruct_s : 0.0,
              cost.events ? cost.reconstruct_s / double(cost.events) : 0.0, cost.scan_s, cost.refine_s,
              cost.events ? double(cost.renders) / double(cost.events) : 0.0, a.backend.c_str());
  if (cost.ambiguity_s > 0)
    std::printf("ambiguity: %.2f s and %.1f renders per volume event (%.1f s in all)\n",
                cost.ambiguity_s / double(result.volume.size() - result.resumed),
                double(cost.ambiguity_renders) / double(result.volume.size() - result.resumed), cost.ambiguity_s);
  for (const auto& path : write_evaluation(a.out, result))
    std::fprintf(stderr, "prism evaluate: wrote %s\n", path.c_str());
}

}  // namespace

void add_evaluate(CLI::App& app) {
  auto a = std::make_shared<EvaluateArgs>();
  CLI::App* c = app.add_subcommand(
      "evaluate", "accuracy against the truth and the CRLB: the paper's protocol and events over the whole volume");
  c->add_option("--dictionary", a->dictionary, "PSF dictionary directory")->required();
  c->add_option("--scene", a->scene, "built-in scene or JSON file (default: the dictionary's own)");
  c->add_option("--truth-scene", a->truth_scene,
                "built-in scene or JSON file the events come from, when not --scene: an as-built system (for "
                "example prototype-as-built) reconstructed with the nominal or a calibrated model; it gives the "
                "events, the CRLB and the ambiguity, --scene only the refinement's model");
  c->add_option("--experiments", a->experiments,
                "comma-separated: single-lines (x, y, depth lines through (1,1,31) mm at 100 photons), photons "
                "(50, 100, 200, 400 at (1,1,31)), double ((1,1,depth) and (1,1,7.5), 250 photons split 50/50), volume "
                "(--volume-events single vertices of --volume-photons uniform over the field, by depth band)")
      ->capture_default_str()
      ->check([](const std::string& text) -> std::string {
        // Checked as the arguments are read, before the run prints anything.
        try {
          check_experiments(split(text));
        } catch (const std::invalid_argument& e) {
          return e.what();
        }
        return "";
      });
  c->add_option("--model", a->model,
                "continuous refinement after the search: scene (the scene's forward model; the default when the "
                "dictionary was synthesised from a scene or --scene is given), dictionary (its PSFs interpolated; "
                "the default for calibrated ones) or none (the search alone)")
      ->check(CLI::IsMember({"scene", "dictionary", "none"}));
  add_always_scan_options(c, a->options.refine.always_scan_below_mm, a->options.refine.always_scan_below_clicks);
  add_refine_level_option(c, a->options.refine_level);
  c->add_option("--volume-events", a->options.volume_events, "volume: events, each at its own position")
      ->capture_default_str()->check(CLI::Range(1, 10000000));
  c->add_option("--volume-photons", a->options.volume_photons,
                "volume: expected detected photons of each event (the CRLB and the ambiguity at the same count)")
      ->capture_default_str()->check(positive_number);
  c->add_flag("--ambiguity", a->options.volume_ambiguity,
              "volume: also each event's global ambiguity at its true position, as `prism crlb --ambiguity` "
              "(columns alias_kl, alias_*_mm, p_confusion in volume-events.csv), and per depth band the "
              "catastrophic rate it predicts (mean p_confusion) beside the rate measured; about 80 renders per event. "
              "With a refinement, also the refinement's model fitted from the truth on each event's clicks "
              "(columns truth_fit_*): a catastrophic estimate is the search's failure (column search_failure) when "
              "that fit stays within 3 mm of the truth with a lower NLL than the estimate's, and otherwise the "
              "likelihood's, which is what p_confusion predicts");
  c->add_option("--separation-mm", a->options.ambiguity.min_separation_mm,
                "with --ambiguity: the least distance of an impostor (3D)")
      ->capture_default_str()->check(positive_number);
  c->add_option("--volume-x-mm", a->volume_x, "volume: x range lo,hi (default: the dictionary grid's)")
      ->delimiter(',')->expected(2);
  c->add_option("--volume-y-mm", a->volume_y, "volume: y range lo,hi (default: the dictionary grid's)")
      ->delimiter(',')->expected(2);
  c->add_option("--volume-depth-mm", a->volume_depth, "volume: depth range lo,hi (default: the dictionary grid's)")
      ->delimiter(',')->expected(2);
  c->add_option("--band-mm", a->options.band_mm, "volume: width of the depth bands reported")
      ->capture_default_str()->check(positive_number);
  c->add_option("--trials", a->options.trials, "events per point (best and worst dropped); --quick: 5")
      ->capture_default_str()->check(CLI::Range(3, 100000));
  c->add_option("--out", a->out,
                "directory for <experiment>.csv and <experiment>.png, and the journals of the events done so far "
                "(protocol-journal.jsonl, volume-journal.jsonl)")
      ->capture_default_str();
  c->add_option("--binning", a->binning, "click binning: the dictionary's base binning x 2^k (default: base)")
      ->check(CLI::Range(1u, 1024u));
  c->add_option("--rays", a->options.rays, std::string("rays per 3 mm lenslet for the event truth and the CRLB, ") + rays_rounding +
                                           "; default: the dictionary's, and at least 4x the refinement model's")
      ->check(CLI::Range(1u, 1u << 24));
  a->splat.add_to(c, "here for the event truth and the CRLB, by default strata other than the dictionary's (0), so "
                     "that the estimator never sees its own model");
  c->add_flag("--resume", a->options.resume,
              "reconstruct only the events the journals in --out lack (a run stopped or killed, or one given more "
              "--volume-events); the journals must come from the same options and engine");
  c->add_flag("--journal-only", a->options.journal_only,
              "reconstruct nothing: the tables, CSVs and plots from what the journals in --out hold, the events of "
              "a stopped run or of one still running (points with fewer than 3 trials there are left out); give the "
              "events' options of the run that made them (seed, experiments, trials, field, truth), its search "
              "and refinement are read from the journals and printed");
  c->add_option("--seed", a->options.seed, "random seed of the events")->capture_default_str();
  c->add_flag("--quick", a->quick, "a reduced grid (2 points per line, 2 photon counts, 1 double) with 5 trials");
  c->add_option("--backend", a->backend,
                "reconstruction backend: vulkan (sparse scan on the device), dense (the paper's dense correlation "
                "on the device), cpu (the double-precision reference)")
      ->capture_default_str()->check(CLI::IsMember({"vulkan", "dense", "cpu"}));
  c->add_option("--level", a->options.settings.search_level,
                "dictionary level of the support scan (default: as `prism reconstruct`, coarse to fine from a "
                "level chosen by a budget of shifts per click)")
      ->check(non_negative_number);
  c->add_option("--dark-rate", a->options.settings.dark_rate, dark_rate_help)->capture_default_str()->check(positive_number);
  c->add_option("--search-dark-rate", a->options.settings.search_dark_rate, search_dark_rate_help)
      ->capture_default_str()
      ->check(non_negative_number);
  c->add_option("--precision", a->precision, "device backends: the scan level's values as float or half")
      ->capture_default_str()->check(CLI::IsMember({"float", "half"}));
  c->add_option("--device", a->device, "Vulkan device for the reconstruction, the event truth and the CRLB (see "
                                       "`prism devices`)");
  c->callback([a] { run(*a); });
}

}  // namespace prism::cmd
