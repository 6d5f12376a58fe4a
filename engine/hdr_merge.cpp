#include "engine/hdr_merge.h"

#include <algorithm>
#include <cmath>
#include <span>
#include <stdexcept>

#include "engine/hdr_shared.h"
#include "engine/vk/compute.h"
#include "engine/vk/error.h"
#include "spv/hdr_merge.spv.h"

namespace prism {

namespace {

constexpr uint32_t kGroup = 64;           // local_size_x of hdr_merge.comp
constexpr size_t kStatsSamples = 1 << 20; // pixels sampled for frame statistics: plenty for a median

static_assert(kHdrReasons == shared::HDR_REASON_COUNT, "HdrReason must list the kernel's reasons");

double median_of(std::vector<double> v) {
  if (v.empty()) return 0;
  auto mid = v.begin() + v.size() / 2;
  std::nth_element(v.begin(), mid, v.end());
  return *mid;
}

// 1.4826 * median absolute deviation: a standard deviation that outliers
// (hot pixels, the PSF itself) do not move.
double robust_sigma(const std::vector<double>& v, double centre) {
  std::vector<double> dev(v.size());
  for (size_t i = 0; i < v.size(); ++i) dev[i] = std::abs(v[i] - centre);
  return 1.4826 * median_of(dev);
}

// RMS about `centre` of the values within `clip` of it: the MAD of integer
// data is too coarse a noise estimate on its own.
double clipped_rms(const std::vector<double>& v, double centre, double clip) {
  double s = 0;
  size_t n = 0;
  for (double x : v)
    if (std::abs(x - centre) <= clip) {
      s += (x - centre) * (x - centre);
      ++n;
    }
  return n ? std::sqrt(s / double(n)) : 0.0;
}

bool same_time(double a, double b) { return std::abs(a - b) <= 1e-9 * std::max(a, b); }

size_t distinct_times(std::vector<double> t) {
  std::sort(t.begin(), t.end());
  return size_t(std::unique(t.begin(), t.end(), same_time) - t.begin());
}

}  // namespace

void HdrOptions::validate() const {
  auto bad = [](const std::string& what) { throw std::invalid_argument("HDR merge option " + what); };
  if (min_valid_exposures < 2 || min_valid_exposures > shared::HDR_MAX_EXPOSURES)
    bad("--min-valid must be 2..16 (a correlation needs at least two points)");
  if (!(min_correlation >= -1 && min_correlation <= 1)) bad("--min-correlation must be in -1..1");
  if (!(saturation_margin >= 0 && saturation_margin <= 0.5)) bad("--saturation-margin must be in 0..0.5");
  if (!(floor_sigmas >= 0)) bad("--floor-sigmas must be >= 0");
  if (!(floor_min_dn >= 0)) bad("--floor-min-dn must be >= 0");
  if (!(hot_dark_spreads > 0)) bad("--hot-dark-spreads must be > 0");
  if (dark_model != "auto" && dark_model != "linear" && dark_model != "constant")
    bad("--dark-model must be auto, linear or constant, not '" + dark_model + "'");
}

void HdrFrames::validate() const {
  auto bad = [&](const std::string& what) { throw std::invalid_argument(name + ": " + what); };
  if (width <= 0 || height <= 0) bad("empty frame size " + std::to_string(width) + " x " + std::to_string(height));
  if (bit_depth < 1 || bit_depth > 16) bad("bit_depth " + std::to_string(bit_depth) + " is not 1..16");
  if (exposures.empty() || exposures.size() != exposure_s.size()) bad("exposure frames and times do not match");
  if (exposures.size() > shared::HDR_MAX_EXPOSURES)
    bad(std::to_string(exposures.size()) + " exposures; the merge takes at most 16");
  if (darks.empty() || darks.size() != dark_s.size()) bad("needs at least one dark frame, with its time");
  if (darks.size() > shared::HDR_MAX_DARKS) bad(std::to_string(darks.size()) + " darks; the merge takes at most 64");
  for (size_t j = 0; j < exposures.size(); ++j) {
    if (exposures[j].size() != pixels()) bad("exposure " + std::to_string(j) + " is not " + std::to_string(width) +
                                             " x " + std::to_string(height));
    if (!(exposure_s[j] > 0)) bad("exposure " + std::to_string(j) + " has a time <= 0");
  }
  for (size_t k = 0; k < darks.size(); ++k) {
    if (darks[k].size() != pixels())
      bad("dark " + std::to_string(k) + " is not " + std::to_string(width) + " x " + std::to_string(height));
    if (!(dark_s[k] > 0)) bad("dark " + std::to_string(k) + " has a time <= 0");
  }
}

HdrDarkStats hdr_dark_stats(const HdrFrames& f) {
  HdrDarkStats s;
  s.longest_s = *std::max_element(f.dark_s.begin(), f.dark_s.end());
  std::vector<const std::vector<uint16_t>*> longest;
  for (size_t k = 0; k < f.darks.size(); ++k)
    if (same_time(f.dark_s[k], s.longest_s)) longest.push_back(&f.darks[k]);
  size_t stride = std::max<size_t>(1, f.pixels() / kStatsSamples);
  std::vector<double> level, diff;
  for (size_t i = 0; i < f.pixels(); i += stride) {
    double sum = 0;
    for (auto* d : longest) sum += (*d)[i];
    level.push_back(sum / double(longest.size()));
    if (longest.size() >= 2) diff.push_back(double((*longest[0])[i]) - double((*longest[1])[i]));
  }
  s.median_dn = median_of(level);
  s.spread_dn = robust_sigma(level, s.median_dn);
  if (diff.empty()) {
    // One dark frame: its spatial spread (noise plus fixed pattern) bounds the noise from above.
    s.read_noise_dn = clipped_rms(level, s.median_dn, 6 * std::max(s.spread_dn, 1.0));
  } else {
    // Two frames of the same time: their difference is pure temporal noise, sqrt(2) times one frame's.
    double centre = median_of(diff);
    s.read_noise_dn = clipped_rms(diff, centre, 6 * std::max(robust_sigma(diff, centre), 1.0)) / std::sqrt(2.0);
  }
  return s;
}

HdrLimits hdr_limits(const HdrFrames& f, const HdrOptions& o, const HdrDarkStats& s) {
  HdrLimits l;
  l.saturation_dn = (1.0 - o.saturation_margin) * double((1u << f.bit_depth) - 1u);
  l.floor_dn = std::max(o.floor_min_dn, o.floor_sigmas * s.read_noise_dn);
  // The spread is at least one quantisation step, or a noise-free dark would call every pixel above the median hot.
  l.hot_dark_dn = s.median_dn + o.hot_dark_spreads * std::max(s.spread_dn, 1.0);
  size_t times = distinct_times(f.dark_s);
  if (o.dark_model == "linear" && times < 2)
    throw std::invalid_argument(f.name + ": --dark-model linear needs darks at two or more exposure times; "
                                "these are all at " + std::to_string(f.dark_s[0] * 1e6) + " us");
  l.dark_linear = o.dark_model == "linear" || (o.dark_model == "auto" && times >= 2);
  return l;
}

HdrSetup hdr_setup(const HdrFrames& f, const HdrOptions& o) {
  o.validate();
  f.validate();
  if (f.exposures.size() < o.min_valid_exposures)
    throw std::invalid_argument(f.name + ": " + std::to_string(f.exposures.size()) + " exposures, fewer than " +
                                "--min-valid " + std::to_string(o.min_valid_exposures));
  HdrSetup s;
  s.dark = hdr_dark_stats(f);
  s.limits = hdr_limits(f, o, s.dark);
  return s;
}

const char* to_string(HdrReason r) {
  switch (r) {
    case HdrReason::kept: return "kept";
    case HdrReason::hot_dark: return "hot_dark";
    case HdrReason::saturated: return "saturated";
    case HdrReason::faint: return "faint";
    case HdrReason::nonlinear: return "nonlinear";
  }
  return "unknown";
}

HdrResult hdr_finish(const HdrFrames& f, std::vector<float> estimate, std::vector<uint32_t> status,
                     const HdrDarkStats& dark, const HdrLimits& limits) {
  HdrResult r;
  r.width = f.width;
  r.height = f.height;
  r.dark = dark;
  r.limits = limits;
  r.kept_using_exposure.assign(f.exposures.size(), 0);
  for (size_t i = 0; i < status.size(); ++i) {
    HdrReason why = HdrResult::reason(status[i]);
    r.pixels_by_reason[size_t(why)]++;
    if (why != HdrReason::kept) continue;
    r.sum_dn_per_s += estimate[i];
    for (size_t j = 0; j < f.exposures.size(); ++j) r.kept_using_exposure[j] += (status[i] >> (16 + j)) & 1u;
  }
  if (!(r.sum_dn_per_s > 0)) {
    auto n = [&](HdrReason why) { return std::to_string(r.pixels_by_reason[size_t(why)]); };
    throw std::runtime_error(f.name + ": no pixel kept (" + n(HdrReason::saturated) + " saturated, " +
                             n(HdrReason::faint) + " faint, " + n(HdrReason::hot_dark) + " hot, " +
                             n(HdrReason::nonlinear) + " non-linear): if saturated, shorten the exposures; if "
                             "faint, lengthen them or lower --floor-min-dn");
  }
  double inv = 1.0 / r.sum_dn_per_s;
  for (size_t i = 0; i < estimate.size(); ++i) estimate[i] = float(double(estimate[i]) * inv);
  r.psf = std::move(estimate);
  r.status = std::move(status);
  return r;
}

struct HdrMergeVulkan::Impl {
  vk::Context& ctx;
  uint64_t budget;
  vk::Kernel kernel;
  Impl(vk::Context& c, uint64_t b)
      : ctx(c), budget(b), kernel(c, "hdr_merge", std::span<const uint32_t>(spv_hdr_merge, std::size(spv_hdr_merge)), 4,
                                  sizeof(shared::HdrParams)) {}
};

HdrMergeVulkan::HdrMergeVulkan(vk::Context& ctx, uint64_t budget) : impl_(std::make_unique<Impl>(ctx, budget)) {}
HdrMergeVulkan::~HdrMergeVulkan() = default;

HdrResult HdrMergeVulkan::merge(const HdrFrames& f, const HdrOptions& o) {
  const auto [dark, limits] = hdr_setup(f, o);
  vk::Context& ctx = impl_->ctx;

  // Bands of rows so that all frames of one band fit in one storage buffer.
  const uint32_t width = uint32_t(f.width);
  const uint32_t n_exp = uint32_t(f.exposures.size()), n_frames = n_exp + uint32_t(f.darks.size());
  const uint64_t cap = std::min<uint64_t>(impl_->budget, ctx.max_storage_buffer_bytes());
  const uint64_t row_bytes = uint64_t(n_frames) * width * 2;
  const uint64_t pad_bytes = uint64_t(n_frames) * 4;  // each frame rounded up to whole words
  if (cap < row_bytes + pad_bytes)
    throw vk::Error(f.name + ": one row of all " + std::to_string(n_frames) + " frames (" + std::to_string(row_bytes) +
                    " bytes) does not fit the " + std::to_string(cap) + "-byte buffer budget");
  const uint32_t band_rows = uint32_t(std::min<uint64_t>({uint64_t(f.height), (cap - pad_bytes) / row_bytes, 65535}));
  const uint32_t frame_words = (band_rows * width + 1) / 2;

  vk::Buffer frames(ctx, uint64_t(n_frames) * frame_words * 4);
  std::vector<float> times(f.exposure_s.begin(), f.exposure_s.end());
  times.insert(times.end(), f.dark_s.begin(), f.dark_s.end());
  vk::Buffer times_buf(ctx, times.size() * sizeof(float));
  times_buf.upload(std::span<const float>(times));
  vk::Buffer estimate_buf(ctx, uint64_t(band_rows) * width * 4);
  vk::Buffer status_buf(ctx, uint64_t(band_rows) * width * 4);

  shared::HdrParams p{};
  p.width = width;
  p.frame_words = frame_words;
  p.exposure_count = n_exp;
  p.dark_count = uint32_t(f.darks.size());
  p.dark_linear = limits.dark_linear ? 1u : 0u;
  p.min_valid = o.min_valid_exposures;
  p.saturation_dn = float(limits.saturation_dn);
  p.floor_dn = float(limits.floor_dn);
  p.hot_dark_dn = float(limits.hot_dark_dn);
  p.min_correlation = float(o.min_correlation);
  p.longest_dark_s = float(dark.longest_s);

  std::vector<float> estimate(f.pixels());
  std::vector<uint32_t> status(f.pixels());
  vk::Stream stream(ctx);
  last_kernel_ms_ = 0;
  last_bands_ = 0;
  for (uint32_t row0 = 0; row0 < uint32_t(f.height); row0 += band_rows) {
    p.band_rows = std::min<uint32_t>(band_rows, uint32_t(f.height) - row0);
    const size_t first = size_t(row0) * width, count = size_t(p.band_rows) * width;
    for (uint32_t j = 0; j < n_frames; ++j) {
      const auto& frame = j < n_exp ? f.exposures[j] : f.darks[j - n_exp];
      frames.upload(frame.data() + first, count * 2, uint64_t(j) * frame_words * 4);
    }
    stream.dispatch(impl_->kernel, {&frames, &times_buf, &estimate_buf, &status_buf}, &p,
                    (width + kGroup - 1) / kGroup, p.band_rows);
    last_kernel_ms_ += stream.submit();
    estimate_buf.download(estimate.data() + first, count * 4);
    status_buf.download(status.data() + first, count * 4);
    ++last_bands_;
  }
  return hdr_finish(f, std::move(estimate), std::move(status), dark, limits);
}

}  // namespace prism
