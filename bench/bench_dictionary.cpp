// The PSF dictionary's costs, in one run: time to synthesise a PSF (Vulkan vs
// the CPU reference), bytes on disk per PSF for each base resolution, and read
// throughput for whole levels and for tile fetches around clicks; then each
// tier's ray noise per splat (what the full-resolution tier is worth); then
// the build with each file written beside the next render against after it.
//
//   bench_dictionary [--device D] [--sections 1,2,3]
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <random>

#include "bench_util.h"
#include "engine/forward.h"
#include "engine/ref/forward_ref.h"
#include "host/dictionary/build.h"
#include "host/dictionary/service.h"

using namespace prism;
namespace fs = std::filesystem;

namespace {
// Bytes on disk per PSF file of a dictionary.
double mean_file_bytes(const DictionaryReader& r) {
  double bytes = 0;
  for (size_t i = 0; i < r.manifest().grid.size(); ++i) bytes += double(fs::file_size(r.path_of(i)));
  return bytes / double(r.manifest().grid.size());
}
}  // namespace

int main(int argc, char** argv) {
  std::string device, sections = "1,2,3";
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if ((a == "--device" || a == "--sections") && i + 1 < argc) (a == "--device" ? device : sections) = argv[++i];
    else {
      std::fprintf(stderr, "usage: bench_dictionary [--device D] [--sections 1,2,3]\n");
      return a == "--help" || a == "-h" ? 0 : 2;
    }
  }
  auto runs = [&](char section) { return ("," + sections + ",").find(std::string(",") + section + ",") != std::string::npos; };
  vk::Context ctx(vk::ContextOptions{device});
  Scene scene = builtin_scene("prototype");
  std::printf("# bench_dictionary\n# machine: %s\n# device: %s\n# times: medians; PSFs at 4096 rays per lenslet\n",
              bench::machine_line().c_str(), ctx.describe().c_str());
  std::string root = (fs::temp_directory_path() / "prism-bench-dictionary").string();
  if (runs('1')) {
    std::printf("\n%-8s %10s %12s %12s %12s %9s %13s %10s %13s %13s %7s\n", "binning", "level 0", "build s/PSF",
                "Vulkan trace", "CPU ref", "ratio", "disk MiB/PSF", "read MB/s", "tile reads/s", "reopened/s", "ratio");
    for (int binning : {16, 4, 1}) {
      std::string dir = root + "-" + std::to_string(binning);
      fs::remove_all(dir);
      DictionaryBuildOptions o;
      o.grid = {{-5.0, 5.0}, {0.0}, {10.0, 30.0}};
      o.base_binning = binning;
      o.rays_per_lenslet = 4096;
      o.splat = Splat::point;  // as the README's figures were measured
      auto report = build_dictionary(ctx, scene, dir, o);
      TraceSettings t = TraceSettings::defaults_for(o.splat);
      t.rays_per_lenslet = o.rays_per_lenslet;
      t.binning = unsigned(binning);
      ForwardVulkan fw(ctx, scene.optics, t);
      double gpu = bench::median_seconds(3, [&] { fw.psf({1.0, 2.0, 20.0}); });
      double cpu = bench::median_seconds(3, [&] { ref::psf(scene.optics, t, {1.0, 2.0, 20.0}); });
      DictionaryReader r(dir);
      double bytes = mean_file_bytes(r);
      double level0_bytes = double(r.manifest().width) * r.manifest().height * sizeof(float);
      double read_s = bench::median_seconds(3, [&] { r.read_level(0, 0); });
      // Tile fetches around random clicks, every fetch a cache miss (a budget
      // of one tile), from four PSFs in turn: with their files kept open, and
      // with one file open at a time (each fetch opens and checks its file).
      auto tile_reads_per_s = [&](int open_files) {
        ServiceBudget budget{64 * 64 * 4 + uint64_t(open_files) * PsfFile::bytes(r.manifest()) + 4096, 0, open_files};
        DictionaryService svc(r, nullptr, r.manifest().levels - 1, budget);
        std::mt19937 rng(1);
        const int fetches = 200;
        return fetches / bench::median_seconds(3, [&] {
          for (int k = 0; k < fetches; ++k) {
            glm::ivec2 px{int(rng() % r.manifest().width), int(rng() % r.manifest().height)};
            svc.values(size_t(k % 4), 0, std::span<const glm::ivec2>(&px, 1));
          }
        });
      };
      const double tiles_open = tile_reads_per_s(4), tiles_reopened = tile_reads_per_s(1);
      char size[32];
      std::snprintf(size, sizeof size, "%dx%d", r.manifest().width, r.manifest().height);
      std::printf("%-8d %10s %12.3f %12.3f %12.3f %8.1fx %13.2f %10.1f %13.0f %13.0f %6.1fx\n", binning, size,
                  report.seconds_per_psf, gpu, cpu, cpu / gpu, bytes / 1048576.0, level0_bytes / read_s / 1e6, tiles_open,
                  tiles_reopened, tiles_open / tiles_reopened);
      std::fflush(stdout);
      fs::remove_all(dir);
    }
    std::printf("\n1210 PSFs: multiply the per-PSF figures by 1210 (e.g. disk and build time of the whole grid).\n");
    std::printf("build = trace on the device + normalise + write the EXR (all levels, ZIP); Vulkan trace and CPU ref\n"
                "trace and splat one PSF (ratio = CPU ref / Vulkan trace). read = decode a whole level 0.\n"
                "tile reads: single-tile fetches with the files kept open (the service's way) and with each file\n"
                "opened and its header checked for every fetch (ratio = kept open / reopened).\n");
  }

  if (runs('2')) {
    // 2. Signal to noise of each tier and splat: a PSF rendered twice with
    // different stratifications (other jitter for point rays, cells turned for
    // footprints), both normalised to sum 1; their L1 distance is the ray noise
    // (0 for a noiseless model, 2 for disjoint images). The build time and size
    // are of a two-PSF dictionary at the same settings.
    std::printf("\n## 2. Ray noise per tier and splat: L1 distance between two stratifications of one PSF at\n"
                "(1, 2, 20) mm, each normalised to sum 1; build s/PSF and disk per PSF of the tier\n");
    std::printf("%-8s %-10s %8s %12s %13s %10s\n", "binning", "splat", "rays", "build s/PSF", "disk MiB/PSF", "L1 noise");
    struct Row {
      Splat splat;
      unsigned rays;
    };
    for (int binning : {16, 4, 1})
      for (Row row : {Row{Splat::point, 4096}, Row{Splat::footprint, 4096}, Row{Splat::footprint, defaults::rays_per_lenslet}}) {
        std::string dir = root + "-noise";
        fs::remove_all(dir);
        DictionaryBuildOptions o;
        o.grid = {{-5.0, 5.0}, {0.0}, {20.0}};
        o.base_binning = binning;
        o.rays_per_lenslet = row.rays;
        o.splat = row.splat;
        auto report = build_dictionary(ctx, scene, dir, o);
        DictionaryReader r(dir);
        double bytes = mean_file_bytes(r);
        fs::remove_all(dir);
        std::vector<std::vector<float>> images;
        for (unsigned stratification : {0u, 1u}) {
          TraceSettings t = TraceSettings::defaults_for(row.splat);
          t.rays_per_lenslet = row.rays;
          t.binning = unsigned(binning);
          t.stratification = stratification;
          ForwardVulkan fw(ctx, scene.optics, t);
          images.push_back(fw.psf_values({1.0, 2.0, 20.0}));
        }
        double sum0 = 0, sum1 = 0, l1 = 0;
        for (size_t i = 0; i < images[0].size(); ++i) sum0 += images[0][i], sum1 += images[1][i];
        for (size_t i = 0; i < images[0].size(); ++i) l1 += std::abs(images[0][i] / sum0 - images[1][i] / sum1);
        std::printf("%-8d %-10s %8u %12.3f %13.2f %10.4f\n", binning, to_string(row.splat), row.rays,
                    report.seconds_per_psf, bytes / 1048576.0, l1);
        std::fflush(stdout);
      }
  }

  if (!runs('3')) return 0;
  // 3. The build's pipeline: each PSF's file written (binned, converted to
  // half, compressed) on a thread while the device renders the next one,
  // against writing it before the next render. Footprint at 1024 cells, the
  // full-resolution dictionary's settings; the two alternated twice, 6 PSFs
  // a build; the time per PSF is the median interval between files.
  std::printf("\n## 3. Build: a PSF's file written while the next renders vs after it (footprint, 1024 cells,\n"
              "6 PSFs a build, alternated twice; s/PSF: median interval between files, then the median of the two)\n");
  std::printf("%-8s %14s %14s %8s\n", "binning", "after s/PSF", "beside s/PSF", "ratio");
  for (int binning : {4, 1}) {
    std::vector<double> serial, overlapped;
    for (int repeat = 0; repeat < 2; ++repeat)
      for (bool overlap : {false, true}) {
        std::string dir = root + "-pipeline";
        fs::remove_all(dir);
        DictionaryBuildOptions o;
        o.grid = {{-5.0, 0.0, 5.0}, {0.0, 5.0}, {20.0}};
        o.base_binning = binning;
        o.rays_per_lenslet = 1024;
        o.splat = Splat::footprint;
        o.overlap_writes = overlap;
        (overlap ? overlapped : serial).push_back(build_dictionary(ctx, scene, dir, o).seconds_per_psf);
        fs::remove_all(dir);
      }
    const double after = bench::median(serial), beside = bench::median(overlapped);
    std::printf("%-8d %14.3f %14.3f %7.2fx\n", binning, after, beside, after / beside);
    std::fflush(stdout);
  }
  return 0;
}
