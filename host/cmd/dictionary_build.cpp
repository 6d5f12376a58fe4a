// prism dictionary build / info: synthesise a PSF dictionary, and describe one.
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <string>
#include <vector>

#include "host/cmd/commands.h"
#include "engine/defaults.h"
#include "host/cmd/options.h"
#include "host/cmd/ranks.h"
#include "host/dictionary/build.h"
#include "host/util/format.h"
#include "host/util/progress.h"

namespace prism::cmd {

namespace {

struct BuildArgs {
  std::string scene = "prototype";
  std::string out;
  std::string grid_x = "-25:25:5", grid_y = "-25:25:5";
  std::string grid_depth = format_list(defaults::dictionary_depth_planes_mm);
  int binning = 4;
  unsigned rays = 4096;
  SplatOptions splat;
  std::string device;
};

void run_build(const BuildArgs& a) {
  Scene scene = load_scene(a.scene);
  DictionaryBuildOptions o;
  o.grid = {parse_list(a.grid_x, "--grid-x-mm"), parse_list(a.grid_y, "--grid-y-mm"),
            parse_list(a.grid_depth, "--grid-depth-mm")};
  o.base_binning = a.binning;
  o.rays_per_lenslet = a.rays;
  o.splat = a.splat.kind();
  o.stratification = a.splat.stratification;
  check_build_options(a.out, scene, o);  // before the device is set up
  vk::Context ctx(vk::ContextOptions{a.device});
  // Under mpirun rank r renders the PSFs i with i mod N = r, each into its own
  // file; rank 0 alone writes the manifest (or checks the one there) first.
  o.share = ranks::work_share();
  check_build_memory(ctx, scene, o);
  if (ranks::root()) prepare_dictionary(scene, a.out, o);
  ranks::barrier();
  Progress progress(ranks::size() > 1 ? "prism dictionary build (rank 0's share)" : "prism dictionary build",
                    o.share.taken_of(o.grid.size()), ranks::root());
  auto r = build_dictionary(ctx, scene, a.out, o, [&](size_t done, size_t) { progress.update(done); });
  progress.finish();
  const size_t rendered = size_t(ranks::sum(uint64_t(r.rendered))), reused = size_t(ranks::sum(uint64_t(r.reused)));
  const double seconds = ranks::max(r.seconds);
  if (!ranks::root()) return;
  if (ranks::size() > 1)
    std::printf("# %d MPI ranks, each on its own device; rank 0's device and median time per PSF:\n", ranks::size());
  std::printf("# device: %s\n", ctx.describe().c_str());
  std::printf("%s: %zu PSFs rendered, %zu already present, %.1f s (%.3f s per PSF, median)\n", a.out.c_str(), rendered,
              reused, seconds, r.seconds_per_psf);
}

// Every level of every present PSF read back: decompressed (a flipped bit in
// ZIP data fails its checksum), its attributes checked against the manifest,
// and normalised as the format says (sums to 1, or 0 without light on the
// sensor). Returns the problems, one line each.
std::vector<std::string> verify_entries(const DictionaryReader& r) {
  const DictionaryManifest& m = r.manifest();
  constexpr double sum_tolerance = 1e-2;  // half floats: ~2^-11 per value
  std::vector<std::string> problems;
  Progress progress("dictionary info: verifying", m.grid.size());
  for (size_t i = 0; i < m.grid.size(); ++i) {
    progress.update(i + 1);
    if (!r.has(i)) continue;
    try {
      for (int l = 0; l < m.levels; ++l) {
        const PsfLevel level = r.read_level(i, l);
        double sum = 0;
        for (float v : level.p) {
          if (!std::isfinite(v) || v < 0) throw DictionaryError(r.path_of(i) + ": level " + std::to_string(l) +
                                                                " holds a value that is negative or not finite");
          sum += v;
        }
        const bool dark = sum == 0 && r.photons_on_sensor(i) == 0;
        if (!dark && std::abs(sum - 1) > sum_tolerance)
          throw DictionaryError(r.path_of(i) + ": level " + std::to_string(l) + " sums to " + format_number(sum) +
                                ", not 1");
      }
    } catch (const std::exception& e) {
      problems.push_back(e.what());
    }
  }
  progress.finish();
  return problems;
}

void run_info(const std::string& dir, bool verify) {
  DictionaryReader r(dir);
  const DictionaryManifest& m = r.manifest();
  const OpticalSystem& o = m.scene.optics;
  uint64_t bytes = 0;
  size_t present = 0;
  for (size_t i = 0; i < m.grid.size(); ++i)
    if (r.has(i)) {
      ++present;
      bytes += std::filesystem::file_size(r.path_of(i));
    }
  auto range = [](const std::vector<double>& v) {
    char b[96];
    std::snprintf(b, sizeof b, "%zu values, %g .. %g", v.size(), v.front(), v.back());
    return std::string(b);
  };
  std::printf("dictionary %s (format version %d, %s)\n", dir.c_str(), m.version, m.source.c_str());
  std::printf("  scene       %s, %zu lenslets, %s lenses\n", m.scene.name.c_str(), o.lenslets.size(), to_string(o.lens_model));
  std::printf("  sensor      %d x %d px of %.2f um\n", o.sensor_width_px, o.sensor_height_px, o.pixel_um);
  std::printf("  grid x      %s mm\n  grid y      %s mm\n  grid depth  %s mm\n", range(m.grid.x_mm).c_str(),
              range(m.grid.y_mm).c_str(), range(m.grid.depth_mm).c_str());
  std::printf("  entries     %zu of %zu files present%s%s\n", present, m.grid.size(),
              present == m.grid.size()   ? ""
              : m.source == "calibrated" ? " (the others are missing: assemble it again from every PSF)"
                                         : " (run `prism dictionary build` again to finish)",
              verify ? "" : " (not read: --verify reads every level of every file)");
  std::printf("  storage     half floats x 2^15, ZIP, %d px tiles; %.1f MiB on disk (%.2f MiB per PSF)\n", m.tile_px,
              bytes / 1048576.0, present ? bytes / 1048576.0 / present : 0.0);
  if (m.source == "calibrated")
    std::printf("  measured    PSFs merged from calibration exposures (prism dictionary assemble)\n");
  else
    std::printf("  rays        %u per 3 mm lenslet, %s splat, stratification %u\n", m.rays_per_lenslet,
                to_string(m.splat), m.stratification);
  std::printf("  levels      %d; every level of every PSF sums to 1 over the sensor\n", m.levels);
  for (int l = 0; l < m.levels; ++l)
    std::printf("    level %-2d  %5d x %-5d px of %7.1f um\n", l, m.level_width(l), m.level_height(l), m.pixel_mm(l) * 1e3);
  if (!verify) return;
  const auto problems = verify_entries(r);
  std::printf("  verified    %zu of %zu files read back whole and normalised\n", present - problems.size(), present);
  if (problems.empty()) return;
  std::string listed;
  for (size_t k = 0; k < problems.size() && k < 10; ++k) listed += "\n  " + problems[k];
  throw std::runtime_error(std::to_string(problems.size()) + " of " + std::to_string(present) + " files in " + dir +
                           " are damaged" + (problems.size() > 10 ? " (the first 10)" : "") + ":" + listed +
                           "\nremove them and run `prism dictionary build` again to rebuild them");
}

}  // namespace

void add_dictionary_build(CLI::App& dictionary) {
  auto a = std::make_shared<BuildArgs>();
  CLI::App* c = dictionary.add_subcommand("build", "render every grid PSF with the forward model (resumable)");
  c->add_option("--scene", a->scene, "built-in scene or JSON file")->capture_default_str();
  c->add_option("--out", a->out, "dictionary directory (a rerun continues an interrupted build)")->required();
  c->add_option("--grid-x-mm", a->grid_x, "x positions: A,B,C, FIRST:LAST:STEP or both (0:10:1,12.5,15:50:5)")->capture_default_str();
  c->add_option("--grid-y-mm", a->grid_y, "y positions")->capture_default_str();
  c->add_option("--grid-depth-mm", a->grid_depth,
                "depths from the scintillator face (the default is dense near the face, docs/dictionary.md; the paper's planes: 5:50:5)")->capture_default_str();
  c->add_option("--binning", a->binning, "level 0 = sensor pixels binned B x B (1: full resolution, 128 MB/PSF in memory)")
      ->capture_default_str()->check(CLI::Range(1, 256));
  c->add_option("--rays", a->rays, std::string("rays per 3 mm lenslet for each PSF, ") + rays_rounding)->capture_default_str()->check(CLI::Range(4u, 1u << 24));
  a->splat.add_to(c);
  c->add_option("--device", a->device, device_help);
  c->callback([a] { run_build(*a); });
}

void add_dictionary_info(CLI::App& dictionary) {
  auto dir = std::make_shared<std::string>();
  auto verify = std::make_shared<bool>(false);
  CLI::App* c = dictionary.add_subcommand("info", "print a dictionary's manifest, levels and size on disk");
  c->add_option("DIR", *dir, "dictionary directory")->required();
  c->add_flag("--verify", *verify,
              "read every level of every PSF file back: damaged files (a flipped bit, a truncated tile, another "
              "dictionary's file, a level that does not sum to 1) are listed and the exit status is 1");
  c->callback([dir, verify] { run_info(*dir, *verify); });
}

}  // namespace prism::cmd
