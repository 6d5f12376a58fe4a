// CRLB at a list of source positions for one scene: the computation behind
// `prism crlb`, `prism sweep` and the benchmarks.
#pragma once
#include <cmath>
#include <string>
#include <vector>

#include <glm/glm.hpp>

#include "engine/fisher.h"
#include "engine/vk/context.h"
#include "host/scene/scene.h"

namespace prism {

enum class Backend { vulkan, cpu };
enum class SensorModel { poisson, binary };

struct CrlbRow {
  std::string scene;
  LensModel lens_model;
  glm::dvec3 theta;  // x, y, depth (mm)
  double photons;    // expected detected photons
  Crlb crlb;
  unsigned rays_per_lenslet = 0;  // rays through a 3 mm lenslet in the run that gave crlb
  double change = NAN;            // |crlb_3d / crlb_3d at 1/4 the rays - 1|; NaN when not measured
};

// ctx is used only by the Vulkan backend.
std::vector<CrlbRow> crlb_study(const Scene& scene, const std::vector<glm::dvec3>& positions,
                                const TraceSettings& settings, Backend backend, SensorModel sensor,
                                vk::Context* ctx, double* kernel_ms = nullptr);

// Quadruple the rays, from settings.rays_per_lenslet up to max_rays, until the
// 3D CRLB of every position changes by at most `tolerance` (relative) between
// consecutive ray counts. Rows carry the change they reached; a row whose
// change is still above the tolerance at max_rays says so in that number.
std::vector<CrlbRow> crlb_converged(const Scene& scene, const std::vector<glm::dvec3>& positions,
                                    TraceSettings settings, double tolerance, unsigned max_rays, Backend backend,
                                    SensorModel sensor, vk::Context* ctx);

// The rows `prism crlb` prints (and the Python module returns): with
// converge > 0, crlb_converged from settings' rays up to max_rays; otherwise
// each row at settings' rays checked against a quarter of them (one extra
// pass at a quarter of the cost) and flagged "moving" where its 3D CRLB
// changed by more than defaults::crlb_convergence_tol.
std::vector<CrlbRow> crlb_checked(const Scene& scene, const std::vector<glm::dvec3>& positions,
                                  const TraceSettings& settings, double converge, unsigned max_rays, Backend backend,
                                  SensorModel sensor, vk::Context* ctx);

}  // namespace prism
