// The event at each level, the model's rates and weights, and the output rows.
//
// Dark rate and the first gradient (DESIGN.md asks for the choice). Every
// pixel carries a background rate dark_rate (1e-6 expected counts, about a
// dark count). It makes the NLL finite at clicks that no PSF reaches
// (log(1 - exp(-lambda)) -> -inf as lambda -> 0) and it is the floor of the
// first gradient: with no vertex yet, every click has lambda = dark_rate and
// weight 1 / (1 - exp(-dark_rate)) ~ 1e6, so <g, P(shift)> = S - 1e6
// sum_clicks P(c - shift): the scan ranks shifts by how much PSF mass falls on
// the clicks, S breaking ties. In later passes the clicks the model already
// explains weigh ~1/lambda and the unexplained ones ~1e6, so the scan looks
// for what is missing. The constant sum_i dark_rate over all pixels is left
// out of every reported NLL.
//
// S at a level finer than the service's coarse level comes from the coarse
// summed-area table, bilinear between the neighbouring whole coarse-pixel
// shifts: exact for PSFs wholly on the sensor, wrong at most by the mass within
// one coarse pixel of the sensor's edge otherwise.
#include <algorithm>
#include <cmath>

#include "engine/ref/likelihood_ref.h"
#include "engine/ref/support_scan_ref.h"
#include "host/dictionary/placement.h"
#include "host/reconstruct/event_fit.h"

namespace prism::detail {

int scan_radius_px(const DictionaryManifest& m, double tau_mm, size_t psf, int level) {
  double depth = m.grid.depth_mm[size_t(m.grid.node(psf).z)];
  const double radius = std::floor(tau_mm * m.scene.optics.magnification(depth) / m.pixel_mm(level) + 0.5 + 1e-9);
  // Beyond the image's size every shift puts the PSF off the grid: no more to scan.
  return int(std::min(radius, double(std::max(m.level_width(level), m.level_height(level)))));
}

int search_level_of(const DictionaryService& d, const ReconstructionSettings& s, int click_level) {
  return std::clamp(s.search_level < 0 ? d.coarse_level() : s.search_level, click_level, d.manifest().levels - 1);
}

int select_level_of(int search_level, const ReconstructionSettings& s, const DictionaryManifest& m, int click_level) {
  return std::clamp(select_level(s, m, click_level), click_level, search_level);
}

int rank_level_of(int select_level, const ReconstructionSettings& s, const DictionaryManifest& m, int click_level) {
  return std::clamp(rank_level(s, m, click_level), click_level, select_level);
}

EventFit::EventFit(const Event& e, int level, DictionaryService& d, const ReconstructionSettings& s)
    : d_(d), m_(d.manifest()), s_(s), level_(level) {
  const int w = m_.level_width(level);
  auto& cl = clicks_[level];
  for (uint32_t c : e.clicks) cl.push_back({int(c % uint32_t(w)), int(c / uint32_t(w))});
  search_level_ = search_level_of(d, s, level);
  dark_.assign(cl.size(), s.dark_rate);
}

// --- geometry ---

glm::dvec2 EventFit::source_xy(const Vertex& v, double depth_mm) const {
  return source_lateral_mm(m_, level_, v.psf, v.shift, depth_mm);
}

std::optional<Vertex> EventFit::place(glm::dvec2 xy, int iz, double alpha) const {
  DictionaryPlacement p = place_on_plane(m_, level_, xy, iz, m_.grid.depth_mm[size_t(iz)]);
  const int r = radius_px(p.index, level_);
  if (std::abs(p.shift_px.x) > r || std::abs(p.shift_px.y) > r) return std::nullopt;
  return Vertex{p.index, p.shift_px, alpha};
}

// --- the event at each level ---

const std::vector<glm::ivec2>& EventFit::clicks_at(int level) {
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
double EventFit::sensor_mass(size_t psf, int level, Shift shift) const {
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

std::vector<float> EventFit::values_at(size_t psf, int level, Shift shift) {
  const auto& cl = clicks_at(level);
  std::vector<glm::ivec2> pixels(cl.size());
  for (size_t i = 0; i < cl.size(); ++i) pixels[i] = cl[i] - shift;
  return d_.values(psf, level, pixels);
}

const Column& EventFit::column(size_t psf, Shift shift) {
  auto key = std::make_tuple(psf, shift.x, shift.y);
  auto it = columns_.find(key);
  if (it != columns_.end()) return it->second;
  auto v = values_at(psf, level_, shift);
  Column c{std::vector<double>(v.begin(), v.end()), sensor_mass(psf, level_, shift)};
  return columns_.emplace(key, std::move(c)).first->second;
}

double EventFit::search_floor() const {
  const double side = double(m_.base_binning) * std::ldexp(1.0, level_);  // sensor pixels per click pixel, per axis
  return std::max(s_.dark_rate, s_.search_dark_rate * side * side);
}

std::vector<double> EventFit::rates(int level, const std::vector<Vertex>& vs, double floor, int skip) {
  const auto& cl = clicks_at(level);
  std::vector<double> lam(cl.size(), floor * double(1 << (2 * (level - level_))));
  for (size_t k = 0; k < vs.size(); ++k) {
    if (int(k) == skip || vs[k].alpha <= 0) continue;
    Shift sh = vs[k].shift;
    if (level == level_) {
      const Column& c = column(vs[k].psf, sh);
      for (size_t i = 0; i < cl.size(); ++i) lam[i] += vs[k].alpha * c.p[i];
      continue;
    }
    double f = std::ldexp(1.0, level_ - level);
    auto v = values_at(vs[k].psf, level, Shift(int(std::lround(sh.x * f)), int(std::lround(sh.y * f))));
    for (size_t i = 0; i < cl.size(); ++i) lam[i] += vs[k].alpha * double(v[i]);
  }
  return lam;
}

std::vector<double> EventFit::dense_rates(int level) {
  const int w = m_.level_width(level), h = m_.level_height(level);
  std::vector<double> lam(size_t(w) * size_t(h), search_floor() * double(1 << (2 * (level - level_))));
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

double EventFit::fit(std::vector<Vertex>& vs) {
  std::vector<const std::vector<double>*> p;
  std::vector<double> s, alpha;
  for (auto& v : vs) {
    const Column& c = column(v.psf, v.shift);
    p.push_back(&c.p);
    s.push_back(c.s);
    alpha.push_back(v.alpha > 0 ? v.alpha : ref::initial_alpha(c.p, c.s, s_.alpha_max));
  }
  double f = ref::fit_weights(p, s, dark_, alpha, s_.newton_iterations, s_.alpha_max);
  for (size_t k = 0; k < vs.size(); ++k) vs[k].alpha = alpha[k];
  return f;
}

double EventFit::fit_one(const std::vector<double>& p, double s, const std::vector<double>& background,
                         double& alpha) const {
  std::vector<double> a{alpha > 0 ? alpha : ref::initial_alpha(p, s, s_.alpha_max)};
  const std::vector<double>* columns[] = {&p};
  double f = ref::fit_weights(columns, std::span<const double>(&s, 1), background, a, s_.newton_iterations,
                              s_.alpha_max);
  alpha = a[0];
  return f;
}

// --- the scan's input, the passes, the output ---

ScanEvent EventFit::scan_input(bool dense) {
  ScanEvent e;
  e.clicks = clicks_at(search_level_);
  e.rate = rates(search_level_, vs_, search_floor());
  if (dense) e.dense_rate = dense_rates(search_level_);
  return e;
}

std::vector<SupportScore> EventFit::scan_cpu() {
  LevelSource level(*this, search_level_);
  return ref::support_scan(level, scan_input(false), {s_.scan_step_px, s_.newton_iterations, s_.alpha_max});
}

void EventFit::add_vertex(std::vector<SupportScore> scored) {
  runners_up_.emplace_back();
  vs_.push_back(refine(std::move(scored), runners_up_.back()));
  fit(vs_);
  descend(vs_);
}

std::vector<ReconstructedVertex> EventFit::result() {
  if (clicks_[level_].empty()) {
    std::vector<ReconstructedVertex> out(size_t(s_.vertices));
    for (auto& v : out) v.flags = no_clicks | few_clicks | alpha_zero;
    return out;
  }
  return finish(vs_);
}

std::vector<ReconstructedVertex> EventFit::finish(std::vector<Vertex>& vs) {
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
    if (v.alpha > 0) z = refine_depth(v, rates(level_, vs, s_.dark_rate, int(k)));
    glm::dvec2 xy = source_xy(v, z.depth_mm);
    o.x_mm = xy.x;
    o.y_mm = xy.y;
    o.depth_mm = z.depth_mm;
    // Lateral edge: pushed to tau beyond an outermost node (within one pixel).
    glm::ivec3 n = g.node(v.psf);
    double slack = s_.tau_mm - m_.pixel_mm(level_) / m_.scene.optics.magnification(z.depth_mm);
    auto outside = [&](const std::vector<double>& axis, int i, double value) {
      return (i == 0 && value <= axis.front() - slack) || (i == int(axis.size()) - 1 && value >= axis.back() + slack);
    };
    if (z.at_edge || outside(g.x_mm, n.x, xy.x) || outside(g.y_mm, n.y, xy.y)) o.flags |= edge;
    if (k < runners_up_.size())
      for (const Vertex& r : runners_up_[k]) {
        const double d = depth_of(r.psf);
        const glm::dvec2 rxy = source_xy(r, d);
        o.runners_up.push_back({rxy.x, rxy.y, d, r.alpha});
      }
  }
  return out;
}

}  // namespace prism::detail
