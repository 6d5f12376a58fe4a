#include "host/reconstruct/reconstruct.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <map>
#include <optional>
#include <tuple>

// Documented choices (DESIGN.md asks for them):
//
// Dark rate and the first gradient. Every pixel carries a background rate
// dark_rate (1e-6 expected counts, about a dark count). It makes the NLL finite
// at clicks that no PSF reaches (log(1 - exp(-lambda)) -> -inf as lambda -> 0)
// and it is the floor of the first gradient: with no vertex yet, every click
// has lambda = dark_rate and weight 1 / (1 - exp(-dark_rate)) ~ 1e6, so
// <g, P(shift)> = S - 1e6 sum_clicks P(c - shift): the scan ranks shifts by
// how much PSF mass falls on the clicks, S breaking ties. In later passes the
// clicks the model already explains weigh ~1/lambda and the unexplained ones
// ~1e6, so the scan looks for what is missing. The constant sum_i dark_rate
// over all pixels is left out of every reported NLL.
//
// Shift search. For each PSF the scan tries every whole-pixel shift of the
// search level within +-tau (source mm, times the magnification at the PSF's
// depth, per axis), keeps the one with the lowest <g, P>, fits its weight and
// ranks the PSFs by NLL at that level (the binary model is exact at any level:
// a block clicks when any of its pixels does, with rate the block's sum).
// The best refine_candidates go down level by level to the click grid,
// doubling the shift and trying +-1 pixel around it; the lowest click-level
// NLL wins (pruning, eq. 19).
//
// S at a level finer than the service's coarse level comes from the coarse
// summed-area table, bilinear between the neighbouring whole coarse-pixel
// shifts: exact for PSFs wholly on the sensor, wrong at most by the mass within
// one coarse pixel of the sensor's edge otherwise.
//
// Joint re-optimisation (ADCG's local descent). After each new vertex, all
// weights by projected Newton, then coordinate moves of each vertex in turn
// (+-1 click-grid pixel in x or y, moving to the nearest grid node when the
// source crosses the midpoint, and +-1 depth plane with the lateral offset
// rescaled by the magnification), each trial with all weights re-fitted,
// the best improving move kept, until a round improves nothing (at most
// descent_rounds).
//
// Depth parabola. With the other vertices as fixed background, the vertex's
// NLL at its own plane and at the two neighbouring planes (same lateral
// source position, shift rescaled, +-1 pixel re-searched), a parabola through
// the three, its minimum clamped between the neighbours. The lateral offset is
// then -shift * pixel / M(z) at the refined z: the shift convention of
// place_in_dictionary (lateral source shift d moves every lenslet image by
// -d * lens_to_sensor / (z + working_distance)).

namespace prism {

namespace nll {
double log_click(double lambda) { return std::log(-std::expm1(-lambda)); }
double click_curvature(double lambda) {
  // Below 1e-150 the square underflows; 1 / lambda^2 there is >= 1e300, still
  // finite. sinh overflows to inf for huge lambda: curvature 0, as it should.
  double s = std::sinh(0.5 * std::max(lambda, 1e-150));
  return 1.0 / (4.0 * s * s);
}
}  // namespace nll

std::string flags_to_string(uint32_t flags) {
  static const std::pair<uint32_t, const char*> names[] = {
      {no_clicks, "no_clicks"}, {few_clicks, "few_clicks"}, {alpha_zero, "alpha_zero"},
      {alpha_at_bound, "alpha_at_bound"}, {edge, "edge"}, {merged, "merged"}};
  std::string out;
  for (auto [bit, name] : names)
    if (flags & bit) {
      if (!out.empty()) out += '|';
      out += name;
    }
  return out;
}

int click_level(const DictionaryManifest& m, const EventFileHeader& h, const std::string& events_path,
                const std::string& dictionary_dir) {
  for (int l = 0; l < m.levels; ++l) {
    if ((m.base_binning << l) != int(h.binning)) continue;
    if (m.level_width(l) != int(h.grid_width()) || m.level_height(l) != int(h.grid_height()))
      throw DictionaryError(events_path + ": click grid " + std::to_string(h.grid_width()) + " x " +
                            std::to_string(h.grid_height()) + " differs from " + dictionary_dir + " level " +
                            std::to_string(l) + " (" + std::to_string(m.level_width(l)) + " x " +
                            std::to_string(m.level_height(l)) + "): the two are for different sensors");
    return l;
  }
  throw DictionaryError(events_path + ": clicks on " + std::to_string(h.binning) + " x " + std::to_string(h.binning) +
                        " binned pixels, but " + dictionary_dir + " stores binnings " +
                        std::to_string(m.base_binning) + " x 2^k (k < " + std::to_string(m.levels) +
                        "); simulate with one of those or build a dictionary with that base binning");
}

namespace {

using Shift = glm::ivec2;

// A vertex of the model: a dictionary PSF moved by whole click-grid pixels.
struct Vertex {
  size_t psf = 0;
  Shift shift{};
  double alpha = 0;
};

// A PSF at one shift seen at the click level: P at each click, and S.
struct Column {
  std::vector<double> p;
  double s = 0;
};

// Projected Newton on alpha >= 0 (eq. 18) for the NLL
//   f(alpha) = sum_k alpha_k S_k - sum_c [lambda_c + log(1 - exp(-lambda_c))],
//   lambda_c = background_c + sum_k alpha_k P_kc,
// convex in alpha. Backtracking keeps every step a descent; a small ridge keeps
// a singular Hessian (two vertices with the same PSF) solvable. Returns f.
double fit_weights(const std::vector<const std::vector<double>*>& p, const std::vector<double>& s,
                   const std::vector<double>& background, std::vector<double>& alpha, int max_iterations,
                   double alpha_max) {
  const size_t K = alpha.size(), C = background.size();
  std::vector<double> lam(C), trial(K), grad(K), dir(K);
  auto eval = [&](const std::vector<double>& a) {
    double f = 0;
    for (size_t k = 0; k < K; ++k) f += a[k] * s[k];
    for (size_t c = 0; c < C; ++c) {
      double l = background[c];
      for (size_t k = 0; k < K; ++k) l += a[k] * (*p[k])[c];
      lam[c] = l;
      f -= l + nll::log_click(l);
    }
    return f;
  };
  for (double& a : alpha) a = std::clamp(a, 0.0, alpha_max);
  double f = eval(alpha);
  std::vector<double> H(K * K);
  for (int it = 0; it < max_iterations; ++it) {
    std::fill(H.begin(), H.end(), 0.0);
    for (size_t k = 0; k < K; ++k) grad[k] = s[k];
    for (size_t c = 0; c < C; ++c) {
      double w = 1.0 / -std::expm1(-lam[c]), h = nll::click_curvature(lam[c]);
      for (size_t k = 0; k < K; ++k) {
        double pk = (*p[k])[c];
        if (pk == 0) continue;
        grad[k] -= pk * w;
        for (size_t j = 0; j < K; ++j) H[k * K + j] += pk * (*p[j])[c] * h;
      }
    }
    // Free variables: not held at a bound by the sign of their gradient.
    std::vector<size_t> free;
    for (size_t k = 0; k < K; ++k)
      if (!(alpha[k] <= 0 && grad[k] >= 0) && !(alpha[k] >= alpha_max && grad[k] <= 0)) free.push_back(k);
    if (free.empty()) break;
    // Solve H_FF d = -g_F by Gaussian elimination (K <= 8) with a relative ridge.
    const size_t F = free.size();
    std::vector<double> A(F * F), b(F);
    double diag_max = 0;
    for (size_t i = 0; i < F; ++i) diag_max = std::max(diag_max, H[free[i] * K + free[i]]);
    for (size_t i = 0; i < F; ++i) {
      for (size_t j = 0; j < F; ++j) A[i * F + j] = H[free[i] * K + free[j]];
      A[i * F + i] += 1e-9 * diag_max + 1e-300;
      b[i] = -grad[free[i]];
    }
    for (size_t i = 0; i < F; ++i) {
      size_t piv = i;
      for (size_t r = i + 1; r < F; ++r)
        if (std::abs(A[r * F + i]) > std::abs(A[piv * F + i])) piv = r;
      for (size_t j = 0; j < F; ++j) std::swap(A[i * F + j], A[piv * F + j]);
      std::swap(b[i], b[piv]);
      for (size_t r = i + 1; r < F; ++r) {
        double m = A[r * F + i] / A[i * F + i];
        for (size_t j = i; j < F; ++j) A[r * F + j] -= m * A[i * F + j];
        b[r] -= m * b[i];
      }
    }
    std::fill(dir.begin(), dir.end(), 0.0);
    for (size_t i = F; i-- > 0;) {
      double v = b[i];
      for (size_t j = i + 1; j < F; ++j) v -= A[i * F + j] * dir[free[j]];
      dir[free[i]] = v / A[i * F + i];
    }
    // Backtracking along the projected path (Armijo).
    bool accepted = false;
    double ft = f, step_max = 0;
    std::vector<double> lam_accepted;
    for (double t = 1; t > 1e-12; t *= 0.5) {
      double decrease = 0;
      step_max = 0;
      for (size_t k = 0; k < K; ++k) {
        trial[k] = std::clamp(alpha[k] + t * dir[k], 0.0, alpha_max);
        decrease += grad[k] * (trial[k] - alpha[k]);
        step_max = std::max(step_max, std::abs(trial[k] - alpha[k]) / (1 + alpha[k]));
      }
      if (step_max == 0) break;
      ft = eval(trial);
      if (ft <= f + 1e-4 * decrease) {
        accepted = true;
        break;
      }
    }
    if (!accepted) {
      eval(alpha);  // lam back to the current point
      break;
    }
    bool converged = f - ft <= 1e-12 * (1 + std::abs(f)) && step_max < 1e-9;
    alpha = trial;
    f = ft;
    if (converged) break;
  }
  return f;
}

using Scored = SupportScore;

glm::ivec3 grid_node(const DictionaryManifest& m, size_t psf) {
  size_t nx = m.grid.x_mm.size(), ny = m.grid.y_mm.size();
  return {int(psf % nx), int(psf / nx % ny), int(psf / (nx * ny))};
}
double magnification(const DictionaryManifest& m, double depth_mm) {
  const auto& o = m.scene.optics;
  return o.lens_to_sensor_mm / (depth_mm + o.working_distance_mm);
}
// tau on the sensor in pixels of `level` for the PSF's depth plane.
int scan_radius_px(const DictionaryManifest& m, double tau_mm, size_t psf, int level) {
  double depth = m.grid.depth_mm[size_t(grid_node(m, psf).z)];
  return int(std::ceil(tau_mm * magnification(m, depth) / m.pixel_mm(level) - 1e-9));
}
int search_level_of(const DictionaryService& d, const ReconstructionSettings& s, int level) {
  return std::clamp(s.search_level < 0 ? d.coarse_level() : s.search_level, level, d.manifest().levels - 1);
}

class EventFit {
 public:
  EventFit(const Event& e, int level, DictionaryService& d, const ReconstructionSettings& s)
      : d_(d), m_(d.manifest()), s_(s), level_(level) {
    const int w = m_.level_width(level);
    for (uint32_t c : e.clicks) clicks_[level].push_back({int(c % uint32_t(w)), int(c / uint32_t(w))});
    search_level_ = search_level_of(d, s, level);
    dark_.assign(clicks_[level].size(), s.dark_rate);
  }

  // Another vertex to add (the event has clicks and fewer than K so far).
  bool wants_vertex() { return !clicks_[level_].empty() && vs_.size() < size_t(s_.vertices); }

  // The support scan's input for the next vertex: the clicks on the search
  // level and the current model's rate there (dense: at every pixel).
  ScanEvent scan_input(bool dense) {
    ScanEvent e;
    e.clicks = clicks_at(search_level_);
    e.rate = rates(search_level_, vs_);
    if (dense) e.dense_rate = dense_rates(search_level_);
    return e;
  }

  // The reference scan: every PSF at its best shift on the search level, its
  // weight fitted against the current model.
  std::vector<Scored> scan_cpu() {
    const int Ls = search_level_;
    auto w = gradient_weights(Ls, vs_);
    auto background = rates(Ls, vs_);
    std::vector<Scored> scored;
    for (size_t m = 0; m < m_.grid.size(); ++m) {
      int r = radius_px(m, Ls);
      Shift sh = best_shift(m, Ls, Shift(0), r, r, w, std::max(1, s_.scan_step_px));
      auto v = values(m, Ls, {sh});
      std::vector<double> p(v.begin(), v.end());
      double alpha = 0, f = fit_one(p, sensor_mass(m, Ls, sh), background, alpha);
      scored.push_back({m, sh, f, alpha});
    }
    return scored;
  }

  // Steps 3-6 for the next vertex from the scan's results.
  void add_vertex(std::vector<Scored> scored) {
    vs_.push_back(refine(std::move(scored)));
    fit(vs_);
    descend(vs_);
  }

  std::vector<ReconstructedVertex> result() {
    if (clicks_[level_].empty()) {
      std::vector<ReconstructedVertex> out(size_t(s_.vertices));
      for (auto& v : out) v.flags = no_clicks | few_clicks | alpha_zero;
      return out;
    }
    return finish(vs_);
  }

 private:
  // --- geometry ---
  glm::ivec3 node(size_t psf) const { return grid_node(m_, psf); }
  size_t psf_at(glm::ivec3 n) const {
    return size_t(n.x) + m_.grid.x_mm.size() * (size_t(n.y) + m_.grid.y_mm.size() * size_t(n.z));
  }
  double magnification(double depth_mm) const { return prism::magnification(m_, depth_mm); }
  double depth_of(size_t psf) const { return m_.grid.depth_mm[size_t(node(psf).z)]; }
  // tau on the sensor in pixels of `level` for the PSF's depth plane.
  int radius_px(size_t psf, int level) const { return scan_radius_px(m_, s_.tau_mm, psf, level); }
  // Lateral source position of a vertex, its shift read at depth `depth_mm`.
  glm::dvec2 source_xy(const Vertex& v, double depth_mm) const {
    glm::ivec3 n = node(v.psf);
    double per_px = m_.pixel_mm(level_) / magnification(depth_mm);
    return {m_.grid.x_mm[size_t(n.x)] - v.shift.x * per_px, m_.grid.y_mm[size_t(n.y)] - v.shift.y * per_px};
  }
  // The vertex for a lateral source position at depth plane iz: nearest node,
  // shift rounded; none when the position lies beyond tau of every node.
  std::optional<Vertex> place(glm::dvec2 xy, int iz, double alpha) const {
    auto nearest = [](const std::vector<double>& g, double v) {
      return size_t(std::min_element(g.begin(), g.end(), [v](double a, double b) {
                      return std::abs(a - v) < std::abs(b - v);
                    }) - g.begin());
    };
    glm::ivec3 n{int(nearest(m_.grid.x_mm, xy.x)), int(nearest(m_.grid.y_mm, xy.y)), iz};
    Vertex v{psf_at(n), {}, alpha};
    double px_per_mm = magnification(m_.grid.depth_mm[size_t(iz)]) / m_.pixel_mm(level_);
    v.shift = {int(std::lround(-(xy.x - m_.grid.x_mm[size_t(n.x)]) * px_per_mm)),
               int(std::lround(-(xy.y - m_.grid.y_mm[size_t(n.y)]) * px_per_mm))};
    int r = radius_px(v.psf, level_);
    if (std::abs(v.shift.x) > r || std::abs(v.shift.y) > r) return std::nullopt;
    return v;
  }

  // --- the event at each level ---
  const std::vector<glm::ivec2>& clicks_at(int level) {
    auto it = clicks_.find(level);
    if (it != clicks_.end()) return it->second;
    const int d = level - level_;
    std::vector<glm::ivec2> out;
    for (auto c : clicks_[level_]) out.push_back({c.x >> d, c.y >> d});
    std::sort(out.begin(), out.end(), [](auto a, auto b) { return std::tie(a.y, a.x) < std::tie(b.y, b.x); });
    out.erase(std::unique(out.begin(), out.end()), out.end());
    return clicks_[level] = std::move(out);
  }
  // S of a PSF shifted by `shift` pixels of `level` (see the note on top).
  double sensor_mass(size_t psf, int level, Shift shift) const {
    const SummedArea& sat = d_.coarse_mass(psf);
    double f = std::ldexp(1.0, level - d_.coarse_level());  // coarse pixels per pixel of `level`
    double x = shift.x * f, y = shift.y * f, x0 = std::floor(x), y0 = std::floor(y);
    double tx = x - x0, ty = y - y0;
    int ix = int(x0), iy = int(y0);
    auto at = [&](int dx, int dy) { return sat.mass_shifted(ix + dx, iy + dy); };
    double top = tx > 0 ? (1 - tx) * at(0, 0) + tx * at(1, 0) : at(0, 0);
    if (ty == 0) return top;
    double bottom = tx > 0 ? (1 - tx) * at(0, 1) + tx * at(1, 1) : at(0, 1);
    return (1 - ty) * top + ty * bottom;
  }
  // P of a PSF at `level` at (clicks - shift) for every shift in `shifts`, shift-major.
  std::vector<float> values(size_t psf, int level, const std::vector<Shift>& shifts) {
    const auto& cl = clicks_at(level);
    pixels_.clear();
    for (Shift sh : shifts)
      for (auto c : cl) pixels_.push_back(c - sh);
    return d_.values(psf, level, pixels_);
  }
  const Column& column(size_t psf, Shift shift) {
    auto key = std::make_tuple(psf, shift.x, shift.y);
    auto it = columns_.find(key);
    if (it != columns_.end()) return it->second;
    auto v = values(psf, level_, {shift});
    Column c{std::vector<double>(v.begin(), v.end()), sensor_mass(psf, level_, shift)};
    return columns_.emplace(key, std::move(c)).first->second;
  }
  // lambda at the clicks of `level` of the vertices `vs` (whose shifts are on
  // the click grid), dark rate included.
  std::vector<double> rates(int level, const std::vector<Vertex>& vs, int skip = -1) {
    const auto& cl = clicks_at(level);
    std::vector<double> lam(cl.size(), s_.dark_rate * double(1 << (2 * (level - level_))));
    for (size_t k = 0; k < vs.size(); ++k) {
      if (int(k) == skip || vs[k].alpha <= 0) continue;
      Shift sh = vs[k].shift;
      if (level == level_) {
        const Column& c = column(vs[k].psf, sh);
        for (size_t i = 0; i < cl.size(); ++i) lam[i] += vs[k].alpha * c.p[i];
        continue;
      }
      double f = std::ldexp(1.0, level_ - level);
      auto v = values(vs[k].psf, level, {Shift(int(std::lround(sh.x * f)), int(std::lround(sh.y * f)))});
      for (size_t i = 0; i < cl.size(); ++i) lam[i] += vs[k].alpha * double(v[i]);
    }
    return lam;
  }

  // lambda at every pixel of `level` (the dense baseline's input).
  std::vector<double> dense_rates(int level) {
    const int w = m_.level_width(level), h = m_.level_height(level);
    std::vector<double> lam(size_t(w) * size_t(h), s_.dark_rate * double(1 << (2 * (level - level_))));
    std::vector<glm::ivec2> px(lam.size());
    for (const Vertex& v : vs_) {
      if (v.alpha <= 0) continue;
      double f = std::ldexp(1.0, level_ - level);
      Shift sh(int(std::lround(v.shift.x * f)), int(std::lround(v.shift.y * f)));
      for (int y = 0; y < h; ++y)
        for (int x = 0; x < w; ++x) px[size_t(y) * size_t(w) + size_t(x)] = glm::ivec2(x, y) - sh;
      auto p = d_.values(v.psf, level, px);
      for (size_t i = 0; i < lam.size(); ++i) lam[i] += v.alpha * double(p[i]);
    }
    return lam;
  }

  // --- weights ---
  // All weights of `vs` jointly at the click level; returns the event's NLL.
  double fit(std::vector<Vertex>& vs) {
    std::vector<const std::vector<double>*> p;
    std::vector<double> s, alpha;
    for (auto& v : vs) {
      const Column& c = column(v.psf, v.shift);
      p.push_back(&c.p);
      s.push_back(c.s);
      alpha.push_back(v.alpha > 0 ? v.alpha : initial_alpha(c.p, c.s));
    }
    double f = fit_weights(p, s, dark_, alpha, s_.newton_iterations, s_.alpha_max);
    for (size_t k = 0; k < vs.size(); ++k) vs[k].alpha = alpha[k];
    return f;
  }
  // One weight against a fixed background; returns the NLL of that vertex's part.
  double fit_one(const std::vector<double>& p, double s, const std::vector<double>& background, double& alpha) {
    std::vector<double> a{alpha > 0 ? alpha : initial_alpha(p, s)};
    double f = fit_weights({&p}, {s}, background, a, s_.newton_iterations, s_.alpha_max);
    alpha = a[0];
    return f;
  }
  // A start for Newton: the clicks this PSF reaches over its on-sensor mass.
  double initial_alpha(const std::vector<double>& p, double s) const {
    double reached = double(std::count_if(p.begin(), p.end(), [](double v) { return v > 0; }));
    return std::clamp(std::max(reached, 1.0) / std::max(s, 1e-3), 1e-3, s_.alpha_max);
  }

  // --- support search (eqs. 17-19) ---
  // The shift around `center` (multiples of step within +-reach, and within
  // +-radius) with the lowest <g, P>; ties to the first in row-major order.
  Shift best_shift(size_t psf, int level, Shift center, int reach, int radius, const std::vector<double>& w,
                   int step = 1) {
    std::vector<Shift> shifts;
    const int first = -(reach / step) * step;
    for (int dy = first; dy <= reach; dy += step)
      for (int dx = first; dx <= reach; dx += step) {
        Shift sh = center + Shift(dx, dy);
        if (std::abs(sh.x) <= radius && std::abs(sh.y) <= radius) shifts.push_back(sh);
      }
    if (shifts.empty()) return glm::clamp(center, Shift(-radius), Shift(radius));
    auto v = values(psf, level, shifts);
    const size_t n = w.size();
    double best = std::numeric_limits<double>::infinity();
    Shift arg = shifts[0];
    for (size_t j = 0; j < shifts.size(); ++j) {
      double score = sensor_mass(psf, level, shifts[j]);
      for (size_t i = 0; i < n; ++i) score -= w[i] * double(v[j * n + i]);
      if (score < best) best = score, arg = shifts[j];
    }
    return arg;
  }
  std::vector<double> gradient_weights(int level, const std::vector<Vertex>& vs) {
    auto lam = rates(level, vs);
    for (double& l : lam) l = 1.0 / -std::expm1(-l);
    return lam;
  }

  // Pruning (eq. 19): the refine_candidates best PSFs of the scan go down
  // level by level to the click grid (shift doubled, +-1 re-searched; first
  // +-(step - 1) on the search level when the scan skipped shifts), and the
  // lowest click-level NLL wins.
  Vertex refine(std::vector<Scored> scored) {
    const int Ls = search_level_, step = std::max(1, s_.scan_step_px);
    size_t keep = std::min(scored.size(), size_t(std::max(1, s_.refine_candidates)));
    std::partial_sort(scored.begin(), scored.begin() + long(keep), scored.end(), [](const Scored& a, const Scored& b) {
      return a.nll < b.nll || (a.nll == b.nll && a.psf < b.psf);
    });
    std::map<int, std::vector<double>> weights;  // per level, shared by the candidates
    auto weights_at = [&](int l) -> const std::vector<double>& {
      if (!weights.count(l)) weights[l] = gradient_weights(l, vs_);
      return weights[l];
    };
    auto background_click = rates(level_, vs_);
    Vertex best;
    double best_nll = std::numeric_limits<double>::infinity();
    for (size_t j = 0; j < keep; ++j) {
      size_t m = scored[j].psf;
      Shift sh = scored[j].shift;
      if (step > 1) sh = best_shift(m, Ls, sh, step - 1, radius_px(m, Ls), weights_at(Ls));
      for (int l = Ls - 1; l >= level_; --l) sh = best_shift(m, l, sh * 2, 1, radius_px(m, l), weights_at(l));
      const Column& c = column(m, sh);
      double alpha = scored[j].alpha;
      double f = fit_one(c.p, c.s, background_click, alpha);
      if (f < best_nll) best_nll = f, best = {m, sh, alpha};
    }
    return best;
  }

  // --- joint local descent (ADCG) ---
  std::vector<Vertex> moves(const Vertex& v) const {
    std::vector<Vertex> out;
    glm::ivec3 n = node(v.psf);
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
  void descend(std::vector<Vertex>& vs) {
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

  // --- refinement and output ---
  struct DepthFit {
    double depth_mm;
    bool at_edge;
  };
  // Parabola through the vertex's NLL at its plane and the neighbouring ones.
  DepthFit refine_depth(const Vertex& v, const std::vector<double>& background) {
    glm::ivec3 n = node(v.psf);
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

  std::vector<ReconstructedVertex> finish(std::vector<Vertex>& vs) {
    double f = fit(vs);
    const auto& cl = clicks_at(level_);
    std::vector<ReconstructedVertex> out(vs.size());
    std::vector<uint32_t> owned(vs.size(), 0);
    for (size_t i = 0; i < cl.size(); ++i) {
      double top = s_.dark_rate;
      int who = -1;
      for (size_t k = 0; k < vs.size(); ++k) {
        double r = vs[k].alpha * column(vs[k].psf, vs[k].shift).p[i];
        if (r > top) top = r, who = int(k);
      }
      if (who >= 0) ++owned[size_t(who)];
    }
    const auto& g = m_.grid;
    for (size_t k = 0; k < vs.size(); ++k) {
      const Vertex& v = vs[k];
      ReconstructedVertex& o = out[k];
      o.psf = v.psf;
      o.shift_px = v.shift;
      o.alpha = v.alpha;
      o.nll = f;
      o.clicks = owned[k];
      if (cl.size() < size_t(s_.min_clicks)) o.flags |= few_clicks;
      if (v.alpha <= 0) o.flags |= alpha_zero;
      if (v.alpha >= s_.alpha_max * (1 - 1e-12)) o.flags |= alpha_at_bound;
      for (size_t j = 0; j < vs.size(); ++j)
        if (j != k && vs[j].psf == v.psf && std::abs(vs[j].shift.x - v.shift.x) <= 1 &&
            std::abs(vs[j].shift.y - v.shift.y) <= 1)
          o.flags |= merged;
      DepthFit z{depth_of(v.psf), false};
      if (v.alpha > 0) z = refine_depth(v, rates(level_, vs, int(k)));
      glm::dvec2 xy = source_xy(v, z.depth_mm);
      o.x_mm = xy.x;
      o.y_mm = xy.y;
      o.depth_mm = z.depth_mm;
      // Lateral edge: pushed to tau beyond an outermost node (within one pixel).
      glm::ivec3 n = node(v.psf);
      double slack = s_.tau_mm - m_.pixel_mm(level_) / magnification(z.depth_mm);
      auto outside = [&](const std::vector<double>& axis, int i, double value) {
        return (i == 0 && value <= axis.front() - slack) || (i == int(axis.size()) - 1 && value >= axis.back() + slack);
      };
      if (z.at_edge || outside(g.x_mm, n.x, xy.x) || outside(g.y_mm, n.y, xy.y)) o.flags |= edge;
    }
    return out;
  }

  DictionaryService& d_;
  const DictionaryManifest& m_;
  const ReconstructionSettings& s_;
  int level_, search_level_ = 0;
  std::map<int, std::vector<glm::ivec2>> clicks_;  // per level
  std::vector<double> dark_;                       // dark rate at each click-level click
  std::map<std::tuple<size_t, int, int>, Column> columns_;
  std::vector<glm::ivec2> pixels_;  // scratch
  std::vector<Vertex> vs_;          // the model so far
};

}  // namespace

namespace {
// The device's results of event j as scores.
std::vector<SupportScore> to_scores(const std::vector<ScanResult>& results, size_t j, size_t n_psf) {
  std::vector<SupportScore> scored(n_psf);
  for (size_t psf = 0; psf < n_psf; ++psf) {
    const ScanResult& r = results[j * n_psf + psf];
    scored[psf] = {psf, r.shift, double(r.nll), double(r.alpha)};
  }
  return scored;
}
}  // namespace

const char* to_string(ReconstructionBackend b) {
  switch (b) {
    case ReconstructionBackend::cpu: return "cpu";
    case ReconstructionBackend::vulkan: return "vulkan";
    case ReconstructionBackend::dense: return "dense";
  }
  return "?";
}

ReconstructionBackend backend_from_string(const std::string& s) {
  for (auto b : {ReconstructionBackend::cpu, ReconstructionBackend::vulkan, ReconstructionBackend::dense})
    if (s == to_string(b)) return b;
  throw std::invalid_argument("reconstruction backend '" + s + "': choose cpu, vulkan or dense");
}

Reconstructor::Reconstructor(DictionaryService& dictionary, int click_level, ReconstructionSettings settings,
                             ReconstructionBackend backend, vk::Context* ctx)
    : d_(dictionary), level_(click_level), s_(settings), backend_(backend) {
  const auto& m = dictionary.manifest();
  if (s_.vertices < 1 || s_.vertices > 8)
    throw std::invalid_argument("reconstruction: vertices = " + std::to_string(s_.vertices) + "; choose K in 1..8");
  if (!(s_.dark_rate > 0) || !(s_.tau_mm >= 0) || !(s_.alpha_max > 0))
    throw std::invalid_argument("reconstruction: dark_rate and alpha_max must be > 0 and tau_mm >= 0");
  if (s_.scan_step_px < 1) throw std::invalid_argument("reconstruction: the scan step must be >= 1 pixel");
  if (level_ < 0 || level_ >= m.levels)
    throw std::invalid_argument("reconstruction: click level " + std::to_string(level_) + " is not in the dictionary");
  if (backend_ == ReconstructionBackend::cpu) return;
  const int Ls = search_level_of(dictionary, s_, level_);
  if (!ctx) throw std::invalid_argument(std::string("reconstruction: the ") + to_string(backend_) + " backend needs a Vulkan device");
  if (Ls != dictionary.coarse_level())
    throw std::invalid_argument("reconstruction: the device scans the level the dictionary service keeps on the device (" +
                                std::to_string(dictionary.coarse_level()) + "), not level " + std::to_string(Ls) +
                                "; make the service with the search level as its coarse level");
  scan_level_ = dictionary.scan_level();
  for (size_t i = 0; i < scan_level_.psfs.size(); ++i)
    scan_level_.psfs[i].radius_px = scan_radius_px(m, s_.tau_mm, i, Ls);
  device_ = std::make_unique<SupportScanVulkan>(
      *ctx, backend_ == ReconstructionBackend::dense ? ScanKernel::dense : ScanKernel::sparse, scan_level_.half);
}

Reconstructor::~Reconstructor() = default;

void Reconstructor::check_clicks(std::span<const Event> events) const {
  const auto& m = d_.manifest();
  const uint64_t pixels = uint64_t(m.level_width(level_)) * uint64_t(m.level_height(level_));
  for (const Event& e : events)
    for (uint32_t c : e.clicks)
      if (c >= pixels)
        throw std::invalid_argument("event " + std::to_string(e.id) + ": click " + std::to_string(c) +
                                    " lies beyond the " + std::to_string(pixels) + "-pixel click grid");
}

std::vector<std::vector<SupportScore>> Reconstructor::first_scan(std::span<const Event> events) {
  check_clicks(events);
  std::vector<EventFit> fits;
  fits.reserve(events.size());
  for (const Event& e : events) fits.emplace_back(e, level_, d_, s_);
  std::vector<std::vector<SupportScore>> out(events.size());
  std::vector<size_t> active;
  for (size_t i = 0; i < fits.size(); ++i)
    if (fits[i].wants_vertex()) active.push_back(i);
  if (backend_ == ReconstructionBackend::cpu) {
    for (size_t i : active) out[i] = fits[i].scan_cpu();
    return out;
  }
  std::vector<ScanEvent> inputs;
  for (size_t i : active) inputs.push_back(fits[i].scan_input(backend_ == ReconstructionBackend::dense));
  ScanSettings scan{s_.scan_step_px, s_.newton_iterations, s_.alpha_max};
  auto results = device_->run(scan_level_, inputs, scan);
  for (size_t j = 0; j < active.size(); ++j) out[active[j]] = to_scores(results, j, d_.manifest().grid.size());
  return out;
}

std::vector<std::vector<ReconstructedVertex>> Reconstructor::run(std::span<const Event> events) {
  using clock = std::chrono::steady_clock;
  auto seconds = [](clock::time_point a, clock::time_point b) { return std::chrono::duration<double>(b - a).count(); };
  const auto& m = d_.manifest();
  check_clicks(events);
  auto t0 = clock::now();
  std::vector<EventFit> fits;
  fits.reserve(events.size());
  for (const Event& e : events) fits.emplace_back(e, level_, d_, s_);
  ScanSettings scan{s_.scan_step_px, s_.newton_iterations, s_.alpha_max};
  const size_t n_psf = m.grid.size();
  double host_s = seconds(t0, clock::now());
  // K passes in lockstep: each pass scans every event that wants a vertex.
  for (int pass = 0; pass < s_.vertices; ++pass) {
    std::vector<size_t> active;
    for (size_t i = 0; i < fits.size(); ++i)
      if (fits[i].wants_vertex()) active.push_back(i);
    if (active.empty()) break;
    timings_.scans += active.size();
    if (backend_ == ReconstructionBackend::cpu) {
      for (size_t i : active) {
        auto a = clock::now();
        auto scored = fits[i].scan_cpu();
        auto b = clock::now();
        fits[i].add_vertex(std::move(scored));
        timings_.scan_s += seconds(a, b);
        host_s += seconds(b, clock::now());
      }
      continue;
    }
    auto a = clock::now();
    std::vector<ScanEvent> inputs;
    for (size_t i : active) inputs.push_back(fits[i].scan_input(backend_ == ReconstructionBackend::dense));
    auto b = clock::now();
    auto results = device_->run(scan_level_, inputs, scan);
    auto c = clock::now();
    timings_.scan_kernel_ms += device_->last_kernel_ms();
    timings_.scan_device_bytes = std::max(timings_.scan_device_bytes, device_->last_device_bytes());
    for (size_t j = 0; j < active.size(); ++j) fits[active[j]].add_vertex(to_scores(results, j, n_psf));
    timings_.scan_s += seconds(b, c);
    host_s += seconds(a, b) + seconds(c, clock::now());
  }
  auto d = clock::now();
  std::vector<std::vector<ReconstructedVertex>> out;
  for (auto& f : fits) out.push_back(f.result());
  timings_.host_s += host_s + seconds(d, clock::now());
  return out;
}

std::vector<ReconstructedVertex> reconstruct(const Event& event, int level, DictionaryService& dictionary,
                                             const ReconstructionSettings& settings) {
  Reconstructor r(dictionary, level, settings);
  return r.run(std::span<const Event>(&event, 1)).at(0);
}

}  // namespace prism
