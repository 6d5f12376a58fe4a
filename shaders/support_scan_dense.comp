// The dense baseline of the support search: the paper's way (Sec. IV.B), the
// correlation of the whole gradient image with each shifted PSF at the scan
// level, and the weight's NLL summed over every pixel. Same shifts, same
// weight fit and same output as support_scan.comp, which gets the same
// numbers from sums over the clicks alone; bench_reconstruct measures what
// the difference costs. One workgroup per (event, PSF), invocations over
// pixels (a workgroup sum per shift).
//
//   <g, P(shifted)> = sum_pixels g_i P(i - shift),  g_i = 1 - y_i / (1 - exp(-lambda_i))
//   f(alpha) = sum_pixels (1 - y_i) alpha P_i - y_i [lambda0_i + log(1 - exp(-lambda_i))]
// with lambda_i = lambda0_i + alpha P_i; f equals the sparse kernel's NLL.
#version 460
#extension GL_GOOGLE_include_directive : require
#define PRISM_FN
#define BLOCK_BINDING 4
#include "likelihood.glsl"
#include "scan.glsl"

// Per event, dense_words words: g (width x height floats), the current
// model's lambda0 (width x height floats), then the clicks y as bits.
layout(std430, binding = 2) readonly buffer Images { uint image_words[]; };
layout(std430, binding = 3) writeonly buffer Out { ScanOut results[]; };  // [event][PSF]

uint image_base, pixels, p_base;
ivec2 best_shift;

float gradient_at(uint i) { return uintBitsToFloat(image_words[image_base + i]); }
float rate_at(uint i) { return uintBitsToFloat(image_words[image_base + pixels + i]); }
bool clicked(uint i) { return ((image_words[image_base + 2u * pixels + (i >> 5u)] >> (i & 31u)) & 1u) != 0u; }
float shifted_psf(uint i) {
  ivec2 q = ivec2(int(i % P.width), int(i / P.width)) - best_shift;
  return psf_value(p_base, q.x, q.y);
}

vec3 objective_slope_curvature(float alpha) {
  float part = 0.0f;
  vec2 slope_curv = vec2(0.0f);
  for (uint i = gl_LocalInvocationID.x; i < pixels; i += GROUP) {
    // f: (1 - y) alpha P - y log(1 - exp(-lambda)), less y lambda0; its
    // slope P - y P / (1 - exp(-lambda)).
    float p = shifted_psf(i);
    slope_curv.x += p;
    if (clicked(i)) {
      float lambda0 = rate_at(i), lambda = lambda0 + alpha * p;
      vec3 terms = click_terms(lambda);
      part -= lambda0 + terms.x;
      slope_curv += vec2(-p * terms.y, p * p * terms.z);
    } else {
      part += alpha * p;
    }
  }
  return vec3(group_sum(part), group_sum2(slope_curv));
}

void main() {
  uint m = P.psf_first + gl_WorkGroupID.x;
  uint e = P.event_first + gl_WorkGroupID.y;
  ScanPsf psf = psfs[m];
  pixels = P.width * P.height;
  image_base = (e - P.event_first) * P.dense_words;
  p_base = psf.p_word;

  int n = lattice_half(psf.radius);
  uint shifts = uint((2 * n + 1) * (2 * n + 1));
  uint row = e * P.psf_total + m;

  if (P.phase == 0u) {
    // Each shift's correlation as a workgroup sum over the pixels (invocations
    // split the image); the block's lowest kept, ties to the lowest index.
    uint j0 = gl_WorkGroupID.z * P.block_shifts, j1 = min(j0 + P.block_shifts, shifts);
    float best = 1.0f / 0.0f;
    uint arg = 0xffffffffu;
    for (uint j = j0; j < j1; ++j) {
      ivec2 sh = lattice_shift(j, n);
      float part = 0.0f;
      for (uint i = gl_LocalInvocationID.x; i < pixels; i += GROUP) {
        ivec2 q = ivec2(int(i % P.width), int(i / P.width)) - sh;
        part += gradient_at(i) * psf_value(p_base, q.x, q.y);
      }
      float total = group_sum(part);
      if (total < best) {
        best = total;
        arg = j;
      }
    }
    if (gl_LocalInvocationID.x == 0u) block_best[row * P.blocks + gl_WorkGroupID.z] = BlockBest(best, arg);
    return;
  }

  float score;
  best_shift = lattice_shift(best_of_blocks(row, score), n);

  // The weight at that shift, from the same start as the sparse kernel.
  vec2 reached_mass = vec2(0.0f);
  for (uint i = gl_LocalInvocationID.x; i < pixels; i += GROUP) {
    float p = shifted_psf(i);
    reached_mass += vec2(clicked(i) && p > 0.0f ? 1.0f : 0.0f, p);
  }
  reached_mass = group_sum2(reached_mass);
  WeightFit fit = fit_weight(initial_alpha(reached_mass.x, reached_mass.y));

  if (gl_LocalInvocationID.x == 0u) {
    ScanOut o;
    o.shift_x = best_shift.x;
    o.shift_y = best_shift.y;
    o.score = score;
    o.nll = fit.f;
    o.alpha = fit.alpha;
    o.newton = fit.iterations;
    o.shifts = shifts;
    o.bound = fit.f;
    results[row] = o;
  }
}
