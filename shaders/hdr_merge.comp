// HDR merge of one calibration stack, one invocation per pixel of a band of
// sensor rows: fit the pixel's dark level, keep the exposures that are neither
// saturated nor lost in noise, and write their summed signal over their
// summed time (DN/s, not yet normalised; hdr_estimate) with a status word saying why.
#version 460
#extension GL_GOOGLE_include_directive : require
#define PRISM_FN
#include "hdr.glsl"

layout(local_size_x = 64) in;

layout(push_constant) uniform Push { HdrParams P; };
// [frame][pixel of band] 16-bit samples, two per word (little-endian): the
// exposures first, then the darks; each frame padded to frame_words.
layout(std430, binding = 0) readonly buffer Frames { uint frames[]; };
// Exposure times in seconds: exposures first, then darks.
layout(std430, binding = 1) readonly buffer Times { float times_s[]; };
layout(std430, binding = 2) writeonly buffer Estimate { float estimate[]; };  // [pixel of band] DN/s
layout(std430, binding = 3) writeonly buffer Status { uint status[]; };       // [pixel of band]

float sample_dn(uint frame, uint pixel) {
  uint word = frames[frame * P.frame_words + (pixel >> 1u)];
  return float((word >> (16u * (pixel & 1u))) & 0xffffu);
}

void main() {
  uint col = gl_GlobalInvocationID.x;
  uint row = gl_GlobalInvocationID.y;
  if (col >= P.width || row >= P.band_rows) return;
  uint pixel = row * P.width + col;

  HdrStats darks = hdr_stats_empty();
  for (uint k = 0u; k < P.dark_count; ++k)
    darks = hdr_stats_add(darks, times_s[P.exposure_count + k], sample_dn(P.exposure_count + k, pixel));
  bool hot = hdr_dark_level(darks, P.dark_linear, P.longest_dark_s) > P.hot_dark_dn;

  HdrStats valid = hdr_stats_empty();
  uint unsaturated = 0u;
  uint mask = 0u;
  for (uint j = 0u; j < P.exposure_count; ++j) {
    float t = times_s[j];
    float raw = sample_dn(j, pixel);
    float signal = raw - hdr_dark_level(darks, P.dark_linear, t);
    if (!hdr_unsaturated(raw, P)) continue;
    unsaturated += 1u;
    if (!hdr_above_floor(signal, P)) continue;
    valid = hdr_stats_add(valid, t, signal);
    mask |= 1u << j;
  }
  uint reason = hdr_reason(hot, unsaturated, valid, P);
  estimate[pixel] = reason == HDR_KEPT ? hdr_estimate(valid) : 0.0f;
  status[pixel] = hdr_status_word(reason, uint(valid.n), mask);
}
