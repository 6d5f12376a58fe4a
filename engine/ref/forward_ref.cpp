#include "engine/ref/forward_ref.h"

#include <algorithm>
#include <cmath>
#include <functional>
#include <vector>

#include "engine/ref/dual_ref.h"
#include "engine/shared_math.h"

namespace prism::ref {

namespace {

struct V3 {
  D x, y, z;
};
V3 operator+(const V3& a, const V3& b) { return {a.x + b.x, a.y + b.y, a.z + b.z}; }
V3 operator-(const V3& a, const V3& b) { return {a.x - b.x, a.y - b.y, a.z - b.z}; }
V3 operator*(const V3& a, D s) { return {a.x * s, a.y * s, a.z * s}; }
D dot(const V3& a, const V3& b) { return a.x * b.x + a.y * b.y + a.z * b.z; }
V3 unit(const V3& a) { return a * (D(1.0) / sqrt(dot(a, a))); }

// Snell's law for unit direction i and unit normal n facing against i, index
// ratio eta = n1 / n2. Empty on total internal reflection.
std::optional<V3> snell(const V3& i, const V3& n, double eta) {
  D cos_i = -dot(n, i);
  D sin2_t = D(eta * eta) * (D(1.0) - cos_i * cos_i);
  if (sin2_t.v >= 1.0) return std::nullopt;
  D cos_t = sqrt(D(1.0) - sin2_t);
  return i * D(eta) + n * (D(eta) * cos_i - cos_t);
}

bool within(const V3& p, double cx, double cy, double r) {
  double dx = p.x.v - cx, dy = p.y.v - cy;
  return dx * dx + dy * dy <= r * r;
}

struct Geometry {
  double cx, cy, radius, focal, R, thickness, sag, n;
};
Geometry geometry(const OpticalSystem& sys, size_t i) {
  const auto& l = sys.lenslets[i];
  return {l.x_mm, l.y_mm, 0.5 * l.diameter_mm, l.focal_mm, sys.curvature_radius_mm(i), sys.center_thickness_mm(i),
          sys.sag_mm(i), sys.glass_index};
}

// Propagate a ray from `o` along `dir` through lenslet g to the sensor plane.
// Returns the landing point (x, y) or nothing when stopped. Sampled rays start
// inside the entrance disk by construction and skip its test.
std::optional<std::pair<D, D>> propagate(const OpticalSystem& sys, const Geometry& g, V3 o, V3 dir,
                                         bool test_entrance) {
  double bore = sys.effects.holder_vignetting ? sys.effects.holder_bore_mm : 0.0;
  double L = sys.lens_to_sensor_mm;
  if (sys.lens_model == LensModel::thin) {
    D t = -o.z / dir.z;
    V3 p = o + dir * t;
    if (test_entrance && !within(p, g.cx, g.cy, g.radius)) return std::nullopt;
    D sx = dir.x / dir.z - (p.x - D(g.cx)) / D(g.focal);
    D sy = dir.y / dir.z - (p.y - D(g.cy)) / D(g.focal);
    if (bore > 0 && !within(V3{p.x + sx * D(bore), p.y + sy * D(bore), D(bore)}, g.cx, g.cy, g.radius)) return std::nullopt;
    return std::make_pair(p.x + sx * D(L), p.y + sy * D(L));
  }
  V3 d = unit(dir);
  V3 exit_point, exit_dir;
  if (!sys.curved_toward_sensor) {
    // Spherical front face, centre (cx, cy, R): first intersection from the source side.
    V3 c{D(g.cx), D(g.cy), D(g.R)};
    V3 oc = o - c;
    D b = dot(oc, d);
    D disc = b * b - (dot(oc, oc) - D(g.R * g.R));
    if (disc.v <= 0) return std::nullopt;
    V3 p1 = o + d * (-b - sqrt(disc));
    if (test_entrance && (!within(p1, g.cx, g.cy, g.radius) || p1.z.v > g.sag)) return std::nullopt;
    auto d1 = snell(d, (p1 - c) * D(1.0 / g.R), 1.0 / g.n);  // outward normal faces the source
    if (!d1) return std::nullopt;
    // Flat back face.
    V3 p2 = p1 + *d1 * ((D(g.thickness) - p1.z) / d1->z);
    if (!within(p2, g.cx, g.cy, g.radius)) return std::nullopt;
    auto d2 = snell(*d1, V3{D(0.0), D(0.0), D(-1.0)}, g.n);
    if (!d2) return std::nullopt;
    exit_point = p2;
    exit_dir = *d2;
  } else {
    // Flat front face at z = 0, then the sphere centred at z = thickness - R, left from inside.
    V3 p0 = o + d * (-o.z / d.z);
    if (test_entrance && !within(p0, g.cx, g.cy, g.radius)) return std::nullopt;
    auto d1 = snell(d, V3{D(0.0), D(0.0), D(-1.0)}, 1.0 / g.n);
    V3 c{D(g.cx), D(g.cy), D(g.thickness - g.R)};
    V3 oc = p0 - c;
    D b = dot(oc, *d1);
    D disc = b * b - (dot(oc, oc) - D(g.R * g.R));
    if (disc.v <= 0) return std::nullopt;
    V3 p1 = p0 + *d1 * (-b + sqrt(disc));
    if (!within(p1, g.cx, g.cy, g.radius) || p1.z.v < g.thickness - g.sag) return std::nullopt;
    auto d2 = snell(*d1, (c - p1) * D(1.0 / g.R), g.n);  // inward normal faces the outgoing ray
    if (!d2) return std::nullopt;
    exit_point = p1;
    exit_dir = *d2;
  }
  if (bore > exit_point.z.v) {
    D tb = (D(bore) - exit_point.z) / exit_dir.z;
    if (!within(exit_point + exit_dir * tb, g.cx, g.cy, g.radius)) return std::nullopt;
  }
  D ts = (D(L) - exit_point.z) / exit_dir.z;
  return std::make_pair(exit_point.x + exit_dir.x * ts, exit_point.y + exit_dir.y * ts);
}

// The sample points: the device's own sampling code (shaders/common/optics.glsl
// through engine/shared_math.h), so both trace the very same rays. The points
// are inputs of the integral, not physics; everything from them to the pixel
// is this file's own double-precision computation.
glm::dvec2 unit_disk_sample(uint32_t lens, uint32_t sample, uint32_t strata, uint32_t seed) {
  return glm::dvec2(shared::aperture_sample(lens, sample, strata, seed));
}
glm::dvec3 source_offset(uint32_t lens, uint32_t sample, double sigma, uint32_t seed) {
  return glm::dvec3(shared::source_offset(lens, sample, float(sigma), seed));
}

// Scintillator face: find the radial distance rho on the face, from the point
// below the source, such that the refracted ray reaches radial distance pr on
// the aperture plane a height w above the face: pr = rho + w tan(theta_air),
// sin(theta_air) = n sin(theta_scint). Newton on rho, run on duals.
struct FacePath {
  D rho_over_pr;  // q = s + (rho / pr) (p - s) laterally
  D weight;       // Fresnel T * cos/L^2 inside * dA_face / dA_aperture
};
FacePath face_path(D h, D pr2, double w, double n) {
  D pr = sqrt(pr2 + D(1e-30));
  auto air_tan = [&](D rho) {
    D L = sqrt(rho * rho + h * h);
    D s = D(n) * rho / L;  // sin in air
    return s / sqrt(D(1.0) - s * s);
  };
  // Start from the paraxial guess, kept below the critical angle (beyond it
  // no ray leaves the scintillator).
  D rho = pr * h / (h + D(n * w));
  double rho_max = n > 1.0 ? h.v / std::sqrt(n * n - 1.0) : INFINITY;
  if (rho.v >= rho_max) rho = D(0.99) * D(rho_max, h.d / std::sqrt(n * n - 1.0));
  for (int it = 0; it < 60; ++it) {
    D L = sqrt(rho * rho + h * h);
    D s = D(n) * rho / L;
    D c3 = (D(1.0) - s * s) * sqrt(D(1.0) - s * s);
    D f = rho + D(w) * air_tan(rho) - pr;
    D fp = D(1.0) + D(w * n) * h * h / (L * L * L * c3);
    D next = rho - f / fp;
    if (next.v >= rho_max) next = D(0.5) * (rho + D(rho_max));
    if (next.v < 0) next = D(0.5) * rho;
    rho = next;
  }
  D L = sqrt(rho * rho + h * h);
  D sin_i = rho / L, cos_i = h / L;
  D sin_t = D(n) * sin_i;
  D cos_t = sqrt(D(1.0) - sin_t * sin_t);
  D rs = (D(n) * cos_i - cos_t) / (D(n) * cos_i + cos_t);
  D rp = (D(n) * cos_t - cos_i) / (D(n) * cos_t + cos_i);
  D transmit = D(1.0) - D(0.5) * (rs * rs + rp * rp);
  D dpr_drho = D(1.0) + D(w * n) * h * h / (L * L * L * (D(1.0) - sin_t * sin_t) * cos_t);
  // Radial area map: dA_aperture / dA_face = (pr / rho) * dpr/drho.
  D ratio = (pr.v < 1e-12) ? D(1.0) / (D(1.0) + D(w * n) / h) : rho / pr;
  D area = ratio / dpr_drho;
  return {ratio, transmit * cos_i / (L * L) * area};
}

// The ray from source `centre` through point `u` of lenslet `lens`'s
// entrance disk (unit-disk coordinates), carrying the photons of `area_mm2`
// of aperture there.
SampleHit trace_point(const OpticalSystem& sys, const TraceSettings& settings, const glm::dvec3& centre, size_t lens,
                      glm::dvec2 u, double area_mm2) {
  Geometry g = geometry(sys, lens);
  double z_ap = (sys.lens_model == LensModel::real && !sys.curved_toward_sensor) ? g.sag : 0.0;
  V3 p{D(g.cx + g.radius * u.x), D(g.cy + g.radius * u.y), D(z_ap)};
  V3 s{D(centre.x, {1, 0, 0}), D(centre.y, {0, 1, 0}), D(-(centre.z + sys.working_distance_mm), {0, 0, -1})};
  double photons = settings.photons_emitted * sys.effects.detection_efficiency / (4 * M_PI) * area_mm2;
  V3 origin = s;
  D weight;
  if (sys.effects.scintillator_refraction) {
    double face_z = -sys.working_distance_mm;
    D h = D(face_z) - s.z;
    if (h.v < 1e-3) h = D(1e-3, h.d);
    D ex = p.x - s.x, ey = p.y - s.y;
    FacePath fp = face_path(h, ex * ex + ey * ey, z_ap - face_z, sys.effects.scintillator_index);
    origin = V3{s.x + ex * fp.rho_over_pr, s.y + ey * fp.rho_over_pr, D(face_z)};
    weight = fp.weight;
  } else {
    V3 r = p - s;
    D len = sqrt(dot(r, r));
    weight = r.z / (len * len * len);  // cos / r^2
  }
  weight = weight * D(photons);
  SampleHit out;
  auto hit = propagate(sys, g, origin, p - origin, false);
  if (!hit) return out;
  out.ok = true;
  out.x_mm = hit->first.v;
  out.y_mm = hit->second.v;
  out.weight = weight.v;
  out.dx = hit->first.d;
  out.dy = hit->second.d;
  out.dweight = weight.d;
  return out;
}

SampleHit trace_sample_impl(const OpticalSystem& sys, const TraceSettings& settings, const glm::dvec3& theta,
                            size_t lens, uint32_t sample) {
  const uint32_t strata = settings.strata_for(sys.lenslets[lens].diameter_mm);
  glm::dvec2 u = unit_disk_sample(uint32_t(lens), sample, strata, settings.stratification);
  glm::dvec3 centre = theta;
  if (sys.effects.source_extent)
    centre += source_offset(uint32_t(lens), sample, sys.effects.source_sigma_mm, settings.stratification);
  const double r = 0.5 * sys.lenslets[lens].diameter_mm;
  return trace_point(sys, settings, centre, lens, u, M_PI * r * r / double(strata * strata));
}

}  // namespace

double SparseImage::photons() const {
  double s = 0;
  for (const auto& [k, v] : pixels) s += v[0];
  return s;
}

std::array<double, 4> SparseImage::value(int64_t key) const {
  auto it = pixels.find(key);
  if (it == pixels.end()) return {0, 0, 0, 0};
  const auto& v = it->second;
  return {v[0], 0.5 * (v[1] + v[4]), 0.5 * (v[2] + v[5]), 0.5 * (v[3] + v[6])};
}

SampleHit trace_sample(const OpticalSystem& sys, const TraceSettings& settings, const glm::dvec3& theta, size_t lens,
                       uint32_t sample) {
  return trace_sample_impl(sys, settings, theta, lens, sample);
}

SparseImage psf(const OpticalSystem& sys, const TraceSettings& settings, const glm::dvec3& theta) {
  if (settings.splat == Splat::footprint) return psf_footprint(sys, settings, theta);
  validate(sys);
  AnalysisGrid grid = AnalysisGrid::of(sys, settings.binning);
  SparseImage img{grid.width, grid.height, {}};
  double half_w = 0.5 * sys.sensor_width_mm(), half_h = 0.5 * sys.sensor_height_mm();
  for (size_t l = 0; l < sys.lenslets.size(); ++l) {
    const uint32_t strata = settings.strata_for(sys.lenslets[l].diameter_mm);
    for (uint32_t k = 0; k < strata * strata; ++k) {
      SampleHit h = trace_sample_impl(sys, settings, theta, l, k);
      // Checkerboard half of the strata; each half estimates the whole gradient.
      const int half = int(shared::ray_half(k, strata));
      if (!h.ok || std::abs(h.x_mm) > half_w || std::abs(h.y_mm) > half_h) continue;
      double u = (h.x_mm + half_w) / grid.pixel_mm - 0.5;
      double v = (h.y_mm + half_h) / grid.pixel_mm - 0.5;
      double iu = std::floor(u), iv = std::floor(v);
      double fx = u - iu, fy = v - iv;
      glm::dvec3 dfx = h.dx / grid.pixel_mm, dfy = h.dy / grid.pixel_mm;
      // Each of the four taps: weight * a(fx) * b(fy) with its product rule.
      for (int j = 0; j < 2; ++j)
        for (int i = 0; i < 2; ++i) {
          int col = int(iu) + i, row = int(iv) + j;
          if (col < 0 || col >= grid.width || row < 0 || row >= grid.height) continue;
          double a = i ? fx : 1 - fx, da_sign = i ? 1 : -1;
          double b = j ? fy : 1 - fy, db_sign = j ? 1 : -1;
          glm::dvec3 grad = h.dweight * a * b + h.weight * (da_sign * dfx * b + db_sign * dfy * a);
          auto& px = img.pixels[int64_t(row) * grid.width + col];
          px[0] += h.weight * a * b;
          for (int c = 0; c < 3; ++c) px[1 + 3 * half + c] += 2.0 * grad[c];
        }
    }
  }
  return img;
}

// ---------------------------------------------------------------------------
// Footprint splat (shaders/psf_footprint.comp), written again in double: the
// cells' corners traced, each triangle's light spread over its image and
// given to box pixels by clipped area. The cell grid, its turn and the
// diagonal each cell is split along come from the shared sampling code, like
// the point rays' sample points.

namespace {

// A traced corner in grid pixels (u, v from the sensor's top-left corner)
// with its weight density (photons per mm^2 of aperture).
struct GridCorner {
  bool ok = false;
  D u, v, w;
};

GridCorner to_grid(const SampleHit& h, double half_w, double half_h, double px) {
  GridCorner c;
  c.ok = h.ok;
  c.u = D((h.x_mm + half_w) / px, h.dx / px);
  c.v = D((h.y_mm + half_h) / px, h.dy / px);
  c.w = D(h.weight, h.dweight);
  return c;
}

struct Point2 {
  D u, v;
};

// The part of a convex polygon on the side `keep(p) >= 0` of a line, where
// keep is affine: the crossings interpolated in duals.
template <class Keep> std::vector<Point2> clip_half_plane(const std::vector<Point2>& poly, Keep keep) {
  std::vector<Point2> out;
  for (size_t i = 0; i < poly.size(); ++i) {
    const Point2& a = poly[i];
    const Point2& b = poly[(i + 1) % poly.size()];
    D ka = keep(a), kb = keep(b);
    if (ka.v >= 0) out.push_back(a);
    if ((ka.v >= 0) != (kb.v >= 0)) {
      D t = ka / (ka - kb);
      out.push_back({a.u + t * (b.u - a.u), a.v + t * (b.v - a.v)});
    }
  }
  return out;
}

D polygon_area(const std::vector<Point2>& poly) {
  D twice(0.0);
  for (size_t i = 0; i < poly.size(); ++i) {
    const Point2& a = poly[i];
    const Point2& b = poly[(i + 1) % poly.size()];
    twice = twice + a.u * b.v - b.u * a.v;
  }
  return abs(twice) * D(0.5);
}

struct FootprintTarget {
  SparseImage& img;
  double u_max, v_max;  // the physical sensor's far edges, grid pixels
  void add(int col, int row, D value, int half) {
    if (col < 0 || row < 0 || col >= img.width || row >= img.height) return;
    auto& p = img.pixels[int64_t(row) * img.width + col];
    p[0] += value.v;
    for (int c = 0; c < 3; ++c) p[size_t(1 + 3 * half + c)] += 2.0 * value.d[c];
  }
  // `weight` spread uniformly along segment p -> q: each pixel gets the
  // share of its length inside it (all pixel-line crossings, sorted).
  void segment(Point2 p, Point2 q, D weight, int half) {
    const D du = q.u - p.u, dv = q.v - p.v;
    std::vector<D> ts{D(0.0), D(1.0)};
    auto crossings = [&](D from, D delta, double lo, double hi, double far) {
      if (delta.v == 0) return;
      for (double line = std::ceil(std::min(lo, hi)); line <= std::floor(std::max(lo, hi)); ++line) {
        D t = (D(line) - from) / delta;
        if (t.v > 0 && t.v < 1) ts.push_back(t);
      }
      // The sensor's far edge: light beyond it is lost.
      D t = (D(far) - from) / delta;
      if (t.v > 0 && t.v < 1) ts.push_back(t);
    };
    crossings(p.u, du, p.u.v, q.u.v, u_max);
    crossings(p.v, dv, p.v.v, q.v.v, v_max);
    std::sort(ts.begin(), ts.end(), [](const D& a, const D& b) { return a.v < b.v; });
    for (size_t k = 0; k + 1 < ts.size(); ++k) {
      const double mid = 0.5 * (ts[k].v + ts[k + 1].v);
      const double u = p.u.v + mid * du.v, v = p.v.v + mid * dv.v;
      if (u < 0 || v < 0 || u >= u_max || v >= v_max) continue;
      add(int(std::floor(u)), int(std::floor(v)), weight * (ts[k + 1] - ts[k]), half);
    }
  }
  // `weight` spread uniformly over triangle (a, b, c), shared by box pixels.
  void triangle(const GridCorner& a, const GridCorner& b, const GridCorner& c, D weight, int half) {
    const double lo_u = std::min({a.u.v, b.u.v, c.u.v}), hi_u = std::max({a.u.v, b.u.v, c.u.v});
    const double lo_v = std::min({a.v.v, b.v.v, c.v.v}), hi_v = std::max({a.v.v, b.v.v, c.v.v});
    if (hi_u <= 0 || hi_v <= 0 || lo_u >= u_max || lo_v >= v_max) return;
    std::vector<Point2> tri{{a.u, a.v}, {b.u, b.v}, {c.u, c.v}};
    const D area = polygon_area(tri);
    // Thin (shaders/common/footprint.glsl, THIN_TRIANGLE): along the longest edge.
    double longest = 0;
    size_t from = 0;
    for (size_t k = 0; k < 3; ++k) {
      const Point2 &p = tri[k], &q = tri[(k + 1) % 3];
      const double l2 = (q.u.v - p.u.v) * (q.u.v - p.u.v) + (q.v.v - p.v.v) * (q.v.v - p.v.v);
      if (l2 > longest) longest = l2, from = k;
    }
    if (!(area.v >= double(shared::THIN_TRIANGLE) * longest)) {
      segment(tri[from], tri[(from + 1) % 3], weight, half);
      return;
    }
    for (int row = std::max(0, int(std::floor(lo_v))); row <= std::min(img.height - 1, int(std::floor(hi_v))); ++row)
      for (int col = std::max(0, int(std::floor(lo_u))); col <= std::min(img.width - 1, int(std::floor(hi_u))); ++col) {
        const double x0 = col, x1 = std::min(col + 1.0, u_max), y0 = row, y1 = std::min(row + 1.0, v_max);
        auto poly = clip_half_plane(tri, [&](const Point2& p) { return p.u - D(x0); });
        poly = clip_half_plane(poly, [&](const Point2& p) { return D(x1) - p.u; });
        poly = clip_half_plane(poly, [&](const Point2& p) { return p.v - D(y0); });
        poly = clip_half_plane(poly, [&](const Point2& p) { return D(y1) - p.v; });
        if (poly.size() < 3) continue;
        const D inside = polygon_area(poly);
        if (inside.v > 0) add(col, row, weight * inside / area, half);
      }
  }
};

double cross2(glm::dvec2 a, glm::dvec2 b, glm::dvec2 c) {
  return std::abs((b.x - a.x) * (c.y - a.y) - (c.x - a.x) * (b.y - a.y));
}

}  // namespace

SparseImage psf_footprint(const OpticalSystem& sys, const TraceSettings& settings, const glm::dvec3& theta) {
  validate(sys);
  const AnalysisGrid grid = AnalysisGrid::of(sys, settings.binning);
  SparseImage img{grid.width, grid.height, {}};
  const double half_w = 0.5 * sys.sensor_width_mm(), half_h = 0.5 * sys.sensor_height_mm(), px = grid.pixel_mm;
  FootprintTarget target{img, 2 * half_w / px, 2 * half_h / px};
  constexpr int kCutSteps = 12;  // as the kernel
  for (size_t l = 0; l < sys.lenslets.size(); ++l) {
    const uint32_t n = settings.strata_for(sys.lenslets[l].diameter_mm);
    const float turn = shared::strata_turn(uint32_t(l), settings.stratification);
    const double r = 0.5 * sys.lenslets[l].diameter_mm;
    const double half_cell_mm2 = 0.5 * M_PI * r * r / double(n * n);
    auto unit = [&](uint32_t i, uint32_t j) { return glm::dvec2(shared::aperture_corner(i, j, n, turn)); };
    auto trace = [&](const glm::dvec3& from, glm::dvec2 u) {
      return to_grid(trace_point(sys, settings, from, l, u, 1.0), half_w, half_h, px);
    };
    // The corners, shared by neighbouring cells (without an extended source).
    std::vector<GridCorner> shared_corners;
    if (!sys.effects.source_extent) {
      shared_corners.resize(size_t(n + 1) * (n + 1));
      for (uint32_t j = 0; j <= n; ++j)
        for (uint32_t i = 0; i <= n; ++i) shared_corners[size_t(j) * (n + 1) + i] = trace(theta, unit(i, j));
    }
    for (uint32_t j = 0; j < n; ++j)
      for (uint32_t i = 0; i < n; ++i) {
        glm::dvec3 from = theta;
        if (sys.effects.source_extent)
          from += source_offset(uint32_t(l), i + j * n, sys.effects.source_sigma_mm, settings.stratification);
        auto corner = [&](uint32_t ci, uint32_t cj) {
          return sys.effects.source_extent ? trace(from, unit(ci, cj)) : shared_corners[size_t(cj) * (n + 1) + ci];
        };
        const int half = int((i + j) & 1u);
        // One triangle: split while its image is large (LARGE_TRIANGLE_PX,
        // SPLIT_DEPTH), cut where an aperture or TIR stops its rays, a piece
        // still large given to its centroid.
        auto centroid = [&](const GridCorner& a, const GridCorner& b, const GridCorner& c, D weight) {
          const double cu = (a.u.v + b.u.v + c.u.v) / 3, cv = (a.v.v + b.v.v + c.v.v) / 3;
          if (cu >= 0 && cv >= 0 && cu < target.u_max && cv < target.v_max) target.add(int(cu), int(cv), weight, half);
        };
        auto large = [](const GridCorner* k) {
          double lo_u = 1e300, hi_u = -1e300, lo_v = 1e300, hi_v = -1e300;
          for (int q = 0; q < 3; ++q)
            if (k[q].ok)
              lo_u = std::min(lo_u, k[q].u.v), hi_u = std::max(hi_u, k[q].u.v), lo_v = std::min(lo_v, k[q].v.v),
              hi_v = std::max(hi_v, k[q].v.v);
          return std::max(hi_u - lo_u, hi_v - lo_v) > double(shared::LARGE_TRIANGLE_PX);
        };
        auto draw = [&](const GridCorner& a, const GridCorner& b, const GridCorner& c, D weight) {
          const GridCorner k[3] = {a, b, c};
          if (large(k)) centroid(a, b, c, weight);
          else target.triangle(a, b, c, weight, half);
        };
        std::function<void(GridCorner*, glm::dvec2*, double, int)> piece = [&](GridCorner* k, glm::dvec2* p,
                                                                               double area_mm2, int depth) {
          const int passed = int(k[0].ok) + int(k[1].ok) + int(k[2].ok);
          if (passed == 0) return;
          if (large(k) && depth < shared::SPLIT_DEPTH) {
            const glm::dvec2 m[3] = {0.5 * (p[0] + p[1]), 0.5 * (p[1] + p[2]), 0.5 * (p[2] + p[0])};
            GridCorner km[3] = {trace(from, m[0]), trace(from, m[1]), trace(from, m[2])};
            GridCorner c0[3] = {k[0], km[0], km[2]}, c1[3] = {km[0], k[1], km[1]}, c2[3] = {km[2], km[1], k[2]},
                       c3[3] = {km[0], km[1], km[2]};
            glm::dvec2 p0[3] = {p[0], m[0], m[2]}, p1[3] = {m[0], p[1], m[1]}, p2[3] = {m[2], m[1], p[2]},
                       p3[3] = {m[0], m[1], m[2]};
            piece(c0, p0, 0.25 * area_mm2, depth + 1);
            piece(c1, p1, 0.25 * area_mm2, depth + 1);
            piece(c2, p2, 0.25 * area_mm2, depth + 1);
            piece(c3, p3, 0.25 * area_mm2, depth + 1);
            return;
          }
          if (passed == 3) {
            draw(k[0], k[1], k[2], (k[0].w + k[1].w + k[2].w) * D(area_mm2 / 3));
            return;
          }
          // The odd one out first (cyclic order kept).
          const bool odd_ok = passed == 1;
          int odd = k[0].ok == odd_ok ? 0 : k[1].ok == odd_ok ? 1 : 2;
          GridCorner q[3] = {k[odd], k[(odd + 1) % 3], k[(odd + 2) % 3]};
          glm::dvec2 pq[3] = {p[odd], p[(odd + 1) % 3], p[(odd + 2) % 3]};
          GridCorner cut[2];
          glm::dvec2 cut_p[2];
          for (int e = 0; e < 2; ++e) {
            glm::dvec2 through = odd_ok ? pq[0] : pq[1 + e], stopped = odd_ok ? pq[1 + e] : pq[0];
            GridCorner best = odd_ok ? q[0] : q[1 + e];
            for (int st = 0; st < kCutSteps; ++st) {
              glm::dvec2 mid = 0.5 * (through + stopped);
              GridCorner m = trace(from, mid);
              if (m.ok) through = mid, best = m;
              else stopped = mid;
            }
            cut[e] = best;
            cut_p[e] = through;
          }
          const double whole = cross2(pq[0], pq[1], pq[2]);
          if (!(whole > 0)) return;
          if (odd_ok) {
            const double a = area_mm2 * cross2(pq[0], cut_p[0], cut_p[1]) / whole;
            draw(q[0], cut[0], cut[1], (q[0].w + cut[0].w + cut[1].w) * D(a / 3));
            return;
          }
          const double a1 = area_mm2 * cross2(cut_p[0], pq[1], pq[2]) / whole;
          const double a2 = area_mm2 * cross2(cut_p[0], pq[2], cut_p[1]) / whole;
          draw(cut[0], q[1], q[2], (cut[0].w + q[1].w + q[2].w) * D(a1 / 3));
          draw(cut[0], q[2], cut[1], (cut[0].w + q[2].w + cut[1].w) * D(a2 / 3));
        };
        auto triangle = [&](uint32_t ai, uint32_t aj, uint32_t bi, uint32_t bj, uint32_t ci, uint32_t cj) {
          GridCorner k[3] = {corner(ai, aj), corner(bi, bj), corner(ci, cj)};
          glm::dvec2 p[3] = {unit(ai, aj), unit(bi, bj), unit(ci, cj)};
          piece(k, p, half_cell_mm2, 0);
        };
        if (shared::split_main_diagonal(i, j, n)) {
          triangle(i, j, i + 1, j, i + 1, j + 1);
          triangle(i, j, i + 1, j + 1, i, j + 1);
        } else {
          triangle(i, j, i + 1, j, i, j + 1);
          triangle(i + 1, j, i + 1, j + 1, i, j + 1);
        }
      }
  }
  return img;
}

FisherResult fisher_of(const SparseImage& image, double dark, FisherEstimator estimator) {
  FisherResult r;
  for (const auto& [key, px] : image.pixels) {
    r.photons += px[0];
    double b = px[0] + dark;
    if (!(b > 0)) continue;
    double inv_p = 1.0 / b, inv_b = 1.0 / std::expm1(b);
    glm::dvec3 ga(px[1], px[2], px[3]), gb(px[4], px[5], px[6]);
    if (estimator == FisherEstimator::naive) ga = gb = 0.5 * (ga + gb);
    int k = 0;
    for (int i = 0; i < 3; ++i)
      for (int j = i; j < 3; ++j, ++k) {
        double term = 0.5 * (ga[i] * gb[j] + ga[j] * gb[i]);
        r.poisson[k] += term * inv_p;
        r.binary[k] += term * inv_b;
      }
  }
  // Pixels no ray reaches still hold dark counts but no information.
  return r;
}

FisherResult fisher(const OpticalSystem& sys, const TraceSettings& settings, const glm::dvec3& theta) {
  return fisher_of(psf(sys, settings, theta), sys.effects.dark_counts_per_pixel, settings.estimator);
}

std::optional<glm::dvec2> trace_ray(const OpticalSystem& sys, size_t lens_index, const glm::dvec3& origin,
                                    const glm::dvec3& direction) {
  Geometry g = geometry(sys, lens_index);
  OpticalSystem plain = sys;
  plain.effects.holder_vignetting = false;
  auto hit = propagate(plain, g, V3{D(origin.x), D(origin.y), D(origin.z)},
                       V3{D(direction.x), D(direction.y), D(direction.z)}, true);
  if (!hit) return std::nullopt;
  return glm::dvec2(hit->first.v, hit->second.v);
}

}  // namespace prism::ref
