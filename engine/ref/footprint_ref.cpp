// The footprint splat (shaders/psf_footprint.comp and its passes), written
// again in double: the cells' corners traced, each triangle's light spread
// over its image and given to box pixels by clipped area. The cell grid, its
// turn and the diagonal each cell is split along come from the shared
// sampling code, like the point rays' sample points.
#include <algorithm>
#include <array>
#include <cmath>
#include <cstring>
#include <functional>
#include <new>
#include <stdexcept>
#include <string>
#include <type_traits>
#include <vector>

#include "engine/ref/dual_ref.h"
#include "engine/ref/forward_ref.h"
#include "engine/shared_math.h"

namespace prism::ref {

namespace {

// A traced corner in grid pixels (u, v from the sensor's top-left corner)
// with its weight density (photons per mm^2 of aperture). `landed`: its ray
// got through the lens (its landing point counts where a piece's size is
// judged); `ok`: and landed within the sensor's band, so its light counts.
struct GridCorner {
  bool ok = false, landed = false;
  D u, v, w;
};

// Stopped where its ray is, or where it lands beyond the sensor's band
// (shared::lands_by_sensor: the kernels' own test).
GridCorner to_grid(const SampleHit& h, double half_w, double half_h, double px, double blur_half_px) {
  GridCorner c;
  c.u = D((h.x_mm + half_w) / px, h.dx / px);
  c.v = D((h.y_mm + half_h) / px, h.dy / px);
  c.w = D(h.weight, h.dweight);
  c.landed = h.ok;
  c.ok = h.ok && shared::lands_by_sensor(float(c.u.v), float(c.v.v), float(2 * half_w / px), float(2 * half_h / px),
                                         float(blur_half_px));
  return c;
}

struct Point2 {
  D u, v;
};

// A short list in fixed storage. The reference clips a polygon and builds a
// blurred profile for every pixel a triangle covers; on the heap those made
// it allocation bound (40% of its time under AddressSanitizer). The storage
// is left uninitialised and a copy moves only the items held: zeroing and
// copying all of a polygon's room was a third of a triangle's time.
template <class T, size_t Capacity> struct FixedList {
  static_assert(std::is_trivially_copyable_v<T> && std::is_trivially_destructible_v<T>);
  FixedList() {}
  FixedList(std::initializer_list<T> items) {
    for (const T& t : items) push_back(t);
  }
  FixedList(const FixedList& o) : n(o.n) { std::memcpy(storage, o.storage, n * sizeof(T)); }
  FixedList& operator=(const FixedList& o) {
    n = o.n;
    std::memcpy(storage, o.storage, n * sizeof(T));
    return *this;
  }
  void push_back(const T& t) {
    if (n == Capacity)
      throw std::logic_error("footprint reference: more than " + std::to_string(Capacity) + " items in a fixed list");
    new (storage + n++ * sizeof(T)) T(t);
  }
  size_t size() const { return n; }
  T& operator[](size_t i) { return begin()[i]; }
  const T& operator[](size_t i) const { return begin()[i]; }
  const T* begin() const { return std::launder(reinterpret_cast<const T*>(storage)); }
  const T* end() const { return begin() + n; }
  T* begin() { return std::launder(reinterpret_cast<T*>(storage)); }
  T* end() { return begin() + n; }

 private:
  alignas(T) unsigned char storage[sizeof(T) * Capacity];
  size_t n = 0;
};
// A triangle clipped by a pixel's four sides has at most 7 corners in exact
// arithmetic; the spare room is for a rounding-made extra crossing.
using Polygon = FixedList<Point2, 12>;

// The part of a convex polygon on the side `keep(p) >= 0` of a line, where
// keep is affine: the crossings interpolated in duals.
template <class Keep> Polygon clip_half_plane(const Polygon& poly, Keep keep) {
  Polygon out;
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

// The part of a polygon inside the box [x0, x1] x [y0, y1] (each clip a
// new list: no copies between them).
Polygon clip_to_box(const Polygon& poly, double x0, double x1, double y0, double y1) {
  const Polygon right_of = clip_half_plane(poly, [&](const Point2& p) { return p.u - D(x0); });
  const Polygon across = clip_half_plane(right_of, [&](const Point2& p) { return D(x1) - p.u; });
  const Polygon below = clip_half_plane(across, [&](const Point2& p) { return p.v - D(y0); });
  return clip_half_plane(below, [&](const Point2& p) { return D(y1) - p.v; });
}

D polygon_area(const Polygon& poly) {
  D twice(0.0);
  for (size_t i = 0; i < poly.size(); ++i) {
    const Point2& a = poly[i];
    const Point2& b = poly[(i + 1) % poly.size()];
    twice = twice + a.u * b.v - b.u * a.v;
  }
  return abs(twice) * D(0.5);
}

// Signed area and first and mixed moments of a polygon (counter-clockwise
// positive): A, integral of u, of v and of u v over it.
struct Moments {
  D area, u, v, uv;
};
Moments moments(const Polygon& poly) {
  Moments m{D(0.0), D(0.0), D(0.0), D(0.0)};
  for (size_t i = 0; i < poly.size(); ++i) {
    const Point2& a = poly[i];
    const Point2& b = poly[(i + 1) % poly.size()];
    const D cross = a.u * b.v - b.u * a.v;
    m.area = m.area + cross * D(0.5);
    m.u = m.u + (a.u + b.u) * cross * D(1.0 / 6);
    m.v = m.v + (a.v + b.v) * cross * D(1.0 / 6);
    m.uv = m.uv + (a.u * b.v + D(2.0) * a.u * a.v + D(2.0) * b.u * b.v + b.u * a.v) * cross * D(1.0 / 24);
  }
  return m;
}

// Effect diffraction, written apart from shaders/common/blur.glsl (same model:
// the Airy core as a uniform square of half side h). Across pixel lines
// [lo, hi] the blurred pixel takes from a point at x the share of
// [x - h, x + h] inside [lo, hi]: linear between the four kinks lo +- h,
// hi +- h. Its pieces, each as (x0, x1, a, b): share = a + b x on [x0, x1].
struct Piece1 {
  double x0, x1, a, b;
};
using Profile = FixedList<Piece1, 3>;
Profile blurred_profile(double lo, double hi, double h) {
  auto share = [&](double x) { return std::max(0.0, std::min(x + h, hi) - std::max(x - h, lo)) / (2 * h); };
  double k[4] = {lo - h, lo + h, hi - h, hi + h};
  std::sort(k, k + 4);
  Profile out;
  for (int i = 0; i < 3; ++i) {
    if (!(k[i + 1] > k[i])) continue;
    const double f0 = share(k[i]), f1 = share(k[i + 1]), b = (f1 - f0) / (k[i + 1] - k[i]);
    out.push_back({k[i], k[i + 1], f0 - b * k[i], b});
  }
  return out;
}
// The share at x (its piece chosen by x's value, or by `at` where given).
D share_at(const Profile& profile, D x, double at) {
  for (const auto& p : profile)
    if (at >= p.x0 && at <= p.x1) return D(p.a) + D(p.b) * x;
  return D(0.0);
}

// `value` into pixel (col, row) if on the grid; its derivative to checkerboard half `half`.
void add_to_pixel(SparseImage& img, int col, int row, D value, int half) {
  if (col < 0 || row < 0 || col >= img.width || row >= img.height) return;
  auto& p = img.pixels[int64_t(row) * img.width + col];
  p[0] += value.v;
  for (int c = 0; c < 3; ++c) p[size_t(1 + 3 * half + c)] += 2.0 * value.d[c];
}

}  // namespace

void add_blurred_point(SparseImage& img, D u, D v, double h, D weight, int half, double u_max, double v_max) {
  for (int row = std::max(0, int(std::floor(v.v - h))); row <= std::min(img.height - 1, int(std::floor(v.v + h))); ++row) {
    const D fy = share_at(blurred_profile(row, std::min(row + 1.0, v_max), h), v, v.v);
    for (int col = std::max(0, int(std::floor(u.v - h))); col <= std::min(img.width - 1, int(std::floor(u.v + h))); ++col) {
      const D fx = share_at(blurred_profile(col, std::min(col + 1.0, u_max), h), u, u.v);
      if (fx.v > 0 || fy.v > 0) add_to_pixel(img, col, row, weight * fx * fy, half);
    }
  }
}

namespace {

struct FootprintTarget {
  SparseImage& img;
  double u_max, v_max;  // the physical sensor's far edges, grid pixels
  double blur_half_px = 0;  // effect diffraction: half side of the lenslet's Airy square, grid pixels (0: off)
  // Effect diffraction: triangle (a, b, c) of uniform light, blurred. Each
  // pixel in reach: the triangle clipped to each cell between the kinks of
  // the pixel's blurred profiles across and along, where the blurred pixel
  // is (a_u + b_u u)(a_v + b_v v), integrated exactly from the clipped
  // polygon's moments.
  void blurred(const GridCorner& a, const GridCorner& b, const GridCorner& c, D weight, int half) {
    const double h = blur_half_px;
    const Polygon tri{{a.u, a.v}, {b.u, b.v}, {c.u, c.v}};
    const D area = moments(tri).area;
    const double lo_u = std::min({a.u.v, b.u.v, c.u.v}), hi_u = std::max({a.u.v, b.u.v, c.u.v});
    const double lo_v = std::min({a.v.v, b.v.v, c.v.v}), hi_v = std::max({a.v.v, b.v.v, c.v.v});
    for (int row = std::max(0, int(std::floor(lo_v - h))); row <= std::min(img.height - 1, int(std::floor(hi_v + h))); ++row) {
      // Relative to the pixel's corner: the moments of a small polygon far
      // from the origin would cancel their digits.
      const auto along = blurred_profile(0.0, std::min(1.0, v_max - row), h);
      for (int col = std::max(0, int(std::floor(lo_u - h))); col <= std::min(img.width - 1, int(std::floor(hi_u + h))); ++col) {
        const auto across = blurred_profile(0.0, std::min(1.0, u_max - col), h);
        Polygon local;
        for (const Point2& p : tri) local.push_back({p.u - D(double(col)), p.v - D(double(row))});
        D light(0.0);
        for (const auto& pu : across)
          for (const auto& pv : along) {
            const Polygon poly = clip_to_box(local, pu.x0, pu.x1, pv.x0, pv.x1);
            if (poly.size() < 3) continue;
            const Moments m = moments(poly);
            light = light + D(pu.a * pv.a) * m.area + D(pu.a * pv.b) * m.v + D(pu.b * pv.a) * m.u + D(pu.b * pv.b) * m.uv;
          }
        if (light.v != 0) add(col, row, weight * light / area, half);
      }
    }
  }
  // Effect diffraction: segment p -> q of uniform light, blurred: every
  // crossing of a kink of a pixel's profiles splits it; Simpson's rule on
  // each piece (exact: the product of two linear shares).
  void blurred_segment(Point2 p, Point2 q, D weight, int half) {
    const double h = blur_half_px;
    const D du = q.u - p.u, dv = q.v - p.v;
    for (int row = std::max(0, int(std::floor(std::min(p.v.v, q.v.v) - h)));
         row <= std::min(img.height - 1, int(std::floor(std::max(p.v.v, q.v.v) + h))); ++row) {
      for (int col = std::max(0, int(std::floor(std::min(p.u.v, q.u.v) - h)));
           col <= std::min(img.width - 1, int(std::floor(std::max(p.u.v, q.u.v) + h))); ++col) {
        const auto across = blurred_profile(col, std::min(col + 1.0, u_max), h);
        const auto along = blurred_profile(row, std::min(row + 1.0, v_max), h);
        FixedList<double, 2 + 2 * 2 * 3> ts{0.0, 1.0};  // the ends, and each piece's two kinks in both profiles
        for (const auto* prof : {&across, &along})
          for (const auto& piece : *prof)
            for (double k : {piece.x0, piece.x1}) {
              const double from = prof == &across ? p.u.v : p.v.v, delta = prof == &across ? du.v : dv.v;
              if (delta != 0 && (k - from) / delta > 0 && (k - from) / delta < 1) ts.push_back((k - from) / delta);
            }
        // Insertion sort: at most 14 (std::sort over the fixed list trips GCC 12's -Warray-bounds).
        for (size_t i = 1; i < ts.size(); ++i)
          for (size_t j = i; j > 0 && ts[j - 1] > ts[j]; --j) std::swap(ts[j - 1], ts[j]);
        D light(0.0);
        for (size_t i = 0; i + 1 < ts.size(); ++i) {
          const double t0 = ts[i], t1 = ts[i + 1], tm = 0.5 * (t0 + t1);
          if (!(t1 > t0)) continue;
          const double um = p.u.v + tm * du.v, vm = p.v.v + tm * dv.v;
          auto f = [&](double t) {
            return share_at(across, p.u + D(t) * du, um) * share_at(along, p.v + D(t) * dv, vm);
          };
          light = light + (f(t0) + D(4.0) * f(tm) + f(t1)) * D((t1 - t0) / 6);
        }
        if (light.v != 0) add(col, row, weight * light, half);
      }
    }
  }
  void add(int col, int row, D value, int half) { add_to_pixel(img, col, row, value, half); }
  // `weight` spread uniformly along segment p -> q: each pixel gets the
  // share of its length inside it (all pixel-line crossings, sorted).
  void segment(Point2 p, Point2 q, D weight, int half) {
    const D du = q.u - p.u, dv = q.v - p.v;
    std::vector<D> ts{D(0.0), D(1.0)};
    auto crossings = [&](D from, D delta, double lo, double hi, double far) {
      if (delta.v == 0) return;
      // The lines on the sensor only: the pieces off it are dropped below
      // (a rim piece's sliver can reach far beyond it).
      for (double line = std::max(std::ceil(std::min(lo, hi)), 0.0); line <= std::min(std::floor(std::max(lo, hi)), std::floor(far));
           ++line) {
        D t = (D(line) - from) / delta;
        if (t.v > 0 && t.v < 1) ts.push_back(t);
      }
      // The sensor's far edge: light beyond it is lost.
      D t = (D(far) - from) / delta;
      if (t.v > 0 && t.v < 1) ts.push_back(t);
    };
    crossings(p.u, du, p.u.v, q.u.v, u_max);
    crossings(p.v, dv, p.v.v, q.v.v, v_max);
    std::stable_sort(ts.begin(), ts.end(), [](const D& a, const D& b) { return a.v < b.v; });
    for (size_t k = 0; k + 1 < ts.size(); ++k) {
      const D &t0 = ts[k], &t1 = ts[k + 1];
      const double mid = 0.5 * (t0.v + t1.v);
      const double u = p.u.v + mid * du.v, v = p.v.v + mid * dv.v;
      if (u < 0 || v < 0 || u >= u_max || v >= v_max) continue;
      add(int(std::floor(u)), int(std::floor(v)), weight * (t1 - t0), half);
    }
  }
  // `weight` spread uniformly over triangle (a, b, c), shared by box pixels.
  void triangle(const GridCorner& a, const GridCorner& b, const GridCorner& c, D weight, int half) {
    const double lo_u = std::min({a.u.v, b.u.v, c.u.v}), hi_u = std::max({a.u.v, b.u.v, c.u.v});
    const double lo_v = std::min({a.v.v, b.v.v, c.v.v}), hi_v = std::max({a.v.v, b.v.v, c.v.v});
    const double reach = blur_half_px;
    if (hi_u <= -reach || hi_v <= -reach || lo_u >= u_max + reach || lo_v >= v_max + reach) return;
    // Wholly inside one pixel (as the kernel: a cell imaged in focus can have
    // no area at all): all of it there, and moving it keeps it there (only
    // the weight's own derivative).
    if (blur_half_px == 0 && std::floor(lo_u) == std::floor(hi_u) && std::floor(lo_v) == std::floor(hi_v) &&
        hi_u <= u_max && hi_v <= v_max) {
      add(int(std::floor(lo_u)), int(std::floor(lo_v)), weight, half);
      return;
    }
    const Polygon tri{{a.u, a.v}, {b.u, b.v}, {c.u, c.v}};
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
      if (blur_half_px > 0) blurred_segment(tri[from], tri[(from + 1) % 3], weight, half);
      else segment(tri[from], tri[(from + 1) % 3], weight, half);
      return;
    }
    if (blur_half_px > 0) {
      blurred(a, b, c, weight, half);
      return;
    }
    const double orientation =
        (b.u.v - a.u.v) * (c.v.v - a.v.v) - (c.u.v - a.u.v) * (b.v.v - a.v.v) < 0 ? -1.0 : 1.0;
    for (int row = std::max(0, int(std::floor(lo_v))); row <= std::min(img.height - 1, int(std::floor(hi_v))); ++row) {
      // The columns the triangle spans within this row (a large rim piece's
      // box is mostly empty), one pixel wider each side than the values say.
      double row_lo = hi_u, row_hi = lo_u;
      for (size_t k = 0; k < 3; ++k) {
        const Point2 &p = tri[k], &q = tri[(k + 1) % 3];
        for (double t : {0.0, 1.0, (row - p.v.v) / (q.v.v - p.v.v), (row + 1.0 - p.v.v) / (q.v.v - p.v.v)}) {
          if (!(t >= 0 && t <= 1)) continue;
          const double u = p.u.v + t * (q.u.v - p.u.v), v = p.v.v + t * (q.v.v - p.v.v);
          if (v >= row - 1e-9 && v <= row + 1 + 1e-9) row_lo = std::min(row_lo, u), row_hi = std::max(row_hi, u);
        }
      }
      for (int col = std::max({0, int(std::floor(lo_u)), int(std::floor(row_lo)) - 1});
           col <= std::min({img.width - 1, int(std::floor(hi_u)), int(std::floor(row_hi)) + 1}); ++col) {
        const double x0 = col, x1 = std::min(col + 1.0, u_max), y0 = row, y1 = std::min(row + 1.0, v_max);
        // A pixel wholly inside: its own area, which no corner moves (a
        // large piece's inner pixels; the clipping below gives the same).
        auto inside_triangle = [&](double u, double v) {
          for (size_t k = 0; k < 3; ++k) {
            const Point2 &p = tri[k], &q = tri[(k + 1) % 3];
            if (orientation * ((q.u.v - p.u.v) * (v - p.v.v) - (q.v.v - p.v.v) * (u - p.u.v)) < 0) return false;
          }
          return true;
        };
        if (inside_triangle(x0, y0) && inside_triangle(x1, y0) && inside_triangle(x0, y1) && inside_triangle(x1, y1)) {
          add(col, row, weight * D((x1 - x0) * (y1 - y0)) / area, half);
          continue;
        }
        const Polygon poly = clip_to_box(tri, x0, x1, y0, y1);
        if (poly.size() < 3) continue;
        const D inside = polygon_area(poly);
        if (inside.v > 0) add(col, row, weight * inside / area, half);
      }
    }
  }
};

double cross2(glm::dvec2 a, glm::dvec2 b, glm::dvec2 c) {
  return std::abs((b.x - a.x) * (c.y - a.y) - (c.x - a.x) * (b.y - a.y));
}

}  // namespace

SparseImage psf_footprint(const OpticalSystem& sys, const TraceSettings& settings, const glm::dvec3& theta,
                          const Tangents& tangents, int only_lens) {
  validate(sys);
  const AnalysisGrid grid = AnalysisGrid::of(sys, settings.binning);
  SparseImage img{grid.width, grid.height, {}};
  const double half_w = 0.5 * sys.sensor_width_mm(), half_h = 0.5 * sys.sensor_height_mm(), px = grid.pixel_mm;
  FootprintTarget target{img, 2 * half_w / px, 2 * half_h / px};
  constexpr int kCutSteps = 8;  // as the kernel (psf_footprint_cuts.comp)
  for (size_t l = 0; l < sys.lenslets.size(); ++l) {
    if (only_lens >= 0 && size_t(only_lens) != l) continue;
    const uint32_t n = settings.strata_for(sys.lenslets[l].diameter_mm);
    const float turn = shared::strata_turn(uint32_t(l), settings.stratification);
    const double r = 0.5 * sys.lenslets[l].diameter_mm;
    const double half_cell_mm2 = 0.5 * M_PI * r * r / double(n * n);
    target.blur_half_px = sys.effects.diffraction ? sys.airy_half_side_mm(l) / px : 0.0;
    auto unit = [&](uint32_t i, uint32_t j) { return glm::dvec2(shared::aperture_corner(i, j, n, turn)); };
    // From the source, moved by sigma times per_sigma (source_extent).
    auto trace = [&](const glm::dvec3& per_sigma, glm::dvec2 u) {
      return to_grid(trace_point(sys, settings, theta, per_sigma, l, u, 1.0, tangents), half_w, half_h, px,
                     target.blur_half_px);
    };
    // The corners, shared by neighbouring cells (without an extended source).
    std::vector<GridCorner> shared_corners;
    if (!sys.effects.source_extent) {
      shared_corners.resize(size_t(n + 1) * (n + 1));
      for (uint32_t j = 0; j <= n; ++j)
        for (uint32_t i = 0; i <= n; ++i) shared_corners[size_t(j) * (n + 1) + i] = trace(glm::dvec3(0.0), unit(i, j));
    }
    for (uint32_t j = 0; j < n; ++j)
      for (uint32_t i = 0; i < n; ++i) {
        const glm::dvec3 per_sigma = source_offset_per_sigma(sys, uint32_t(l), i + j * n, settings.stratification);
        auto corner = [&](uint32_t ci, uint32_t cj) {
          return sys.effects.source_extent ? trace(per_sigma, unit(ci, cj)) : shared_corners[size_t(cj) * (n + 1) + ci];
        };
        const int half = int((i + j) & 1u);
        // One triangle: split while its image is large (LARGE_TRIANGLE_PX,
        // SPLIT_DEPTH), cut where an aperture or TIR stops its rays; every
        // piece, one still large after the last split too, rasterised exactly.
        auto large = [](const GridCorner* k) {
          double lo_u = 1e300, hi_u = -1e300, lo_v = 1e300, hi_v = -1e300;
          for (int q = 0; q < 3; ++q)
            if (k[q].landed)
              lo_u = std::min(lo_u, k[q].u.v), hi_u = std::max(hi_u, k[q].u.v), lo_v = std::min(lo_v, k[q].v.v),
              hi_v = std::max(hi_v, k[q].v.v);
          return std::max(hi_u - lo_u, hi_v - lo_v) > double(shared::LARGE_TRIANGLE_PX);
        };
        std::function<void(GridCorner*, glm::dvec2*, double, int)> piece = [&](GridCorner* k, glm::dvec2* p,
                                                                               double area_mm2, int depth) {
          const int passed = int(k[0].ok) + int(k[1].ok) + int(k[2].ok);
          if (passed == 0) return;
          if (large(k) && depth < shared::SPLIT_DEPTH) {
            const glm::dvec2 m[3] = {0.5 * (p[0] + p[1]), 0.5 * (p[1] + p[2]), 0.5 * (p[2] + p[0])};
            GridCorner km[3] = {trace(per_sigma, m[0]), trace(per_sigma, m[1]), trace(per_sigma, m[2])};
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
            target.triangle(k[0], k[1], k[2], (k[0].w + k[1].w + k[2].w) * D(area_mm2 / 3), half);
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
              GridCorner m = trace(per_sigma, mid);
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
            target.triangle(q[0], cut[0], cut[1], (q[0].w + cut[0].w + cut[1].w) * D(a / 3), half);
            return;
          }
          const double a1 = area_mm2 * cross2(cut_p[0], pq[1], pq[2]) / whole;
          const double a2 = area_mm2 * cross2(cut_p[0], pq[2], cut_p[1]) / whole;
          target.triangle(cut[0], q[1], q[2], (cut[0].w + q[1].w + q[2].w) * D(a1 / 3), half);
          target.triangle(cut[0], q[2], cut[1], (cut[0].w + q[2].w + cut[1].w) * D(a2 / 3), half);
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

}  // namespace prism::ref
