// The Reconstructor: a batch of events through the K passes in lockstep, the
// support scan on the chosen backend, the rest in detail::EventFit.
#include <algorithm>
#include <chrono>
#include <cmath>
#include <functional>
#include <future>
#include <thread>

#include "engine/defaults.h"
#include "host/reconstruct/event_fit.h"
#include "host/reconstruct/reconstruct.h"
#include "host/util/format.h"

namespace prism {

using detail::EventFit;

std::string flags_to_string(uint32_t flags) {
  static const std::pair<uint32_t, const char*> names[] = {
      {no_clicks, "no_clicks"}, {few_clicks, "few_clicks"}, {alpha_zero, "alpha_zero"},
      {alpha_at_bound, "alpha_at_bound"}, {edge, "edge"}, {merged, "merged"},
      {poor_fit, "poor_fit"}};
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
  const OpticalSystem& o = m.scene.optics;
  if (int(h.sensor_width_px) != o.sensor_width_px || int(h.sensor_height_px) != o.sensor_height_px ||
      std::abs(h.pixel_um - o.pixel_um) > 1e-6 * o.pixel_um)
    throw DictionaryError(events_path + ": events from a " + std::to_string(h.sensor_width_px) + " x " +
                          std::to_string(h.sensor_height_px) + " px sensor of " + format_number(h.pixel_um) +
                          " um pixels, but " + dictionary_dir + " is for a " + std::to_string(o.sensor_width_px) +
                          " x " + std::to_string(o.sensor_height_px) + " px sensor of " + format_number(o.pixel_um) +
                          " um pixels: reconstruct with a dictionary of the same sensor");
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

double scan_shifts(const DictionaryManifest& m, int level, double tau_mm) {
  double shifts = 0;
  for (size_t psf = 0; psf < m.grid.size(); ++psf) {
    const double side = 2.0 * detail::scan_radius_px(m, tau_mm, psf, level) + 1.0;
    shifts += side * side;
  }
  return shifts;
}

int default_search_level(const DictionaryManifest& m, int click_level, double tau_mm) {
  // The scan's work is shifts x clicks and so is the carried PSFs' (each
  // re-searched on every finer level): the clicks scale both alike, so the
  // budget is per click.
  int level = std::min(click_level + 2, m.levels - 1);
  while (level + 1 < m.levels && scan_shifts(m, level, tau_mm) > defaults::search_shifts_per_click) ++level;
  return level;
}

namespace {
// The finest level from `from` up whose pixels span at least sensor_px
// sensor pixels per axis (capped at the coarsest stored).
int level_spanning(const DictionaryManifest& m, int from, int sensor_px) {
  int level = from;
  while (level + 1 < m.levels && (m.base_binning << level) < sensor_px) ++level;
  return level;
}
}  // namespace

int select_level(const ReconstructionSettings& s, const DictionaryManifest& m, int click_level) {
  if (s.select_level >= 0) return s.select_level;
  return level_spanning(m, click_level + 2, defaults::select_pixel_sensor_px);
}

int rank_level(const ReconstructionSettings& s, const DictionaryManifest& m, int click_level) {
  if (s.rank_level >= 0) return s.rank_level;
  return level_spanning(m, click_level, defaults::rank_pixel_sensor_px);
}

namespace {
// The device's results of event j as scores (a PSF whose weight was not
// fitted has NLL +inf).
std::vector<SupportScore> to_scores(const std::vector<ScanResult>& results, size_t j, size_t n_psf) {
  std::vector<SupportScore> scored(n_psf);
  for (size_t psf = 0; psf < n_psf; ++psf) {
    const ScanResult& r = results[j * n_psf + psf];
    scored[psf] = {psf, r.shift, double(r.nll), double(r.alpha), double(r.nll_bound)};
  }
  return scored;
}

// Which weights the device scan fits: those that can still be carried from
// a coarse scan (the carry margin) or be among the candidates for the
// click level (refine_candidates); search.cpp ranks them.
ScanSettings scan_settings(const ReconstructionSettings& s, const DictionaryService& d, int click_level) {
  ScanSettings scan{s.scan_step_px, s.newton_iterations, s.alpha_max};
  const int Ls = detail::search_level_of(d, s, click_level);
  const int Lf = detail::select_level_of(Ls, s, d.manifest(), click_level);
  if (!s.fit_all_weights) {
    scan.fit_margin_nll = Ls > Lf ? s.carry_margin_nll : 0.0;
    scan.fit_keep = std::max(1, s.refine_candidates);
  }
  return scan;
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
                             ReconstructionBackend backend, vk::Context* ctx,
                             std::vector<DictionaryService*> host_helpers)
    : d_(dictionary), level_(click_level), s_(settings), backend_(backend) {
  const auto& m = dictionary.manifest();
  services_.push_back(&d_);
  for (DictionaryService* h : host_helpers) {
    if (!h || &h->manifest() != &m || h->coarse_level() != d_.coarse_level())
      throw std::invalid_argument("reconstruction: a host thread's dictionary service must serve the same dictionary "
                                  "and coarse level as the first");
    services_.push_back(h);
  }
  if (s_.vertices < 1 || s_.vertices > 8)
    throw std::invalid_argument("reconstruction: vertices = " + std::to_string(s_.vertices) + "; choose K in 1..8");
  if (!(s_.dark_rate > 0) || !(s_.tau_mm >= 0) || !(s_.alpha_max > 0) || !(s_.search_dark_rate >= 0))
    throw std::invalid_argument(
        "reconstruction: dark_rate and alpha_max must be > 0, tau_mm and search_dark_rate >= 0");
  if (s_.scan_step_px < 1) throw std::invalid_argument("reconstruction: the scan step must be >= 1 pixel");
  if (level_ < 0 || level_ >= m.levels)
    throw std::invalid_argument("reconstruction: click level " + std::to_string(level_) + " is not in the dictionary");
  if (backend_ == ReconstructionBackend::cpu) return;
  const int Ls = detail::search_level_of(dictionary, s_, level_);
  if (!ctx) throw std::invalid_argument(std::string("reconstruction: the ") + to_string(backend_) + " backend needs a Vulkan device");
  if (Ls != dictionary.coarse_level())
    throw std::invalid_argument("reconstruction: the device scans the level the dictionary service keeps on the device (" +
                                std::to_string(dictionary.coarse_level()) + "), not level " + std::to_string(Ls) +
                                "; make the service with the search level as its coarse level");
  scan_level_ = dictionary.scan_level();
  for (size_t i = 0; i < scan_level_.psfs.size(); ++i)
    scan_level_.psfs[i].radius_px = detail::scan_radius_px(m, s_.tau_mm, i, Ls);
  device_ = std::make_unique<SupportScanVulkan>(
      *ctx, backend_ == ReconstructionBackend::dense ? ScanKernel::dense : ScanKernel::sparse, scan_level_.half,
      s_.scan_layout, s_.scan_loads);
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
  const ScanSettings scan = scan_settings(s_, d_, level_);
  auto results = device_->run(scan_level_, inputs, scan);
  timings_.scan_fallbacks += device_->last_fallbacks();
  timings_.scan_fits += device_->last_fits();
  timings_.scan_candidates += device_->last_candidates();
  for (size_t j = 0; j < active.size(); ++j) out[active[j]] = to_scores(results, j, d_.manifest().grid.size());
  return out;
}

std::vector<std::vector<ReconstructedVertex>> Reconstructor::run(std::span<const Event> events) {
  using clock = std::chrono::steady_clock;
  auto seconds = [](clock::time_point a, clock::time_point b) { return std::chrono::duration<double>(b - a).count(); };
  const auto& m = d_.manifest();
  check_clicks(events);
  auto t0 = clock::now();
  // Host threads: event i on services_[i mod T], descended by thread i mod T.
  const size_t T = backend_ == ReconstructionBackend::cpu ? 1 : services_.size();
  std::vector<EventFit> fits;
  fits.reserve(events.size());
  for (size_t i = 0; i < events.size(); ++i) fits.emplace_back(events[i], level_, *services_[i % T], s_);
  auto on_host_threads = [&](const std::function<void(size_t)>& work) {  // work(i) for every event i
    std::vector<std::exception_ptr> failures(T);
    auto share = [&](size_t t) {
      try {
        for (size_t i = t; i < fits.size(); i += T) work(i);
      } catch (...) {
        failures[t] = std::current_exception();
      }
    };
    std::vector<std::thread> helpers;
    for (size_t t = 1; t < T; ++t) helpers.emplace_back(share, t);
    share(0);
    for (auto& h : helpers) h.join();
    for (auto& f : failures)
      if (f) std::rethrow_exception(f);
  };
  const ScanSettings scan = scan_settings(s_, d_, level_);
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
        timings_.scan_wait_s += seconds(a, b);
        host_s += seconds(b, clock::now());
      }
      continue;
    }
    // The device scans chunk c + 1 on a thread of its own while this one
    // descends chunk c (overlap_scans; else each chunk is scanned, then
    // descended): on a CPU device the scan's threads and the host's descent
    // then share the cores instead of taking turns, on a GPU the host's work
    // hides behind the device's. Only the scan thread touches the device,
    // only this one the dictionary service's tiles (the scan's inputs are
    // built here too).
    const size_t per_chunk = size_t(std::max(1, s_.scan_chunk_events));
    struct Scanned {
      std::vector<ScanResult> results;
      double seconds = 0;
    };
    auto launch = [&](size_t first) {
      auto a = clock::now();
      std::vector<ScanEvent> inputs;
      for (size_t j = first; j < std::min(active.size(), first + per_chunk); ++j)
        inputs.push_back(fits[active[j]].scan_input(backend_ == ReconstructionBackend::dense));
      host_s += seconds(a, clock::now());
      return std::async(std::launch::async, [this, &scan, inputs = std::move(inputs)] {
        auto b = clock::now();
        Scanned out{device_->run(scan_level_, inputs, scan), 0.0};
        out.seconds = std::chrono::duration<double>(clock::now() - b).count();
        return out;
      });
    };
    auto next = launch(0);
    for (size_t first = 0; first < active.size(); first += per_chunk) {
      auto w = clock::now();
      Scanned done = next.get();
      const bool more = first + per_chunk < active.size();
      auto c = clock::now();
      timings_.scan_wait_s += seconds(w, c);
      timings_.scan_s += done.seconds;
      timings_.scan_kernel_ms += device_->last_kernel_ms();
      timings_.scan_fallbacks += device_->last_fallbacks();
      timings_.scan_fits += device_->last_fits();
      timings_.scan_candidates += device_->last_candidates();
      timings_.scan_device_bytes = std::max(timings_.scan_device_bytes, device_->last_device_bytes());
      if (more && s_.overlap_scans) next = launch(first + per_chunk);
      auto h = clock::now();
      const size_t last = std::min(active.size(), first + per_chunk);
      std::vector<long> chunk_of(fits.size(), -1);  // event -> its row in this chunk's results
      for (size_t j = first; j < last; ++j) chunk_of[active[j]] = long(j - first);
      on_host_threads([&](size_t i) {
        if (chunk_of[i] >= 0) fits[i].add_vertex(to_scores(done.results, size_t(chunk_of[i]), n_psf));
      });
      host_s += seconds(h, clock::now());
      if (more && !s_.overlap_scans) next = launch(first + per_chunk);
    }
  }
  auto d = clock::now();
  std::vector<std::vector<ReconstructedVertex>> out(fits.size());
  on_host_threads([&](size_t i) { out[i] = fits[i].result(); });
  timings_.host_s += host_s + seconds(d, clock::now());
  return out;
}

std::vector<ReconstructedVertex> reconstruct(const Event& event, int level, DictionaryService& dictionary,
                                             const ReconstructionSettings& settings) {
  Reconstructor r(dictionary, level, settings);
  return r.run(std::span<const Event>(&event, 1)).at(0);
}

}  // namespace prism
