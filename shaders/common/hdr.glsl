// Device math of the HDR calibration merge (paper Sec. III.A.2): per pixel,
// classify each exposure as valid, saturated or lost in noise, model the dark
// level against exposure time, and accumulate the valid exposures' signals
// and times and their correlation.
//
// Same GLSL/C++ subset as dual.glsl; engine/hdr_shared.h compiles it as C++
// and checks HdrParams against its std430 push-constant size. The CPU
// reference (engine/ref/hdr_merge_ref.cpp) is written separately on purpose.
#ifndef PRISM_HDR_GLSL
#define PRISM_HDR_GLSL

// Why a pixel was kept or rejected (the low 8 bits of its status word).
const uint HDR_KEPT = 0u;              // PSF = the valid exposures' signal over their time (hdr_estimate)
const uint HDR_REJECT_HOT_DARK = 1u;   // dark level far above the frame's: dark current unknown at other T
const uint HDR_REJECT_SATURATED = 2u;  // fewer than min_valid exposures below the saturation level
const uint HDR_REJECT_FAINT = 3u;      // enough unsaturated exposures, too few above the noise floor
const uint HDR_REJECT_NONLINEAR = 4u;  // (raw - dark) does not grow linearly with T (r <= min_correlation)
const uint HDR_REASON_COUNT = 5u;
// The status word: bits 0..7 reason, 8..15 valid exposures, 16..31 mask of valid exposures.
const uint HDR_MAX_EXPOSURES = 16u;
const uint HDR_MAX_DARKS = 64u;

// Per-band constants (push constants, std430, 48 bytes).
struct HdrParams {
  uint width;              // pixels per sensor row
  uint band_rows;          // rows in this band
  uint frame_words;        // uint32 words per frame in the band buffer (two 16-bit samples per word)
  uint exposure_count;     // exposures in the stack (<= HDR_MAX_EXPOSURES)
  uint dark_count;         // dark frames in the stack (<= HDR_MAX_DARKS)
  uint dark_linear;        // 1: fit dark = offset + rate * T over the darks; 0: dark level constant in T
  uint min_valid;          // valid exposures a kept pixel needs
  float saturation_dn;     // raw >= this is saturated
  float floor_dn;          // raw - dark <= this is lost in noise or quantisation
  float hot_dark_dn;       // dark level at the longest dark time above this: hot pixel
  float min_correlation;   // Pearson r of (raw - dark) against T must exceed this
  float longest_dark_s;    // the longest dark exposure time
};

// Running mean, variances and covariance of (t, s) pairs (Welford's update:
// stable in float for any spread of exposure times).
struct HdrStats {
  float n;
  float mean_t;
  float mean_s;
  float m2_t;   // sum of squared deviations of t
  float m2_s;   // sum of squared deviations of s
  float c_ts;   // sum of products of deviations
};

PRISM_FN HdrStats hdr_stats_empty() { return HdrStats(0.0f, 0.0f, 0.0f, 0.0f, 0.0f, 0.0f); }

PRISM_FN HdrStats hdr_stats_add(HdrStats a, float t, float s) {
  float n = a.n + 1.0f;
  float dt = t - a.mean_t;
  float ds = s - a.mean_s;
  float mean_t = a.mean_t + dt / n;
  float mean_s = a.mean_s + ds / n;
  return HdrStats(n, mean_t, mean_s, a.m2_t + dt * (t - mean_t), a.m2_s + ds * (s - mean_s),
                  a.c_ts + dt * (s - mean_s));
}

// The pixel's rate (DN/s): the valid exposures' summed signal over their
// summed time, each exposure weighed by its time (the estimate of a photon
// count, shot noise alone). Not the paper's mean of the exposure-normalised
// signals s / t: an exposure counts only when its own noisy signal clears
// the floor, so the shortest valid one is kept on upward noise, and in the
// mean it weighs as much as the longest; the merged values rose and fell by
// about 1% with brightness, one tooth per exposure step, which tilted a
// calibrated lenslet (docs/dictionary.md "HDR calibration merge"). Weighed by time, the
// shortest of n valid exposures 4.2x apart counts 1 / 4.2^(n-1) of the
// longest. (The longest is kept near saturation only on downward noise, and
// now weighs the most; on the prototype's stacks no tooth of that sign
// showed above 0.06%.)
PRISM_FN float hdr_estimate(HdrStats valid) { return valid.mean_s / valid.mean_t; }

// Pearson correlation; 0 when either variable does not vary (no evidence of linearity).
PRISM_FN float hdr_correlation(HdrStats a) {
  float d = a.m2_t * a.m2_s;
  if (!(d > 0.0f)) return 0.0f;
  return a.c_ts / sqrt(d);
}

// Dark level in DN at exposure time t, from the dark frames' (t, value) stats.
// Linear: least-squares offset + rate * t. Constant: their mean at every t
// (capture-hdr takes darks at one time only; docs/dictionary.md "HDR calibration merge" measures the bias).
PRISM_FN float hdr_dark_level(HdrStats darks, uint linear, float t) {
  if (linear == 0u || !(darks.m2_t > 0.0f)) return darks.mean_s;
  float rate = darks.c_ts / darks.m2_t;
  return darks.mean_s + rate * (t - darks.mean_t);
}

// An exposure is valid when unsaturated and clearly above the dark level.
PRISM_FN bool hdr_unsaturated(float raw, HdrParams p) { return raw < p.saturation_dn; }
PRISM_FN bool hdr_above_floor(float signal_dn, HdrParams p) { return signal_dn > p.floor_dn; }

// The verdict on one pixel, in the order the tests are applied.
PRISM_FN uint hdr_reason(bool hot, uint unsaturated, HdrStats valid, HdrParams p) {
  if (hot) return HDR_REJECT_HOT_DARK;
  if (unsaturated < p.min_valid) return HDR_REJECT_SATURATED;
  if (uint(valid.n) < p.min_valid) return HDR_REJECT_FAINT;
  if (!(hdr_correlation(valid) > p.min_correlation)) return HDR_REJECT_NONLINEAR;
  return HDR_KEPT;
}

PRISM_FN uint hdr_status_word(uint reason, uint valid_count, uint valid_mask) {
  return reason | (valid_count << 8u) | (valid_mask << 16u);
}

#endif
