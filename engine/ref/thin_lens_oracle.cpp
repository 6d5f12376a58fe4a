#include "engine/ref/thin_lens_oracle.h"

#include <algorithm>
#include <array>
#include <cmath>
#include <stdexcept>
#include <vector>

#include "engine/ref/dual_ref.h"

namespace prism::ref {

namespace {

// Gauss-Legendre nodes and weights on [-1, 1] (Newton on P_n from the usual
// cosine guesses; computed once).
constexpr int kOrder = 16;
struct GaussLegendre {
  std::array<double, kOrder> x{}, w{};
  GaussLegendre() {
    for (int i = 0; i < kOrder; ++i) {
      double z = std::cos(M_PI * (i + 0.75) / (kOrder + 0.5)), dp = 0;
      for (int it = 0; it < 100; ++it) {
        double p0 = 1, p1 = 0;
        for (int j = 1; j <= kOrder; ++j) {
          double p2 = p1;
          p1 = p0;
          p0 = ((2.0 * j - 1) * z * p1 - (j - 1.0) * p2) / j;
        }
        dp = kOrder * (z * p0 - p1) / (z * z - 1);
        double step = p0 / dp;
        z -= step;
        if (std::abs(step) < 1e-16) break;
      }
      x[size_t(i)] = z;
      w[size_t(i)] = 2 / ((1 - z * z) * dp * dp);
    }
  }
};
const GaussLegendre& gauss() {
  static const GaussLegendre g;
  return g;
}


// Source-relative coordinates: u, v lateral from the source, h its distance to
// the lens plane. The weight's integral over [0, u] x [0, v] is the solid angle
// of that rectangle seen from the source; over [0, v] alone (per unit u) it is
// `column`.
D solid_angle(D u, D v, D h) { return atan(u * v / (h * sqrt(u * u + v * v + h * h))); }
D column(D u, D v, D h) { return h * v / ((u * u + h * h) * sqrt(u * u + v * v + h * h)); }

// Integral of h / r^3 over the rectangle [u0, u1] x [v0, v1] intersected with
// the disc of centre (cu, cv) and radius R (lens-plane millimetres).
D disc_rectangle(D cu, D cv, double R, D u0, D u1, D v0, D v1, D h) {
  // Entirely inside the disc: the closed form at the corners.
  auto inside = [&](D u, D v) { return std::hypot(u.v - cu.v, v.v - cv.v) <= R; };
  if (inside(u0, v0) && inside(u1, v0) && inside(u0, v1) && inside(u1, v1))
    return solid_angle(u1, v1, h) - solid_angle(u0, v1, h) - solid_angle(u1, v0, h) + solid_angle(u0, v0, h);
  // Disjoint from it: nothing.
  const double nu = std::clamp(cu.v, u0.v, u1.v), nv = std::clamp(cv.v, v0.v, v1.v);
  if (std::hypot(nu - cu.v, nv - cv.v) >= R) return D(0.0);

  // The edge crosses the rectangle: integrate over the disc's angle phi,
  // u = cu - R cos(phi), whose half chord R sin(phi) is smooth in phi (the
  // square root of the chord in u has an infinite slope at the disc's ends).
  // Piece ends in phi: the disc's own ends are fixed (0 and pi), the
  // rectangle's sides and the points where the edge meets v0 or v1 move with
  // theta (duals).
  struct End {
    double u;  // for sorting
    D phi;
  };
  std::vector<End> ends;
  // A side strictly inside (cu - R, cu + R) (else the rectangle would miss the disc).
  auto phi_of_u = [&](D u) { return acos((cu - u) / D(R)); };
  const double left = cu.v - R, right = cu.v + R;
  if (u0.v > left) ends.push_back({u0.v, phi_of_u(u0)});
  else ends.push_back({left, D(0.0)});
  if (u1.v < right) ends.push_back({u1.v, phi_of_u(u1)});
  else ends.push_back({right, D(M_PI)});
  const double lo = ends[0].u, hi = ends[1].u;
  for (D b : {v0, v1}) {
    const D dv = b - cv;
    if (std::abs(dv.v) >= R) continue;
    const D half = sqrt(D(R * R) - dv * dv);  // the edge meets v = b at u = cu -+ half
    for (int sign : {-1, 1}) {
      const double u = cu.v + sign * half.v;
      if (u > lo && u < hi) ends.push_back({u, acos(D(-sign) * half / D(R))});
    }
  }
  std::sort(ends.begin(), ends.end(), [](const End& a, const End& b) { return a.u < b.u; });

  const auto& g = gauss();
  D total(0.0);
  for (size_t p = 0; p + 1 < ends.size(); ++p) {
    const D a = ends[p].phi, b = ends[p + 1].phi;
    if (!(b.v > a.v)) continue;
    // Which of the rectangle's sides and the disc's edge bound v on this
    // piece: fixed between the ends, so decided at its middle.
    const double mid = 0.5 * (a.v + b.v), chord = R * std::sin(mid);
    const bool top_is_edge = cv.v + chord < v1.v, bottom_is_edge = cv.v - chord > v0.v;
    if (std::min(v1.v, cv.v + chord) <= std::max(v0.v, cv.v - chord)) continue;  // empty here
    const D half_width = (b - a) * D(0.5), centre = (a + b) * D(0.5);
    for (int k = 0; k < kOrder; ++k) {
      const D phi = centre + half_width * D(g.x[size_t(k)]);
      const D s = sin(phi), u = cu - D(R) * cos(phi), arc = D(R) * s;
      const D top = top_is_edge ? cv + arc : v1, bottom = bottom_is_edge ? cv - arc : v0;
      total = total + D(g.w[size_t(k)]) * half_width * (column(u, top, h) - column(u, bottom, h)) * arc;
    }
  }
  return total;
}

}  // namespace

SparseImage thin_lens_image(const OpticalSystem& sys, const TraceSettings& settings, const glm::dvec3& theta) {
  const auto& e = sys.effects;
  if (sys.lens_model != LensModel::thin)
    throw std::invalid_argument("thin-lens oracle: the system has real lenses; the oracle is exact for ideal thin lenses only");
  if (sys.as_built())
    throw std::invalid_argument("thin-lens oracle: tilted lenslets or a sensor off its nominal pose; the oracle is for "
                                "lenses in the lens plane and the sensor parallel to it, trace as-built systems instead");
  if (e.scintillator_refraction || e.holder_vignetting || e.source_extent)
    throw std::invalid_argument("thin-lens oracle: effects other than detection efficiency and dark counts are not "
                                "affine in the aperture point; trace them instead");
  const AnalysisGrid grid = AnalysisGrid::of(sys, settings.binning);
  const double px = grid.pixel_mm, half_w = 0.5 * sys.sensor_width_mm(), half_h = 0.5 * sys.sensor_height_mm();
  const double L = sys.lens_to_sensor_mm;
  const D photons_per_sr(settings.photons_emitted * e.detection_efficiency / (4 * M_PI));
  // theta as duals: the source at lateral (sx, sy), distance h = depth + w to the lens plane.
  const D sx(theta.x, {1, 0, 0}), sy(theta.y, {0, 1, 0}), h(theta.z + sys.working_distance_mm, {0, 0, 1});

  SparseImage img;
  img.width = grid.width;
  img.height = grid.height;
  for (const auto& l : sys.lenslets) {
    const double R = 0.5 * l.diameter_mm;
    const D k = D(1.0) + D(L) / h - D(L / l.focal_mm);
    const D tx = D(l.x_mm * L / l.focal_mm) - sx * D(L) / h, ty = D(l.y_mm * L / l.focal_mm) - sy * D(L) / h;
    const D cu = D(l.x_mm) - sx, cv = D(l.y_mm) - sy;  // disc centre, source-relative
    // The image disc: centre k c + t, radius |k| R.
    const double ix = k.v * l.x_mm + tx.v, iy = k.v * l.y_mm + ty.v, ir = std::abs(k.v) * R;
    auto deposit = [&](int col, int row, D b) {
      if (b.v <= 0 && b.d == glm::dvec3(0.0)) return;
      auto& p = img.pixels[int64_t(row) * grid.width + col];
      p[0] += b.v;
      for (int c = 0; c < 3; ++c) p[size_t(1 + c)] += b.d[c], p[size_t(4 + c)] += b.d[c];
    };
    if (ir < 1e-12) {
      // In focus to a point: the whole disc lands in one pixel, which does
      // not move to first order (no positional derivative).
      const int col = int(std::floor((ix + half_w) / px)), row = int(std::floor((iy + half_h) / px));
      if (std::abs(ix) > half_w || std::abs(iy) > half_h || col >= grid.width || row >= grid.height) continue;
      deposit(col, row, photons_per_sr * disc_rectangle(cu, cv, R, cu - D(R), cu + D(R), cv - D(R), cv + D(R), h));
      continue;
    }
    const int c0 = std::max(0, int(std::floor((ix - ir + half_w) / px)));
    const int c1 = std::min(grid.width - 1, int(std::floor((ix + ir + half_w) / px)));
    const int r0 = std::max(0, int(std::floor((iy - ir + half_h) / px)));
    const int r1 = std::min(grid.height - 1, int(std::floor((iy + ir + half_h) / px)));
    for (int row = r0; row <= r1; ++row) {
      const double y0 = -half_h + row * px, y1 = std::min(y0 + px, half_h);
      if (y1 <= y0) continue;
      for (int col = c0; col <= c1; ++col) {
        const double x0 = -half_w + col * px, x1 = std::min(x0 + px, half_w);
        if (x1 <= x0) continue;
        // The pixel's preimage on the lens plane, source-relative.
        D a0 = (D(x0) - tx) / k - sx, a1 = (D(x1) - tx) / k - sx;
        D b0 = (D(y0) - ty) / k - sy, b1 = (D(y1) - ty) / k - sy;
        if (k.v < 0) std::swap(a0, a1), std::swap(b0, b1);
        deposit(col, row, photons_per_sr * disc_rectangle(cu, cv, R, a0, a1, b0, b1, h));
      }
    }
  }
  return img;
}

FisherResult thin_lens_fisher(const OpticalSystem& sys, const TraceSettings& settings, const glm::dvec3& theta) {
  return fisher_of(thin_lens_image(sys, settings, theta), sys.effects.dark_counts_per_pixel, settings.estimator);
}

}  // namespace prism::ref
