// The PSF dictionary's costs, in one run: time to synthesise a PSF (Vulkan vs
// the CPU reference), bytes on disk per PSF for each base resolution, and read
// throughput for whole levels and for tile fetches around clicks; then each
// tier's ray noise per splat (what the full-resolution tier is worth); then
// the build with each file written beside the next render against after it;
// then every tile of levels 0-3 decoded by PsfFile::read_tile (libdeflate,
// host/dictionary/exr_zip.h) against OpenEXR's own readTile.
//
//   bench_dictionary [--device D] [--sections 1,2,3,4] (section 4 reads section 1's dictionaries)
#include <OpenEXR/ImfFrameBuffer.h>
#include <OpenEXR/ImfTiledInputFile.h>

#include <cmath>
#include <cstdio>
#include <cstring>
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

// Every tile of levels 0-3 of every PSF, decoded by PsfFile::read_tile and by
// OpenEXR's readTile into the same tile_px x tile_px buffer (median seconds
// of 3 sweeps each; the files open throughout, so neither path pays opens).
struct DecodeRow {
  int binning = 0;
  long tiles = 0;
  double exr_zip_s = 0, openexr_s = 0;
  bool same = true;
};
DecodeRow decode_times(const DictionaryReader& r, int binning) {
  const DictionaryManifest& m = r.manifest();
  const int t = m.tile_px, levels = std::min(4, m.levels);
  std::vector<PsfFile> files;
  std::vector<std::unique_ptr<Imf::TiledInputFile>> exr;
  for (size_t i = 0; i < m.grid.size(); ++i) {
    files.emplace_back(r, i);
    exr.push_back(std::make_unique<Imf::TiledInputFile>(r.path_of(i).c_str()));
  }
  std::vector<uint16_t> a(size_t(t) * t), b(size_t(t) * t);
  DecodeRow row{binning};
  auto sweep = [&](auto&& read) {
    for (size_t i = 0; i < files.size(); ++i)
      for (int l = 0; l < levels; ++l)
        for (int ty = 0; ty * t < m.level_height(l); ++ty)
          for (int tx = 0; tx * t < m.level_width(l); ++tx) read(i, l, tx, ty);
  };
  auto openexr = [&](size_t i, int l, int tx, int ty, std::vector<uint16_t>& out) {
    std::fill(out.begin(), out.end(), uint16_t(0));
    Imf::FrameBuffer fb;
    fb.insert("Y", Imf::Slice(Imf::HALF, (char*)(out.data() - tx * t - size_t(ty) * t * t), 2, 2 * size_t(t)));
    exr[i]->setFrameBuffer(fb);
    exr[i]->readTile(tx, ty, l, l);
  };
  sweep([&](size_t i, int l, int tx, int ty) {
    files[i].read_tile(l, tx, ty, a);
    openexr(i, l, tx, ty, b);
    row.same = row.same && a == b;
    ++row.tiles;
  });
  row.exr_zip_s = bench::median_seconds(3, [&] { sweep([&](size_t i, int l, int tx, int ty) { files[i].read_tile(l, tx, ty, a); }); });
  row.openexr_s = bench::median_seconds(3, [&] { sweep([&](size_t i, int l, int tx, int ty) { openexr(i, l, tx, ty, b); }); });
  return row;
}
}  // namespace

int main(int argc, char** argv) {
  std::string device, sections = "1,2,3,4";
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if ((a == "--device" || a == "--sections") && i + 1 < argc) (a == "--device" ? device : sections) = argv[++i];
    else {
      std::fprintf(stderr, "usage: bench_dictionary [--device D] [--sections 1,2,3,4]\n");
      return a == "--help" || a == "-h" ? 0 : 2;
    }
  }
  auto runs = [&](char section) { return ("," + sections + ",").find(std::string(",") + section + ",") != std::string::npos; };
  vk::Context ctx(vk::ContextOptions{device});
  Scene scene = builtin_scene("prototype");
  std::printf("# bench_dictionary\n# machine: %s\n# device: %s\n# times: medians; PSFs at 4096 rays per lenslet\n",
              bench::machine_line().c_str(), ctx.describe().c_str());
  std::string root = (fs::temp_directory_path() / "prism-bench-dictionary").string();
  std::vector<DecodeRow> decodes;  // section 4, on section 1's dictionaries
  if (runs('1') || runs('4')) {
    std::printf("\n%-8s %10s %12s %12s %12s %9s %13s %10s %13s %13s %7s\n", "binning", "level 0", "build s/PSF",
                "Vulkan trace", "CPU ref", "ratio", "disk MiB/PSF", "read MB/s", "tile reads/s", "reopened/s", "ratio");
    for (int binning : {16, 4, 1}) {
      std::string dir = root + "-" + std::to_string(binning);
      fs::remove_all(dir);
      DictionaryBuildOptions o;
      o.grid = {{-5.0, 5.0}, {0.0}, {10.0, 30.0}};
      o.base_binning = binning;
      o.rays_per_lenslet = 4096;
      o.splat = Splat::point;  // as docs/dictionary.md's figures were measured
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
      if (runs('4')) decodes.push_back(decode_times(r, binning));
      fs::remove_all(dir);
    }
    std::printf("\n1210 PSFs: multiply the per-PSF figures by 1210 (e.g. disk and build time of the whole grid).\n");
    std::printf("build = trace on the device + normalise + write the EXR (all levels, ZIP); Vulkan trace and CPU ref\n"
                "trace and splat one PSF (ratio = CPU ref / Vulkan trace). read = decode a whole level 0.\n"
                "tile reads: single-tile fetches with the files kept open (the service's way) and with each file\n"
                "opened and its header checked for every fetch (ratio = kept open / reopened).\n");
  }

  if (!decodes.empty()) {
    std::printf("\n## 4. Tile decode: every tile of levels 0-3 of section 1's PSFs (the files kept open), by\n"
                "PsfFile::read_tile (chunk through OpenEXR's core, inflated by libdeflate) and by OpenEXR's readTile\n");
    std::printf("%-8s %8s %14s %14s %8s %10s\n", "binning", "tiles", "exr_zip us", "OpenEXR us", "ratio", "same bits");
    for (const DecodeRow& d : decodes)
      std::printf("%-8d %8ld %14.2f %14.2f %7.2fx %10s\n", d.binning, d.tiles, 1e6 * d.exr_zip_s / double(d.tiles),
                  1e6 * d.openexr_s / double(d.tiles), d.openexr_s / d.exr_zip_s, d.same ? "yes" : "NO");
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
