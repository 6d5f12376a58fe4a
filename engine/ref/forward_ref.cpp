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

// `value` as a dual whose gradient is 1 in the slots of `t` that name
// parameter p (of lenslet `lens`, for a lens parameter).
D seeded(double value, Param p, int lens, const Tangents& t) {
  glm::dvec3 g(0.0);
  for (int k = 0; k < 3; ++k)
    if (t[k].param == p && (t[k].lens < 0 || t[k].lens == lens || p < Param::lens_x || p > Param::lens_tilt_y)) g[k] = 1;
  return D(value, g);
}
bool seeds(const Tangents& t, Param p, int lens) { return seeded(0.0, p, lens, t).d != glm::dvec3(0.0); }

// A lenslet's geometry, with the derivatives of its position and focal
// length: R = f (n - 1), sag at the rim, centre thickness = sag + edge.
struct Geometry {
  D cx, cy, focal, R, thickness, sag;
  double radius, n;
};
Geometry geometry(const OpticalSystem& sys, size_t i, const Tangents& t) {
  const auto& l = sys.lenslets[i];
  const int lens = int(i);
  const D f = seeded(l.focal_mm, Param::lens_focal, lens, t);
  const D R = f * D(sys.glass_index - 1.0);
  const double a = 0.5 * l.diameter_mm;
  const D sag = R - sqrt(R * R - D(a * a));
  return {seeded(l.x_mm, Param::lens_x, lens, t), seeded(l.y_mm, Param::lens_y, lens, t), f, R,
          sag + D(sys.edge_thickness_mm), sag, a, sys.glass_index};
}

// A ray leaving the lens: a point and a direction, in the lens's own frame.
struct LensExit {
  V3 p, d;
};

// Rotation of an as-built tilt: about x by ax, then about y by ay (degrees),
// v -> Ry Rx v, as rows.
struct Turn {
  D m[3][3];
  V3 apply(const V3& v) const {  // m v
    return {v.x * m[0][0] + v.y * m[0][1] + v.z * m[0][2], v.x * m[1][0] + v.y * m[1][1] + v.z * m[1][2],
            v.x * m[2][0] + v.y * m[2][1] + v.z * m[2][2]};
  }
  V3 undo(const V3& v) const {  // m^T v
    return {v.x * m[0][0] + v.y * m[1][0] + v.z * m[2][0], v.x * m[0][1] + v.y * m[1][1] + v.z * m[2][1],
            v.x * m[0][2] + v.y * m[1][2] + v.z * m[2][2]};
  }
  V3 column(int j) const { return {m[0][j], m[1][j], m[2][j]}; }
};
Turn turn_of(D ax_deg, D ay_deg) {
  const D ax = ax_deg * D(M_PI / 180), ay = ay_deg * D(M_PI / 180);
  const D cx = cos(ax), sx = sin(ax), cy = cos(ay), sy = sin(ay);
  // Ry = [cy 0 sy; 0 1 0; -sy 0 cy], Rx = [1 0 0; 0 cx -sx; 0 sx cx].
  return {{{cy, sy * sx, sy * cx}, {D(0.0), cx, -sx}, {-sy, cy * sx, cy * cx}}};
}

// Through lenslet g from `o` along `dir`, both in the lens's own frame:
// where the ray leaves the glass (thin: the lens plane) and the holder's
// bore, or nothing when stopped. Sampled rays start inside the entrance disk
// by construction and skip its test.
std::optional<LensExit> through_lens(const OpticalSystem& sys, const Geometry& g, V3 o, V3 dir, bool test_entrance) {
  double bore = sys.effects.holder_vignetting ? sys.effects.holder_bore_mm : 0.0;
  if (sys.lens_model == LensModel::thin) {
    D t = -o.z / dir.z;
    V3 p = o + dir * t;
    if (test_entrance && !within(p, g.cx.v, g.cy.v, g.radius)) return std::nullopt;
    D sx = dir.x / dir.z - (p.x - g.cx) / g.focal;
    D sy = dir.y / dir.z - (p.y - g.cy) / g.focal;
    if (bore > 0 && !within(V3{p.x + sx * D(bore), p.y + sy * D(bore), D(bore)}, g.cx.v, g.cy.v, g.radius))
      return std::nullopt;
    return LensExit{p, V3{sx, sy, D(1.0)}};
  }
  V3 d = unit(dir);
  V3 exit_point, exit_dir;
  if (!sys.curved_toward_sensor) {
    // Spherical front face, centre (cx, cy, R): first intersection from the source side.
    V3 c{g.cx, g.cy, g.R};
    V3 oc = o - c;
    D b = dot(oc, d);
    D disc = b * b - (dot(oc, oc) - g.R * g.R);
    if (disc.v <= 0) return std::nullopt;
    V3 p1 = o + d * (-b - sqrt(disc));
    if (test_entrance && (!within(p1, g.cx.v, g.cy.v, g.radius) || p1.z.v > g.sag.v)) return std::nullopt;
    auto d1 = snell(d, (p1 - c) * (D(1.0) / g.R), 1.0 / g.n);  // outward normal faces the source
    if (!d1) return std::nullopt;
    // Flat back face.
    V3 p2 = p1 + *d1 * ((g.thickness - p1.z) / d1->z);
    if (!within(p2, g.cx.v, g.cy.v, g.radius)) return std::nullopt;
    auto d2 = snell(*d1, V3{D(0.0), D(0.0), D(-1.0)}, g.n);
    if (!d2) return std::nullopt;
    exit_point = p2;
    exit_dir = *d2;
  } else {
    // Flat front face at z = 0, then the sphere centred at z = thickness - R, left from inside.
    V3 p0 = o + d * (-o.z / d.z);
    if (test_entrance && !within(p0, g.cx.v, g.cy.v, g.radius)) return std::nullopt;
    auto d1 = snell(d, V3{D(0.0), D(0.0), D(-1.0)}, 1.0 / g.n);
    V3 c{g.cx, g.cy, g.thickness - g.R};
    V3 oc = p0 - c;
    D b = dot(oc, *d1);
    D disc = b * b - (dot(oc, oc) - g.R * g.R);
    if (disc.v <= 0) return std::nullopt;
    V3 p1 = p0 + *d1 * (-b + sqrt(disc));
    if (!within(p1, g.cx.v, g.cy.v, g.radius) || p1.z.v < g.thickness.v - g.sag.v) return std::nullopt;
    auto d2 = snell(*d1, (c - p1) * (D(1.0) / g.R), g.n);  // inward normal faces the outgoing ray
    if (!d2) return std::nullopt;
    exit_point = p1;
    exit_dir = *d2;
  }
  if (bore > exit_point.z.v) {
    D tb = (D(bore) - exit_point.z) / exit_dir.z;
    if (!within(exit_point + exit_dir * tb, g.cx.v, g.cy.v, g.radius)) return std::nullopt;
  }
  return LensExit{exit_point, exit_dir};
}

// A lenslet as one ray sees it: its geometry and, where it is tilted (or
// its tilt's derivative is asked for), the turn about its centre c on the
// lens plane; the turn's trigonometry only then.
struct LensFrame {
  Geometry g;
  V3 c;
  bool tilted = false;
  Turn m{};
};
LensFrame lens_frame(const OpticalSystem& sys, size_t lens, const Tangents& t) {
  const auto& l = sys.lenslets[lens];
  const int li = int(lens);
  LensFrame f{geometry(sys, lens, t), {}, false, {}};
  f.c = V3{f.g.cx, f.g.cy, D(0.0)};
  f.tilted = l.tilt_x_deg != 0 || l.tilt_y_deg != 0 || seeds(t, Param::lens_tilt_x, li) || seeds(t, Param::lens_tilt_y, li);
  if (f.tilted)
    f.m = turn_of(seeded(l.tilt_x_deg, Param::lens_tilt_x, li, t), seeded(l.tilt_y_deg, Param::lens_tilt_y, li, t));
  return f;
}

// Propagate a world ray from `o` along `dir` through lenslet `lens` (traced in
// its own frame `f`) to the sensor as built (the plane through (offset,
// lens_to_sensor) turned by its tilt). Returns the landing point in the
// sensor's own axes from its centre, or nothing when stopped. For a nominal
// system: the plane z = lens_to_sensor.
std::optional<std::pair<D, D>> propagate(const OpticalSystem& sys, size_t lens, const LensFrame& f, V3 o, V3 dir,
                                         bool test_entrance, const Tangents& t) {
  const int li = int(lens);
  const V3& c = f.c;
  auto out = f.tilted ? through_lens(sys, f.g, c + f.m.undo(o - c), f.m.undo(dir), test_entrance)
                      : through_lens(sys, f.g, o, dir, test_entrance);
  if (!out) return std::nullopt;
  const V3 p = f.tilted ? c + f.m.apply(out->p - c) : out->p, d = f.tilted ? f.m.apply(out->d) : out->d;
  const SensorPose& pose = sys.sensor_pose;
  const D L = seeded(sys.lens_to_sensor_mm, Param::lens_to_sensor, li, t);
  const bool moved = !pose.nominal() || seeds(t, Param::sensor_offset_x, li) || seeds(t, Param::sensor_offset_y, li) ||
                     seeds(t, Param::sensor_tilt_x, li) || seeds(t, Param::sensor_tilt_y, li);
  if (!moved) {
    const D ts = (L - p.z) / d.z;
    return std::make_pair(p.x + d.x * ts, p.y + d.y * ts);
  }
  const Turn s = turn_of(seeded(pose.tilt_x_deg, Param::sensor_tilt_x, li, t),
                         seeded(pose.tilt_y_deg, Param::sensor_tilt_y, li, t));
  const V3 s0{seeded(pose.offset_x_mm, Param::sensor_offset_x, li, t),
              seeded(pose.offset_y_mm, Param::sensor_offset_y, li, t), L};
  const V3 normal = s.column(2);
  const D along = dot(s0 - p, normal) / dot(d, normal);
  const V3 h = p + d * along - s0;
  return std::make_pair(dot(h, s.column(0)), dot(h, s.column(1)));
}

// The sample points: the device's own sampling code (shaders/common/optics.glsl
// through engine/shared_math.h), so both trace the very same rays. The points
// are inputs of the integral, not physics; everything from them to the pixel
// is this file's own double-precision computation.
glm::dvec2 unit_disk_sample(uint32_t lens, uint32_t sample, uint32_t strata, uint32_t seed) {
  return glm::dvec2(shared::aperture_sample(lens, sample, strata, seed));
}

// Scintillator face: find the radial distance rho on the face, from the point
// below the source, such that the refracted ray reaches radial distance pr on
// the aperture plane a height w above the face: pr = rho + w tan(theta_air),
// sin(theta_air) = n sin(theta_scint). Newton on rho, run on duals.
struct FacePath {
  D rho_over_pr;  // q = s + (rho / pr) (p - s) laterally
  D weight;       // Fresnel T * cos/L^2 inside * dA_face / dA_aperture
};
FacePath face_path(D h, D pr2, D w, double n) {
  D pr = sqrt(pr2 + D(1e-30));
  auto air_tan = [&](D rho) {
    D L = sqrt(rho * rho + h * h);
    D s = D(n) * rho / L;  // sin in air
    return s / sqrt(D(1.0) - s * s);
  };
  // Start from the paraxial guess, kept below the critical angle (beyond it
  // no ray leaves the scintillator).
  D rho = pr * h / (h + D(n) * w);
  double rho_max = n > 1.0 ? h.v / std::sqrt(n * n - 1.0) : INFINITY;
  if (rho.v >= rho_max) rho = D(0.99) * D(rho_max, h.d / std::sqrt(n * n - 1.0));
  for (int it = 0; it < 60; ++it) {
    D L = sqrt(rho * rho + h * h);
    D s = D(n) * rho / L;
    D c3 = (D(1.0) - s * s) * sqrt(D(1.0) - s * s);
    D f = rho + w * air_tan(rho) - pr;
    D fp = D(1.0) + w * D(n) * h * h / (L * L * L * c3);
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
  D dpr_drho = D(1.0) + w * D(n) * h * h / (L * L * L * (D(1.0) - sin_t * sin_t) * cos_t);
  // Radial area map: dA_aperture / dA_face = (pr / rho) * dpr/drho.
  D ratio = (pr.v < 1e-12) ? D(1.0) / (D(1.0) + w * D(n) / h) : rho / pr;
  D area = ratio / dpr_drho;
  return {ratio, transmit * cos_i / (L * L) * area};
}

SampleHit trace_sample_impl(const OpticalSystem& sys, const TraceSettings& settings, const glm::dvec3& theta,
                            size_t lens, uint32_t sample, const Tangents& t) {
  const uint32_t strata = settings.strata_for(sys.lenslets[lens].diameter_mm);
  glm::dvec2 u = unit_disk_sample(uint32_t(lens), sample, strata, settings.stratification);
  const glm::dvec3 per_sigma = source_offset_per_sigma(sys, uint32_t(lens), sample, settings.stratification);
  const double r = 0.5 * sys.lenslets[lens].diameter_mm;
  return trace_point(sys, settings, theta, per_sigma, lens, u, M_PI * r * r / double(strata * strata), t);
}

}  // namespace

glm::dvec3 source_offset_per_sigma(const OpticalSystem& sys, uint32_t lens, uint32_t sample, uint32_t seed) {
  return sys.effects.source_extent ? glm::dvec3(shared::source_offset(lens, sample, 1.0f, seed)) : glm::dvec3(0.0);
}

// The ray from source `centre` through point `u` of lenslet `lens`'s
// entrance disk (unit-disk coordinates), carrying the photons of `area_mm2`
// of aperture there.
SampleHit trace_point(const OpticalSystem& sys, const TraceSettings& settings, const glm::dvec3& theta,
                      const glm::dvec3& per_sigma, size_t lens, glm::dvec2 u, double area_mm2, const Tangents& t) {
  const int li = int(lens);
  const LensFrame f = lens_frame(sys, lens, t);
  const Geometry& g = f.g;
  const D z_ap = (sys.lens_model == LensModel::real && !sys.curved_toward_sensor) ? g.sag : D(0.0);
  // The entrance disk turns with its lens (as built).
  const V3 on_disk{D(g.radius * u.x), D(g.radius * u.y), z_ap};
  const V3 p = f.tilted ? f.c + f.m.apply(on_disk) : f.c + on_disk;
  const D wd = seeded(sys.working_distance_mm, Param::working_distance, li, t);
  // The source point, moving with sigma along per_sigma (source_extent).
  const D sigma = seeded(sys.effects.source_sigma_mm, Param::source_sigma, li, t);
  auto coordinate = [&](int k, Param p) { return seeded(theta[k], p, li, t) + sigma * D(per_sigma[k]); };
  V3 s{coordinate(0, Param::source_x), coordinate(1, Param::source_y), -(coordinate(2, Param::source_depth) + wd)};
  double photons = settings.photons_emitted * sys.effects.detection_efficiency / (4 * M_PI) * area_mm2;
  V3 origin = s;
  D weight;
  if (sys.effects.scintillator_refraction) {
    const D face_z = -wd;
    D h = face_z - s.z;
    if (h.v < 1e-3) h = D(1e-3, h.d);
    D ex = p.x - s.x, ey = p.y - s.y;
    FacePath fp = face_path(h, ex * ex + ey * ey, p.z - face_z, sys.effects.scintillator_index);  // p.z: the turned disk's point
    origin = V3{s.x + ex * fp.rho_over_pr, s.y + ey * fp.rho_over_pr, face_z};
    weight = fp.weight;
  } else {
    V3 r = p - s;
    D len = sqrt(dot(r, r));
    weight = r.z / (len * len * len);  // cos / r^2
  }
  // The flux through a disk turned away from z: the emitters' weight is per
  // area seen along z, the disk is seen along its normal.
  const V3 along = p - origin;
  weight = weight * D(photons);
  if (f.tilted) weight = weight * (dot(along, f.m.column(2)) / along.z);
  SampleHit out;
  auto hit = propagate(sys, lens, f, origin, along, false, t);
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


double SparseImage::photons() const {
  double s = 0;
  for (const auto& [k, v] : pixels) s += v[0];
  return s;
}

std::array<double, 4> SparseImage::value(int64_t key) const {
  const std::array<double, 7>* found = pixels.find(key);
  if (!found) return {0, 0, 0, 0};
  const auto& v = *found;
  return {v[0], 0.5 * (v[1] + v[4]), 0.5 * (v[2] + v[5]), 0.5 * (v[3] + v[6])};
}

SampleHit trace_sample(const OpticalSystem& sys, const TraceSettings& settings, const glm::dvec3& theta, size_t lens,
                       uint32_t sample) {
  return trace_sample_impl(sys, settings, theta, lens, sample, source_tangents);
}

SparseImage psf(const OpticalSystem& sys, const TraceSettings& settings, const glm::dvec3& theta, const Tangents& t,
                int only_lens) {
  if (settings.splat == Splat::footprint) return psf_footprint(sys, settings, theta, t, only_lens);
  validate(sys);
  AnalysisGrid grid = AnalysisGrid::of(sys, settings.binning);
  SparseImage img{grid.width, grid.height, {}};
  double half_w = 0.5 * sys.sensor_width_mm(), half_h = 0.5 * sys.sensor_height_mm();
  for (size_t l = 0; l < sys.lenslets.size(); ++l) {
    if (only_lens >= 0 && size_t(only_lens) != l) continue;
    const uint32_t strata = settings.strata_for(sys.lenslets[l].diameter_mm);
    for (uint32_t k = 0; k < strata * strata; ++k) {
      SampleHit h = trace_sample_impl(sys, settings, theta, l, k, t);
      // Checkerboard half of the strata; each half estimates the whole gradient.
      const int half = int(shared::ray_half(k, strata));
      if (sys.effects.diffraction) {
        // The ray's light blurred by its lenslet's Airy square over box pixels.
        if (!h.ok) continue;
        add_blurred_point(img, D((h.x_mm + half_w) / grid.pixel_mm, h.dx / grid.pixel_mm),
                          D((h.y_mm + half_h) / grid.pixel_mm, h.dy / grid.pixel_mm),
                          sys.airy_half_side_mm(l) / grid.pixel_mm, D(h.weight, h.dweight), half,
                          2 * half_w / grid.pixel_mm, 2 * half_h / grid.pixel_mm);
        continue;
      }
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
  OpticalSystem plain = sys;
  plain.effects.holder_vignetting = false;
  auto hit = propagate(plain, lens_index, lens_frame(plain, lens_index, source_tangents),
                       V3{D(origin.x), D(origin.y), D(origin.z)},
                       V3{D(direction.x), D(direction.y), D(direction.z)}, true, source_tangents);
  if (!hit) return std::nullopt;
  return glm::dvec2(hit->first.v, hit->second.v);
}

}  // namespace prism::ref
