// What both support-scan kernels share (GLSL only: buffers and workgroup
// reductions): the dictionary's scan level as stored on the device, the
// per-PSF table, the output record, and sums over the workgroup.
//
// Each kernel runs in phases (dispatches): phase 0 scores one block of the
// shift lattice per workgroup and keeps the block's best; phase 1 picks the
// best block's shift and fits the weight there (dense) or bounds the NLL the
// weight can reach (sparse: support_scan.comp's phase 2 then fits the weights
// of the candidates the launcher lists, those whose bound can still win). Blocks bound the
// loop iterations of one invocation: Mesa's llvmpipe (lavapipe) ends every
// shader loop after 65535 iterations of all loops together, silently, so an
// unsplit scan of 529 shifts x 7875 pixels came back wrong there.
//
// Device layout of one PSF (host/dictionary/service.cpp writes it): its
// values, width x height row-major, as float bits or, with HALF, as pairs of
// half floats times half_scale in one word (low half first); then, from
// sat_word, its summed-area table, (width + 1) x (height + 1) floats, so the
// on-sensor mass S of a shifted PSF is four look-ups; on a CPU device, float
// values, then its row table (support_scan.comp's psf_row).
#ifndef PRISM_SCAN_GLSL
#define PRISM_SCAN_GLSL

layout(constant_id = 0) const uint HALF = 0u;  // 1: PSF values stored as half floats
const uint GROUP = 64u;
layout(local_size_x = 64) in;

layout(push_constant) uniform Push { ScanParams P; };
layout(std430, binding = 0) readonly buffer Dictionary { uint words[]; };  // one chunk of the scan level
struct ScanPsf {
  uint chunk;     // which chunk holds it (dispatches are per chunk)
  uint p_word;    // first word of its values in the chunk
  uint sat_word;  // first word of its summed-area table
  int radius;     // shifts within +-radius pixels per axis (tau times the magnification at its depth)
};
layout(std430, binding = 1) readonly buffer Psfs { ScanPsf psfs[]; };
// Per (event, PSF, block of shifts): the best score in the block and its
// index, from phase 0 for phase 1.
struct BlockBest {
  float score;
  uint j;
};
layout(std430, binding = BLOCK_BINDING) buffer Blocks { BlockBest block_best[]; };  // [event][PSF][block]
// Per (event, PSF): the best shift, its score <g, P>, and the weight fitted there.
struct ScanOut {
  int shift_x;
  int shift_y;
  float score;  // <g, P(shifted)> = S - sum_clicks w P (sparse) or the dense sum
  float nll;    // the NLL of this vertex against the event's background, at alpha
  float alpha;  // expected photons, projected Newton on alpha >= 0
  uint newton;  // Newton iterations taken; FIT_UNFINISHED: the serial fit ran out of loop budget;
                // FIT_SKIPPED: not fitted (nll and alpha are not set)
  uint shifts;  // shifts tried
  float bound;  // a lower bound on nll (likelihood.glsl's nll_lower_bound; the dense kernel: nll itself)
};

// A kernel that defines PSF_TEXELS (a binding) reads the values, where
// TEXELS is set, through the chunk seen as a uniform texel buffer, of floats
// or, with HALF, of half floats: the same values, fetched as one vector
// gather on llvmpipe where a storage buffer load runs one invocation at a
// time (vk::Kernel, engine/support_scan.h's ScanLoads).
#ifdef PSF_TEXELS
layout(binding = PSF_TEXELS) uniform samplerBuffer psf_texels;
layout(constant_id = 4) const uint TEXELS = 1u;
#endif

float psf_value(uint base, int x, int y) {
  if (x < 0 || y < 0 || x >= int(P.width) || y >= int(P.height)) return 0.0f;  // off the sensor: no light
  uint i = uint(y) * P.width + uint(x);
#ifdef PSF_TEXELS
  if (TEXELS == 1u)
    return HALF == 1u ? texelFetch(psf_texels, int(2u * base + i)).r / P.half_scale : texelFetch(psf_texels, int(base + i)).r;
#endif
  if (HALF == 1u) {
    vec2 pair = unpackHalf2x16(words[base + (i >> 1u)]);
    return ((i & 1u) == 0u ? pair.x : pair.y) / P.half_scale;
  }
  return uintBitsToFloat(words[base + i]);
}

float sat_at(uint base, int x, int y) {
  uint i = base + uint(y) * (P.width + 1u) + uint(x);
#ifdef PSF_TEXELS
  if (TEXELS == 1u && HALF == 0u) return texelFetch(psf_texels, int(i)).r;  // the float view spans the tables too
#endif
  return uintBitsToFloat(words[i]);
}

// Mass of the PSF still on the sensor after shifting it by (dx, dy) pixels:
// the table over columns [-dx, width - dx) and rows [-dy, height - dy), clipped.
float mass_shifted(uint sat, int dx, int dy) {
  int x0 = clamp(-dx, 0, int(P.width)), x1 = clamp(int(P.width) - dx, 0, int(P.width));
  int y0 = clamp(-dy, 0, int(P.height)), y1 = clamp(int(P.height) - dy, 0, int(P.height));
  if (x1 <= x0 || y1 <= y0) return 0.0f;
  return sat_at(sat, x1, y1) - sat_at(sat, x0, y1) - sat_at(sat, x1, y0) + sat_at(sat, x0, y0);
}

// The lattice of shifts: multiples of step within +-radius, row-major from
// (-n, -n), the order the CPU reference scans them in.
int lattice_half(int radius) { return radius / int(max(P.step, 1u)); }
ivec2 lattice_shift(uint j, int n) {
  int side = 2 * n + 1;
  return ivec2(int(j) % side - n, int(j) / side - n) * int(max(P.step, 1u));
}

// Workgroup sums and arg-min. Every invocation calls them (uniform control
// flow) and every invocation gets the same result.
shared float red_a[GROUP];
shared float red_b[GROUP];
shared uint red_j[GROUP];

vec2 group_sum2(vec2 v) {
  uint t = gl_LocalInvocationID.x;
  red_a[t] = v.x;
  red_b[t] = v.y;
  barrier();
  for (uint s = GROUP / 2u; s > 0u; s >>= 1u) {
    if (t < s) {
      red_a[t] += red_a[t + s];
      red_b[t] += red_b[t + s];
    }
    barrier();
  }
  vec2 r = vec2(red_a[0], red_b[0]);
  barrier();
  return r;
}
float group_sum(float v) { return group_sum2(vec2(v, 0.0f)).x; }

// The lowest score (left in group_min_score) and its index; ties go to the
// lowest index j, as in the CPU reference.
float group_min_score;
uint group_argmin(float score, uint j) {
  uint t = gl_LocalInvocationID.x;
  red_a[t] = score;
  red_j[t] = j;
  barrier();
  for (uint s = GROUP / 2u; s > 0u; s >>= 1u) {
    if (t < s) {
      float o = red_a[t + s];
      uint oj = red_j[t + s];
      if (o < red_a[t] || (o == red_a[t] && oj < red_j[t])) {
        red_a[t] = o;
        red_j[t] = oj;
      }
    }
    barrier();
  }
  uint r = red_j[0];
  group_min_score = red_a[0];
  barrier();
  return r;
}

// The weight of one candidate: projected Newton on alpha in [0, alpha_max]
// (paper eq. 18) with Armijo backtracking, the one-vertex case of the CPU
// reference's fit_weights, in float: it stops when a step no longer lowers
// the objective by more than float resolves. Each kernel defines the
// objective f(alpha) with its slope and curvature, sums over the clicks (or
// over every pixel for the dense kernel) in one pass: an accepted trial's
// slope and curvature are the next Newton step's, so a step costs one pass.
vec3 objective_slope_curvature(float alpha);  // (f, f', f'')

struct WeightFit {
  float alpha;
  float f;
  uint iterations;
};

WeightFit fit_weight(float alpha0) {
  float a = clamp(alpha0, 0.0f, P.alpha_max);
  vec3 at = objective_slope_curvature(a);
  uint it = 0u;
  for (; it < P.max_newton; ++it) {
    float g = at.y;
    // Held at a bound by the sign of the slope: the projected optimum.
    if ((a <= 0.0f && g >= 0.0f) || (a >= P.alpha_max && g <= 0.0f)) break;
    float dir = -g / (at.z * (1.0f + 1e-6f) + 1e-30f);
    bool accepted = false;
    float trial = a, step = 0.0f;
    vec3 tried = at;
    for (float t = 1.0f; t > 1e-12f; t *= 0.5f) {
      trial = clamp(a + t * dir, 0.0f, P.alpha_max);
      step = abs(trial - a) / (1.0f + a);
      if (step == 0.0f) break;
      tried = objective_slope_curvature(trial);
      if (tried.x <= at.x + 1e-4f * g * (trial - a)) {
        accepted = true;
        break;
      }
    }
    if (!accepted) break;
    bool converged = at.x - tried.x <= 1e-6f * (1.0f + abs(at.x)) && step < 1e-5f;
    a = trial;
    at = tried;
    if (converged) break;
  }
  return WeightFit(a, at.x, it);
}

// Newton's start, as the CPU reference: the clicks the PSF reaches over its
// on-sensor mass.
float initial_alpha(float reached, float s) {
  return clamp(max(reached, 1.0f) / max(s, 1e-3f), 1e-3f, P.alpha_max);
}

// Phase 1's start: the best of the blocks' bests (blocks hold increasing
// shift indices, so strict < keeps the lowest index among ties).
uint best_of_blocks(uint row, out float score) {
  score = 1.0f / 0.0f;
  uint j = 0u;
  for (uint b = 0u; b < P.blocks; ++b) {
    BlockBest o = block_best[row * P.blocks + b];
    if (o.score < score) {
      score = o.score;
      j = o.j;
    }
  }
  return j;
}

#endif
