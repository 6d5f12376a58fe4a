#include "host/reconstruct/click_geometry.h"

#include <algorithm>
#include <cmath>

namespace prism {

std::vector<VotePeak> vote_source_positions(const OpticalSystem& sys, const AnalysisGrid& grid,
                                            std::span<const uint32_t> clicks, glm::dvec3 lo, glm::dvec3 hi,
                                            size_t count, double min_depth_apart_mm) {
  std::vector<VotePeak> best_per_depth;
  if (clicks.empty() || sys.lenslets.empty() || count == 0) return {};
  // Bins of 0.2 mm; a peak sums 3 x 3 of them, so the clicks of one lenslet
  // image (a defocus disc tenths of a mm across in source space near the
  // face) fall in one peak.
  constexpr double kBinMm = 0.2;
  const int nx = std::max(1, int(std::ceil((hi.x - lo.x) / kBinMm))), ny = std::max(1, int(std::ceil((hi.y - lo.y) / kBinMm)));
  std::vector<int> bins(size_t(nx) * size_t(ny), 0);
  std::vector<size_t> touched;
  // Click centres on the sensor, mm from its centre (the optical axis).
  std::vector<glm::dvec2> at;
  at.reserve(clicks.size());
  for (uint32_t c : clicks)
    at.push_back({(double(c % uint32_t(grid.width)) + 0.5) * grid.pixel_mm - 0.5 * sys.sensor_width_mm(),
                  (double(c / uint32_t(grid.width)) + 0.5) * grid.pixel_mm - 0.5 * sys.sensor_height_mm()});
  double reach_mm = 0;  // the outermost lenslet centre
  for (const auto& l : sys.lenslets) reach_mm = std::max(reach_mm, std::hypot(l.x_mm, l.y_mm));
  reach_mm = std::max(reach_mm, grid.pixel_mm);

  for (double depth = lo.z; depth <= hi.z;) {
    const double m = sys.magnification(depth);
    touched.clear();
    for (const glm::dvec2& c : at)
      for (const auto& l : sys.lenslets) {
        const double sx = (l.x_mm * (1 + m) - c.x) / m, sy = (l.y_mm * (1 + m) - c.y) / m;
        const int bx = int(std::floor((sx - lo.x) / kBinMm)), by = int(std::floor((sy - lo.y) / kBinMm));
        if (bx < 0 || by < 0 || bx >= nx || by >= ny) continue;
        const size_t b = size_t(by) * size_t(nx) + size_t(bx);
        if (bins[b]++ == 0) touched.push_back(b);
      }
    VotePeak peak{{0, 0, depth}, -1};
    for (size_t b : touched) {
      const int bx = int(b % size_t(nx)), by = int(b / size_t(nx));
      int sum = 0;
      for (int dy = -1; dy <= 1; ++dy)
        for (int dx = -1; dx <= 1; ++dx) {
          const int x = bx + dx, y = by + dy;
          if (x >= 0 && y >= 0 && x < nx && y < ny) sum += bins[size_t(y) * size_t(nx) + size_t(x)];
        }
      if (sum > peak.votes)
        peak = {{lo.x + (bx + 0.5) * kBinMm, lo.y + (by + 0.5) * kBinMm, depth}, double(sum)};
    }
    for (size_t b : touched) bins[b] = 0;
    if (peak.votes > 0) {
      peak.votes /= double(clicks.size());
      best_per_depth.push_back(peak);
    }
    // The next depth moves the outermost images by about a pixel:
    // d(c)/d(depth) = (l - s) dm/d(depth), |dm/d(depth)| = m^2 / L.
    depth += grid.pixel_mm * sys.lens_to_sensor_mm / (reach_mm * m * m);
  }
  std::stable_sort(best_per_depth.begin(), best_per_depth.end(),
                   [](const VotePeak& a, const VotePeak& b) { return a.votes > b.votes; });
  std::vector<VotePeak> out;
  for (const VotePeak& p : best_per_depth) {
    bool apart = true;
    for (const VotePeak& q : out) apart = apart && std::abs(p.position_mm.z - q.position_mm.z) >= min_depth_apart_mm;
    if (apart) out.push_back(p);
    if (out.size() == count) break;
  }
  return out;
}

}  // namespace prism
