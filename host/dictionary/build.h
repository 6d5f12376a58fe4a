// Synthesising a PSF dictionary with the device forward model: every grid
// position rendered, normalised to sum 1 over the sensor, and stored with all
// its levels. Resumable: entries already on disk (written atomically, so whole)
// are kept, so an interrupted build continues where it stopped.
#pragma once
#include <functional>
#include <string>

#include "engine/vk/context.h"
#include "host/dictionary/store.h"
#include "host/util/work_share.h"

namespace prism {

struct DictionaryBuildOptions {
  DictionaryGrid grid = DictionaryGrid::fine_near_face();
  int base_binning = 4;       // level 0 = sensor binned B x B (1: full resolution)
  unsigned rays_per_lenslet = 4096;
  Splat splat = TraceSettings{}.splat;  // how the forward model's rays become pixel values
  unsigned stratification = 0;
  int tile_px = 64;
  // A PSF's file is written on a thread while the device renders the next;
  // false writes it before the next render (the path before, measured
  // against by bench_dictionary).
  bool overlap_writes = true;
  // This process renders the entries its share takes (an MPI rank's,
  // interleaved so that each gets near and far depths alike); the others are
  // left to the processes whose share they are.
  WorkShare share;
};

struct DictionaryBuildReport {
  size_t rendered = 0, reused = 0;
  double seconds = 0;
  double seconds_per_psf = 0;  // median time between two PSF files written (rendering overlaps writing)
};

// A grid larger than this is refused before any work: the default has 2783
// PSFs, and a build renders about one PSF per second on a CPU device.
inline constexpr size_t max_dictionary_psfs = 1000000;

// Throws DictionaryError, naming `dir` and the axis, unless the options'
// grid is valid (DictionaryGrid::validate), in front of the scene's lenses
// and at most max_dictionary_psfs;
// nothing is written. Callers that must set up a device first check here
// before it. The build itself also stops after its first PSF file when the
// rest, at that file's size, would not fit on the disk.
void check_build_options(const std::string& dir, const Scene& scene, const DictionaryBuildOptions& options);

// Throws ResourceError (host/util/memory.h) when one PSF's buffers on the
// host and device exceed the memory limit; the build checks it first.
void check_build_memory(const vk::Context& ctx, const Scene& scene, const DictionaryBuildOptions& options);

// Creates the folder and writes the manifest of a new dictionary, or checks
// that an existing one is this very dictionary (to be resumed). The build
// does this first; MPI rank 0 does it alone before the ranks build.
void prepare_dictionary(const Scene& scene, const std::string& dir, const DictionaryBuildOptions& options);

// progress(done, total) is called after each entry of this process's share
// (options checked first); `reused` counts the share's entries already there.
DictionaryBuildReport build_dictionary(vk::Context& ctx, const Scene& scene, const std::string& dir,
                                       const DictionaryBuildOptions& options,
                                       const std::function<void(size_t, size_t)>& progress = {});

}  // namespace prism
