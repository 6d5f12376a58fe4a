#include "host/calibrate/source_blur.h"

#include <algorithm>
#include <cmath>

#include "engine/ref/forward_ref.h"

namespace prism {

std::optional<std::array<double, 6>> chief_ray_motion(const OpticalSystem& sys, const TraceSettings& settings,
                                                      const glm::dvec3& theta, std::size_t lens) {
  const ref::SampleHit h = ref::trace_point(sys, settings, theta, glm::dvec3(0.0), lens, glm::dvec2(0.0), 1.0);
  if (!h.ok) return std::nullopt;
  const double px = AnalysisGrid::of(sys, settings.binning).pixel_mm;
  return std::array<double, 6>{h.dx.x / px, h.dx.y / px, h.dx.z / px, h.dy.x / px, h.dy.y / px, h.dy.z / px};
}

std::array<double, 6> centroid_jacobian(const LensImage& image) {
  const size_t C = image.channels;
  double total = 0, cx = 0, cy = 0;
  for (size_t i = 0; i < image.keys.size(); ++i) {
    const double b = image.values[i * C];
    total += b;
    cx += b * double(image.keys[i] % image.width);
    cy += b * double(image.keys[i] / image.width);
  }
  std::array<double, 6> J{};
  if (!(total > 0)) return J;
  cx /= total, cy /= total;
  // d(sum x b / sum b) = sum (x - cx) db / sum b.
  for (size_t i = 0; i < image.keys.size(); ++i) {
    const double dx = double(image.keys[i] % image.width) - cx, dy = double(image.keys[i] / image.width) - cy;
    for (size_t k = 0; k < 3; ++k) {
      J[k] += dx * image.values[i * C + 1 + k] / total;
      J[3 + k] += dy * image.values[i * C + 1 + k] / total;
    }
  }
  return J;
}

BlurKernel source_blur_kernel(const std::array<double, 6>& J, double sigma_mm) {
  // A = J J^T, plus (1e-3 px/mm)^2 so that an image that does not move one
  // way (clipped by the sensor's edge) still has an invertible kernel.
  constexpr double kFloor = 1e-6;
  const double a = J[0] * J[0] + J[1] * J[1] + J[2] * J[2] + kFloor;
  const double b = J[0] * J[3] + J[1] * J[4] + J[2] * J[5];
  const double c = J[3] * J[3] + J[4] * J[4] + J[5] * J[5] + kFloor;
  const double det = a * c - b * b;
  const double largest = 0.5 * (a + c) + std::sqrt(0.25 * (a - c) * (a - c) + b * b);  // px^2 / mm^2
  BlurKernel k;
  // Four standard deviations hold all but 3e-4 of the light. The cap of 64
  // pixels bounds the work: a 0.3 mm source imaged at 8 px / mm needs 10;
  // a sigma near its 2 mm bound on supersampled pixels is cut (the kernel
  // still normalised, its derivative that of the cut kernel).
  k.radius = std::min(64, int(std::ceil(4.0 * sigma_mm * std::sqrt(largest))));
  const int n = 2 * k.radius + 1;
  std::vector<double> e(size_t(n) * n), de(size_t(n) * n);
  double sum = 0, dsum = 0;
  for (int dy = -k.radius; dy <= k.radius; ++dy)
    for (int dx = -k.radius; dx <= k.radius; ++dx) {
      // q = r^T A^-1 r; the kernel exp(-q / (2 sigma^2)) moves with sigma by q / sigma^3 of itself.
      const double q = (c * dx * dx - 2 * b * dx * dy + a * dy * dy) / det;
      const size_t i = size_t(dy + k.radius) * n + size_t(dx + k.radius);
      e[i] = std::exp(-0.5 * q / (sigma_mm * sigma_mm));
      de[i] = e[i] * q / (sigma_mm * sigma_mm * sigma_mm);
      sum += e[i], dsum += de[i];
    }
  k.g.resize(e.size());
  k.dg_dsigma.resize(e.size());
  for (size_t i = 0; i < e.size(); ++i) {
    k.g[i] = e[i] / sum;
    k.dg_dsigma[i] = (de[i] - k.g[i] * dsum) / sum;  // the normalisation's share
  }
  return k;
}

LensImage blur(const LensImage& image, const BlurKernel& kernel, bool sigma_channel) {
  const size_t C = image.channels, OC = C + (sigma_channel ? 1 : 0);
  LensImage out{image.width, image.height, OC, {}, {}};
  if (image.keys.empty()) return out;
  // A dense window: the image's bounding box widened by the kernel's radius.
  int64_t c0 = image.width, c1 = -1, r0 = image.height, r1 = -1;
  for (int64_t key : image.keys) {
    c0 = std::min(c0, key % image.width), c1 = std::max(c1, key % image.width);
    r0 = std::min(r0, key / image.width), r1 = std::max(r1, key / image.width);
  }
  const int R = kernel.radius, n = 2 * R + 1;
  c0 = std::max<int64_t>(0, c0 - R), c1 = std::min<int64_t>(image.width - 1, c1 + R);
  r0 = std::max<int64_t>(0, r0 - R), r1 = std::min<int64_t>(image.height - 1, r1 + R);
  const int64_t W = c1 - c0 + 1, H = r1 - r0 + 1;
  std::vector<double> window(size_t(W * H) * OC, 0.0);
  for (size_t i = 0; i < image.keys.size(); ++i) {
    const int64_t col = image.keys[i] % image.width, row = image.keys[i] / image.width;
    const double* v = &image.values[i * C];
    for (int dy = -R; dy <= R; ++dy) {
      const int64_t y = row + dy;
      if (y < r0 || y > r1) continue;  // beyond the sensor
      for (int dx = -R; dx <= R; ++dx) {
        const int64_t x = col + dx;
        if (x < c0 || x > c1) continue;
        const size_t ki = size_t(dy + R) * n + size_t(dx + R);
        const double g = kernel.g[ki];
        double* o = &window[size_t((y - r0) * W + (x - c0)) * OC];
        for (size_t ch = 0; ch < C; ++ch) o[ch] += g * v[ch];
        if (sigma_channel) o[C] += kernel.dg_dsigma[ki] * v[0];
      }
    }
  }
  for (int64_t y = 0; y < H; ++y)
    for (int64_t x = 0; x < W; ++x) {
      const double* o = &window[size_t(y * W + x) * OC];
      if (std::none_of(o, o + OC, [](double v) { return v != 0; })) continue;
      out.keys.push_back((y + r0) * image.width + (x + c0));
      out.values.insert(out.values.end(), o, o + OC);
    }
  return out;
}

}  // namespace prism
