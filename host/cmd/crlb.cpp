// prism crlb: Cramer-Rao lower bounds against depth for one or more scenes.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <map>

#include "host/cmd/commands.h"
#include "host/cmd/options.h"
#include "host/util/format.h"
#include "host/util/image_io.h"
#include "host/util/plot.h"

namespace prism::cmd {

namespace {

struct CrlbArgs {
  std::vector<std::string> scenes{"prototype"};
  std::string depths = "0:50:2.5";
  double x_mm = 0, y_mm = 0;
  std::string sensor = "poisson";
  std::string csv, plot;
  double converge = 0;
  unsigned max_rays = 1u << 20;
  ForwardOptions fw;
};


void run(const CrlbArgs& a) {
  auto depths = parse_list(a.depths, "--depth-mm");
  std::vector<glm::dvec3> positions;
  for (double d : depths) positions.push_back({a.x_mm, a.y_mm, d});
  SensorModel sensor = a.sensor == "binary" ? SensorModel::binary : SensorModel::poisson;

  // Load every scene first: a bad scene fails before any work is done.
  std::vector<Scene> scenes;
  for (const auto& name : a.scenes) {
    scenes.push_back(load_scene(name));
    a.fw.apply(scenes.back());
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
  std::printf("%-14s %-4s %7s %7s %7s %9s %10s %10s %10s %10s %8s %7s  %s\n", "scene", "lens", "x_mm", "y_mm", "depth",
              "photons", "crlb_x", "crlb_y", "crlb_z", "crlb_3d", "rays", "change", "flag");

  std::vector<CrlbRow> all;
  for (const auto& scene : scenes) {
    TraceSettings t = a.fw.settings(scene);
    auto start = std::chrono::steady_clock::now();
    std::fprintf(stderr, "prism crlb: %s (%s lens), %zu positions, %u rays/lenslet ...", scene.name.c_str(),
                 to_string(scene.optics.lens_model), positions.size(), t.rays());
    std::fflush(stderr);
    std::vector<CrlbRow> rows;
    if (a.converge > 0) {
      rows = crlb_converged(scene, positions, t, a.converge, a.max_rays, a.fw.backend_kind(), sensor, ctx.get());
    } else {
      TraceSettings quarter = t;
      quarter.rays_per_lenslet = std::max(4u, t.rays_per_lenslet / 4);
      rows = crlb_converged(scene, positions, quarter, tol, t.rays_per_lenslet, a.fw.backend_kind(), sensor, ctx.get());
    }
    for (auto& r : rows)
      if (r.crlb.flag == "ok" && !(r.change <= tol)) r.crlb.flag = "moving";
    double s = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
    std::fprintf(stderr, " %.2f s\n", s);
    for (const auto& r : rows) {
      std::printf("%-14s %-4s %7.2f %7.2f %7.2f %9.2f %10s %10s %10s %10s %8u %7s  %s\n", r.scene.c_str(),
                  to_string(r.lens_model), r.theta.x, r.theta.y, r.theta.z, r.photons, format_number(r.crlb.x_mm).c_str(),
                  format_number(r.crlb.y_mm).c_str(), format_number(r.crlb.depth_mm).c_str(), format_number(r.crlb.r3_mm).c_str(),
                  r.rays_per_lenslet, std::isnan(r.change) ? "-" : format_number(r.change).c_str(), r.crlb.flag.c_str());
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
                  "(README \"Convergence\")\n",
                  scene.name.c_str(), g0.pixel_mm * 1e3, scene.name.c_str());
  }

  if (!a.csv.empty()) {
    write_atomically(a.csv, [&](const std::string& tmp) {
      std::ofstream out(tmp);
      out << "scene,x_mm,y_mm,depth_mm,photons,crlb_x_mm,crlb_y_mm,crlb_z_mm,crlb_3d_mm,"
             "lens_model,sensor_model,rays_per_lenslet,binning,analysis_pixel_um,change_vs_quarter_rays,flag\n";
      for (const auto& r : all)
        out << r.scene << ',' << format_number(r.theta.x) << ',' << format_number(r.theta.y) << ',' << format_number(r.theta.z) << ','
            << format_number(r.photons) << ',' << format_number(r.crlb.x_mm) << ',' << format_number(r.crlb.y_mm) << ',' << format_number(r.crlb.depth_mm)
            << ',' << format_number(r.crlb.r3_mm) << ',' << to_string(r.lens_model) << ',' << a.sensor << ','
            << r.rays_per_lenslet << ',' << t0.binning << ',' << format_number(g0.pixel_mm * 1e3) << ','
            << (std::isnan(r.change) ? "" : format_number(r.change)) << ',' << r.crlb.flag << '\n';
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
  }
}

}  // namespace

void add_crlb(CLI::App& app) {
  auto a = std::make_shared<CrlbArgs>();
  CLI::App* c = app.add_subcommand("crlb", "Cramer-Rao lower bounds (Fisher information) against depth");
  c->add_option("--scene", a->scenes,
                "built-in scene or JSON file; repeat for several (prototype, unifocal-f3/9/15, single-f3/9/15)")
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
  a->fw.add_to(c, defaults::analysis_binning);
  c->callback([a] { run(*a); });
}

}  // namespace prism::cmd
