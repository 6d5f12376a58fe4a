// After the scan: ADCG's joint local descent on the dictionary grid, and the
// depth parabola that takes a vertex off the grid's planes.
//
// Joint re-optimisation. After each new vertex, all weights by projected
// Newton, then coordinate moves of each vertex in turn (+-1 click-grid pixel
// in x or y, moving to the nearest grid node when the source crosses the
// midpoint, and +-1 depth plane with the lateral offset rescaled by the
// magnification), each trial with all weights re-fitted, the best improving
// move kept, until a round improves nothing (at most descent_rounds).
//
// Depth parabola. With the other vertices as fixed background, the vertex's
// NLL at its own plane and at the two neighbouring planes (same lateral
// source position, shift rescaled, +-1 pixel re-searched), a parabola through
// the three, its minimum clamped between the neighbours. The lateral offset is
// then read at the refined depth (host/dictionary/placement.h).
#include <algorithm>
#include <cmath>
#include <limits>

#include "host/reconstruct/event_fit.h"

namespace prism::detail {

std::vector<Vertex> EventFit::moves(const Vertex& v) const {
  std::vector<Vertex> out;
  glm::ivec3 n = m_.grid.node(v.psf);
  double z = depth_of(v.psf);
  for (Shift step : {Shift(1, 0), Shift(-1, 0), Shift(0, 1), Shift(0, -1)}) {
    Vertex t = v;
    t.shift += step;
    if (auto p = place(source_xy(t, z), n.z, v.alpha)) out.push_back(*p);
  }
  for (int dz : {-1, 1}) {
    int iz = n.z + dz;
    if (iz < 0 || iz >= int(m_.grid.depth_mm.size())) continue;
    if (auto p = place(source_xy(v, z), iz, v.alpha)) out.push_back(*p);
  }
  return out;
}

void EventFit::descend(std::vector<Vertex>& vs) {
  double f = fit(vs);
  for (int round = 0; round < s_.descent_rounds; ++round) {
    bool improved = false;
    for (size_t k = 0; k < vs.size(); ++k) {
      std::vector<Vertex> best;
      double best_f = f;
      for (const Vertex& t : moves(vs[k])) {
        auto trial = vs;
        trial[k] = t;
        double ft = fit(trial);
        if (ft < best_f - 1e-9 * (1 + std::abs(best_f))) best_f = ft, best = std::move(trial);
      }
      if (!best.empty()) vs = std::move(best), f = best_f, improved = true;
    }
    if (!improved) break;
  }
}

EventFit::DepthFit EventFit::refine_depth(const Vertex& v, const std::vector<double>& background) {
  glm::ivec3 n = m_.grid.node(v.psf);
  const auto& planes = m_.grid.depth_mm;
  double z0 = planes[size_t(n.z)];
  glm::dvec2 xy = source_xy(v, z0);
  auto plane_nll = [&](int iz) -> std::optional<double> {
    if (iz < 0 || iz >= int(planes.size())) return std::nullopt;
    auto centre = place(xy, iz, v.alpha);
    if (!centre) return std::nullopt;
    double best = std::numeric_limits<double>::infinity();
    int r = radius_px(centre->psf, level_);
    for (int dy = -1; dy <= 1; ++dy)
      for (int dx = -1; dx <= 1; ++dx) {
        Shift sh = centre->shift + Shift(dx, dy);
        if (std::abs(sh.x) > r || std::abs(sh.y) > r) continue;
        const Column& c = column(centre->psf, sh);
        double alpha = v.alpha;
        best = std::min(best, fit_one(c.p, c.s, background, alpha));
      }
    return best;
  };
  const int P = int(planes.size());
  if (P < 3) return {z0, false};
  // Three consecutive planes around the vertex's own (at an outermost plane,
  // the two inner neighbours: the parabola then says whether the minimum
  // lies beyond the dictionary).
  const int a = std::clamp(n.z - 1, 0, P - 3);
  double zs[3], fs[3];
  for (int j = 0; j < 3; ++j) {
    zs[j] = planes[size_t(a + j)];
    auto f = plane_nll(a + j);
    fs[j] = f ? *f : std::numeric_limits<double>::infinity();
  }
  const double lo = planes[size_t(std::max(n.z - 1, 0))], hi = planes[size_t(std::min(n.z + 1, P - 1))];
  // Newton form through planes za, zb, zc: q(z) = fa + d1 (z - za) +
  // c (z - za)(z - zb), uneven spacing allowed: q' = 0 at (za + zb) / 2 -
  // d1 / (2c) when c > 0.
  double d1 = (fs[1] - fs[0]) / (zs[1] - zs[0]), d2 = (fs[2] - fs[1]) / (zs[2] - zs[1]);
  double curvature = (d2 - d1) / (zs[2] - zs[0]);
  double z;
  if (std::isfinite(curvature) && curvature > 0)
    z = 0.5 * (zs[0] + zs[1]) - d1 / (2 * curvature);
  else
    z = zs[std::min_element(fs, fs + 3) - fs];  // no upward parabola: the best plane
  // Beyond by more than half a plane spacing: past what the outermost plane covers.
  const double half = 0.25 * (zs[2] - zs[0]);
  bool beyond = z < planes.front() - half || z > planes.back() + half ||
                (!(curvature > 0) && (z == planes.front() || z == planes.back()));
  return {std::clamp(z, lo, hi), beyond};
}

}  // namespace prism::detail
