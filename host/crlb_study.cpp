#include "host/crlb_study.h"

#include "engine/forward.h"
#include "engine/ref/forward_ref.h"

namespace prism {

std::vector<CrlbRow> crlb_study(const Scene& scene, const std::vector<glm::dvec3>& positions,
                                const TraceSettings& settings, Backend backend, SensorModel sensor,
                                vk::Context* ctx, double* kernel_ms) {
  std::vector<FisherResult> fisher;
  if (backend == Backend::vulkan) {
    ForwardVulkan fw(*ctx, scene.optics, settings);
    fisher = fw.fisher(positions);
    if (kernel_ms) *kernel_ms = fw.last_kernel_ms();
  } else {
    for (const auto& p : positions) fisher.push_back(ref::fisher(scene.optics, settings, p));
  }
  std::vector<CrlbRow> rows;
  for (size_t i = 0; i < positions.size(); ++i) {
    const FisherResult& f = fisher[i];
    rows.push_back({scene.name, scene.optics.lens_model, positions[i], f.photons,
                    crlb_from_fisher(sensor == SensorModel::binary ? f.binary : f.poisson, f.photons)});
  }
  return rows;
}

}  // namespace prism
