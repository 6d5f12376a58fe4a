#include "host/reconstruct/refine.h"

#include <algorithm>
#include <chrono>
#include <cmath>
#include <limits>
#include <optional>
#include <random>
#include <tuple>
#include <unordered_map>

#include "engine/ref/forward_ref.h"
#include "engine/ref/likelihood_ref.h"
#include "host/reconstruct/click_geometry.h"
#include "host/reconstruct/levenberg_marquardt.h"
#include "host/util/memory.h"

namespace prism {

const ModelPixel* SourceImage::find(uint32_t index) const {
  auto it = std::lower_bound(pixels.begin(), pixels.end(), index,
                             [](const ModelPixel& m, uint32_t i) { return m.index < i; });
  return it != pixels.end() && it->index == index ? &*it : nullptr;
}

SourceImage blurred(const SourceImage& image, double sigma_px, const AnalysisGrid& grid) {
  if (!(sigma_px > 0) || image.pixels.empty()) return image;
  // The Gaussian is separable: along rows, then along columns (light that
  // leaves the grid is lost). Both passes keep only the rows the light
  // reaches, each as its lit columns: at the sensor's own 6.9 um pixels an
  // image's 42 lenslet discs span the whole 32 M pixel sensor, whose dense
  // window (as this was first written) took 2 GB and half the polish's time.
  const int radius = int(std::ceil(defaults::refine_blur_radius_sigmas * sigma_px));
  std::vector<double> taps;  // 2 radius + 1, normalised
  double total = 0;
  for (int d = -radius; d <= radius; ++d) total += taps.emplace_back(std::exp(-double(d * d) / (2 * sigma_px * sigma_px)));
  for (double& t : taps) t /= total;
  const int W = grid.width, H = grid.height;
  // (p, dp/dx, dp/dy, dp/ddepth) of one row, dense; lit columns [lo, hi].
  std::vector<glm::dvec4> line(size_t(W), glm::dvec4(0.0));
  struct Lit {
    int col;
    glm::dvec4 v;
  };
  // Row pass: the image's pixels are sorted by index, so row by row.
  std::vector<int> rows;            // rows with light, ascending
  std::vector<size_t> row_begin;    // their runs in `lit` (one more at the end)
  std::vector<Lit> lit;
  for (size_t i = 0; i < image.pixels.size();) {
    const int row = int(image.pixels[i].index / uint32_t(W));
    int lo = W, hi = -1;
    for (; i < image.pixels.size() && int(image.pixels[i].index / uint32_t(W)) == row; ++i) {
      const ModelPixel& m = image.pixels[i];
      const int col = int(m.index % uint32_t(W));
      const glm::dvec4 v(m.p, m.g);
      for (int d = -radius; d <= radius; ++d)
        if (const int c = col + d; c >= 0 && c < W) line[size_t(c)] += taps[size_t(d + radius)] * v;
      lo = std::min(lo, std::max(0, col - radius)), hi = std::max(hi, std::min(W - 1, col + radius));
    }
    rows.push_back(row);
    row_begin.push_back(lit.size());
    for (int c = lo; c <= hi; ++c)
      if (line[size_t(c)] != glm::dvec4(0.0)) lit.push_back({c, line[size_t(c)]}), line[size_t(c)] = glm::dvec4(0.0);
  }
  row_begin.push_back(lit.size());
  // Column pass, an output row at a time from the lit rows within the radius.
  SourceImage out;
  out.photons = image.photons;
  size_t first = 0, end = 0;  // lit rows within the radius of y: [first, end)
  for (int y = std::max(0, rows.front() - radius); y < H && first < rows.size();) {
    while (first < rows.size() && rows[first] < y - radius) ++first;
    while (end < rows.size() && rows[end] <= y + radius) ++end;
    if (first == end) {  // no light within reach: on to the next lit row's reach
      if (first < rows.size()) y = std::max(y + 1, rows[first] - radius);
      continue;
    }
    int lo = W, hi = -1;
    for (size_t j = first; j < end; ++j) {
      if (row_begin[j] == row_begin[j + 1]) continue;
      const double t = taps[size_t(y - rows[j] + radius)];
      for (size_t e = row_begin[j]; e < row_begin[j + 1]; ++e) line[size_t(lit[e].col)] += t * lit[e].v;
      lo = std::min(lo, lit[row_begin[j]].col), hi = std::max(hi, lit[row_begin[j + 1] - 1].col);
    }
    for (int c = lo; c <= hi; ++c)  // row-major: sorted by index
      if (const glm::dvec4 v = line[size_t(c)]; v != glm::dvec4(0.0)) {
        out.pixels.push_back({uint32_t(y) * uint32_t(W) + uint32_t(c), v.x, glm::dvec3(v.y, v.z, v.w)});
        line[size_t(c)] = glm::dvec4(0.0);
      }
    ++y;
  }
  return out;
}

namespace {

// b and db at sorted pixels -> P = b / B and dP = (db - P dB) / B, with B
// and dB the sum of the pixels' or, where given, the sensor's.
SourceImage normalise(std::vector<ModelPixel> raw, const double* sensor_b = nullptr,
                      const glm::dvec3* sensor_db = nullptr) {
  SourceImage out;
  double total = 0;
  glm::dvec3 dtotal(0);
  for (const auto& m : raw) total += m.p, dtotal += m.g;
  if (sensor_b) total = *sensor_b, dtotal = *sensor_db;
  if (!(total > 0)) return out;
  out.photons = total;
  for (auto& m : raw) {
    m.p /= total;
    m.g = (m.g - m.p * dtotal) / total;
  }
  out.pixels = std::move(raw);
  return out;
}

// The pixels of `im` that hold light or a gradient, by index.
std::vector<ModelPixel> lit_pixels(const PixelImage& im) {
  std::vector<ModelPixel> raw;
  const size_t n = size_t(im.width) * size_t(im.height);
  for (size_t i = 0; i < n; ++i) {
    const float* v = &im.data[4 * i];
    if (v[0] != 0 || v[1] != 0 || v[2] != 0 || v[3] != 0)
      raw.push_back({uint32_t(i), double(v[0]), glm::dvec3(v[1], v[2], v[3])});
  }
  return raw;
}

class SceneModelVulkan : public SourceModel {
 public:
  SceneModelVulkan(vk::Context& ctx, const Scene& scene, const TraceSettings& t) : fw_(ctx, scene.optics, t) {}

 protected:
  std::vector<ModelPixel> render_raw(const glm::dvec3& theta) override { return lit_pixels(fw_.psf(theta)); }

 private:
  ForwardVulkan fw_;
};

class SceneModelMasked : public SourceModel {
 public:
  SceneModelMasked(vk::Context& ctx, const Scene& scene, const TraceSettings& t, const TraceSettings& photons,
                   uint64_t image_budget_bytes)
      : fw_(ctx, scene.optics, t, image_budget_bytes), photons_(ctx, scene.optics, photons), mask_(TileMask::of(fw_.grid())) {}
  void focus(std::span<const uint32_t> clicks, int reach_px) override {
    mask_ = TileMask::of(fw_.grid());
    const uint32_t W = uint32_t(fw_.grid().width);
    for (uint32_t c : clicks) mask_.mark_around(int(c % W), int(c / W), reach_px);
    // Clicks so many that their tiles outgrow an image buffer: every pixel.
    whole_ = mask_.count() > fw_.max_masked_tiles();
  }

 protected:
  std::vector<ModelPixel> render_raw(const glm::dvec3& theta) override {
    if (mask_.count() == 0) throw std::logic_error("SceneModelMasked: focus on an event's clicks before rendering");
    if (whole_) return lit_pixels(fw_.psf(theta));
    std::vector<ModelPixel> raw;
    for (const LitPixel& q : fw_.psf(theta, mask_)) raw.push_back({q.index, double(q.b), glm::dvec3(q.db)});
    return raw;
  }
  bool sensor_photons(const glm::dvec3& theta, double& b, glm::dvec3& db) override {
    if (whole_) return false;
    const PixelImage im = photons_.psf(theta);
    b = 0, db = glm::dvec3(0);
    for (size_t i = 0; i < im.data.size(); i += 4)
      b += im.data[i], db += glm::dvec3(im.data[i + 1], im.data[i + 2], im.data[i + 3]);
    return true;
  }

 private:
  ForwardVulkan fw_, photons_;
  TileMask mask_;
  bool whole_ = false;
};

class SceneModelCpu : public SourceModel {
 public:
  SceneModelCpu(const Scene& scene, const TraceSettings& t) : sys_(scene.optics), t_(t) {}

 protected:
  std::vector<ModelPixel> render_raw(const glm::dvec3& theta) override {
    ref::SparseImage im = ref::psf(sys_, t_, theta);
    std::vector<ModelPixel> raw;
    raw.reserve(im.pixels.size());
    for (const auto& [key, unused] : im.pixels) {
      auto v = im.value(key);
      raw.push_back({uint32_t(key), v[0], glm::dvec3(v[1], v[2], v[3])});
    }
    std::sort(raw.begin(), raw.end(), [](const ModelPixel& a, const ModelPixel& b) { return a.index < b.index; });
    return raw;
  }

 private:
  OpticalSystem sys_;
  TraceSettings t_;
};

}  // namespace

std::vector<SourceImage> SourceModel::render(std::span<const glm::dvec3> theta) {
  std::vector<SourceImage> out;
  for (const auto& th : theta) {
    double b;
    glm::dvec3 db;
    const bool sensor = sensor_photons(th, b, db);
    out.push_back(sensor ? normalise(render_raw(th), &b, &db) : normalise(render_raw(th)));
    ++renders_;
  }
  return out;
}

std::unique_ptr<SourceModel> make_masked_scene_model(const Scene& scene, const TraceSettings& settings,
                                                     const TraceSettings& photons_settings, vk::Context& ctx,
                                                     uint64_t image_budget_bytes) {
  if (photons_settings.rays_per_lenslet != settings.rays_per_lenslet ||
      photons_settings.stratification != settings.stratification || photons_settings.splat != settings.splat)
    throw std::invalid_argument("make_masked_scene_model: the sensor's photons need the render's own cells");
  return std::make_unique<SceneModelMasked>(ctx, scene, settings, photons_settings, image_budget_bytes);
}

std::unique_ptr<SourceModel> make_scene_model(const Scene& scene, const TraceSettings& settings, vk::Context* ctx) {
  // One render at a time, up to every pixel lit: the image with derivatives
  // (the device's) or the reference's sparse image, and the model's pixels.
  const AnalysisGrid grid = AnalysisGrid::of(scene.optics, settings.binning);
  const double px = double(grid.width) * grid.height;
  MemoryEstimate memory("the scene's model for the refinement at binning " + std::to_string(settings.binning) + " (" +
                        std::to_string(grid.width) + " x " + std::to_string(grid.height) + " px)");
  memory.add("a render's pixels, each with its gradient in double", double(sizeof(ModelPixel)) * px);
  if (!ctx) memory.add("the CPU reference's sparse image", ref::SparseImage::bytes_per_pixel * px);
  memory.add("the blur's two dense windows, 4 doubles per pixel each", 2 * sizeof(glm::dvec4) * px);
  if (ctx) memory.add("a render read back from the device, 4 floats per pixel", 16 * px);
  if (ctx) memory.add_device_buffers(double(ForwardVulkan::device_bytes_at_most(grid, settings.splat)), ctx->is_cpu());
  memory.require_within_limit("Use coarser clicks (events at a larger binning) or --model dictionary");
  if (ctx) return std::make_unique<SceneModelVulkan>(*ctx, scene, settings);
  return std::make_unique<SceneModelCpu>(scene, settings);
}

TraceSettings refine_trace_settings(unsigned binning) {
  TraceSettings t = TraceSettings::defaults_for(Splat::footprint);
  t.rays_per_lenslet = defaults::refine_rays_per_lenslet;
  t.binning = binning;
  return t;
}

RefineModel choose_refine_model(const std::string& name, const DictionaryManifest& m, bool scene_given,
                                const std::string& dictionary_dir) {
  const bool synthesised = m.rays_per_lenslet > 0;
  if (name.empty()) return synthesised || scene_given ? RefineModel::scene : RefineModel::dictionary;
  if (name == "none") return RefineModel::none;
  if (name == "dictionary") return RefineModel::dictionary;
  if (name != "scene") throw std::invalid_argument("--model " + name + ": choose scene, dictionary or none");
  if (!synthesised && !scene_given)
    throw std::runtime_error(dictionary_dir + " was calibrated, not synthesised: it names no scene to refine with; "
                             "give --scene, or --model dictionary, or --model none for the search alone");
  return RefineModel::scene;
}

std::unique_ptr<SourceModel> make_refine_model(RefineModel choice, const Scene& scene,
                                               const DictionaryReader& dictionary, int level, vk::Context* ctx) {
  switch (choice) {
    case RefineModel::scene:
      return make_scene_model(scene, refine_trace_settings(unsigned(dictionary.manifest().base_binning << level)),
                              ctx);
    case RefineModel::dictionary: return make_dictionary_model(dictionary, level);
    case RefineModel::none: break;
  }
  return nullptr;
}

std::string describe(RefineModel choice, const Scene& scene) {
  switch (choice) {
    case RefineModel::scene:
      return "scene model " + scene.name + ", footprint " + std::to_string(defaults::refine_rays_per_lenslet) +
             " cells per lenslet";
    case RefineModel::dictionary: return "dictionary model: 8 PSFs around each position, cubic shifts, blended";
    case RefineModel::none: break;
  }
  return "none: positions from the dictionary search alone";
}

RefineBounds RefineBounds::of(const Scene& scene) {
  const Volume& v = scene.volume;
  return {{v.x_min_mm, v.y_min_mm, v.depth_min_mm}, {v.x_max_mm, v.y_max_mm, v.depth_max_mm}};
}

// The unit eigenvector of the largest eigenvalue of symmetric `c` (power
// iteration from the depth axis, where the prototype's weakest direction lies).
glm::dvec3 largest_eigenvector(const glm::dmat3& c) {
  glm::dvec3 u(0, 0, 1);
  for (int i = 0; i < 100; ++i) {
    const glm::dvec3 v = c * u;
    const double len = glm::length(v);
    if (!(len > 0)) return glm::dvec3(0, 0, 1);
    u = v / len;
  }
  return u;
}

std::vector<glm::dvec2> lattice_vectors(const OpticalSystem& sys, double max_pitches) {
  const auto& ls = sys.lenslets;
  double nearest = std::numeric_limits<double>::infinity();
  for (size_t i = 0; i < ls.size(); ++i)
    for (size_t j = i + 1; j < ls.size(); ++j)
      nearest = std::min(nearest, std::hypot(ls[j].x_mm - ls[i].x_mm, ls[j].y_mm - ls[i].y_mm));
  std::vector<glm::dvec2> out;
  for (size_t i = 0; i < ls.size(); ++i)
    for (size_t j = 0; j < ls.size(); ++j) {
      glm::dvec2 d(ls[j].x_mm - ls[i].x_mm, ls[j].y_mm - ls[i].y_mm);
      if (i == j || glm::length(d) > nearest * (max_pitches + 0.01)) continue;
      bool seen = false;
      for (const auto& o : out) seen = seen || glm::length(o - d) < 1e-6 * nearest;
      if (!seen) out.push_back(d);
    }
  return out;
}

// ---------------------------------------------------------------------------
// One event's fit. Parameters: per vertex k, (x, y, depth, alpha) at 4k..4k+3.

struct Refiner::Fit {
  const Refiner* r;
  std::span<const uint32_t> clicks;  // the event's (it outlives the fit)
  size_t K;
  std::vector<glm::dvec3> theta;
  std::vector<double> alpha;
  std::vector<SourceImage> img;
  double nll = std::numeric_limits<double>::infinity();
  double blur_px = 0;  // the images blurred by a Gaussian of this sigma (the continuation's smoothed fits)

  size_t n() const { return 4 * K; }
  double param(size_t i) const { return i % 4 == 3 ? alpha[i / 4] : theta[i / 4][int(i % 4)]; }
  void set(size_t i, double v) {
    if (i % 4 == 3) alpha[i / 4] = v;
    else theta[i / 4][int(i % 4)] = v;
  }
  double lo(size_t i) const { return i % 4 == 3 ? 0.0 : r->bounds_.lo[int(i % 4)]; }
  double hi(size_t i) const { return i % 4 == 3 ? r->s_.alpha_max : r->bounds_.hi[int(i % 4)]; }

  // lambda at each click (dark included).
  std::vector<double> click_rates() const {
    std::vector<double> lam(clicks.size(), r->s_.dark_rate);
    for (size_t k = 0; k < K; ++k)
      for (size_t c = 0; c < clicks.size(); ++c)
        if (const ModelPixel* m = img[k].find(clicks[c])) lam[c] += alpha[k] * m->p;
    return lam;
  }
  // The vertex that explains click c best: the largest expected photons
  // there, above the dark rate (the first of equals); -1 for the dark.
  int owner(uint32_t c) const {
    double top = r->s_.dark_rate;
    int who = -1;
    for (size_t k = 0; k < K; ++k)
      if (const ModelPixel* m = img[k].find(c))
        if (alpha[k] * m->p > top) top = alpha[k] * m->p, who = int(k);
    return who;
  }
  double nll_now() const {
    double f = 0;
    for (size_t k = 0; k < K; ++k) f += img[k].photons > 0 ? alpha[k] : 0.0;
    for (double l : click_rates()) f -= l + ref::log_click(l);
    return f;
  }
  void render() {
    img = r->model_.render(theta);
    for (auto& i : img) i = blurred(i, blur_px, r->grid_);
    nll = nll_now();
  }
  // The same parameters, not yet rendered (a trial: its images would be
  // replaced anyway).
  Fit unrendered() const { return {r, clicks, K, theta, alpha, {}, std::numeric_limits<double>::infinity(), blur_px}; }

  // Gradient of the NLL and the binary sensor's Fisher information (n x n,
  // row-major) over every pixel any vertex reaches.
  void derivatives(std::vector<double>& grad, std::vector<double>& fisher) const {
    const size_t N = n();
    grad.assign(N, 0.0);
    fisher.assign(N * N, 0.0);
    auto lam = click_rates();
    for (size_t k = 0; k < K; ++k) {
      if (img[k].photons > 0) grad[4 * k + 3] = 1.0;
      for (size_t c = 0; c < clicks.size(); ++c)
        if (const ModelPixel* m = img[k].find(clicks[c])) {
          const double w = ref::click_weight(lam[c]);
          grad[4 * k + 3] -= m->p * w;
          for (int j = 0; j < 3; ++j) grad[4 * k + size_t(j)] -= alpha[k] * m->g[j] * w;
        }
    }
    // The union of the images' pixels: lambda and J per pixel.
    std::unordered_map<uint32_t, size_t> row;
    std::vector<double> lam_px, J;
    for (size_t k = 0; k < K; ++k)
      for (const auto& m : img[k].pixels) {
        auto [it, fresh] = row.try_emplace(m.index, lam_px.size());
        if (fresh) {
          lam_px.push_back(r->s_.dark_rate);
          J.resize(J.size() + N, 0.0);
        }
        const size_t at = it->second;
        lam_px[at] += alpha[k] * m.p;
        double* j = &J[at * N + 4 * k];
        j[0] = alpha[k] * m.g.x;
        j[1] = alpha[k] * m.g.y;
        j[2] = alpha[k] * m.g.z;
        j[3] = m.p;
      }
    for (size_t at = 0; at < lam_px.size(); ++at) {
      const double w = 1.0 / std::expm1(lam_px[at]);
      const double* j = &J[at * N];
      for (size_t a = 0; a < N; ++a) {
        if (j[a] == 0) continue;
        for (size_t b = a; b < N; ++b) fisher[a * N + b] += w * j[a] * j[b];
      }
    }
    for (size_t a = 0; a < N; ++a)
      for (size_t b = 0; b < a; ++b) fisher[a * N + b] = fisher[b * N + a];
  }
};

namespace {

// The diagonal of the inverse of SPD `A` (n x n); +inf where A is singular
// (smallest pivot below 1e-12 of the largest diagonal).
std::vector<double> inverse_diagonal(const std::vector<double>& A, size_t n) {
  double scale = 0;
  for (size_t i = 0; i < n; ++i) scale = std::max(scale, A[i * n + i]);
  std::vector<double> out(n, std::numeric_limits<double>::infinity());
  if (!(scale > 0)) return out;
  // Jacobi-scaled so that a pivot test is relative.
  std::vector<double> d(n), S(n * n);
  for (size_t i = 0; i < n; ++i) d[i] = A[i * n + i] > 0 ? 1.0 / std::sqrt(A[i * n + i]) : 0.0;
  for (size_t i = 0; i < n; ++i)
    for (size_t j = 0; j < n; ++j) S[i * n + j] = A[i * n + j] * d[i] * d[j];
  for (size_t i = 0; i < n; ++i) {
    if (d[i] == 0) return out;
    std::vector<double> e(n, 0.0);
    e[i] = 1.0;
    if (!solve_spd(S, e, n) || !(e[i] > 0) || e[i] > 1e12) return std::vector<double>(n, std::numeric_limits<double>::infinity());
    out[i] = e[i] * d[i] * d[i];
  }
  return out;
}

// The position block (rows and columns 4k..4k+2) of the inverse of SPD `A`
// (n x n): vertex k's position covariance with every other parameter as a
// nuisance. Zero when A is singular.
glm::dmat3 inverse_position_block(const std::vector<double>& A, size_t n, size_t k) {
  glm::dmat3 c(0.0);
  for (int i = 0; i < 3; ++i) {
    std::vector<double> e(n, 0.0);
    e[4 * k + size_t(i)] = 1.0;
    if (!solve_spd(A, e, n)) return glm::dmat3(0.0);
    for (int j = 0; j < 3; ++j) c[i][j] = e[4 * k + size_t(j)];
  }
  return c;
}

}  // namespace

Refiner::Refiner(SourceModel& model, const Scene& scene, const AnalysisGrid& clicks, RefineSettings settings)
    : model_(model),
      s_(settings),
      bounds_(RefineBounds::of(scene)),
      optics_(scene.optics),
      grid_(clicks),
      lattice_mm_(lattice_vectors(scene.optics)),
      rescue_lattice_mm_(lattice_vectors(scene.optics, defaults::refine_rescue_alias_pitches)) {
  if (s_.iterations < 1 || s_.alias_starts < 0 || s_.search_starts < 0 || s_.ladder_starts < 0 || s_.ladder_reach_px < 0 ||
      s_.pvalue_draws < 1 || !(s_.site_blur_px >= 0))
    throw std::invalid_argument(
        "refinement: iterations and p-value draws must be >= 1, search, alias and ladder starts, the ladder's reach and the "
        "sites' blur >= 0");
}

double binary_fit_pvalue(const std::unordered_map<uint32_t, double>& rates, std::span<const uint32_t> clicks,
                         double dark, double pixels, int draws, uint64_t seed) {
  // T = const + sum over clicked pixels of (-log p - lambda), p = 1 - exp(-lambda):
  // only the clicks' terms vary.
  auto click_term = [](double l) { return -ref::log_click(l) - l; };
  const double dark_term = click_term(dark);
  double t_obs = 0;
  for (uint32_t c : clicks) {
    auto it = rates.find(c);
    t_obs += it != rates.end() ? click_term(it->second) : dark_term;
  }
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> U(0.0, 1.0);
  const double dark_pixels = std::max(0.0, pixels - double(rates.size()));
  std::poisson_distribution<int> dark_draw(dark_pixels * -std::expm1(-dark));
  std::vector<double> t(size_t(std::max(0, draws)));
  for (double& x : t) x = double(dark_draw(rng)) * dark_term;
  // In index order, so that a seed gives one answer whatever the map's order.
  std::vector<std::pair<uint32_t, double>> lit(rates.begin(), rates.end());
  std::sort(lit.begin(), lit.end());
  for (const auto& [index, lambda] : lit) {
    const double p = -std::expm1(-lambda), term = click_term(lambda);
    if (!(p > 0)) continue;
    if (p >= 1) {
      for (double& x : t) x += term;
      continue;
    }
    // The draws where this pixel clicks: gaps of failures, floor(log V / log(1 - p)).
    const double log_q = std::log1p(-p);
    for (double d = -1;;) {
      d += 1 + std::floor(std::log(1.0 - U(rng)) / log_q);
      if (!(d < double(t.size()))) break;
      t[size_t(d)] += term;
    }
  }
  size_t at_least = 0;
  for (double x : t) at_least += x >= t_obs;
  return (1.0 + double(at_least)) / (1.0 + double(t.size()));
}

// Goodness of fit of the fitted model (binary_fit_pvalue), seeded by the event id.
double Refiner::fit_pvalue(const Fit& f, uint64_t event_id) const {
  std::unordered_map<uint32_t, double> lam;
  for (size_t k = 0; k < f.K; ++k)
    for (const auto& m : f.img[k].pixels) lam.try_emplace(m.index, s_.dark_rate).first->second += f.alpha[k] * m.p;
  return binary_fit_pvalue(lam, f.clicks, s_.dark_rate, double(grid_.width) * double(grid_.height), s_.pvalue_draws,
                           0x9e3779b97f4a7c15ull ^ event_id);
}

Refiner::LocalFit Refiner::local_fit(const Event& event, const glm::dvec3& at, double alpha) {
  if (event.clicks.empty()) return {};
  Fit f{this, event.clicks, 1, {glm::clamp(at, bounds_.lo, bounds_.hi)}, {std::clamp(alpha, 0.0, s_.alpha_max)}, {}, {}, 0};
  f.render();
  levenberg_marquardt(f, s_.iterations);
  return {f.theta[0], f.alpha[0], f.nll};
}

std::vector<ReconstructedVertex> Refiner::refine(const Event& event, std::vector<ReconstructedVertex> rows) {
  constexpr int kProbeSteps = 4;            // LM steps before a start is judged
  constexpr double kDistinctStartMm = 1.0;  // starts closer than this to one tried are skipped
  // The lattice scan's sites are tried moved by up to this many click-grid
  // pixels: 0.2 mm of source at the face (magnification 3.7) for 110 um pixels.
  constexpr int kLatticeReachPx = 6;
  const auto start_time = std::chrono::steady_clock::now();
  ++stats_.events;
  const std::vector<size_t> live = live_rows(rows);
  if (live.empty() || event.clicks.empty()) return rows;
  Fit f = first_fit(event, rows, live);

  // Further starts per vertex, the others held where they are: the search's
  // runners-up (other planes and nodes), the lattice aliases of the current
  // estimate and its ladder. Each is probed for a few steps; one that has overtaken
  // the best is followed to convergence.
  // With blur_px > 0 the start is fitted with blurred images first (the
  // sharp likelihood's cliffs stop a start a few tenths of a mm off), then
  // probed sharp like any other.
  auto try_start = [&](size_t k, glm::dvec3 at, double alpha, double blur_px = 0) {
    Fit g = f.unrendered();
    g.theta[k] = glm::clamp(at, bounds_.lo, bounds_.hi);
    g.alpha[k] = std::min(alpha, s_.alpha_max);
    ++stats_.starts;
    if (blur_px > 0) {
      g.blur_px = blur_px;
      g.render();
      stats_.iterations += uint64_t(levenberg_marquardt(g, s_.iterations));
      g.blur_px = 0;
    }
    g.render();
    int taken = levenberg_marquardt(g, std::min(s_.iterations, kProbeSteps));
    if (g.nll < f.nll && taken == kProbeSteps) taken += levenberg_marquardt(g, s_.iterations - taken);
    stats_.iterations += uint64_t(taken);
    if (g.nll < f.nll) f = std::move(g);
  };
  // Candidates for vertex k scored with the weight refitted (one render
  // each); the best `n` are probed. With reach_px > 0 each image is also
  // tried moved by up to that many whole pixels (a source moved laterally by
  // -shift / magnification, near enough), and the candidate moved with the
  // best: sites predicted a few tenths of a mm off, where sharp images
  // near the face score as badly as wrong ones.
  // With blur_px > 0 the images of candidates shallower than
  // always_scan_below_mm, or of any candidate in an event of few clicks, are scored
  // blurred by it, and the best of them fitted blurred first (try_start).
  const bool few_clicks = event.clicks.size() < size_t(std::max(0, s_.always_scan_below_clicks));
  auto blur_at = [&](const glm::dvec3& at, double blur_px) {
    return at.z < s_.always_scan_below_mm || few_clicks ? blur_px : 0.0;
  };
  auto probe_best = [&](size_t k, std::vector<glm::dvec3> cand, int n, int reach_px = 0, double blur_px = 0) {
    if (cand.empty() || n <= 0) return;
    auto imgs = model_.render(cand);
    for (size_t j = 0; j < cand.size(); ++j)
      if (const double b = blur_at(cand[j], blur_px); b > 0) imgs[j] = blurred(imgs[j], b, grid_);
    Fit others = f;
    others.alpha[k] = 0;
    const auto background = others.click_rates();
    std::vector<std::tuple<double, size_t, double>> scored;  // NLL, candidate, alpha
    std::vector<double> p(f.clicks.size());
    for (size_t j = 0; j < cand.size(); ++j) {
      if (!(imgs[j].photons > 0)) continue;
      std::tuple<double, size_t, double> best{std::numeric_limits<double>::infinity(), j, 0.0};
      glm::ivec2 best_shift(0);
      for (int sy = -reach_px; sy <= reach_px; ++sy)
        for (int sx = -reach_px; sx <= reach_px; ++sx) {
          for (size_t c = 0; c < f.clicks.size(); ++c) {
            const int col = int(f.clicks[c] % uint32_t(grid_.width)) - sx, row = int(f.clicks[c] / uint32_t(grid_.width)) - sy;
            const ModelPixel* m = col >= 0 && row >= 0 && col < grid_.width && row < grid_.height
                                      ? imgs[j].find(uint32_t(row) * uint32_t(grid_.width) + uint32_t(col))
                                      : nullptr;
            p[c] = m ? m->p : 0.0;
          }
          std::vector<double> a{f.alpha[k]};
          const std::vector<double>* cols[] = {&p};
          const double one = 1.0;
          const double nll = ref::fit_weights(cols, std::span<const double>(&one, 1), background, a, 60, s_.alpha_max);
          if (nll < std::get<0>(best)) best = {nll, j, a[0]}, best_shift = {sx, sy};
        }
      if (best_shift != glm::ivec2(0))
        cand[j] = glm::clamp(cand[j] - glm::dvec3(glm::dvec2(best_shift) * grid_.pixel_mm /
                                                      optics_.magnification(cand[j].z), 0.0),
                             bounds_.lo, bounds_.hi);
      scored.push_back(best);
    }
    std::sort(scored.begin(), scored.end());
    for (size_t t = 0; t < scored.size() && t < size_t(n); ++t)
      try_start(k, cand[std::get<1>(scored[t])], std::get<2>(scored[t]), blur_at(cand[std::get<1>(scored[t])], blur_px));
  };
  auto inside = [&](glm::dvec3 a) {
    return glm::all(glm::greaterThanEqual(a, bounds_.lo)) && glm::all(glm::lessThanEqual(a, bounds_.hi));
  };
  // Lattice aliases of vertex k (OpticalSystem::alias_scale).
  auto aliases = [&](size_t k, const std::vector<glm::dvec2>& lattice, auto&& is_new) {
    std::vector<glm::dvec3> cand;
    const double scale = optics_.alias_scale(f.theta[k].z);
    for (const auto& v : lattice) {
      glm::dvec3 a = f.theta[k] + glm::dvec3(v * scale, 0.0);
      if (inside(a) && is_new(a)) cand.push_back(a);
    }
    return cand;
  };
  const bool use_aliases = s_.aliases && !lattice_mm_.empty() && s_.alias_starts > 0;
  for (size_t k = 0; k < f.K; ++k) {
    std::vector<glm::dvec3> tried{f.theta[k]};
    auto is_new = [&](glm::dvec3 p) {
      for (const auto& t : tried)
        if (glm::length(p - t) < kDistinctStartMm) return false;
      return true;
    };
    int taken = 0;
    for (const glm::dvec4& r : rows[live[k]].runners_up) {
      if (taken >= s_.search_starts) break;
      const glm::dvec3 p(r);
      if (!is_new(p)) continue;
      tried.push_back(p);
      ++taken;
      try_start(k, p, r.w);
    }
    if (use_aliases) probe_best(k, aliases(k, lattice_mm_, is_new), s_.alias_starts);
    if (s_.ladder_starts > 0) {
      // The ladder: the converged estimate moved along its weakest direction
      // (the position covariance's principal axis, mostly depth) and along
      // depth itself, where the likelihood's other optima lie a millimetre or
      // two away (docs/reconstruction.md).
      std::vector<double> grad, fisher;
      f.derivatives(grad, fisher);
      glm::dvec3 weakest = largest_eigenvector(inverse_position_block(fisher, f.n(), k));
      std::vector<glm::dvec3> cand;
      for (const glm::dvec3& u : {weakest, glm::dvec3(0, 0, 1)})
        for (int j = 1; j <= defaults::refine_ladder_rungs; ++j)
          for (double sign : {-1.0, 1.0}) {
            const glm::dvec3 a = f.theta[k] + u * (sign * j * defaults::refine_ladder_step_mm);
            if (inside(a)) cand.push_back(a);
          }
      probe_best(k, cand, s_.ladder_starts, s_.ladder_reach_px);
    }
  }

  if (f.K > 1 && s_.reseed) {
    // The re-seed (K > 1): the search adds vertices greedily, and a vertex
    // it placed on light another one half explains can leave a source
    // unclaimed, while the leftover vertex sits on stray clicks far off,
    // where its own runners-up, aliases and rungs stay. The unclaimed
    // source is often among the runners-up of another vertex's scan (both
    // sources scored there). So each vertex in turn is tried at every
    // vertex's runners-up, scored against what the others explain. The
    // fit's p-value cannot gate this: a deep vertex's wide faint images can
    // stand in for a missing source well enough to pass.
    ++stats_.reseeds;
    std::vector<glm::dvec3> pool;
    for (size_t k : live)
      for (const glm::dvec4& r : rows[k].runners_up) pool.push_back(glm::dvec3(r));
    for (size_t k = 0; k < f.K; ++k) {
      std::vector<glm::dvec3> cand;
      for (const glm::dvec3& p : pool) {
        bool taken = false;  // by a vertex already
        for (size_t j = 0; j < f.K; ++j) taken = taken || glm::length(p - f.theta[j]) < kDistinctStartMm;
        if (!taken && inside(p)) cand.push_back(p);
      }
      probe_best(k, cand, s_.search_starts, kLatticeReachPx, s_.site_blur_px);
    }
  }
  double pvalue = fit_pvalue(f, event.id);
  if (pvalue < defaults::fit_pvalue_flag && s_.rescue && use_aliases && !rescue_lattice_mm_.empty()) {
    // Rescue of a poor fit: near the face the lenslet images lie about a
    // sensor width apart and the search also confuses sources two pitches
    // apart; the aliases of the estimate out to 2 pitches are probed only
    // here, where they can pay.
    ++stats_.rescues;
    for (size_t k = 0; k < f.K; ++k)
      probe_best(k, aliases(k, rescue_lattice_mm_, [](glm::dvec3) { return true; }), s_.alias_starts);
    pvalue = fit_pvalue(f, event.id);
  }
  auto scan_always = [&] {  // a vertex shallower than always_scan_below_mm, or an event of few clicks
    bool any = few_clicks;
    for (size_t k = 0; k < f.K; ++k) any = any || f.theta[k].z < s_.always_scan_below_mm;
    return any;
  };
  // Vertex k moved to `at` (a voted position, a few tenths of a mm off a
  // site of the alias lattice) and fitted there, so that it lands on that
  // site's optimum; from it every other site of the lattice inside the field
  // gets a render and the best are probed.
  glm::dvec2 lat_a{}, lat_b{};
  if (!lattice_mm_.empty()) {
    lat_a = lattice_mm_[0];
    for (const auto& v : lattice_mm_)
      if (std::abs(lat_a.x * v.y - lat_a.y * v.x) > 1e-6 * glm::dot(lat_a, lat_a)) lat_b = v;
  }
  auto scan_sites = [&](size_t k, glm::dvec3 voted) {
    Fit g = f.unrendered();
    g.theta[k] = voted;
    g.render();
    ++stats_.starts;
    stats_.iterations += uint64_t(levenberg_marquardt(g, s_.iterations));
    const glm::dvec3 at = g.theta[k];
    if (g.nll < f.nll) f = std::move(g);
    const double scale = optics_.alias_scale(at.z);
    const glm::dvec2 sa = lat_a * scale, sb = lat_b * scale;
    // Sites i a + j b around it (j = 0 for a single row of lenslets):
    // enough of them to cover the field.
    const double field = glm::length(glm::dvec2(bounds_.hi - bounds_.lo));
    const double spacing = lat_b == glm::dvec2(0)
                                ? glm::length(sa)
                                : std::abs(sa.x * sb.y - sa.y * sb.x) / std::max(glm::length(sa), glm::length(sb));
    const int n = int(std::ceil(field / spacing)), n_b = lat_b == glm::dvec2(0) ? 0 : n;
    std::vector<glm::dvec3> sites;
    for (int i = -n; i <= n; ++i)
      for (int j = -n_b; j <= n_b; ++j) {
        const glm::dvec3 site = at + glm::dvec3(double(i) * sa + double(j) * sb, 0.0);
        if ((i != 0 || j != 0) && inside(site)) sites.push_back(site);
      }
    probe_best(k, sites, s_.alias_starts, kLatticeReachPx, s_.site_blur_px);
  };
  // The clicks vertex k may claim: those no other vertex explains better
  // than it does (all of them for K = 1).
  auto unclaimed_clicks = [&](size_t k) {
    std::vector<uint32_t> out;
    for (uint32_t c : f.clicks)
      if (const int who = f.owner(c); who < 0 || size_t(who) == k) out.push_back(c);
    return out;
  };
  if ((pvalue < defaults::refine_lattice_scan_pvalue || scan_always()) && s_.lattice_scan && !lattice_mm_.empty()) {
    // The lattice scan: near the face the search can miss the source's
    // depth altogether (click_geometry.h). The votes of the clicks vertex k
    // may claim give a depth and one site of the alias lattice: the vertex
    // is tried there and on the lattice's other sites (scan_sites). With
    // K > 1 the clicks the other vertices explain are left out, so that a
    // vertex the search left on stray light is sent to the source nobody
    // claims, not to the brightest. The next best voted depth is tried
    // while the fit stays poor or marginal and the depth before it
    // improved the fit: a fit that is poor for another reason (a biased
    // model, clicks the model does not expect) costs one depth. An
    // estimate shallower than always_scan_below_mm, or with fewer clicks
    // than always_scan_below_clicks, gets the best voted depth whatever its
    // fit: near the face, and at any depth with few clicks, a wrong site can
    // fit as well as the model expects (defaults.h).
    ++stats_.lattice_scans;
    // Vertex k's q-th voted position, from the clicks the others leave now.
    auto voted = [&](size_t k, size_t q) -> std::optional<glm::dvec3> {
      auto peaks = vote_source_positions(optics_, grid_, unclaimed_clicks(k), bounds_.lo, bounds_.hi, q + 1);
      if (q < peaks.size()) return peaks[q].position_mm;
      return std::nullopt;
    };
    for (size_t q = 0; q < size_t(defaults::refine_lattice_scan_depths) &&
                       (q == 0 || pvalue < defaults::refine_lattice_scan_pvalue);
         ++q) {
      const double nll_before = f.nll;
      ++stats_.lattice_depths;
      // With K > 1 a vertex's votes change when another one moves: one
      // scanned while the others were still wrong voted with their light.
      // So the pass over the vertices is repeated, with fresh votes, while
      // it improves the fit (at most K passes).
      bool voted_any = false;
      for (size_t pass = 0; pass < f.K; ++pass) {
        const double pass_before = f.nll;
        for (size_t k = 0; k < f.K; ++k)
          if (auto at = voted(k, q)) {
            voted_any = true;
            scan_sites(k, *at);
          }
        if (!(f.nll < pass_before)) break;
      }
      if (!voted_any || !(f.nll < nll_before)) break;
      pvalue = fit_pvalue(f, event.id);
    }
  }

  // The best fit followed to convergence: a start adopted late (the
  // lattice scan's, a rung's) may have spent its steps before it stopped
  // improving. Near the face a start 0.5 mm off in depth took 19-20 steps.
  if (const int polish = levenberg_marquardt(f, s_.iterations); polish > 0) {
    stats_.iterations += uint64_t(polish);
    pvalue = fit_pvalue(f, event.id);
  }
  // The continuation: the geometric images have hard edges, so a click
  // that an image's edge leaves costs up to -log(dark_rate) at once, and the
  // likelihood near the face (and with few clicks at any depth) is a
  // staircase of such cliffs, which a local step cannot see across. Fitted again with
  // the images blurred (the cliffs become slopes), then less, then not, from
  // the estimate; kept if the unblurred NLL is lower.
  if (s_.continuation && scan_always() && continuation(f, f, defaults::refine_continuation_blur_px))
    pvalue = fit_pvalue(f, event.id);

  finish(f, live, rows, pvalue);
  stats_.seconds += std::chrono::duration<double>(std::chrono::steady_clock::now() - start_time).count();
  return rows;
}

bool Refiner::continuation(Fit& f, Fit g, std::span<const double> blur_px) {
  for (double sigma : blur_px) {
    g.blur_px = sigma;
    g.render();
    stats_.iterations += uint64_t(levenberg_marquardt(g, s_.iterations));
  }
  g.blur_px = 0;
  g.render();
  stats_.iterations += uint64_t(levenberg_marquardt(g, s_.iterations));
  ++stats_.continuations;
  if (!(g.nll < f.nll)) return false;
  ++stats_.continuations_kept;
  f = std::move(g);
  return true;
}

std::vector<size_t> Refiner::live_rows(const std::vector<ReconstructedVertex>& rows) {
  std::vector<size_t> live;  // the vertices the search gave light to
  for (size_t k = 0; k < rows.size(); ++k)
    if (!(rows[k].flags & (no_clicks | alpha_zero)) && rows[k].alpha > 0) live.push_back(k);
  return live;
}

Refiner::Fit Refiner::start_fit(const Event& event, const std::vector<ReconstructedVertex>& rows,
                                const std::vector<size_t>& live) const {
  Fit f{this, event.clicks, live.size(), {}, {}, {}, std::numeric_limits<double>::infinity(), 0};
  for (size_t k : live) {
    const auto& v = rows[k];
    f.theta.push_back(glm::clamp(glm::dvec3(v.x_mm, v.y_mm, v.depth_mm), bounds_.lo, bounds_.hi));
    f.alpha.push_back(std::min(v.alpha, s_.alpha_max));
  }
  return f;
}

Refiner::Fit Refiner::first_fit(const Event& event, const std::vector<ReconstructedVertex>& rows,
                                const std::vector<size_t>& live) {
  Fit f = start_fit(event, rows, live);
  f.render();
  ++stats_.starts;
  stats_.iterations += uint64_t(levenberg_marquardt(f, s_.iterations));
  return f;
}

void Refiner::finish(const Fit& f, const std::vector<size_t>& live, std::vector<ReconstructedVertex>& rows,
                     double pvalue) const {
  // CRLB at the estimate: the inverse of the full Fisher information (all
  // vertices' positions and weights), diagonal.
  std::vector<double> grad, fisher;
  f.derivatives(grad, fisher);
  const auto inv = inverse_diagonal(fisher, f.n());
  auto variance_3d = [&](size_t k) { return inv[4 * k] + inv[4 * k + 1] + inv[4 * k + 2]; };

  // Rows: refined positions, weights, CRLB; flags redone where the
  // refinement decides them (edge, merged, poor_fit, alpha_*).
  std::vector<uint32_t> owned(f.K, 0);
  for (uint32_t c : f.clicks)
    if (const int who = f.owner(c); who >= 0) ++owned[size_t(who)];
  for (size_t j = 0; j < f.K; ++j) {
    ReconstructedVertex& o = rows[live[j]];
    o.x_mm = f.theta[j].x;
    o.y_mm = f.theta[j].y;
    o.depth_mm = f.theta[j].z;
    o.alpha = f.alpha[j];
    o.nll = f.nll;
    o.clicks = owned[j];
    o.refined = true;
    o.crlb_x_mm = std::sqrt(inv[4 * j]);
    o.crlb_y_mm = std::sqrt(inv[4 * j + 1]);
    o.crlb_z_mm = std::sqrt(inv[4 * j + 2]);
    o.crlb_3d_mm = std::sqrt(variance_3d(j));
    o.fit_pvalue = pvalue;
    o.flags &= ~uint32_t(edge | merged | poor_fit | alpha_zero | alpha_at_bound);
    // On the field's boundary within one CRLB: the source may lie beyond it.
    bool on_bound = false;
    for (int a = 0; a < 3; ++a) {
      const double sigma = std::sqrt(inv[4 * j + size_t(a)]);
      on_bound = on_bound || f.theta[j][a] - bounds_.lo[a] <= sigma || bounds_.hi[a] - f.theta[j][a] <= sigma;
    }
    if (on_bound) o.flags |= edge;
    if (f.alpha[j] <= 0 || f.img[j].photons <= 0) o.flags |= alpha_zero;
    if (f.alpha[j] >= s_.alpha_max * (1 - 1e-12)) o.flags |= alpha_at_bound;
    if (pvalue < defaults::fit_pvalue_flag) o.flags |= poor_fit;
    for (size_t i = 0; i < f.K; ++i)
      if (i != j && glm::length(f.theta[i] - f.theta[j]) < std::sqrt(std::max(variance_3d(i), variance_3d(j))))
        o.flags |= merged;
  }
}

std::vector<ReconstructedVertex> Refiner::polish(const Event& event, std::vector<ReconstructedVertex> rows,
                                                 std::span<const double> blur_px) {
  const auto start_time = std::chrono::steady_clock::now();
  ++stats_.events;
  const std::vector<size_t> live = live_rows(rows);
  if (live.empty() || event.clicks.empty()) return rows;
  // Straight from the start, and through the blurred images (the
  // continuation of refine()), the lower NLL kept.
  Fit f = first_fit(event, rows, live);
  if (!blur_px.empty()) continuation(f, start_fit(event, rows, live), blur_px);
  finish(f, live, rows, fit_pvalue(f, event.id));
  stats_.seconds += std::chrono::duration<double>(std::chrono::steady_clock::now() - start_time).count();
  return rows;
}

int refine_level(const DictionaryManifest& m, int click_level, int requested) {
  if (requested >= 0) return requested;
  int level = click_level;
  while (level + 1 < m.levels && (m.base_binning << level) < defaults::refine_pixel_sensor_px) ++level;
  return level;
}

void check_refine_level(const DictionaryManifest& m, int click_level, int refine_level) {
  if (refine_level < click_level || refine_level >= m.levels)
    throw std::invalid_argument("--refine-level " + std::to_string(refine_level) + ": choose " +
                                std::to_string(click_level) + " (the clicks' own) to " + std::to_string(m.levels - 1));
}

Refinement::Refinement(RefineModel choice, const Scene& scene, const DictionaryReader& dictionary, int click_level,
                       int refine_level, vk::Context* ctx, const RefineSettings& settings)
    : click_level_(click_level), refine_level_(refine_level) {
  const auto& m = dictionary.manifest();
  check_refine_level(m, click_level, refine_level);
  click_width_ = uint32_t(m.level_width(click_level));
  refine_width_ = uint32_t(m.level_width(refine_level));
  coarse_model_ = make_refine_model(choice, scene, dictionary, refine_level, ctx);
  if (!coarse_model_) throw std::logic_error("Refinement: no model to refine with (--model none)");
  coarse_ = std::make_unique<Refiner>(*coarse_model_, scene, m.level_grid(refine_level), settings);
  if (refine_level == click_level) return;
  // On the device the scene's model renders only around each event's
  // clicks (focus, in refine and local_fit), with the sensor's light from
  // the refine level's whole render.
  fine_focused_ = choice == RefineModel::scene && ctx;
  if (fine_focused_)
    fine_model_ = make_masked_scene_model(scene, refine_trace_settings(m.base_binning << click_level),
                                          refine_trace_settings(m.base_binning << refine_level), *ctx);
  else
    fine_model_ = make_refine_model(choice, scene, dictionary, click_level, ctx);
  polish_ = std::make_unique<Refiner>(*fine_model_, scene, m.level_grid(click_level), settings);
  for (double sigma : defaults::refine_polish_blur_refine_px) polish_blur_px_.push_back(sigma * (1 << (refine_level - click_level)));
  // Every pixel a blurred image's value at a click sums (blurred's radius).
  focus_reach_px_ = int(std::ceil(defaults::refine_blur_radius_sigmas *
                                  *std::max_element(polish_blur_px_.begin(), polish_blur_px_.end()))) + 1;
}

Refinement::~Refinement() = default;

std::vector<ReconstructedVertex> Refinement::refine(const Event& event, std::vector<ReconstructedVertex> rows) {
  if (!polish_) return coarse_->refine(event, std::move(rows));
  Event binned = event;
  binned.clicks = binned_clicks(event.clicks, click_width_, refine_level_ - click_level_, refine_width_);
  const std::vector<ReconstructedVertex> coarse = coarse_->refine(binned, std::move(rows));
  fine_model_->focus(event.clicks, focus_reach_px_);
  std::vector<ReconstructedVertex> out = polish_->polish(event, coarse, polish_blur_px_);
  // A focused model's draws would fall in the clicks' tiles alone, all the
  // event's clicks do: its p-value would not test the fit. The coarse
  // level's does (every pixel, the same clicks binned).
  if (fine_focused_)
    for (size_t i = 0; i < out.size(); ++i) {
      out[i].fit_pvalue = coarse[i].fit_pvalue;
      out[i].flags = (out[i].flags & ~uint32_t(poor_fit)) | (coarse[i].flags & uint32_t(poor_fit));
    }
  return out;
}

Refiner::LocalFit Refinement::local_fit(const Event& event, const glm::dvec3& at, double alpha) {
  if (!polish_) return coarse_->local_fit(event, at, alpha);
  fine_model_->focus(event.clicks, focus_reach_px_);
  return polish_->local_fit(event, at, alpha);
}

RefineStats Refinement::stats() const {
  RefineStats r = coarse_->stats();
  if (polish_) r.seconds += polish_->stats().seconds;
  return r;
}

uint64_t Refinement::renders() const {
  return coarse_model_->renders() + (fine_model_ ? fine_model_->renders() : 0);
}

}  // namespace prism
