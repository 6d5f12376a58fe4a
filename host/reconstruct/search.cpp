// Pruning (paper eq. 19): the support scan scores every PSF at its best shift
// on the search level (the backends: engine/ref/support_scan_ref.h and the
// device kernels). The best refine_candidates of it go down level by level to
// the click grid, the shift doubled and +-1 pixel re-searched at each level
// (first +-(step - 1) on the search level when the scan skipped shifts), with
// the same shift search as the reference scan; the lowest click-level NLL wins.
// The binary model is exact at any level: a block clicks when any of its
// pixels does, with rate the block's sum.
#include <algorithm>
#include <cmath>
#include <limits>
#include <map>

#include "engine/ref/likelihood_ref.h"
#include "engine/ref/support_scan_ref.h"
#include "host/reconstruct/event_fit.h"

namespace prism::detail {

Vertex EventFit::refine(std::vector<SupportScore> scored, std::vector<Vertex>& runners_up) {
  const int Ls = search_level_, step = std::max(1, s_.scan_step_px);
  size_t keep = std::min(scored.size(), size_t(std::max(1, s_.refine_candidates)));
  std::partial_sort(scored.begin(), scored.begin() + long(keep), scored.end(),
                    [](const SupportScore& a, const SupportScore& b) {
                      return a.nll < b.nll || (a.nll == b.nll && a.psf < b.psf);
                    });
  // The gradient's click weights per level, shared by the candidates.
  std::map<int, std::vector<double>> weights;
  auto weights_at = [&](int l) -> const std::vector<double>& {
    auto it = weights.find(l);
    if (it != weights.end()) return it->second;
    auto w = rates(l, vs_);
    for (double& x : w) x = ref::click_weight(x);
    return weights[l] = std::move(w);
  };
  auto search = [&](size_t psf, int level, Shift center, int reach) {
    LevelSource source(*this, level);
    return ref::best_shift(source, psf, clicks_at(level), weights_at(level), center, reach);
  };
  auto background_click = rates(level_, vs_);
  std::vector<std::pair<double, Vertex>> tried;
  for (size_t j = 0; j < keep; ++j) {
    size_t m = scored[j].psf;
    Shift sh = scored[j].shift;
    if (step > 1) sh = search(m, Ls, sh, step - 1);
    for (int l = Ls - 1; l >= level_; --l) sh = search(m, l, sh * 2, 1);
    const Column& c = column(m, sh);
    double alpha = scored[j].alpha;
    double f = fit_one(c.p, c.s, background_click, alpha);
    tried.push_back({f, {m, sh, alpha}});
  }
  std::stable_sort(tried.begin(), tried.end(), [](const auto& a, const auto& b) { return a.first < b.first; });
  runners_up.clear();
  for (size_t j = 1; j < tried.size(); ++j) runners_up.push_back(tried[j].second);
  return tried.empty() ? Vertex{} : tried.front().second;
}

}  // namespace prism::detail
