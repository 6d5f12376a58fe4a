// CRLB at a list of source positions for one scene: the computation behind
// `prism crlb`, `prism sweep` and the benchmarks.
#pragma once
#include <string>
#include <vector>

#include <glm/glm.hpp>

#include "engine/fisher.h"
#include "engine/vk/context.h"
#include "host/scene.h"

namespace prism {

enum class Backend { vulkan, cpu };
enum class SensorModel { poisson, binary };

struct CrlbRow {
  std::string scene;
  LensModel lens_model;
  glm::dvec3 theta;  // x, y, depth (mm)
  double photons;    // expected detected photons
  Crlb crlb;
};

// ctx is used only by the Vulkan backend.
std::vector<CrlbRow> crlb_study(const Scene& scene, const std::vector<glm::dvec3>& positions,
                                const TraceSettings& settings, Backend backend, SensorModel sensor,
                                vk::Context* ctx, double* kernel_ms = nullptr);

}  // namespace prism
