#include "engine/ref/hdr_merge_ref.h"

#include <cmath>
#include <stdexcept>

namespace prism::ref {

namespace {

double mean(const std::vector<double>& v) {
  double s = 0;
  for (double x : v) s += x;
  return s / double(v.size());
}

// Least-squares line through (t, d), or the mean of d when constant.
struct DarkLine {
  double offset = 0, rate = 0;
  double at(double t) const { return offset + rate * t; }
};

DarkLine fit_dark(const std::vector<double>& t, const std::vector<double>& d, bool linear) {
  const double mt = mean(t), md = mean(d);
  DarkLine line{md, 0.0};
  if (!linear) return line;
  double sxx = 0, sxy = 0;
  for (size_t k = 0; k < t.size(); ++k) {
    sxx += (t[k] - mt) * (t[k] - mt);
    sxy += (t[k] - mt) * (d[k] - md);
  }
  if (sxx > 0) line.rate = sxy / sxx;
  line.offset = md - line.rate * mt;
  return line;
}

// Pearson r by two passes; 0 when either side is constant.
double pearson(const std::vector<double>& x, const std::vector<double>& y) {
  const double mx = mean(x), my = mean(y);
  double sxx = 0, syy = 0, sxy = 0;
  for (size_t i = 0; i < x.size(); ++i) {
    sxx += (x[i] - mx) * (x[i] - mx);
    syy += (y[i] - my) * (y[i] - my);
    sxy += (x[i] - mx) * (y[i] - my);
  }
  return sxx > 0 && syy > 0 ? sxy / std::sqrt(sxx * syy) : 0.0;
}

}  // namespace

HdrResult hdr_merge(const HdrFrames& f, const HdrOptions& o) {
  const auto [dark, lim] = hdr_setup(f, o);
  const size_t m = f.exposures.size();
  std::vector<float> estimate(f.pixels(), 0.0f);
  std::vector<uint32_t> status(f.pixels());
  std::vector<double> dark_values(f.darks.size()), valid_t, valid_signal;
  for (size_t i = 0; i < f.pixels(); ++i) {
    for (size_t k = 0; k < f.darks.size(); ++k) dark_values[k] = f.darks[k][i];
    DarkLine line = fit_dark(f.dark_s, dark_values, lim.dark_linear);
    bool hot = line.at(dark.longest_s) > lim.hot_dark_dn;

    valid_t.clear();
    valid_signal.clear();
    uint32_t unsaturated = 0, mask = 0;
    double sum_signal = 0, sum_t = 0;
    for (size_t j = 0; j < m; ++j) {
      double raw = f.exposures[j][i];
      if (raw >= lim.saturation_dn) continue;
      ++unsaturated;
      double signal = raw - line.at(f.exposure_s[j]);
      if (signal <= lim.floor_dn) continue;
      valid_t.push_back(f.exposure_s[j]);
      valid_signal.push_back(signal);
      sum_signal += signal, sum_t += f.exposure_s[j];
      mask |= 1u << j;
    }
    HdrReason why = HdrReason::kept;
    if (hot) why = HdrReason::hot_dark;
    else if (unsaturated < o.min_valid_exposures) why = HdrReason::saturated;
    else if (valid_t.size() < o.min_valid_exposures) why = HdrReason::faint;
    else if (!(pearson(valid_t, valid_signal) > o.min_correlation)) why = HdrReason::nonlinear;
    if (why == HdrReason::kept) estimate[i] = float(sum_signal / sum_t);
    status[i] = uint32_t(why) | uint32_t(valid_t.size()) << 8 | mask << 16;
  }
  return hdr_finish(f, std::move(estimate), std::move(status), dark, lim);
}

}  // namespace prism::ref
