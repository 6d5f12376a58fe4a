// Support search on the sparse likelihood (paper eqs. 17-18; DESIGN.md
// "Reconstruction ... and why it can be fast"), one workgroup per (event,
// PSF): every shift of the lattice within +-radius is scored by
//   <g, P(shifted)> = S(shift) - sum_clicks w_c P(c - shift),
// w_c = 1 / (1 - exp(-lambda_c)) of the event's current model at click c,
// S from the summed-area table in four look-ups (phase 0); at the best
// shift, a lower bound on the NLL any weight can reach there, from one pass
// over the clicks (phase 1, likelihood.glsl's nll_lower_bound); and for the
// candidates the launcher lists, those whose bound can still win, the weight
// fitted by projected Newton on the NLL (phase 2)
//   f(alpha) = alpha S - sum_clicks [lambda_c + log(1 - exp(-lambda_c))],
//   lambda_c = background_c + alpha P_c.
// Work per (event, PSF) is shifts x clicks, never shifts x pixels.
//
// Two layouts per phase (SERIAL_SCAN for phase 0, SERIAL_FIT for phases 1
// and 2): a workgroup per (event, PSF) whose 64 invocations split the shifts
// or the clicks and meet in shared-memory reductions, or one invocation per
// (event, PSF) running over them alone. On a CPU device (llvmpipe) a
// workgroup barrier is dear and most of the 64 invocations sit idle through
// a coarse level's few shifts and the Newton steps, so the second is several
// times faster there; since it scores 8 shifts per pass over the clicks, it
// is also 1.8x faster for the many shifts of a fine level (level 2 of the
// default dictionary; before, the workgroups were 1.5x faster there, their
// invocations reading neighbouring values of one PSF). Its blocks of shifts
// are sized by the launcher to the loop budget;
// a weight fit that would pass the budget stops and says so, and the
// launcher fits that candidate again in workgroups.
#version 460
#extension GL_GOOGLE_include_directive : require
#extension GL_EXT_control_flow_attributes : require
#define PRISM_FN
#define BLOCK_BINDING 6
#define PSF_TEXELS 8
#include "likelihood.glsl"
#include "scan.glsl"

// Per event: its first click and click count in the two arrays below.
layout(std430, binding = 2) readonly buffer Events { uvec2 event_clicks[]; };
// Per click: x | y << 16 on the scan level, and lambda of the event's
// current model (dark rate included) with the gradient weight 1 / (1 -
// exp(-lambda)), formed once on the host in double. Read, where TEXELS is
// set, as one texel per click of binding 9 (R32G32B32A32_UINT: the word,
// lambda's and the weight's bits, 0; scan.glsl's PSF_TEXELS says why): one
// fetch for all three, where the two buffers below take two.
layout(std430, binding = 3) readonly buffer Clicks { uint click_words[]; };
layout(std430, binding = 4) readonly buffer Rates { vec2 rate_words[]; };
layout(binding = 9) uniform usamplerBuffer click_texels;
// Phase 0's row table where ROWS is set (DictionaryService puts it after each
// PSF's summed-area table, from the next multiple of 4 words): (width + 3) x
// height texels of four floats, texel (x, y) = (P(x, y), P(x - 1, y),
// P(x - 2, y), P(x - 3, y)), zero off the sensor. One fetch at click - shift
// gives the values of four neighbouring shifts of a lattice row (step 1):
// on llvmpipe a fetch of four floats costs about what one float's does.
layout(constant_id = 5) const uint ROWS = 0u;
layout(binding = 10) uniform samplerBuffer row_texels;  // the dictionary's chunk again, four floats a texel
uint row_texel_base(uint sat_word) { return (sat_word + (P.width + 1u) * (P.height + 1u) + 3u) >> 2u; }
vec4 psf_row(uint base, int x, int y) {
  if (x < 0 || y < 0 || x >= int(P.width) + 3 || y >= int(P.height)) return vec4(0.0f);  // no light
  return texelFetch(row_texels, int(base + uint(y) * (P.width + 3u) + uint(x)));
}
layout(std430, binding = 5) buffer Out { ScanOut results[]; };                 // [event][PSF]
// Phase 2: the candidates whose weights to fit, (event, PSF) pairs; the
// entries of one dispatch lie in its chunk.
layout(std430, binding = 7) readonly buffer FitList { uvec2 fit_list[]; };

uint first_click, click_count, p_base;
ScanPsf psf;
int n;        // the shift lattice's half width
uint shifts;  // shifts in it
uint row;     // e * psf_total + m: this (event, PSF)'s results
ivec2 best_shift;
float best_mass;

// Click c of this invocation's event.
struct Click {
  ivec2 at;
  float lambda;
  float w;
};
Click click_of(uint c) {
  uint i = first_click + c, v;
  Click k;
  if (TEXELS == 1u) {
    uvec4 r = texelFetch(click_texels, int(i));
    v = r.x, k.lambda = uintBitsToFloat(r.y), k.w = uintBitsToFloat(r.z);
  } else {
    v = click_words[i], k.lambda = rate_words[i].x, k.w = rate_words[i].y;
  }
  k.at = ivec2(int(v & 0xffffu), int(v >> 16u));
  return k;
}

// The serial layout: one invocation per (event, PSF), no sums across the
// workgroup. A weight fit's click iterations are counted against
// FIT_BUDGET, under llvmpipe's limit on one invocation's loop iterations
// (65535, all loops together; the Newton and backtracking loops' own
// iterations and the blocks' are the rest).
layout(constant_id = 1) const uint SERIAL_SCAN = 0u;  // phase 0 in one invocation per (event, PSF, block)
layout(constant_id = 2) const uint SERIAL_FIT = 0u;   // phase 1 in one invocation per (event, PSF)
// Loop iterations the launcher allows one serial invocation's scan
// (support_scan.cpp's kCpuLoopBudget; it sizes the blocks of shifts by it).
layout(constant_id = 3) const uint SCAN_BUDGET = 32768u;
const uint FIT_BUDGET = 30000u;
uint spent = 0u;
bool exhausted = false;
// The weight fit's loops over the clicks (phase 1 only).
uint lane() { return SERIAL_FIT == 1u ? 0u : gl_LocalInvocationID.x; }
uint lanes() { return SERIAL_FIT == 1u ? 1u : GROUP; }
vec2 lanes_sum2(vec2 v) { return SERIAL_FIT == 1u ? v : group_sum2(v); }
float lanes_sum(float v) { return SERIAL_FIT == 1u ? v : group_sum(v); }
// False once a pass over the clicks would pass the budget (serial only).
bool within_budget() {
  if (SERIAL_FIT == 0u) return true;
  exhausted = exhausted || spent + click_count > FIT_BUDGET;
  spent += exhausted ? 0u : click_count;
  return !exhausted;
}

// The NLL less its terms free of alpha (the clicks the PSF does not reach;
// fit_listed adds them once), with its slope and curvature: the line search
// compares values of a few tens, not of thousands, where float resolves the
// steps near the optimum.
vec3 objective_slope_curvature(float alpha) {
  // Past the budget: +inf ends the backtracking, and with it the fit.
  if (!within_budget()) return vec3(1.0f / 0.0f, 0.0f, 1.0f);
  float part = 0.0f;
  vec2 slope_curv = vec2(0.0f);
  for (uint c = lane(); c < click_count; c += lanes()) {
    Click k = click_of(c);
    ivec2 q = k.at - best_shift;
    float p = psf_value(p_base, q.x, q.y);
    if (p <= 0.0f) continue;  // a click the PSF does not reach: no term in alpha
    float lambda = k.lambda + alpha * p;
    vec3 terms = click_terms(lambda);
    part += lambda + terms.x;
    slope_curv += vec2(p * terms.y, p * p * terms.z);
  }
  part = lanes_sum(part);
  slope_curv = lanes_sum2(slope_curv);
  return vec3(alpha * best_mass - part, best_mass - slope_curv.x, slope_curv.y);
}

// This invocation's (event e, PSF m).
void locate_pair(uint e, uint m) {
  psf = psfs[m];
  uvec2 ec = event_clicks[e];
  first_click = ec.x;
  click_count = ec.y;
  p_base = psf.p_word;
  n = lattice_half(psf.radius);
  shifts = uint((2 * n + 1) * (2 * n + 1));
  row = e * P.psf_total + m;
}

// The (event, PSF) of this invocation in phases 0 and 1: its workgroup's, or
// in the serial layout its own (false past the dispatch's PSFs).
bool locate(bool serial) {
  uint m = P.psf_first + (serial ? gl_WorkGroupID.y * GROUP + gl_LocalInvocationID.x : gl_WorkGroupID.x);
  if (serial && m >= P.psf_first + P.psf_count) return false;
  locate_pair(P.event_first + (serial ? gl_WorkGroupID.x : gl_WorkGroupID.y), m);
  return true;
}

// Phase 0: score this block's shifts; each invocation keeps its best (the
// lowest index among equals: strict <, in increasing order).
//
// Serial: SUB shifts at a time, each click read once for all of them (its
// position and weight), the SUB scores in registers. Each score is the same
// sum in the same order as one shift at a time; measured on llvmpipe, phase
// 0 takes half the time (docs/reconstruction.md, the scan kernel). The
// shifts left after the whole passes of SUB go one at a time (a lattice of
// (2n + 1)^2 shifts leaves one: for 9 shifts, 9 look-ups per click instead
// of 16). An event with more clicks than SCAN_BUDGET / SUB goes one shift at
// a time (a pass counts SUB iterations per click should the compiler keep the
// inner loop; the launcher's blocks are then at most SCAN_BUDGET / clicks
// shifts; the shifts left of a block cost fewer iterations than its pass).
//
// With ROWS (step 1): passes of SEGMENTS runs of up to 4 neighbouring shifts
// of one lattice row, each run one row-table fetch per click. The lattice of
// 121 shifts (n = 5) costs 33 fetches per click instead of 121, and 11 reads
// of the click (one per pass) instead of 16. The scores are the same sums in
// the same order as without it.
const uint SUB = 8u;
const uint SEGMENTS = 3u;
void score_block() {
  const bool serial = SERIAL_SCAN == 1u;
  // Branches on specialisation constants only: a barrier never follows a
  // return that the compiler cannot prove uniform (llvmpipe got the first
  // workgroup's reduction wrong when it could not).
  if (!locate(serial)) return;
  uint j0 = gl_WorkGroupID.z * P.block_shifts, j1 = min(j0 + P.block_shifts, shifts);
  float best = 1.0f / 0.0f;
  uint arg = 0xffffffffu;
  uint j_single = j0;  // where the one-shift-per-pass loop below starts
  if (serial && ROWS == 1u && click_count * SUB <= SCAN_BUDGET) {
    const uint side = uint(2 * n + 1);
    const uint rows = row_texel_base(psf.sat_word);
    for (uint j = j0; j < j1;) {
      // The pass's runs: from j, up to 4 shifts each, none past its row or the block.
      uint start[SEGMENTS], len[SEGMENTS];
      ivec2 sh[SEGMENTS];
      float score[4u * SEGMENTS];
      [[unroll]] for (uint g = 0u; g < SEGMENTS; ++g) {
        start[g] = j;
        len[g] = min(min(4u, (j / side + 1u) * side - j), j1 - j);
        sh[g] = lattice_shift(j, n);
        [[unroll]] for (uint k = 0u; k < 4u; ++k)
          score[4u * g + k] = k < len[g] ? mass_shifted(psf.sat_word, sh[g].x + int(k), sh[g].y) : 0.0f;
        j += len[g];
      }
      for (uint c = 0u; c < click_count; ++c) {
        Click k = click_of(c);
        [[unroll]] for (uint g = 0u; g < SEGMENTS; ++g) {
          if (len[g] == 0u) continue;
          ivec2 q = k.at - sh[g];
          vec4 v = psf_row(rows, q.x, q.y);  // P at click - (sh + (s, 0)), s = 0..3
          [[unroll]] for (uint s = 0u; s < 4u; ++s) score[4u * g + s] -= k.w * v[s];
        }
      }
      [[unroll]] for (uint g = 0u; g < SEGMENTS; ++g)
        [[unroll]] for (uint k = 0u; k < 4u; ++k)
          if (k < len[g] && score[4u * g + k] < best) {
            best = score[4u * g + k];
            arg = start[g] + k;
          }
    }
    j_single = j1;
  } else if (serial && click_count * SUB <= SCAN_BUDGET) {
    // Whole passes of SUB shifts; the few left (a lattice of (2n + 1)^2
    // shifts leaves one) go one per pass below, rather than a pass of SUB
    // look-ups per click for them.
    for (; j_single + SUB <= j1; j_single += SUB) {
      uint j = j_single;
      ivec2 sh[SUB];
      float score[SUB];
      [[unroll]] for (uint k = 0u; k < SUB; ++k) {
        sh[k] = lattice_shift(j + k, n);
        score[k] = mass_shifted(psf.sat_word, sh[k].x, sh[k].y);
      }
      for (uint c = 0u; c < click_count; ++c) {
        Click k = click_of(c);
        [[unroll]] for (uint s = 0u; s < SUB; ++s) {
          ivec2 q = k.at - sh[s];
          score[s] -= k.w * psf_value(p_base, q.x, q.y);
        }
      }
      [[unroll]] for (uint k = 0u; k < SUB; ++k)
        if (score[k] < best) {
          best = score[k];
          arg = j + k;
        }
    }
  }
  {
    // One shift per pass over the clicks: each invocation of a workgroup its
    // own shifts, or the serial invocation those left.
    for (uint j = j_single + (serial ? 0u : gl_LocalInvocationID.x); j < j1; j += (serial ? 1u : GROUP)) {
      ivec2 sh = lattice_shift(j, n);
      float score = mass_shifted(psf.sat_word, sh.x, sh.y);
      for (uint c = 0u; c < click_count; ++c) {
        Click k = click_of(c);
        ivec2 q = k.at - sh;
        score -= k.w * psf_value(p_base, q.x, q.y);
      }
      if (score < best) {
        best = score;
        arg = j;
      }
    }
  }
  if (!serial) {
    arg = group_argmin(best, arg);
    best = group_min_score;
  }
  if (serial || gl_LocalInvocationID.x == 0u) block_best[row * P.blocks + gl_WorkGroupID.z] = BlockBest(best, arg);
}

// Phase 1: the best block's shift, and a bound on the NLL a weight can
// reach there. The candidate is left unfitted (FIT_SKIPPED) for phase 2.
void bound_best() {
  if (!locate(SERIAL_FIT == 1u)) return;
  float best_score;
  best_shift = lattice_shift(best_of_blocks(row, best_score), n);
  best_mass = mass_shifted(psf.sat_word, best_shift.x, best_shift.y);
  // The sums over the clicks that bound the NLL (nll_lower_bound).
  float alpha0 = bound_tangent_alpha(float(click_count), best_mass, P.alpha_max);
  BoundSums t = no_bound_sums();
  for (uint c = lane(); c < click_count; c += lanes()) {
    Click k = click_of(c);
    ivec2 q = k.at - best_shift;
    t = bound_sums_add(t, psf_value(p_base, q.x, q.y), k.lambda, alpha0);
  }
  vec2 v = lanes_sum2(vec2(t.reached, t.q));
  t.reached = v.x, t.q = v.y;
  v = lanes_sum2(vec2(t.log_p, t.ratio));
  t.log_p = v.x, t.ratio = v.y;
  v = lanes_sum2(vec2(t.fixed_part, t.curved));
  t.fixed_part = v.x, t.curved = v.y;
  v = lanes_sum2(vec2(t.curved_log_p, t.curved_ratio));
  t.curved_log_p = v.x, t.curved_ratio = v.y;
  v = lanes_sum2(vec2(t.tangent_slope, t.tangent_offset));
  t.tangent_slope = v.x, t.tangent_offset = v.y;
  if (lane() == 0u) {
    ScanOut o;
    o.shift_x = best_shift.x;
    o.shift_y = best_shift.y;
    o.score = best_score;
    o.nll = 0.0f;
    o.alpha = 0.0f;
    o.newton = FIT_SKIPPED;
    o.shifts = shifts;
    o.bound = nll_lower_bound(t, best_mass, P.alpha_max);
    results[row] = o;
  }
}

// Phase 2: the weight of one listed candidate at phase 1's shift. In
// workgroups the dispatch may hold a few more groups than entries; they fit
// the last entry again and write nothing (no return before the barriers).
void fit_listed() {
  const bool serial = SERIAL_FIT == 1u;
  uint k = serial ? gl_GlobalInvocationID.x : gl_WorkGroupID.y * gl_NumWorkGroups.x + gl_WorkGroupID.x;
  if (serial && k >= P.list_count) return;
  bool writes = k < P.list_count;
  uvec2 em = fit_list[P.list_first + min(k, P.list_count - 1u)];
  locate_pair(em.x, em.y);
  best_shift = ivec2(results[row].shift_x, results[row].shift_y);
  best_mass = mass_shifted(psf.sat_word, best_shift.x, best_shift.y);

  spent = click_count + P.blocks;  // as when phase 1 also read the blocks: the same budget, the same fits
  // The clicks reached, for Newton's start; the NLL's terms of the others.
  vec2 reached_fixed = vec2(0.0f);
  for (uint c = lane(); c < click_count; c += lanes()) {
    Click k = click_of(c);
    ivec2 q = k.at - best_shift;
    float b = k.lambda;
    reached_fixed += psf_value(p_base, q.x, q.y) > 0.0f ? vec2(1.0f, 0.0f) : vec2(0.0f, b + log_click(b));
  }
  reached_fixed = lanes_sum2(reached_fixed);
  WeightFit fit = fit_weight(initial_alpha(reached_fixed.x, best_mass));

  if (writes && lane() == 0u) {
    results[row].nll = fit.f - reached_fixed.y;
    results[row].alpha = fit.alpha;
    results[row].newton = exhausted ? FIT_UNFINISHED : fit.iterations;
  }
}

void main() {
  if (P.phase == 0u)
    score_block();
  else if (P.phase == 1u)
    bound_best();
  else
    fit_listed();
}
