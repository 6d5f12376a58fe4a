// Scoring estimates against the truth: the 3D error, and which estimate
// belongs to which true vertex. One convention for `prism reconstruct`,
// `prism evaluate`, the benchmarks and the tests.
#pragma once
#include <cstddef>
#include <limits>
#include <vector>

#include <glm/glm.hpp>

#include "host/reconstruct/reconstruct.h"

namespace prism {

// Euclidean distance in (x, y, depth) between an estimate and a true position, mm.
double error_3d_mm(const ReconstructedVertex& estimate, const glm::dvec3& truth_mm);

inline constexpr size_t unmatched = std::numeric_limits<size_t>::max();

// The one-to-one assignment of estimates to true vertices with the smallest
// summed 3D error, over every assignment (K <= 8). Returns, per truth, the
// index of its estimate; when there are fewer estimates than truths, the
// truths left over get `unmatched`.
std::vector<size_t> match_vertices(const std::vector<ReconstructedVertex>& estimates,
                                   const std::vector<glm::dvec3>& truth_mm);

}  // namespace prism
