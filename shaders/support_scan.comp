// Support search on the sparse likelihood (paper eqs. 17-18; DESIGN.md
// "Reconstruction ... and why it can be fast"), one workgroup per (event,
// PSF): every shift of the lattice within +-radius is scored by
//   <g, P(shifted)> = S(shift) - sum_clicks w_c P(c - shift),
// w_c = 1 / (1 - exp(-lambda_c)) of the event's current model at click c,
// S from the summed-area table in four look-ups; the best shift's weight is
// then fitted by projected Newton on the NLL
//   f(alpha) = alpha S - sum_clicks [lambda_c + log(1 - exp(-lambda_c))],
//   lambda_c = background_c + alpha P_c.
// Work per (event, PSF) is shifts x clicks, never shifts x pixels.
#version 460
#extension GL_GOOGLE_include_directive : require
#define PRISM_FN
#define BLOCK_BINDING 6
#include "likelihood.glsl"
#include "scan.glsl"

// Per event: its first click and click count in the two arrays below.
layout(std430, binding = 2) readonly buffer Events { uvec2 event_clicks[]; };
layout(std430, binding = 3) readonly buffer Clicks { uint click_xy[]; };       // x | y << 16 on the scan level
// Per click: lambda of the event's current model (dark rate included) and the
// gradient weight 1 / (1 - exp(-lambda)), formed once on the host in double.
layout(std430, binding = 4) readonly buffer Rates { vec2 rate_weight[]; };
layout(std430, binding = 5) writeonly buffer Out { ScanOut results[]; };       // [event][PSF]

uint first_click, click_count, p_base;
ivec2 best_shift;
float best_mass;

ivec2 click_at(uint c) {
  uint v = click_xy[first_click + c];
  return ivec2(int(v & 0xffffu), int(v >> 16u));
}

float objective(float alpha) {
  float part = 0.0f;
  for (uint c = gl_LocalInvocationID.x; c < click_count; c += GROUP) {
    ivec2 q = click_at(c) - best_shift;
    float lambda = rate_weight[first_click + c].x + alpha * psf_value(p_base, q.x, q.y);
    part += lambda + log_click(lambda);
  }
  return alpha * best_mass - group_sum(part);
}

vec2 slope_curvature(float alpha) {
  vec2 part = vec2(0.0f);
  for (uint c = gl_LocalInvocationID.x; c < click_count; c += GROUP) {
    ivec2 q = click_at(c) - best_shift;
    float p = psf_value(p_base, q.x, q.y);
    float lambda = rate_weight[first_click + c].x + alpha * p;
    part += vec2(p * click_weight(lambda), p * p * click_curvature(lambda));
  }
  vec2 s = group_sum2(part);
  return vec2(best_mass - s.x, s.y);
}

void main() {
  uint m = P.psf_first + gl_WorkGroupID.x;
  uint e = P.event_first + gl_WorkGroupID.y;
  ScanPsf psf = psfs[m];
  uvec2 ec = event_clicks[e];
  first_click = ec.x;
  click_count = ec.y;
  p_base = psf.p_word;

  int n = lattice_half(psf.radius);
  uint shifts = uint((2 * n + 1) * (2 * n + 1));
  uint row = e * P.psf_total + m;

  if (P.phase == 0u) {
    // Score this block's shifts; each invocation keeps its best.
    uint j0 = gl_WorkGroupID.z * P.block_shifts, j1 = min(j0 + P.block_shifts, shifts);
    float best = 1.0f / 0.0f;
    uint arg = 0xffffffffu;
    for (uint j = j0 + gl_LocalInvocationID.x; j < j1; j += GROUP) {
      ivec2 sh = lattice_shift(j, n);
      float score = mass_shifted(psf.sat_word, sh.x, sh.y);
      for (uint c = 0u; c < click_count; ++c) {
        ivec2 q = click_at(c) - sh;
        score -= rate_weight[first_click + c].y * psf_value(p_base, q.x, q.y);
      }
      if (score < best) {
        best = score;
        arg = j;
      }
    }
    uint j = group_argmin(best, arg);
    if (gl_LocalInvocationID.x == 0u) block_best[row * P.blocks + gl_WorkGroupID.z] = BlockBest(group_min_score, j);
    return;
  }

  float best_score;
  best_shift = lattice_shift(best_of_blocks(row, best_score), n);
  best_mass = mass_shifted(psf.sat_word, best_shift.x, best_shift.y);

  // The weight at that shift.
  float reached = 0.0f;
  for (uint c = gl_LocalInvocationID.x; c < click_count; c += GROUP) {
    ivec2 q = click_at(c) - best_shift;
    reached += psf_value(p_base, q.x, q.y) > 0.0f ? 1.0f : 0.0f;
  }
  reached = group_sum(reached);
  WeightFit fit = fit_weight(initial_alpha(reached, best_mass));

  if (gl_LocalInvocationID.x == 0u) {
    ScanOut o;
    o.shift_x = best_shift.x;
    o.shift_y = best_shift.y;
    o.score = best_score;
    o.nll = fit.f;
    o.alpha = fit.alpha;
    o.newton = fit.iterations;
    o.shifts = shifts;
    o.pad = 0u;
    results[row] = o;
  }
}
