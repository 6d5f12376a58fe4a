#include "host/reconstruct/match.h"

#include <cmath>
#include <stdexcept>

namespace prism {

double error_3d_mm(const ReconstructedVertex& v, const glm::dvec3& t) {
  return std::hypot(v.x_mm - t.x, v.y_mm - t.y, v.depth_mm - t.z);
}

std::vector<size_t> match_vertices(const std::vector<ReconstructedVertex>& est, const std::vector<glm::dvec3>& truth) {
  const size_t T = truth.size(), E = est.size();
  if (T > 8 || E > 8) throw std::invalid_argument("match_vertices: at most 8 vertices");
  const size_t matches = std::min(T, E);
  std::vector<size_t> current(T, unmatched), best(T, unmatched);
  std::vector<bool> used(E, false);
  double best_sum = INFINITY;
  // Depth-first over truths: each takes an unused estimate, or none while
  // enough truths remain to use up the estimates.
  auto visit = [&](auto&& self, size_t t, size_t matched, double sum) -> void {
    if (sum >= best_sum) return;
    if (t == T) {
      if (matched == matches) best_sum = sum, best = current;
      return;
    }
    for (size_t e = 0; e < E; ++e) {
      if (used[e]) continue;
      used[e] = true;
      current[t] = e;
      self(self, t + 1, matched + 1, sum + error_3d_mm(est[e], truth[t]));
      used[e] = false;
    }
    if (T - t - 1 >= matches - matched) {  // this truth may go unmatched
      current[t] = unmatched;
      self(self, t + 1, matched, sum);
    }
  };
  visit(visit, 0, 0, 0.0);
  return best;
}

}  // namespace prism
