// The forward model on the device: trace point sources through the lenslets,
// splat b and db/dtheta into the analysis grid, reduce to Fisher information.
// Sensors larger than one storage buffer are processed in bands of rows; many
// sources share one dispatch.
#pragma once
#include <cstdint>
#include <memory>
#include <span>
#include <vector>

#include <glm/glm.hpp>

#include "engine/fisher.h"
#include "engine/optical_system.h"
#include "engine/shared_math.h"
#include "engine/vk/compute.h"

namespace prism {

// Expected photons and their derivatives on the analysis grid: 4 floats per
// pixel (b, db/dx, db/dy, db/ddepth), row-major.
struct PixelImage {
  int width = 0;
  int height = 0;
  double pixel_mm = 0;
  std::vector<float> data;
  float b(int col, int row) const { return data[4 * (size_t(row) * width + col)]; }
  double photons() const;
};

// The tiles of shared::LARGE_TILE_PX x LARGE_TILE_PX grid pixels (from
// pixel (0, 0)) a masked render gives light to: the rest of its image is
// zero, and the kernels skip the pieces whose light reaches none of them, so
// a render around a few clicks at the sensor's own pixels costs their
// neighbourhoods, not the whole sensor. Footprint splat only.
struct TileMask {
  int tiles_w = 0, tiles_h = 0;
  std::vector<uint32_t> bits;  // row-major, tile t in bit t % 32 of word t / 32
  static TileMask of(const AnalysisGrid& grid);  // no tile marked
  // Every tile within reach_px pixels (per axis) of pixel (col, row).
  void mark_around(int col, int row, int reach_px);
  bool marked(int tile_col, int tile_row) const;
  bool covers(int col, int row) const { return marked(col / shared::LARGE_TILE_PX, row / shared::LARGE_TILE_PX); }
  size_t count() const;  // tiles marked
};

// A pixel of a masked render: its grid index (row-major), b and d b/d(x, y,
// depth) (the mean of the two halves' estimates, as PixelImage).
struct LitPixel {
  uint32_t index;
  float b;
  glm::vec3 db;
};

class ForwardVulkan {
 public:
  static constexpr uint64_t default_image_budget_bytes = 256ull << 20;
  // What the kernels' derivatives can be taken with respect to: the source's
  // position, or any three scene parameters a call names (calibration: the
  // kernels' calibrate variants, which also trace the as-built path).
  enum class Derivatives { source, scene };
  ForwardVulkan(vk::Context& ctx, const OpticalSystem& sys, const TraceSettings& settings,
                uint64_t image_budget_bytes = default_image_budget_bytes, Derivatives derivatives = Derivatives::source);
  // Several designs traced in the same dispatches (design sweeps). They must
  // share the sensor, distances, lens model and effects; only the lenslets
  // differ. Each design traces the very rays it would trace alone.
  ForwardVulkan(vk::Context& ctx, const std::vector<OpticalSystem>& designs, const TraceSettings& settings,
                uint64_t image_budget_bytes = default_image_budget_bytes);
  // The most device memory a forward model of `grid` holds: its image buffer
  // and, for the footprint splat, its two lists, each within the budget (for
  // memory estimates: on a CPU device it is host memory).
  static uint64_t device_bytes_at_most(const AnalysisGrid& grid, Splat splat,
                                       uint64_t image_budget_bytes = default_image_budget_bytes);
  ~ForwardVulkan();

  // theta = (x_mm, y_mm, depth_mm) per source, through design 0.
  std::vector<FisherResult> fisher(std::span<const glm::dvec3> theta);
  // Source i through design design_of[i].
  std::vector<FisherResult> fisher(std::span<const glm::dvec3> theta, std::span<const uint32_t> design_of);
  PixelImage psf(const glm::dvec3& theta);
  // b and d b/d(tangents) (the mean of the two halves' estimates), of
  // lenslet `only_lens` alone (its very rays; -1: every lenslet). Other than
  // the source's tangents of every lenslet, it needs Derivatives::scene.
  PixelImage psf(const glm::dvec3& theta, const Tangents& tangents, int only_lens = -1);
  // psf(theta) on the tiles `mask` marks (of this grid) alone: their pixels
  // that hold light, the same light as the whole image's there; the rest is
  // not computed. Throws where the marked tiles outgrow one image buffer.
  std::vector<LitPixel> psf(const glm::dvec3& theta, const TileMask& mask);
  size_t max_masked_tiles() const;  // the most tiles a mask may mark (one image buffer)
  // Trace another scene with the same kernels: the same lenslets (count,
  // diameters), lens model, effects and sensor, with other positions, focal
  // lengths, tilts, distances and sensor pose (calibration's steps; a tilted
  // scene needs the as-built kernels that Derivatives::scene always has).
  void set_scene(const OpticalSystem& sys);
  // Expected photons per pixel only, row-major: 4 bytes per pixel on the
  // device instead of 32 (no derivatives); for dictionaries and events.
  std::vector<float> psf_values(const glm::dvec3& theta);

  double last_kernel_ms() const { return last_kernel_ms_; }  // device time of the last call
  // Each dispatch of the last call and its device time: the footprint's
  // passes (the first over the cells, a split level each, the cut) and the
  // Fisher reduction, in order (empty where the queue has no timestamps).
  const std::vector<vk::Stream::KernelTime>& last_kernel_times() const;
  // Footprint splat: the chunks its first pass takes the cells in (1 while its
  // lists fit in a storage buffer within the budget; 0 for the point splat).
  unsigned footprint_cell_chunks() const;
  uint64_t rays_per_source() const;
  const AnalysisGrid& grid() const { return grid_; }

 public:
  struct Impl;  // the kernels and their buffers (forward.cpp)

 private:
  std::unique_ptr<Impl> impl_;
  AnalysisGrid grid_;
  double last_kernel_ms_ = 0;
};

// The lenslets as the kernels see them: geometry, strata, first ray.
std::vector<shared::Lenslet> device_lenslets(const OpticalSystem& sys, const TraceSettings& settings);

// Where explicit rays (origin, direction pairs) through one lenslet land on
// the sensor plane, on the device; returns (x_mm, y_mm, ok) per ray. For the
// check against an independent optics library (tests/engine/test_lens_landing.cpp),
// not part of the forward model.
std::vector<glm::vec3> landing_points_vulkan(vk::Context& ctx, const OpticalSystem& sys, size_t lens_index,
                                             std::span<const glm::vec3> origin_dir_pairs);

}  // namespace prism
