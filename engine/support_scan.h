// The support search of the reconstruction on the device (paper eqs. 17-18):
// for a batch of events and every PSF of the dictionary's scan level, the
// lateral shift within +-radius with the lowest gradient correlation <g, P>,
// and the weight alpha fitted there by projected Newton: for every PSF, or
// (sparse kernel, ScanSettings::fit_margin_nll >= 0) only for those whose
// lower bound on the NLL can still win. Two kernels give the same answer: shaders/support_scan.comp sums over each event's clicks (the
// sparse likelihood), shaders/support_scan_dense.comp over every pixel of the
// scan level (the paper's dense way, kept as the baseline to measure against).
// The double-precision reference is engine/ref/support_scan_ref.h.
#pragma once
#include <cmath>
#include <cstdint>
#include <memory>
#include <span>
#include <vector>

#include <glm/glm.hpp>

#include "engine/vk/compute.h"

namespace prism {

namespace shared {
using namespace glm;
using uint = unsigned int;
#define PRISM_FN inline
#include "common/likelihood.glsl"
#undef PRISM_FN
static_assert(sizeof(ScanParams) == 68, "ScanParams must match its std430 push-constant layout");
}  // namespace shared

// One PSF of the scan level on the device (std430, 16 bytes; scan.glsl's ScanPsf).
struct ScanPsf {
  uint32_t chunk = 0;     // index into ScanLevel::chunks
  uint32_t p_word = 0;    // first word of its values in that chunk
  uint32_t sat_word = 0;  // first word of its summed-area table
  int32_t radius_px = 0;  // shifts within +-radius per axis
};
static_assert(sizeof(ScanPsf) == 16);

// The dictionary's scan level as it lies on the device (host/dictionary/service.h
// puts it there). PSFs of one chunk are consecutive.
struct ScanLevel {
  int width = 0, height = 0;
  bool half = false;        // values as half floats times half_scale
  // Float values only: each PSF's summed-area table is followed, from the
  // next multiple of 4 words, by its row table (support_scan.comp's
  // psf_row), which the serial scan reads on a CPU device.
  bool rows = false;
  float half_scale = 1.0f;
  std::vector<const vk::Buffer*> chunks;
  std::vector<ScanPsf> psfs;
};

// One event as the scan sees it, on the scan level.
struct ScanEvent {
  std::vector<glm::ivec2> clicks;  // distinct clicked pixels of the scan level
  std::vector<double> rate;        // lambda of the current model at each click, dark rate included (> 0)
  // Dense kernel only: lambda at every pixel of the scan level, row-major.
  std::vector<double> dense_rate;
};

struct ScanResult {
  glm::ivec2 shift{};  // best shift, pixels of the scan level
  float score = 0;     // <g, P(shifted)> there
  float nll = 0;       // NLL of the candidate with its fitted weight, against the event's current model;
                       // +inf where the weight was not fitted
  float alpha = 0;     // fitted weight, expected photons (0 where not fitted)
  uint32_t newton_iterations = 0;
  uint32_t shifts = 0;  // shifts scored
  float nll_bound = 0;  // a lower bound on nll (likelihood.glsl's nll_lower_bound); nll is +inf where
                        // that bound showed the candidate cannot be among the winners
};

// One PSF's result of a support scan in double (the reference's own, or a
// device result converted): its best shift and the NLL and weight fitted
// there; a candidate not fitted has nll = +inf.
struct SupportScore {
  size_t psf = 0;
  glm::ivec2 shift{};
  double nll = 0, alpha = 0;
  double nll_bound = -INFINITY;  // the device's lower bound on nll (the reference fits every weight: none)
};

struct ScanSettings {
  int step_px = 1;          // shifts on multiples of this
  int newton_iterations = 60;
  double alpha_max = 1e6;
  // Which weights to fit (sparse kernel). Negative: every PSF's. Otherwise
  // every PSF whose NLL may lie within fit_margin_nll of the event's best, or
  // among its fit_keep best: first the 2 fit_keep with the lowest bounds are
  // fitted, which gives the best NLL U and the fit_keep-th U_k from above;
  // then every PSF whose bound is at most max(U + margin, U_k). The others'
  // NLLs provably exceed that, so a ranking by NLL of the fitted ones (the
  // coarse-to-fine carry, the candidates for the click level) is the ranking
  // of all of them as far as it goes.
  double fit_margin_nll = -1;
  int fit_keep = 8;
};

enum class ScanKernel { sparse, dense };

// The sparse kernel's layout on the device: a workgroup per (event, PSF),
// its invocations splitting the shifts (phase 0) and the clicks (the weight
// fit, phase 1), or one invocation per (event, PSF). automatic: serial on a
// CPU device (llvmpipe; shaders/support_scan.comp says why), workgroups
// elsewhere. The same results either way.
enum class ScanLayout { automatic, group, serial };

// How the sparse kernel reads the PSF values, the clicks and their rates:
// through uniform texel buffers (one vector gather per look-up on llvmpipe,
// where a storage-buffer load runs one invocation at a time: 1.28x the
// reconstruction, docs/reconstruction.md), or as storage buffers, the way
// before, kept to measure against. The same results either way.
enum class ScanLoads { texel, storage };

class SupportScanVulkan {
 public:
  SupportScanVulkan(vk::Context& ctx, ScanKernel kernel, bool half, ScanLayout layout = ScanLayout::automatic,
                    ScanLoads loads = ScanLoads::texel);
  ~SupportScanVulkan();

  // results[e * psfs + m]. Events go to the device in batches whose buffers
  // stay within maxStorageBufferRange.
  std::vector<ScanResult> run(const ScanLevel& level, std::span<const ScanEvent> events, const ScanSettings& s);

  double last_kernel_ms() const { return last_kernel_ms_; }
  uint64_t last_device_bytes() const { return last_device_bytes_; }  // event and result buffers of the last run
  // Rounds of weight fits in the last run in which serial fits ran out of loop budget (those candidates
  // were fitted again in workgroups).
  uint64_t last_fallbacks() const { return last_fallbacks_; }
  // Weights fitted in the last run, of last_candidates() (events x PSFs).
  uint64_t last_fits() const { return last_fits_; }
  uint64_t last_candidates() const { return last_candidates_; }

 private:
  struct Impl;
  std::unique_ptr<Impl> impl_;
  double last_kernel_ms_ = 0;
  uint64_t last_device_bytes_ = 0;
  uint64_t last_fallbacks_ = 0;
  uint64_t last_fits_ = 0, last_candidates_ = 0;
};

}  // namespace prism
