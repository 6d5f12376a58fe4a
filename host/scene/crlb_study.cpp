#include "host/scene/crlb_study.h"

#include <algorithm>

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
                    crlb_from_fisher(sensor == SensorModel::binary ? f.binary : f.poisson, f.photons),
                    settings.rays()});
  }
  return rows;
}

std::vector<CrlbRow> crlb_converged(const Scene& scene, const std::vector<glm::dvec3>& positions,
                                    TraceSettings settings, double tolerance, unsigned max_rays, Backend backend,
                                    SensorModel sensor, vk::Context* ctx) {
  auto previous = crlb_study(scene, positions, settings, backend, sensor, ctx);
  while (true) {
    if (uint64_t(settings.rays_per_lenslet) * 4 > max_rays) return previous;
    settings.rays_per_lenslet *= 4;
    auto rows = crlb_study(scene, positions, settings, backend, sensor, ctx);
    bool all = true;
    for (size_t i = 0; i < rows.size(); ++i) {
      double a = rows[i].crlb.r3_mm, b = previous[i].crlb.r3_mm;
      // Both infinite: as converged as it gets (no light); one infinite: not converged.
      rows[i].change = (std::isinf(a) && std::isinf(b)) ? 0.0 : std::isinf(a) || std::isinf(b) ? INFINITY : std::abs(a / b - 1);
      all = all && rows[i].change <= tolerance;
    }
    if (all) return rows;
    previous = rows;
  }
}

std::vector<CrlbRow> crlb_checked(const Scene& scene, const std::vector<glm::dvec3>& positions,
                                  const TraceSettings& settings, double converge, unsigned max_rays, Backend backend,
                                  SensorModel sensor, vk::Context* ctx) {
  if (converge > 0) return crlb_converged(scene, positions, settings, converge, max_rays, backend, sensor, ctx);
  const double tol = defaults::crlb_convergence_tol;
  TraceSettings quarter = settings;
  quarter.rays_per_lenslet = std::max(4u, settings.rays_per_lenslet / 4);
  auto rows = crlb_converged(scene, positions, quarter, tol, settings.rays_per_lenslet, backend, sensor, ctx);
  for (auto& r : rows)
    if (r.crlb.flag == "ok" && !(r.change <= tol)) r.crlb.flag = "moving";
  return rows;
}

}  // namespace prism
