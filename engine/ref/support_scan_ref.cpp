#include "engine/ref/support_scan_ref.h"

#include <algorithm>
#include <cmath>
#include <limits>

#include "engine/ref/likelihood_ref.h"

namespace prism::ref {

glm::ivec2 best_shift(ScanSource& level, size_t psf, std::span<const glm::ivec2> clicks, std::span<const double> w,
                      glm::ivec2 center, int reach, int step) {
  const int radius = level.radius_px(psf);
  std::vector<glm::ivec2> shifts;
  const int first = -(reach / step) * step;
  for (int dy = first; dy <= reach; dy += step)
    for (int dx = first; dx <= reach; dx += step) {
      glm::ivec2 sh = center + glm::ivec2(dx, dy);
      if (std::abs(sh.x) <= radius && std::abs(sh.y) <= radius) shifts.push_back(sh);
    }
  if (shifts.empty()) return glm::clamp(center, glm::ivec2(-radius), glm::ivec2(radius));
  // The shifts' pixels asked for in blocks of at most kBlockPixels, through one
  // buffer: a request for every shift at once was megabytes at the coarse
  // levels, fresh memory each call, and its page faults took half the
  // reference's time. A block's tiles are few and stay in the dictionary's cache.
  constexpr size_t kBlockPixels = 8192;
  const size_t n = clicks.size();
  const size_t block_shifts = std::max<size_t>(1, kBlockPixels / std::max<size_t>(1, n));
  std::vector<glm::ivec2> pixels;
  pixels.reserve(std::min(shifts.size(), block_shifts) * n);
  double best = std::numeric_limits<double>::infinity();
  glm::ivec2 arg = shifts[0];
  for (size_t first_shift = 0; first_shift < shifts.size(); first_shift += block_shifts) {
    const size_t end = std::min(shifts.size(), first_shift + block_shifts);
    pixels.clear();
    for (size_t j = first_shift; j < end; ++j)
      for (glm::ivec2 c : clicks) pixels.push_back(c - shifts[j]);
    const std::vector<float> v = level.values(psf, pixels);
    for (size_t j = first_shift; j < end; ++j) {
      double score = level.mass_shifted(psf, shifts[j]);
      for (size_t i = 0; i < n; ++i) score -= w[i] * double(v[(j - first_shift) * n + i]);
      if (score < best) best = score, arg = shifts[j];
    }
  }
  return arg;
}

std::vector<SupportScore> support_scan(ScanSource& level, const ScanEvent& event, const ScanSettings& settings) {
  std::vector<double> w(event.rate.size());
  for (size_t i = 0; i < w.size(); ++i) w[i] = click_weight(event.rate[i]);
  const int step = std::max(1, settings.step_px);
  std::vector<SupportScore> scored;
  scored.reserve(level.psf_count());
  for (size_t m = 0; m < level.psf_count(); ++m) {
    const int r = level.radius_px(m);
    glm::ivec2 sh = best_shift(level, m, event.clicks, w, glm::ivec2(0), r, step);
    std::vector<glm::ivec2> pixels;
    for (glm::ivec2 c : event.clicks) pixels.push_back(c - sh);
    auto v = level.values(m, pixels);
    std::vector<double> p(v.begin(), v.end());
    const double s = level.mass_shifted(m, sh);
    std::vector<double> alpha{initial_alpha(p, s, settings.alpha_max)};
    const std::vector<double>* columns[] = {&p};
    double f = fit_weights(columns, std::span<const double>(&s, 1), event.rate, alpha, settings.newton_iterations,
                           settings.alpha_max);
    scored.push_back({m, sh, f, alpha[0]});
  }
  return scored;
}

}  // namespace prism::ref
