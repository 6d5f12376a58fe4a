// The refinement's model from a dictionary alone (refine.h,
// make_dictionary_model): for dictionaries measured on a bench, where no
// scene's forward model is trusted.
//
// A source at (x, y, d) is the blend of the 8 dictionary PSFs around it: the
// two depth planes that bracket d, on each the four lateral nodes around
// (x, y). Each PSF is moved on the sensor by -(xy - node) * magnification(d)
// (placement.h's convention, here continuous in the shift) and resampled with
// the Catmull-Rom cubic, so the model and its gradient are continuous in x
// and y; the blend weights are bilinear in (x, y) between nodes and linear in
// depth between planes. Outside the grid the nearest nodes are held (the
// weights stop changing; the shift still follows the source).
//
// What this cannot know: how a PSF changes between planes. Linear blending of
// two defocus patterns is not the pattern in between (two rings of different
// radii instead of one in the middle), so the depth estimate is only as good
// as the planes are close; docs/reconstruction.md measures it against the
// forward model.
#include <algorithm>
#include <array>
#include <cmath>
#include <list>
#include <memory>

#include "host/dictionary/store.h"
#include "host/reconstruct/refine.h"

namespace prism {

namespace {

// Catmull-Rom weights of the taps at -1, 0, 1, 2 for a sample at t in [0, 1),
// and their derivatives in t.
struct CubicTaps {
  std::array<double, 4> w, dw;
};
CubicTaps catmull_rom(double t) {
  const double t2 = t * t, t3 = t2 * t;
  return {{(-t3 + 2 * t2 - t) / 2, (3 * t3 - 5 * t2 + 2) / 2, (-3 * t3 + 4 * t2 + t) / 2, (t3 - t2) / 2},
          {(-3 * t2 + 4 * t - 1) / 2, (9 * t2 - 10 * t) / 2, (-9 * t2 + 8 * t + 1) / 2, (3 * t2 - 2 * t) / 2}};
}

// Where `v` lies in the sorted `nodes`: the lower index, the upper and the
// fraction between them (held at the ends: fraction 0 and no derivative).
struct Bracket {
  int lo = 0, hi = 0;
  double t = 0, dt = 0;  // t in [0, 1]; dt = dt/dv (0 where held)
};
Bracket bracket(const std::vector<double>& nodes, double v) {
  Bracket b;
  const int n = int(nodes.size());
  if (n == 1 || v <= nodes.front()) return b;
  if (v >= nodes.back()) {
    b.lo = b.hi = n - 1;
    return b;
  }
  b.lo = int(std::upper_bound(nodes.begin(), nodes.end(), v) - nodes.begin()) - 1;
  b.hi = b.lo + 1;
  const double span = nodes[size_t(b.hi)] - nodes[size_t(b.lo)];
  b.t = (v - nodes[size_t(b.lo)]) / span;
  b.dt = 1.0 / span;
  return b;
}

class DictionaryModel : public SourceModel {
 public:
  DictionaryModel(const DictionaryReader& reader, int level)
      : reader_(reader), m_(reader.manifest()), level_(level), width_(m_.level_width(level)),
        height_(m_.level_height(level)) {}

 protected:
  std::vector<ModelPixel> render_raw(const glm::dvec3& theta) override {
    const auto& g = m_.grid;
    const Bracket bx = bracket(g.x_mm, theta.x), by = bracket(g.y_mm, theta.y), bz = bracket(g.depth_mm, theta.z);
    const OpticalSystem& o = m_.scene.optics;
    const double mag = o.magnification(theta.z);
    const double dmag_dd = -mag / (theta.z + o.working_distance_mm);
    const double px = m_.pixel_mm(level_);

    const size_t n = size_t(width_) * size_t(height_);
    std::vector<double> b(n, 0.0);
    std::vector<glm::dvec3> grad(n, glm::dvec3(0.0));
    for (int corner = 0; corner < 8; ++corner) {
      const int cx = corner & 1, cy = (corner >> 1) & 1, cz = corner >> 2;
      // Blend weight and its gradient in (x, y, depth).
      const double wx = cx ? bx.t : 1 - bx.t, wy = cy ? by.t : 1 - by.t, wz = cz ? bz.t : 1 - bz.t;
      const double sx = cx ? bx.dt : -bx.dt, sy = cy ? by.dt : -by.dt, sz = cz ? bz.dt : -bz.dt;
      const double w = wx * wy * wz;
      const glm::dvec3 dw(sx * wy * wz, wx * sy * wz, wx * wy * sz);
      if (w == 0 && dw == glm::dvec3(0.0)) continue;
      const glm::ivec3 node(cx ? bx.hi : bx.lo, cy ? by.hi : by.lo, cz ? bz.hi : bz.lo);
      const size_t index = g.index(node);
      const PsfLevel& psf = level_of(index);
      const glm::dvec2 node_xy(g.x_mm[size_t(node.x)], g.y_mm[size_t(node.y)]);
      // The shift on the sensor in pixels and its derivatives.
      const glm::dvec2 rel = glm::dvec2(theta) - node_xy;
      const glm::dvec2 shift = -rel * mag / px;
      const double dshift_dxy = -mag / px;            // d shift.x / dx = d shift.y / dy
      const glm::dvec2 dshift_dd = -rel * dmag_dd / px;
      // Sample position in the PSF: pixel - shift = pixel + offset + fraction.
      const glm::dvec2 start = -shift;
      const glm::ivec2 offset(int(std::floor(start.x)), int(std::floor(start.y)));
      const CubicTaps tx = catmull_rom(start.x - offset.x), ty = catmull_rom(start.y - offset.y);
      for (int r = 0; r < height_; ++r) {
        // Rows -1..2 around r + offset.y, each resampled along x.
        if (r + offset.y + 2 < 0 || r + offset.y - 1 >= psf.height) continue;
        for (int c = 0; c < width_; ++c) {
          double v = 0, dvx = 0, dvy = 0;  // value and d/d(sample position) x, y
          for (int l = 0; l < 4; ++l) {
            const int sr = r + offset.y + l - 1;
            if (sr < 0 || sr >= psf.height) continue;
            const float* row = &psf.p[size_t(sr) * size_t(psf.width)];
            double a = 0, da = 0;
            for (int k = 0; k < 4; ++k) {
              const int sc = c + offset.x + k - 1;
              if (sc < 0 || sc >= psf.width) continue;
              a += tx.w[size_t(k)] * row[sc];
              da += tx.dw[size_t(k)] * row[sc];
            }
            v += ty.w[size_t(l)] * a;
            dvx += ty.w[size_t(l)] * da;
            dvy += ty.dw[size_t(l)] * a;
          }
          if (v == 0 && dvx == 0 && dvy == 0) continue;
          // The sample position moves by -d(shift): chain to (x, y, depth).
          const glm::dvec3 dq(-dvx * dshift_dxy, -dvy * dshift_dxy, -(dvx * dshift_dd.x + dvy * dshift_dd.y));
          const size_t i = size_t(r) * size_t(width_) + size_t(c);
          b[i] += w * v;
          grad[i] += dw * v + w * dq;
        }
      }
    }
    std::vector<ModelPixel> raw;
    for (size_t i = 0; i < n; ++i) {
      // The cubic overshoots below zero next to sharp edges; a pixel's
      // expected light cannot, so those pixels are dropped (value and slope).
      if (b[i] > 0) raw.push_back({uint32_t(i), b[i], grad[i]});
    }
    return raw;
  }

 private:
  // PSFs of the click level, the most recently used first.
  const PsfLevel& level_of(size_t index) {
    for (auto it = cache_.begin(); it != cache_.end(); ++it)
      if (it->first == index) {
        cache_.splice(cache_.begin(), cache_, it);
        return cache_.front().second;
      }
    cache_.emplace_front(index, reader_.read_level(index, level_));
    if (cache_.size() > kCacheEntries) cache_.pop_back();
    return cache_.front().second;
  }
  static constexpr size_t kCacheEntries = 32;  // a refinement stays among a few nodes

  const DictionaryReader& reader_;
  const DictionaryManifest& m_;
  int level_, width_, height_;
  std::list<std::pair<size_t, PsfLevel>> cache_;
};

}  // namespace

std::unique_ptr<SourceModel> make_dictionary_model(const DictionaryReader& reader, int level) {
  const auto& m = reader.manifest();
  if (level < 0 || level >= m.levels)
    throw std::invalid_argument("dictionary model: level " + std::to_string(level) + " is not stored in " +
                                reader.dir());
  return std::make_unique<DictionaryModel>(reader, level);
}

}  // namespace prism
