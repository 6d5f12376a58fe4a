#include "host/scene/psf_render.h"

#include "engine/ref/forward_ref.h"

namespace prism {

PixelImage render_psf(const Scene& scene, const TraceSettings& t, const glm::dvec3& theta, bool derivatives,
                      Backend backend, vk::Context* ctx, MemoryEstimate& memory) {
  const AnalysisGrid grid = AnalysisGrid::of(scene.optics, t.binning);
  const double px = double(grid.width) * grid.height;
  memory.add("the image and its derivatives, 4 floats per pixel", 16 * px);
  if (backend == Backend::vulkan) {
    if (!derivatives) memory.add("the values from the device", 4 * px);
    memory.add_device_buffers(double(ForwardVulkan::device_bytes_at_most(grid, t.splat)), ctx->is_cpu());
    memory.require_within_limit("Use a coarser --binning");
    ForwardVulkan fw(*ctx, scene.optics, t);
    if (derivatives) return fw.psf(theta);
    // b alone: 4 bytes per pixel on the device instead of 32.
    auto b = fw.psf_values(theta);
    PixelImage img{fw.grid().width, fw.grid().height, fw.grid().pixel_mm, std::vector<float>(4 * b.size(), 0.0f)};
    for (size_t i = 0; i < b.size(); ++i) img.data[4 * i] = b[i];
    return img;
  }
  memory.add("the CPU reference's sparse image, up to every pixel", ref::SparseImage::bytes_per_pixel * px);
  memory.require_within_limit("Use a coarser --binning");
  auto sparse = ref::psf(scene.optics, t, theta);
  PixelImage img{sparse.width, sparse.height, grid.pixel_mm,
                 std::vector<float>(size_t(sparse.width) * sparse.height * 4, 0.0f)};
  for (const auto& [k, v] : sparse.pixels) {
    auto value = sparse.value(k);
    for (int c = 0; c < 4; ++c) img.data[size_t(k) * 4 + c] = derivatives || c == 0 ? float(value[c]) : 0.0f;
  }
  return img;
}

}  // namespace prism
