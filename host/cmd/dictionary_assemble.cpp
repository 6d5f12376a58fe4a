// prism dictionary assemble: the PSFs `prism dictionary merge-hdr` wrote
// (measured at grid positions) as a calibrated dictionary, the one the
// paper reconstructs with: the grid is read off the PSFs' source positions
// (a whole grid, one PSF per node), every PSF binned to the base binning and
// stored with all its levels.
#include <algorithm>
#include <bit>
#include <cmath>
#include <cstdio>
#include <filesystem>
#include <map>
#include <unistd.h>

#include "host/calibrate/calibrate.h"  // read_merged_psfs
#include "host/cmd/commands.h"
#include "host/cmd/options.h"
#include "host/dictionary/build.h"  // max_dictionary_psfs
#include "host/dictionary/store.h"
#include "host/util/format.h"
#include "host/util/output_file.h"
#include "host/util/progress.h"

namespace fs = std::filesystem;

namespace prism::cmd {

namespace {

struct AssembleArgs {
  std::string merged, scene, out;
  unsigned binning = 4;  // as `prism dictionary build`
};

// The sorted distinct values of one coordinate; positions within kSameMm
// of each other are one grid line (a position printed and read back
// differs in its last digits).
constexpr double kSameMm = 1e-6;
std::vector<double> grid_line(const std::vector<MeasuredPsf>& psfs, int axis) {
  std::vector<double> v;
  for (const auto& p : psfs) v.push_back(p.theta_mm[axis]);
  std::sort(v.begin(), v.end());
  std::vector<double> out;
  for (double x : v)
    if (out.empty() || x - out.back() > kSameMm) out.push_back(x);
  return out;
}

void run(const AssembleArgs& a) {
  check_not_input(a.out, "--out", {{"--merged", a.merged}});
  if (fs::exists(a.out))
    throw std::runtime_error(a.out + " exists; give --out a new folder (assemble writes a whole dictionary or none)");
  if (!std::has_single_bit(a.binning))
    throw std::runtime_error("--binning " + std::to_string(a.binning) + ": give a power of two (1, 2, 4, ...)");
  const Scene scene = load_scene(a.scene);
  std::vector<MeasuredPsf> psfs = read_merged_psfs(a.merged, scene.optics, a.binning);
  for (const auto& p : psfs) require_in_front(scene, p.theta_mm.z, p.name + "'s source");

  DictionaryManifest m;
  m.scene = scene;
  m.grid = {grid_line(psfs, 0), grid_line(psfs, 1), grid_line(psfs, 2)};
  m.base_binning = int(a.binning);
  const AnalysisGrid g = AnalysisGrid::of(scene.optics, a.binning);
  m.width = g.width;
  m.height = g.height;
  m.levels = DictionaryManifest::mip_levels(m.width, m.height);
  m.rays_per_lenslet = 0;
  m.source = "calibrated";
  if (m.grid.size() > max_dictionary_psfs)
    throw std::runtime_error(a.merged + ": the PSFs' positions span a grid of " + std::to_string(m.grid.x_mm.size()) +
                             " x " + std::to_string(m.grid.y_mm.size()) + " x " + std::to_string(m.grid.depth_mm.size()) +
                             " nodes, more than a dictionary holds (" + std::to_string(max_dictionary_psfs) +
                             "): were they taken on a grid?");
  // One PSF per node.
  std::map<size_t, size_t> at;  // node -> PSF
  for (size_t k = 0; k < psfs.size(); ++k) {
    const glm::dvec3& t = psfs[k].theta_mm;
    const size_t i = m.grid.index(m.grid.nearest_node(t));  // every position is a node, to kSameMm
    if (auto [it, fresh] = at.emplace(i, k); !fresh)
      throw std::runtime_error(psfs[k].name + " and " + psfs[it->second].name + " were both taken at (" +
                               format_number(t.x) + ", " + format_number(t.y) + ", " + format_number(t.z) +
                               ") mm: keep one of them");
  }
  // The search scores every node: the grid must be whole.
  if (at.size() < m.grid.size()) {
    std::string missing;
    for (size_t i = 0, listed = 0; i < m.grid.size() && listed < 5; ++i)
      if (!at.count(i)) {
        const glm::dvec3 p = m.grid.position(i);
        missing += std::string(listed++ ? ", " : "") + "(" + format_number(p.x) + ", " + format_number(p.y) + ", " +
                   format_number(p.z) + ")";
      }
    throw std::runtime_error(a.merged + ": the PSFs' positions span a " + std::to_string(m.grid.x_mm.size()) + " x " +
                             std::to_string(m.grid.y_mm.size()) + " x " + std::to_string(m.grid.depth_mm.size()) +
                             " grid, and " + std::to_string(m.grid.size() - at.size()) + " of its nodes have no PSF: " +
                             missing + (m.grid.size() - at.size() > 5 ? ", ..." : "") +
                             " mm; measure them, or leave out the PSFs off the grid (the search needs every node)");
  }

  // Written beside --out and renamed into place when whole.
  const std::string tmp = a.out + ".assembling-" + std::to_string(::getpid());
  fs::remove_all(tmp);
  try {
    fs::create_directories(tmp);
    write_manifest(tmp, m);
    Progress progress("prism dictionary assemble", at.size());
    size_t done = 0;
    for (const auto& [i, k] : at) {
      PsfLevel level0{0, m.width, m.height, std::move(psfs[k].p)};
      double sum = 0;
      for (float v : level0.p) sum += v;
      if (!(sum > 0)) throw std::runtime_error(psfs[k].name + ": no light on the sensor");
      // Merged PSFs sum to 1 over the pixels kept; stored as probabilities over the sensor.
      for (float& v : level0.p) v = float(v / sum);
      write_psf_file(tmp + "/" + m.file_of(i), m, i, level0, 0.0);
      progress.update(++done);
    }
    progress.finish();
    fs::rename(tmp, a.out);
  } catch (...) {
    std::error_code ec;
    fs::remove_all(tmp, ec);
    throw;
  }
  std::printf("%s: %zu merged PSFs, a %zu x %zu x %zu grid (x %g .. %g, y %g .. %g, depth %g .. %g mm), level 0 "
              "binned %u x %u (%d x %d px), %d levels; a calibrated dictionary: `prism reconstruct` searches it and "
              "refines with its PSFs interpolated (--model dictionary), `prism calibrate` fits a scene to it\n",
              a.out.c_str(), at.size(), m.grid.x_mm.size(), m.grid.y_mm.size(),
              m.grid.depth_mm.size(), m.grid.x_mm.front(), m.grid.x_mm.back(), m.grid.y_mm.front(), m.grid.y_mm.back(),
              m.grid.depth_mm.front(), m.grid.depth_mm.back(), a.binning, a.binning, m.width, m.height, m.levels);
}

}  // namespace

void add_dictionary_assemble(CLI::App& dictionary) {
  auto a = std::make_shared<AssembleArgs>();
  CLI::App* c = dictionary.add_subcommand(
      "assemble", "the PSFs merge-hdr wrote, measured on a grid of source positions, as a calibrated dictionary");
  c->add_option("--merged", a->merged, "the folder prism dictionary merge-hdr wrote (<name>.exr, <name>.json)")
      ->required();
  c->add_option("--scene", a->scene, "the camera's scene (built-in name or JSON file): its sensor must be the frames'")
      ->required();
  c->add_option("--out", a->out, "the dictionary folder to create (must not exist)")->required();
  c->add_option("--binning", a->binning, "level 0 = the camera's pixels binned B x B, B a power of two")
      ->capture_default_str()
      ->check(CLI::Range(1u, 256u));
  c->footer("The grid is read off the PSFs' source positions (each PSF's JSON sidecar): the distinct x, y and "
            "depths, every node with exactly one PSF. Each PSF is normalised to sum to 1 over the sensor. Nothing "
            "is written unless the whole dictionary is.");
  c->callback([a] { run(*a); });
}

}  // namespace prism::cmd
