#include "engine/support_scan.h"

#include <algorithm>
#include <cmath>
#include <cstring>
#include <limits>
#include <map>
#include <numeric>
#include <string>
#include <tuple>

#include "engine/vk/error.h"
#include "spv/support_scan.spv.h"
#include "spv/support_scan_dense.spv.h"

namespace prism {

namespace {

// scan.glsl's ScanOut.
struct ScanOut {
  int32_t shift_x, shift_y;
  float score, nll, alpha;
  uint32_t newton, shifts;
  float bound;
};
static_assert(sizeof(ScanOut) == 32);

uint32_t pack_click(glm::ivec2 c) { return uint32_t(c.x) | (uint32_t(c.y) << 16); }

// Loop iterations one invocation may run on a CPU device. llvmpipe (lavapipe)
// counts the iterations of all loops of an invocation together and ends them
// after 65535 (gallivm's loop limiter, there against hung shaders), silently;
// half of that leaves room for the weight fit's loops. GPUs have no such limit.
constexpr uint64_t kCpuLoopBudget = 32768;
// Shifts the serial scan scores per pass over the clicks (support_scan.comp's
// SUB): a pass counts this many iterations per click should the compiler keep
// the inner loop. An event with more clicks than kCpuLoopBudget /
// kSerialShiftsPerPass is scored one shift per pass (the kernel decides per
// event from the budget, its specialisation constant).
constexpr uint64_t kSerialShiftsPerPass = 8;

// The sparse kernel's texel bindings (support_scan.comp): the dictionary's
// chunk again (8) for the PSF values, as half floats where the chunk holds
// them; each click with its rate and weight in one texel (9: the words of
// bindings 3 and 4 side by side); and the chunk once more (10), four floats
// a texel, for the row tables (ScanLevel::rows).
std::vector<VkFormat> sparse_texel_formats(bool half) {
  std::vector<VkFormat> f(11, VK_FORMAT_UNDEFINED);
  f[8] = half ? VK_FORMAT_R16_SFLOAT : VK_FORMAT_R32_SFLOAT;
  f[9] = VK_FORMAT_R32G32B32A32_UINT;
  f[10] = VK_FORMAT_R32G32B32A32_SFLOAT;
  return f;
}

}  // namespace

struct SupportScanVulkan::Impl {
  vk::Context& ctx;
  ScanKernel which;
  bool half;
  ScanLayout layout;
  ScanLoads loads;
  std::map<std::tuple<bool, bool, bool>, std::unique_ptr<vk::Kernel>> kernels;  // by (serial scan, serial fit, rows)
  Impl(vk::Context& c, ScanKernel k, bool h, ScanLayout l, ScanLoads d)
      : ctx(c), which(k), half(h), layout(l), loads(d) {}
  vk::Kernel& kernel(bool serial_scan, bool serial_fit, bool rows) {
    auto& k = kernels[{serial_scan, serial_fit, rows}];
    if (k) return *k;
    if (which == ScanKernel::dense)
      k = std::make_unique<vk::Kernel>(
          ctx, "support_scan_dense",
          std::span<const uint32_t>(spv_support_scan_dense, std::size(spv_support_scan_dense)), 5,
          sizeof(shared::ScanParams), std::vector<uint32_t>{half ? 1u : 0u});
    else
      k = std::make_unique<vk::Kernel>(
          ctx, "support_scan", std::span<const uint32_t>(spv_support_scan, std::size(spv_support_scan)), 11,
          sizeof(shared::ScanParams),
          std::vector<uint32_t>{half ? 1u : 0u, serial_scan ? 1u : 0u, serial_fit ? 1u : 0u, uint32_t(kCpuLoopBudget),
                                loads == ScanLoads::texel ? 1u : 0u, rows ? 1u : 0u},
          sparse_texel_formats(half));
    return *k;
  }
  // The layouts of a run (ScanLayout): serial scan and fits on a CPU device,
  // workgroups elsewhere (measured on llvmpipe: docs/reconstruction.md,
  // kernel layout).
  std::pair<bool, bool> serial() const {
    if (which == ScanKernel::dense || layout == ScanLayout::group) return {false, false};
    if (layout == ScanLayout::serial) return {true, true};
    return {ctx.is_cpu(), ctx.is_cpu()};
  }
};

SupportScanVulkan::SupportScanVulkan(vk::Context& ctx, ScanKernel kernel, bool half, ScanLayout layout,
                                     ScanLoads loads)
    : impl_(std::make_unique<Impl>(ctx, kernel, half, layout, loads)) {}

SupportScanVulkan::~SupportScanVulkan() = default;

std::vector<ScanResult> SupportScanVulkan::run(const ScanLevel& level, std::span<const ScanEvent> events,
                                               const ScanSettings& s) {
  vk::Context& ctx = impl_->ctx;
  const bool dense = impl_->which == ScanKernel::dense;
  const size_t n_psf = level.psfs.size(), n_events = events.size();
  std::vector<ScanResult> out(n_events * n_psf);
  last_kernel_ms_ = 0;
  last_device_bytes_ = 0;
  last_fallbacks_ = 0;
  last_fits_ = 0;
  last_candidates_ = 0;
  if (n_events == 0 || n_psf == 0) return out;
  if (level.width > 65535 || level.height > 65535)
    throw vk::Error("support scan: a scan level of " + std::to_string(level.width) + " x " +
                    std::to_string(level.height) + " pixels does not fit 16-bit click coordinates; scan a coarser level");
  if (s.step_px < 1) throw vk::Error("support scan: the shift step must be >= 1 pixel");

  const uint64_t cap = ctx.max_storage_buffer_bytes();
  const uint64_t pixels = uint64_t(level.width) * uint64_t(level.height);
  const uint32_t dense_words = dense ? uint32_t(2 * pixels + (pixels + 31) / 32) : 0;

  // Events in batches: results of a batch, and its images for the dense kernel,
  // within one storage buffer.
  size_t batch = std::max<uint64_t>(1, cap / (n_psf * sizeof(ScanOut)));
  if (dense) batch = std::min<uint64_t>(batch, std::max<uint64_t>(1, cap / (uint64_t(dense_words) * 4)));
  // Phases 0 and 1 dispatch workgroups over (events, PSFs) in the serial
  // layout and over (PSFs, events) in workgroups (the record below says why).
  const auto [serial_scan, serial_fit] = impl_->serial();
  const uint32_t* max_groups = ctx.properties().limits.maxComputeWorkGroupCount;
  const uint32_t event_groups_max = std::min(serial_scan ? max_groups[0] : max_groups[1],
                                             serial_fit ? max_groups[0] : max_groups[1]);
  const uint32_t psf_groups_max = std::min(serial_scan ? max_groups[1] : max_groups[0],
                                           serial_fit ? max_groups[1] : max_groups[0]);
  if ((serial_scan || serial_fit ? (n_psf + 63) / 64 : n_psf) > psf_groups_max)
    throw vk::Error("support scan: " + std::to_string(n_psf) + " PSFs need more workgroups than " + ctx.describe() +
                    " dispatches (" + std::to_string(psf_groups_max) + "); split the dictionary");
  batch = std::min<size_t>(batch, std::min<size_t>(n_events, event_groups_max));

  vk::Buffer psfs(ctx, n_psf * sizeof(ScanPsf));
  psfs.upload(level.psfs.data(), n_psf * sizeof(ScanPsf));
  vk::Buffer results(ctx, batch * n_psf * sizeof(ScanOut));
  // What one batch holds on the device; the run's figure is the largest batch's.
  const uint64_t run_bytes = psfs.bytes() + results.bytes();

  shared::ScanParams p{};
  p.psf_total = uint32_t(n_psf);
  p.width = uint32_t(level.width);
  p.height = uint32_t(level.height);
  p.step = uint32_t(s.step_px);
  p.max_newton = uint32_t(std::max(0, s.newton_iterations));
  p.half_scale = level.half_scale;
  p.alpha_max = float(s.alpha_max);
  p.dense_words = dense_words;

  // PSF ranges per chunk (consecutive by contract).
  struct Range {
    uint32_t chunk, first, count;
  };
  std::vector<Range> ranges;
  for (uint32_t m = 0; m < n_psf; ++m) {
    if (ranges.empty() || ranges.back().chunk != level.psfs[m].chunk) {
      if (!ranges.empty() && level.psfs[m].chunk < ranges.back().chunk)
        throw vk::Error("support scan: PSFs of one chunk must be consecutive");
      ranges.push_back({level.psfs[m].chunk, m, 0});
    }
    ++ranges.back().count;
  }

  int max_half = 0;
  for (const ScanPsf& psf : level.psfs) {
    const int h = psf.radius_px / s.step_px;
    max_half = std::max(max_half, h);
  }
  const uint64_t max_shifts = uint64_t(2 * max_half + 1) * uint64_t(2 * max_half + 1);
  const uint64_t group = 64;  // scan.glsl's GROUP
  // The row tables serve the serial scan's texel loads on a lattice of step 1.
  const bool rows = level.rows && !dense && serial_scan && impl_->loads == ScanLoads::texel && s.step_px == 1;
  vk::Kernel& kernel = impl_->kernel(serial_scan, serial_fit, rows);

  std::vector<ScanOut> raw(batch * n_psf);
  for (size_t e0 = 0; e0 < n_events; e0 += batch) {
    const size_t ne = std::min(batch, n_events - e0);
    std::unique_ptr<vk::Buffer> b_events, b_clicks, b_rates, b_records, b_images;
    uint64_t batch_bytes = run_bytes;
    if (!dense) {
      std::vector<uint32_t> ranges_words, xy;
      std::vector<float> rw;
      for (size_t e = 0; e < ne; ++e) {
        const ScanEvent& ev = events[e0 + e];
        ranges_words.push_back(uint32_t(xy.size()));
        ranges_words.push_back(uint32_t(ev.clicks.size()));
        for (size_t c = 0; c < ev.clicks.size(); ++c) {
          xy.push_back(pack_click(ev.clicks[c]));
          const double lambda = ev.rate.at(c);
          rw.push_back(float(lambda));
          rw.push_back(float(1.0 / -std::expm1(-lambda)));  // the gradient's click weight, in double
        }
      }
      if (xy.empty()) xy.push_back(0), rw.push_back(1), rw.push_back(1);  // no zero-sized buffers
      b_events = std::make_unique<vk::Buffer>(ctx, ranges_words.size() * 4);
      b_events->upload(std::span<const uint32_t>(ranges_words));
      b_clicks = std::make_unique<vk::Buffer>(ctx, xy.size() * 4);
      b_clicks->upload(std::span<const uint32_t>(xy));
      b_rates = std::make_unique<vk::Buffer>(ctx, rw.size() * 4);
      b_rates->upload(std::span<const float>(rw));
      // The texel loads' copy: per click its word, then lambda's and the weight's bits, then 0.
      std::vector<uint32_t> records(4 * xy.size(), 0u);
      for (size_t c = 0; c < xy.size(); ++c) {
        records[4 * c] = xy[c];
        std::memcpy(&records[4 * c + 1], &rw[2 * c], 8);
      }
      b_records = std::make_unique<vk::Buffer>(ctx, records.size() * 4);
      b_records->upload(std::span<const uint32_t>(records));
      batch_bytes += b_events->bytes() + b_clicks->bytes() + b_rates->bytes() + b_records->bytes();
    } else {
      std::vector<uint32_t> words(ne * dense_words, 0);
      for (size_t e = 0; e < ne; ++e) {
        const ScanEvent& ev = events[e0 + e];
        if (ev.dense_rate.size() != pixels)
          throw vk::Error("support scan (dense): event " + std::to_string(e0 + e) + " has " +
                          std::to_string(ev.dense_rate.size()) + " rates for " + std::to_string(pixels) + " pixels");
        uint32_t* img = &words[e * dense_words];
        std::vector<uint8_t> y(pixels, 0);
        for (auto c : ev.clicks) y[size_t(c.y) * size_t(level.width) + size_t(c.x)] = 1;
        for (size_t i = 0; i < pixels; ++i) {
          const double lambda = ev.dense_rate[i];
          const float g = float(1.0 - (y[i] ? 1.0 / -std::expm1(-lambda) : 0.0));
          const float l = float(lambda);
          std::memcpy(&img[i], &g, 4);
          std::memcpy(&img[pixels + i], &l, 4);
          if (y[i]) img[2 * pixels + i / 32] |= 1u << (i % 32);
        }
      }
      b_images = std::make_unique<vk::Buffer>(ctx, words.size() * 4);
      b_images->upload(std::span<const uint32_t>(words));
      batch_bytes += b_images->bytes();
    }

    // Blocks of shifts per workgroup (phase 0): on a CPU device, few enough
    // that one invocation stays within the loop budget.
    uint64_t block = max_shifts;
    if (ctx.is_cpu()) {
      if (dense) {
        const uint64_t per_shift = (pixels + group - 1) / group;  // pixel iterations per shift and invocation
        if (per_shift > kCpuLoopBudget)
          throw vk::Error("support scan (dense): a scan level of " + std::to_string(pixels) + " pixels needs more " +
                          "loop iterations per invocation than " + ctx.describe() + " runs; scan a coarser level");
        block = std::max<uint64_t>(1, kCpuLoopBudget / per_shift);
      } else {
        uint64_t clicks = 1;
        for (size_t e = 0; e < ne; ++e) clicks = std::max<uint64_t>(clicks, events[e0 + e].clicks.size());
        if (clicks > kCpuLoopBudget)
          throw vk::Error("support scan: an event with " + std::to_string(clicks) + " clicks on the scan level needs " +
                          "more loop iterations per invocation than " + ctx.describe() + " runs; scan a coarser level");
        // Serial: one invocation scores the whole block, kSerialShiftsPerPass
        // shifts per pass where the batch's largest event allows, else one.
        if (!serial_scan)
          block = group * std::max<uint64_t>(1, kCpuLoopBudget / clicks);
        else if (clicks * kSerialShiftsPerPass <= kCpuLoopBudget)
          block = kSerialShiftsPerPass * (kCpuLoopBudget / (kSerialShiftsPerPass * clicks));
        else
          block = std::max<uint64_t>(1, kCpuLoopBudget / clicks);
      }
      block = std::min(block, max_shifts);
    }
    const uint64_t blocks = (max_shifts + block - 1) / block;
    vk::Buffer block_best(ctx, std::max<uint64_t>(8, ne * n_psf * blocks * 8));
    vk::Buffer no_list(ctx, 8);  // phases 0 and 1 read no candidate list
    batch_bytes += block_best.bytes();
    last_device_bytes_ = std::max(last_device_bytes_, batch_bytes);
    p.block_shifts = uint32_t(block);
    p.blocks = uint32_t(blocks);

    vk::Stream stream(ctx, 2 * uint32_t(ranges.size()) + 2);
    p.event_first = 0;
    p.event_count = uint32_t(ne);
    // Phases 0 and 1 over every (PSF, event): a workgroup per (PSF, event[,
    // block]), or one invocation each when serial. Serial, the events run
    // along x: llvmpipe runs the workgroups in x's order, so the next ones
    // read the same 64 PSFs (their values stay in the core's cache) rather
    // than the next 64 of the dictionary (1.09x over the 1000 volume events:
    // docs/reconstruction.md "The scan's kernels, this round").
    auto record = [&](vk::Stream& st, vk::Kernel& k, uint32_t phase, bool serial) {
      p.phase = phase;
      for (const Range& r : ranges) {
        p.psf_first = r.first;
        p.psf_count = r.count;
        const vk::Buffer* chunk = level.chunks.at(r.chunk);
        const uint32_t x = serial ? (r.count + uint32_t(group) - 1) / uint32_t(group) : r.count;
        const uint32_t z = phase == 0 ? uint32_t(blocks) : 1u;
        if (dense)
          st.dispatch(k, {chunk, &psfs, b_images.get(), &results, &block_best}, &p, x, uint32_t(ne), z);
        else
          st.dispatch(k, {chunk, &psfs, b_events.get(), b_clicks.get(), b_rates.get(), &results, &block_best,
                          &no_list, chunk, b_records.get(), chunk},
                      &p, serial ? uint32_t(ne) : x, serial ? x : uint32_t(ne), z);
      }
      st.barrier();
    };
    record(stream, kernel, 0, serial_scan);
    record(stream, kernel, 1, serial_fit);
    last_kernel_ms_ += stream.submit();
    results.download(raw.data(), ne * n_psf * sizeof(ScanOut));
    last_candidates_ += ne * n_psf;

    if (!dense) {
      // Phase 2: the weights of a list of (event, PSF) candidates, per chunk.
      const uint64_t scan_bytes = batch_bytes;
      auto dispatch_fits = [&](const std::vector<glm::uvec2>& list, bool serial) {
        vk::Buffer b_list(ctx, list.size() * sizeof(glm::uvec2));
        last_device_bytes_ = std::max(last_device_bytes_, scan_bytes + b_list.bytes());
        b_list.upload(list.data(), list.size() * sizeof(glm::uvec2));
        vk::Stream st(ctx, uint32_t(ranges.size()) + 1);
        vk::Kernel& k = impl_->kernel(serial_scan, serial, rows);
        p.phase = 2;
        size_t first = 0;
        for (const Range& r : ranges) {
          size_t end = first;
          while (end < list.size() && list[end].y < r.first + r.count) ++end;
          if (end == first) continue;
          p.list_first = uint32_t(first);
          p.list_count = uint32_t(end - first);
          // Serial: one invocation per entry; workgroups: one per entry, in rows.
          const uint32_t max_x = ctx.properties().limits.maxComputeWorkGroupCount[0];
          const uint32_t x = serial ? (p.list_count + uint32_t(group) - 1) / uint32_t(group)
                                    : std::min(p.list_count, max_x);
          const uint32_t y = serial ? 1u : (p.list_count + x - 1) / x;
          st.dispatch(k, {level.chunks.at(r.chunk), &psfs, b_events.get(), b_clicks.get(), b_rates.get(), &results,
                          &block_best, &b_list, level.chunks.at(r.chunk), b_records.get(), level.chunks.at(r.chunk)},
                      &p, x, y);
          first = end;
        }
        last_kernel_ms_ += st.submit();
        results.download(raw.data(), ne * n_psf * sizeof(ScanOut));
      };
      auto fit_list = [&](std::vector<glm::uvec2> list) {
        if (list.empty()) return;
        // Per chunk (a dispatch each), then by event: neighbouring serial
        // invocations read one event's clicks and rates (phase 2 1.10x on
        // llvmpipe against an order by PSF alone; each fit is its own, so the
        // same results in any order).
        std::sort(list.begin(), list.end(), [&](glm::uvec2 a, glm::uvec2 b) {
          const uint32_t ca = level.psfs[a.y].chunk, cb = level.psfs[b.y].chunk;
          return ca != cb ? ca < cb : a.x != b.x ? a.x < b.x : a.y < b.y;
        });
        dispatch_fits(list, serial_fit);
        last_fits_ += list.size();
        // A serial fit that ran out of loop budget: those candidates again in workgroups.
        std::vector<glm::uvec2> again;
        for (glm::uvec2 em : list)
          if (raw[size_t(em.x) * n_psf + em.y].newton == shared::FIT_UNFINISHED) again.push_back(em);
        if (serial_fit && !again.empty()) {
          dispatch_fits(again, false);
          ++last_fallbacks_;
        }
      };
      std::vector<glm::uvec2> list;
      if (s.fit_margin_nll < 0) {
        for (uint32_t e = 0; e < ne; ++e)
          for (uint32_t m = 0; m < n_psf; ++m) list.push_back({e, m});
        fit_list(list);
      } else {
        // First the candidates with the lowest bounds, then every one whose
        // bound does not exceed what they reached (ScanSettings).
        const size_t keep = size_t(std::max(1, s.fit_keep)), first_round = std::min(n_psf, 2 * keep);
        // A bound that is not a number bounds nothing: such a candidate goes first.
        auto bound_of = [](const ScanOut& o) { return std::isnan(o.bound) ? -INFINITY : o.bound; };
        std::vector<uint32_t> order(n_psf);
        for (uint32_t e = 0; e < ne; ++e) {
          const ScanOut* row = &raw[size_t(e) * n_psf];
          std::iota(order.begin(), order.end(), 0u);
          std::nth_element(order.begin(), order.begin() + long(first_round - 1), order.end(),
                           [&](uint32_t a, uint32_t b) { return bound_of(row[a]) < bound_of(row[b]); });
          for (size_t j = 0; j < first_round; ++j) list.push_back({e, order[j]});
        }
        fit_list(list);
        list.clear();
        std::vector<float> fitted;
        for (uint32_t e = 0; e < ne; ++e) {
          const ScanOut* row = &raw[size_t(e) * n_psf];
          fitted.clear();
          for (size_t m = 0; m < n_psf; ++m)
            if (row[m].newton != shared::FIT_SKIPPED) fitted.push_back(row[m].nll);
          std::sort(fitted.begin(), fitted.end());
          const double limit = std::max(double(fitted.front()) + s.fit_margin_nll,
                                        double(fitted[std::min(keep, fitted.size()) - 1]));
          // Float slack: the bound and the NLLs are sums of ~clicks float terms.
          const double slack = 1e-4 * (1.0 + std::abs(limit));
          for (uint32_t m = 0; m < n_psf; ++m)
            if (row[m].newton == shared::FIT_SKIPPED && double(bound_of(row[m])) <= limit + slack) list.push_back({e, m});
        }
        fit_list(list);
      }
    }
    for (size_t i = 0; i < ne * n_psf; ++i) {
      const ScanOut& o = raw[i];
      const bool fitted = o.newton != shared::FIT_SKIPPED;
      out[e0 * n_psf + i] = {glm::ivec2(o.shift_x, o.shift_y),
                             o.score,
                             fitted ? o.nll : std::numeric_limits<float>::infinity(),
                             fitted ? o.alpha : 0.0f,
                             fitted ? o.newton : 0u,
                             o.shifts,
                             o.bound};
    }
    if (dense) last_fits_ += ne * n_psf;
  }
  return out;
}

}  // namespace prism
