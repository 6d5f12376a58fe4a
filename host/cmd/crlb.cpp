// prism crlb: Cramer-Rao lower bounds against depth for one or more scenes.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <map>

#include "host/cmd/commands.h"
#include "host/cmd/options.h"
#include "host/util/output_file.h"
#include "host/reconstruct/ambiguity.h"
#include "host/util/format.h"
#include "host/util/image_io.h"
#include "host/util/plot.h"

namespace prism::cmd {

namespace {

constexpr double kConfusionFloor = 1e-9;  // the confusion plot's log axis starts here

// out/crlb.png -> out/crlb-ambiguity.png
std::string ambiguity_plot_path(const std::string& plot) {
  const auto dot = plot.find_last_of('.');
  const auto slash = plot.find_last_of('/');
  if (dot == std::string::npos || (slash != std::string::npos && dot < slash)) return plot + "-ambiguity";
  return plot.substr(0, dot) + "-ambiguity" + plot.substr(dot);
}

struct CrlbArgs {
  std::vector<std::string> scenes{"prototype"};
  std::string depths = "0:50:2.5";
  double x_mm = 0, y_mm = 0;
  std::string sensor = "poisson";
  std::string csv, plot;
  double converge = 0;
  unsigned max_rays = 1u << 20;
  bool ambiguity = false;
  double separation_mm = AmbiguitySettings{}.min_separation_mm;
  ForwardOptions fw;
};


void run(const CrlbArgs& a) {
  if (!a.csv.empty()) check_writable(a.csv);
  if (!a.plot.empty()) check_writable(a.plot), check_plot_path(a.plot);
  if (!a.plot.empty() && a.ambiguity) check_writable(ambiguity_plot_path(a.plot));
  for (const std::string& scene : a.scenes)
    for (const auto& [option, out] : {std::pair{"--csv", a.csv}, {"--plot", a.plot}})
      if (!out.empty()) check_not_input(out, option, {{"--scene", scene}});
  auto depths = parse_list(a.depths, "--depth-mm");
  std::vector<glm::dvec3> positions;
  for (double d : depths) positions.push_back({a.x_mm, a.y_mm, d});
  SensorModel sensor = a.sensor == "binary" ? SensorModel::binary : SensorModel::poisson;

  // Load every scene first: a bad scene fails before any work is done.
  std::vector<Scene> scenes;
  for (const auto& name : a.scenes) {
    scenes.push_back(load_scene(name));
    a.fw.apply(scenes.back());
    for (double d : depths) require_in_front(scenes.back(), d, "--depth-mm");
  }
  std::unique_ptr<vk::Context> ctx;
  std::string device = "CPU reference (double precision)";
  if (a.fw.backend_kind() == Backend::vulkan) {
    ctx = std::make_unique<vk::Context>(vk::ContextOptions{a.fw.device});
    device = ctx->describe();
  }
  TraceSettings t0 = a.fw.settings(scenes.front());
  AnalysisGrid g0 = AnalysisGrid::of(scenes.front().optics, t0.binning);
  std::printf("# device: %s\n# %s splat, %u %s per lenslet, analysis pixel: %u x %u binned = %.1f um, sensor model: %s, "
              "%s Fisher estimator\n",
              device.c_str(), to_string(t0.splat), t0.rays(), t0.splat == Splat::footprint ? "cells" : "rays", t0.binning,
              t0.binning, g0.pixel_mm * 1e3, a.sensor.c_str(), to_string(t0.estimator));
  // Without --converge every row is checked against a quarter of its cells
  // (rays): one extra pass at a quarter of the cost. Where the CRLB is
  // dominated by sharp edges it converges fast; where little information is on
  // the sensor (a blur disc larger than the sensor, heavy aberration) the
  // splat's own discretisation can dominate, and the check shows it.
  const double tol = a.converge > 0 ? a.converge : defaults::crlb_convergence_tol;
  if (a.converge > 0)
    std::printf("# convergence: rays x4 until the 3D CRLB changes by <= %s%% (column 'change'), at most %u rays\n",
                format_number(100 * a.converge).c_str(), a.max_rays);
  else
    std::printf("# convergence: each row against a quarter of the %s (column 'change'); flag 'moving' where it "
                "changed by more than %s%%: use --converge for those\n",
                t0.splat == Splat::footprint ? "cells" : "rays", format_number(100 * tol).c_str());
  if (t0.binning > 1)
    std::printf("# CRLB at %.0f um analysis pixels: an upper bound on the CRLB at the native %.1f um pixels "
                "(--binning 1)\n",
                g0.pixel_mm * 1e3, scenes.front().optics.pixel_um);
  else
    std::printf("# CRLB at the sensor's native %.1f um pixels\n", scenes.front().optics.pixel_um);
  AmbiguitySettings as;
  as.min_separation_mm = a.separation_mm;
  if (a.ambiguity)
    std::printf("# ambiguity: binary sensor (dark rate %s per pixel), the closest impostor at least %s mm away "
                "(lattice aliases to 2 pitches, depth moves and the CRLB's weakest direction, the best %d refined; photons "
                "fitted), scene model at %u cells per lenslet; alias_kl in nats at the row's photons, p_confusion "
                "per event (an estimate that far or farther) "
                "(host/reconstruct/ambiguity.h)\n",
                format_number(as.dark_rate).c_str(), format_number(as.min_separation_mm).c_str(), as.refined,
                refine_trace_settings(t0.binning).rays_per_lenslet);
  std::printf("%-14s %-4s %7s %7s %7s %9s %10s %10s %10s %10s %8s %7s  %s%s\n", "scene", "lens", "x_mm", "y_mm", "depth",
              "photons", "crlb_x", "crlb_y", "crlb_z", "crlb_3d", "rays", "change", "flag",
              a.ambiguity ? "  alias_kl alias_x alias_y alias_z p_confusion" : "");

  std::vector<CrlbRow> all;
  std::vector<Ambiguity> ambiguities;  // beside `all`, with --ambiguity
  for (const auto& scene : scenes) {
    TraceSettings t = a.fw.settings(scene);
    auto start = std::chrono::steady_clock::now();
    std::fprintf(stderr, "prism crlb: %s (%s lens), %zu positions, %u rays/lenslet ...", scene.name.c_str(),
                 to_string(scene.optics.lens_model), positions.size(), t.rays());
    std::fflush(stderr);
    std::vector<CrlbRow> rows =
        crlb_checked(scene, positions, t, a.converge, a.max_rays, a.fw.backend_kind(), sensor, ctx.get());
    double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    std::fprintf(stderr, " %.2f s\n", s);
    std::unique_ptr<SourceModel> model;
    if (a.ambiguity) model = make_scene_model(scene, refine_trace_settings(t.binning), ctx.get());
    for (size_t i = 0; i < rows.size(); ++i) {
      const auto& r = rows[i];
      std::string extra;
      if (model) {
        std::fprintf(stderr, "prism crlb: %s ambiguity at depth %s (%zu of %zu) ...", scene.name.c_str(),
                     format_number(r.theta.z).c_str(), i + 1, rows.size());
        const auto t_start = std::chrono::steady_clock::now();
        const Ambiguity amb = ambiguity(*model, scene, r.theta, r.photons, as);
        std::fprintf(stderr, " %.1f s\n", std::chrono::duration<double>(std::chrono::steady_clock::now() - t_start).count());
        ambiguities.push_back(amb);
        char buf[160];
        std::snprintf(buf, sizeof buf, "  %8s %7.2f %7.2f %7.2f %11s", format_number(amb.kl).c_str(), amb.impostor_mm.x,
                      amb.impostor_mm.y, amb.impostor_mm.z, format_number(amb.p_confusion).c_str());
        extra = buf;
      }
      std::printf("%-14s %-4s %7.2f %7.2f %7.2f %9.2f %10s %10s %10s %10s %8u %7s  %s%s\n", r.scene.c_str(),
                  to_string(r.lens_model), r.theta.x, r.theta.y, r.theta.z, r.photons, format_number(r.crlb.x_mm).c_str(),
                  format_number(r.crlb.y_mm).c_str(), format_number(r.crlb.depth_mm).c_str(), format_number(r.crlb.r3_mm).c_str(),
                  r.rays_per_lenslet, std::isnan(r.change) ? "-" : format_number(r.change).c_str(), r.crlb.flag.c_str(),
                  extra.c_str());
      all.push_back(r);
    }
    // Real lenses at fine pixels: the geometric CRLB follows slivers of light
    // at the caustics and need not settle; the Airy core smooths them.
    const bool caustics = scene.optics.lens_model == LensModel::real && !scene.optics.effects.diffraction &&
                          g0.pixel_mm < defaults::caustic_pixel_mm;
    if (caustics && std::any_of(rows.begin(), rows.end(), [](const CrlbRow& r) { return r.crlb.flag == "moving"; }))
      std::printf("# %s: real lenses at %.1f um pixels without the diffraction effect: the geometric CRLB follows the "
                  "caustics' slivers of light and does not settle with more cells; with the lenslets' Airy core it "
                  "does: a scene file with {\"base\": \"%s\", \"effects\": [\"diffraction\"]} "
                  "(docs/model.md \"Convergence\")\n",
                  scene.name.c_str(), g0.pixel_mm * 1e3, scene.name.c_str());
  }

  if (!a.csv.empty()) {
    write_atomically(a.csv, [&](const std::string& tmp) {
      std::ofstream out(tmp);
      out << "scene,x_mm,y_mm,depth_mm,photons,crlb_x_mm,crlb_y_mm,crlb_z_mm,crlb_3d_mm,"
             "lens_model,sensor_model,rays_per_lenslet,binning,analysis_pixel_um,change_vs_quarter_rays,flag"
          << (a.ambiguity ? ",alias_kl,alias_x_mm,alias_y_mm,alias_depth_mm,p_confusion" : "") << '\n';
      for (size_t i = 0; i < all.size(); ++i) {
        const auto& r = all[i];
        out << r.scene << ',' << format_number(r.theta.x) << ',' << format_number(r.theta.y) << ',' << format_number(r.theta.z) << ','
            << format_number(r.photons) << ',' << format_number(r.crlb.x_mm) << ',' << format_number(r.crlb.y_mm) << ',' << format_number(r.crlb.depth_mm)
            << ',' << format_number(r.crlb.r3_mm) << ',' << to_string(r.lens_model) << ',' << a.sensor << ','
            << r.rays_per_lenslet << ',' << t0.binning << ',' << format_number(g0.pixel_mm * 1e3) << ','
            << (std::isnan(r.change) ? "" : format_number(r.change)) << ',' << r.crlb.flag;
        if (a.ambiguity) {
          const Ambiguity& m = ambiguities[i];
          out << ',' << format_number(m.kl) << ',' << format_number(m.impostor_mm.x) << ',' << format_number(m.impostor_mm.y)
              << ',' << format_number(m.impostor_mm.z) << ',' << format_number(m.p_confusion);
        }
        out << '\n';
      }
      if (!out) throw std::runtime_error("cannot write " + a.csv);
    });
    std::fprintf(stderr, "prism crlb: wrote %s\n", a.csv.c_str());
  }
  if (!a.plot.empty()) {
    std::map<std::string, Series> by_scene;
    std::vector<std::string> order;
    for (const auto& r : all) {
      std::string key = r.scene + " (" + to_string(r.lens_model) + ")";
      if (!by_scene.count(key)) order.push_back(key);
      Series& s = by_scene[key];
      s.label = key;
      s.dashed = r.scene.rfind("single", 0) == 0;
      s.x.push_back(r.theta.z);
      s.y.push_back(r.crlb.r3_mm);
    }
    std::vector<Series> series;
    for (const auto& k : order) series.push_back(by_scene[k]);
    plot_lines(a.plot,
               {"3D CRLB against depth (" + format_number(t0.photons_emitted) + " photons emitted, " + a.sensor + " sensor)",
                "depth from scintillator face (mm)", "3D CRLB (mm)", true},
               series);
    std::fprintf(stderr, "prism crlb: wrote %s\n", a.plot.c_str());
    if (a.ambiguity) {
      // Beside it: the predicted confusion against depth, floored for the log axis.
      std::map<std::string, Series> conf;
      for (size_t i = 0; i < all.size(); ++i) {
        const std::string key = all[i].scene + " (" + to_string(all[i].lens_model) + ")";
        Series& s = conf[key];
        s.label = key;
        s.dashed = all[i].scene.rfind("single", 0) == 0;
        s.x.push_back(all[i].theta.z);
        s.y.push_back(std::max(ambiguities[i].p_confusion, kConfusionFloor));
      }
      std::vector<Series> cs;
      for (const auto& k : order) cs.push_back(conf[k]);
      const std::string path = ambiguity_plot_path(a.plot);
      plot_lines(path,
                 {"Predicted probability of an estimate >= " + format_number(as.min_separation_mm) +
                      " mm off (binary sensor; floor " + format_number(kConfusionFloor) + ")",
                  "depth from scintillator face (mm)", "p_confusion per event", true},
                 cs);
      std::fprintf(stderr, "prism crlb: wrote %s\n", path.c_str());
    }
  }
}

}  // namespace

void add_crlb(CLI::App& app) {
  auto a = std::make_shared<CrlbArgs>();
  CLI::App* c = app.add_subcommand("crlb", "Cramer-Rao lower bounds (Fisher information) against depth");
  c->add_option("--scene", a->scenes,
                "built-in scene or JSON file; repeat for several (prototype, prototype-as-built, unifocal-f3/9/15, single-f3/9/15)")
      ->capture_default_str();
  c->add_option("--depth-mm", a->depths, "depths from the scintillator face: A,B,C or FIRST:LAST:STEP")
      ->capture_default_str();
  c->add_option("--x-mm", a->x_mm, "lateral source position x")->capture_default_str();
  c->add_option("--y-mm", a->y_mm, "lateral source position y")->capture_default_str();
  c->add_option("--sensor", a->sensor, "poisson (paper eq. 2) or binary single-photon pixels")
      ->capture_default_str()->check(CLI::IsMember({"poisson", "binary"}));
  c->add_option("--csv", a->csv, "write one row per (scene, position)");
  c->add_option("--plot", a->plot, "draw 3D CRLB against depth (.png or .svg)");
  c->add_option("--converge", a->converge,
                "quadruple the rays until every 3D CRLB changes by at most this fraction (e.g. 0.02); without it "
                "each row is checked against a quarter of the rays")
      ->check(CLI::Range(0.0, 1.0));
  c->add_option("--max-rays", a->max_rays, "with --converge: most rays per 3 mm lenslet")->capture_default_str();
  c->add_flag("--ambiguity", a->ambiguity,
              "also the global figure per row: the closest impostor source at least --separation-mm away on the "
              "binary sensor (KL divergence in nats at the row's photons, its position) and the predicted "
              "probability per event that the estimate lands --separation-mm or more away (columns alias_kl, alias_x_mm, alias_y_mm, "
              "alias_depth_mm, p_confusion; with --plot also PLOT-ambiguity.png)");
  c->add_option("--separation-mm", a->separation_mm, "with --ambiguity: the least distance of an impostor (3D)")
      ->capture_default_str()->check(positive_number);
  a->fw.add_to(c, defaults::analysis_binning);
  c->callback([a] { run(*a); });
}

}  // namespace prism::cmd
