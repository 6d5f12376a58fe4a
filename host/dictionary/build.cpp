#include "host/dictionary/build.h"

#include <algorithm>
#include <chrono>
#include <filesystem>
#include <fstream>
#include <future>
#include <memory>

#include "engine/forward.h"
#include "host/util/format.h"
#include "host/util/image_io.h"
#include "host/util/memory.h"

namespace prism {

namespace {

DictionaryManifest manifest_for(const Scene& scene, const DictionaryBuildOptions& o) {
  DictionaryManifest m;
  m.scene = scene;
  m.grid = o.grid;
  m.base_binning = o.base_binning;
  AnalysisGrid g = AnalysisGrid::of(scene.optics, unsigned(o.base_binning));
  m.width = g.width;
  m.height = g.height;
  m.levels = DictionaryManifest::mip_levels(m.width, m.height);
  m.tile_px = o.tile_px;
  m.rays_per_lenslet = TraceSettings{o.rays_per_lenslet}.rays();
  m.splat = o.splat;
  m.stratification = o.stratification;
  m.source = "synthesised";
  return m;
}

}  // namespace

void check_build_options(const std::string& dir, const Scene& scene, const DictionaryBuildOptions& o) {
  try {
    o.grid.validate();
    o.grid.require_in_front(scene.optics);
  } catch (const DictionaryError& e) {
    throw DictionaryError(dir + ": grid: " + e.what() + "; nothing written");
  }
  if (o.share.count == 0 || o.share.index >= o.share.count)
    throw std::logic_error("dictionary build: share " + std::to_string(o.share.index) + " of " +
                           std::to_string(o.share.count));
  const double psfs = double(o.grid.x_mm.size()) * double(o.grid.y_mm.size()) * double(o.grid.depth_mm.size());
  if (psfs > double(max_dictionary_psfs))
    throw DictionaryError(dir + ": grid: " + format_number(psfs) + " PSFs (" + std::to_string(o.grid.x_mm.size()) +
                          " x " + std::to_string(o.grid.y_mm.size()) + " x " + std::to_string(o.grid.depth_mm.size()) +
                          "), more than " + format_number(double(max_dictionary_psfs)) +
                          "; choose coarser --grid-x-mm, --grid-y-mm or --grid-depth-mm; nothing written");
}

namespace {

// After the first PSF file of a build: the rest, at its size, must fit on the disk.
void check_disk(const std::string& dir, const std::string& first_file, size_t remaining) {
  std::error_code ec;
  const double each = double(std::filesystem::file_size(first_file, ec));
  const auto space = std::filesystem::space(dir, ec);
  if (ec) return;  // no figure to judge by
  const double needed = each * double(remaining);
  if (needed > double(space.available))
    throw DictionaryError(dir + ": the " + std::to_string(remaining) + " PSFs left need about " +
                          format_number(needed / 1073741824.0) + " GiB at " + format_number(each / 1048576.0) +
                          " MiB each (the first one's size), but the disk has " +
                          format_number(double(space.available) / 1073741824.0) +
                          " GiB free; free space, choose another --out, or a coarser --binning or grid "
                          "(the files written so far are kept: a rerun continues)");
}

}  // namespace

void check_build_memory(const vk::Context& ctx, const Scene& scene, const DictionaryBuildOptions& o) {
  const DictionaryManifest wanted = manifest_for(scene, o);
  // One PSF written at a time: level 0, its copy in half floats, and a
  // coarser level with its double accumulator (binned from level 0); beside
  // it the next PSF's level 0 as the device renders it.
  const double px = double(wanted.width) * wanted.height;
  MemoryEstimate memory("dictionary build at binning " + std::to_string(o.base_binning) + " (" +
                        std::to_string(wanted.width) + " x " + std::to_string(wanted.height) + " px per PSF)");
  memory.add("a PSF's level 0 in float and half", 6 * px).add("its coarser levels as they are binned", 3 * px);
  memory.add("the next PSF's level 0, rendered while one is written", 4 * px);
  memory.add_device_buffers(
      double(ForwardVulkan::device_bytes_at_most(AnalysisGrid::of(scene.optics, unsigned(o.base_binning)), o.splat)),
      ctx.is_cpu());
  memory.require_within_limit("Use a coarser --binning");
}

DictionaryBuildReport build_dictionary(vk::Context& ctx, const Scene& scene, const std::string& dir,
                                       const DictionaryBuildOptions& o,
                                       const std::function<void(size_t, size_t)>& progress) {
  check_build_options(dir, scene, o);
  check_build_memory(ctx, scene, o);
  const DictionaryManifest wanted = manifest_for(scene, o);
  prepare_dictionary(scene, dir, o);
  DictionaryReader reader(dir);

  TraceSettings t;
  t.rays_per_lenslet = o.rays_per_lenslet;
  t.binning = unsigned(o.base_binning);
  t.photons_emitted = scene.photons_emitted;
  t.splat = o.splat;
  t.stratification = o.stratification;
  ForwardVulkan fw(ctx, scene.optics, t);

  DictionaryBuildReport report;
  std::vector<double> per_psf;  // seconds between one PSF's file and the next's
  auto start = std::chrono::steady_clock::now();
  auto last_written = start;
  const size_t share = o.share.taken_of(wanted.grid.size());
  size_t done = 0;
  // A PSF's file is written (binned, converted, compressed: a thread's work)
  // while the device renders the next one, so the two overlap.
  std::future<void> writing;
  size_t writing_index = 0;
  auto finish_writing = [&] {
    if (!writing.valid()) return;
    writing.get();
    if (report.rendered == 0) check_disk(dir, reader.path_of(writing_index), share - done - 1);  // at most that many left
    auto now = std::chrono::steady_clock::now();
    per_psf.push_back(std::chrono::duration<double>(now - last_written).count());
    last_written = now;
    ++report.rendered;
    if (progress) progress(++done, share);
  };
  for (size_t i = o.share.index; i < wanted.grid.size(); i += o.share.count) {
    if (reader.has(i)) {
      ++report.reused;
      if (progress) progress(++done, share);
      continue;
    }
    auto l0 = std::make_shared<PsfLevel>(PsfLevel{0, wanted.width, wanted.height, fw.psf_values(wanted.grid.position(i))});
    double total = 0;
    for (float b : l0->p) total += b;
    // A position that puts no light on the sensor is stored as zeros.
    for (float& p : l0->p) p = total > 0 ? float(p / total) : 0.0f;
    finish_writing();
    writing_index = i;
    writing = std::async(std::launch::async, [&, i, l0, total] { write_psf_file(reader.path_of(i), wanted, i, *l0, total); });
    if (!o.overlap_writes) finish_writing();
  }
  finish_writing();
  report.seconds = std::chrono::duration<double>(std::chrono::steady_clock::now() - start).count();
  if (!per_psf.empty()) {
    std::sort(per_psf.begin(), per_psf.end());
    report.seconds_per_psf = per_psf[per_psf.size() / 2];
  }
  return report;
}

void prepare_dictionary(const Scene& scene, const std::string& dir, const DictionaryBuildOptions& o) {
  const DictionaryManifest wanted = manifest_for(scene, o);
  {
    // Said in words, where create_directories would throw "Not a directory [DIR/psf]".
    std::error_code ec;
    for (const std::string& d : {dir, dir + "/psf"})
      if (std::filesystem::exists(d, ec) && !std::filesystem::is_directory(d, ec))
        throw DictionaryError(d + ": is a file, not a folder; give --out a new or dictionary folder");
    std::filesystem::create_directories(dir + "/psf", ec);
    if (ec) throw DictionaryError(dir + "/psf: cannot create the folder (" + ec.message() + ")");
  }
  if (std::filesystem::exists(dir + "/manifest.json")) {
    // Resume only the very same dictionary.
    DictionaryReader existing(dir);
    if (existing.manifest().to_json() != wanted.to_json())
      throw DictionaryError(dir + ": holds a different dictionary (scene, grid, binning, rays or splat differ); "
                                  "choose another --out or delete it");
  } else {
    write_manifest(dir, wanted);
  }
}

}  // namespace prism
