// The exposure and dark times of an HDR calibration stack: one home for
// `prism camera capture-hdr` (hw/capture.cpp), `prism dictionary
// simulate-hdr` and the synthetic camera of the tests (host/calibrate/
// synthetic.h). Header-only and unit-free (seconds or microseconds alike), so
// that hw/, which links no engine, can use it.
#pragma once
#include <cmath>
#include <vector>

namespace prism {

// m times spread log-uniformly over [min_t, max_t] (m = 1: min_t).
inline std::vector<double> log_spaced_times(double min_t, double max_t, unsigned m) {
  std::vector<double> t(m);
  for (unsigned i = 0; i < m; ++i) t[i] = m == 1 ? min_t : min_t * std::pow(max_t / min_t, double(i) / double(m - 1));
  return t;
}

// The times of `darks` dark frames for the exposures `exposure_t`: at the
// longest, the shortest and exposure times evenly between by index (some
// times twice when there are more darks than exposures), so that the
// merge fits each pixel's dark level as offset + rate T (HdrOptions
// dark_model "auto" takes the line for darks at two or more times). Darks
// at one time alone give a constant level, subtracted from every exposure:
// a pixel's dark current is then over-subtracted from an exposure T by
// rate (T_dark - T). That matters for the faint pixels, which the merge
// keeps on its three longest exposures: at a 2 s longest exposure and 5 DN/s,
// 7.6 and 9.4 DN off the second and third longest, beside the 16 DN floor.
// The error depends on where a pixel's exposures fall against the floor, a
// saw-tooth of a few per cent in brightness that no photon scale absorbs
// (docs/dictionary.md "HDR calibration merge"). One dark: the longest exposure.
inline std::vector<double> dark_times(const std::vector<double>& exposure_t, unsigned darks) {
  std::vector<double> t;
  if (exposure_t.empty()) return t;
  const size_t last = exposure_t.size() - 1;
  for (unsigned i = 0; i < darks; ++i) {
    const double at = darks == 1 ? 0.0 : double(i) * double(last) / double(darks - 1);
    t.push_back(exposure_t[last - size_t(std::lround(at))]);
  }
  return t;
}

}  // namespace prism
