// Pruning (paper eq. 19): the support scan scores every PSF at its best shift
// on the search level (the backends: engine/ref/support_scan_ref.h and the
// device kernels). The best refine_candidates of it go down level by level to
// the rank level, the shift doubled and +-1 pixel re-searched at each level
// (first +-(step - 1) on the search level when the scan skipped shifts), with
// the same shift search as the reference scan; the lowest NLL there wins and
// goes on to the click grid the same way (the rank level is the clicks' own
// unless they are finer than 27.6 um: defaults::rank_pixel_sensor_px).
// Coarse to fine (a scan coarser than select_level): every PSF within the
// carry margin goes down to select_level first and is ranked again there;
// with the staged carry (the default) the margin applies again at each level
// on the way down, to the candidates' way to the rank level as well.
// The binary model is exact at any level: a block clicks when any of its
// pixels does, with rate the block's sum. The search's floor is
// search_floor() throughout; the weights fitted after it (event_fit.cpp) keep dark_rate.
#include <algorithm>
#include <cmath>
#include <limits>
#include <map>
#include <span>

#include "engine/ref/likelihood_ref.h"
#include "engine/ref/support_scan_ref.h"
#include "host/reconstruct/event_fit.h"

namespace prism::detail {

Vertex EventFit::refine(std::vector<SupportScore> scored, std::vector<Vertex>& runners_up) {
  const int Ls = search_level_, step = std::max(1, s_.scan_step_px);
  const int Lf = select_level_of(Ls, s_, m_, level_);
  auto by_nll = [](const SupportScore& a, const SupportScore& b) {
    return a.nll < b.nll || (a.nll == b.nll && a.psf < b.psf);
  };
  const size_t keep = std::min(scored.size(), size_t(std::max(1, s_.refine_candidates)));
  // Coarse to fine: every PSF within the margin of the scan's best goes down
  // to the select level, where the candidates are ranked again.
  size_t carry = keep;
  if (Lf < Ls && !scored.empty()) {
    const double best = std::min_element(scored.begin(), scored.end(), by_nll)->nll;
    const size_t within = size_t(std::count_if(scored.begin(), scored.end(), [&](const SupportScore& c) {
      return c.nll <= best + s_.carry_margin_nll;
    }));
    carry = std::clamp(within, keep, std::max(keep, size_t(std::max(1, s_.carry_max))));
  }
  std::partial_sort(scored.begin(), scored.begin() + long(carry), scored.end(), by_nll);
  // The gradient's click weights per level, shared by the candidates.
  std::map<int, std::vector<double>> weights;
  auto weights_at = [&](int l) -> const std::vector<double>& {
    auto it = weights.find(l);
    if (it != weights.end()) return it->second;
    auto w = rates(l, vs_, search_floor());
    for (double& x : w) x = ref::click_weight(x);
    return weights[l] = std::move(w);
  };
  auto search = [&](size_t psf, int level, Shift center, int reach) {
    LevelSource source(*this, level);
    return ref::best_shift(source, psf, clicks_at(level), weights_at(level), center, reach);
  };
  // Ranks candidates by their NLL at `level` (the weight refitted there), in
  // the order of their lower bounds on it (ref::nll_lower_bound): fitted until
  // the next bound exceeds both the n-th NLL so far and, with a margin (>= 0),
  // the best NLL so far plus the margin; the rest cannot be among those kept,
  // and are left unfitted. Returns every candidate, the fitted in NLL order
  // and then the others in their bounds' order, and how many of them lead
  // (kept): the n best, and with a margin every one within it of the best.
  struct Ranked {
    std::vector<SupportScore> all;
    size_t kept = 0;
  };
  auto rank_at = [&](int level, const std::vector<SupportScore>& cands, size_t n, double margin) {
    const auto background = rates(level, vs_, search_floor());
    struct Carried {
      double bound;
      size_t j;
      std::vector<double> p;
      double s;
    };
    std::vector<Carried> carried;
    for (size_t j = 0; j < cands.size(); ++j) {
      const SupportScore& c = cands[j];
      const auto v = values_at(c.psf, level, c.shift);
      Carried k{0, j, std::vector<double>(v.begin(), v.end()), sensor_mass(c.psf, level, c.shift)};
      k.bound = ref::nll_lower_bound(k.p, k.s, background, s_.alpha_max);
      if (std::isnan(k.bound)) k.bound = -INFINITY;  // bounds nothing: fitted first
      carried.push_back(std::move(k));
    }
    std::stable_sort(carried.begin(), carried.end(), [](const Carried& a, const Carried& b) { return a.bound < b.bound; });
    std::vector<double> best_nlls;  // the n lowest NLLs fitted so far, ascending
    auto threshold = [&] {
      double t = best_nlls.size() >= n ? best_nlls.back() : INFINITY;
      return margin >= 0 && !best_nlls.empty() ? std::max(t, best_nlls.front() + margin) : t;
    };
    std::vector<SupportScore> refitted = cands;
    std::vector<size_t> fitted;
    size_t next = 0;
    for (; next < carried.size(); ++next) {
      const Carried& k = carried[next];
      if (best_nlls.size() >= n && k.bound > threshold()) break;
      SupportScore& c = refitted[k.j];
      c.nll = fit_one(k.p, k.s, background, c.alpha);
      fitted.push_back(k.j);
      best_nlls.insert(std::upper_bound(best_nlls.begin(), best_nlls.end(), c.nll), c.nll);
      if (best_nlls.size() > n) best_nlls.pop_back();
    }
    std::sort(fitted.begin(), fitted.end());  // the carry's order, for the same ties as fitting all
    Ranked r;
    for (size_t j : fitted) r.all.push_back(refitted[j]);
    std::stable_sort(r.all.begin(), r.all.end(), by_nll);
    const double t = threshold();
    r.kept = std::min(n, r.all.size());
    while (margin >= 0 && r.kept < r.all.size() && r.all[r.kept].nll <= t) ++r.kept;
    for (; next < carried.size(); ++next) r.all.push_back(refitted[carried[next].j]);
    return r;
  };
  // Down to the select level, each shift doubled and re-searched +-1 pixel.
  // Coarse to fine: at each level above the select level the carried PSFs
  // are ranked again and only those within the carry margin of the best there
  // go further (s_.staged_carry), at the select level the keep best.
  std::vector<SupportScore> selected(scored.begin(), scored.begin() + long(carry));
  if (step > 1)
    for (SupportScore& c : selected) c.shift = search(c.psf, Ls, c.shift, step - 1);
  for (int l = Ls - 1; l >= Lf; --l) {
    for (SupportScore& c : selected) c.shift = search(c.psf, l, c.shift * 2, 1);
    if (l == Lf || s_.staged_carry) {
      Ranked r = rank_at(l, selected, keep, l == Lf ? -1 : s_.carry_margin_nll);
      selected.assign(r.all.begin(), r.all.begin() + long(r.kept));
    }
  }
  // The candidates down to the rank level, ranked there by their NLL; the
  // best goes on to the clicks. With the staged carry only those within the
  // carry margin of the best go down, at the select level and at each level
  // on the way; the others stay runners-up at the shift they reached, scaled
  // to the clicks' level, after the ranked ones (the last dropped first).
  const int Lr = rank_level_of(Lf, s_, m_, level_);
  const auto background_click = rates(level_, vs_, search_floor());
  auto click_nll = [&](Vertex& v) {
    const Column& col = column(v.psf, v.shift);
    return fit_one(col.p, col.s, background_click, v.alpha);
  };
  std::vector<std::pair<double, Vertex>> tried;
  std::vector<Vertex> unranked;
  auto drop = [&](std::span<const SupportScore> cs, int l) {
    std::vector<Vertex> v;
    for (const SupportScore& c : cs) v.push_back({c.psf, c.shift * (1 << (l - level_)), c.alpha});
    unranked.insert(unranked.begin(), v.begin(), v.end());
  };
  {
    std::vector<SupportScore> going;
    for (size_t j = 0; j < selected.size(); ++j) {
      if (s_.staged_carry && j > 0 && !(selected[j].nll <= selected.front().nll + s_.carry_margin_nll)) {
        drop(std::span(selected).subspan(j), Lf);
        break;
      }
      going.push_back(selected[j]);
    }
    for (int l = Lf - 1; l >= Lr; --l) {
      for (SupportScore& c : going) c.shift = search(c.psf, l, c.shift * 2, 1);
      if (l > Lr && s_.staged_carry && going.size() > 1) {
        Ranked r = rank_at(l, going, 1, s_.carry_margin_nll);
        drop(std::span(r.all).subspan(r.kept), l);
        going.assign(r.all.begin(), r.all.begin() + long(r.kept));
      }
    }
    const auto background = Lr == level_ ? background_click : rates(Lr, vs_, search_floor());
    for (const SupportScore& c : going) {
      Vertex v{c.psf, c.shift, c.alpha};
      double f;
      if (Lr == level_) {
        f = click_nll(v);
      } else {
        const auto p = values_at(v.psf, Lr, v.shift);
        f = fit_one(std::vector<double>(p.begin(), p.end()), sensor_mass(v.psf, Lr, v.shift), background, v.alpha);
      }
      tried.push_back({f, v});
    }
  }
  std::stable_sort(tried.begin(), tried.end(), [](const auto& a, const auto& b) { return a.first < b.first; });
  if (Lr > level_ && !tried.empty()) {
    Vertex& best = tried.front().second;
    for (int l = Lr - 1; l >= level_; --l) best.shift = search(best.psf, l, best.shift * 2, 1);
    click_nll(best);
    for (size_t j = 1; j < tried.size(); ++j) tried[j].second.shift *= 1 << (Lr - level_);
  }
  runners_up.clear();
  for (size_t j = 1; j < tried.size(); ++j) runners_up.push_back(tried[j].second);
  runners_up.insert(runners_up.end(), unranked.begin(), unranked.end());
  return tried.empty() ? Vertex{} : tried.front().second;
}

}  // namespace prism::detail
