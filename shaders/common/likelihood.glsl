// Device math of the binary-sensor likelihood (paper eq. 12; DESIGN.md
// "Reconstruction"): a pixel with rate lambda clicks with probability
// 1 - exp(-lambda). The three per-click terms the support search needs, in
// float, finite for every lambda > 0, plus a lower bound on a candidate's NLL and the scan's push constants.
//
// Same GLSL/C++ subset as dual.glsl; engine/support_scan.h compiles it as C++
// so tests call the very functions the kernels run. The double-precision
// reference (host/reconstruct/reconstruct.cpp, namespace nll) is written separately with
// std::expm1, on purpose.
//
// GLSL has no expm1, and exp/log on a GPU may be off by a few ulp (log by
// 2^-21 absolute near 1), so 1 - exp(-lambda) is a series below 0.1, where
// forming it by subtraction would lose digits; above, the subtraction loses
// at most exp's own error relative to a number >= 0.095.
#ifndef PRISM_LIKELIHOOD_GLSL
#define PRISM_LIKELIHOOD_GLSL

// 1 - exp(-lambda) for lambda < 0.1, by its series
// lambda (1 - lambda/2 (1 - lambda/3 (1 - lambda/4 (1 - lambda/5 (1 - lambda/6))))):
// the omitted term is below lambda^7 / 5040 = 2e-11 lambda.
PRISM_FN float click_probability_series(float l) {
  return l * (1.0f - 0.5f * l * (1.0f - l / 3.0f * (1.0f - 0.25f * l * (1.0f - 0.2f * l * (1.0f - l / 6.0f)))));
}

// 1 - exp(-lambda), relative error ~1e-7 for every lambda > 0.
PRISM_FN float click_probability(float lambda) {
  if (lambda < 0.1f) return click_probability_series(lambda);
  return 1.0f - exp(-lambda);
}

// log(1 - exp(-lambda)): the log-probability of a click. For lambda > 8 it is
// -exp(-lambda) to within exp(-2 lambda) / 2 (log1p's series), which a plain
// log of a number within 3e-4 of 1 would lose.
PRISM_FN float log_click(float lambda) {
  if (lambda > 8.0f) return -exp(-lambda) - 0.5f * exp(-2.0f * lambda);
  return log(click_probability(lambda));
}

// 1 / (1 - exp(-lambda)): the weight of a click in the gradient
// g = 1 - y / (1 - exp(-lambda)) (DESIGN.md step 1); ~1/lambda for small lambda.
PRISM_FN float click_weight(float lambda) { return 1.0f / click_probability(lambda); }

// d2/dlambda2 of -log(1 - exp(-lambda)) = exp(-lambda) / (1 - exp(-lambda))^2,
// i.e. 1 / (4 sinh^2(lambda / 2)); 0 where it underflows (lambda > ~88), and
// capped at float's range below lambda ~ 1e-19.
PRISM_FN float click_curvature(float lambda) {
  if (lambda > 80.0f) return 0.0f;
  float p = click_probability(lambda);
  if (p < 1e-19f) return 3.0e38f;
  return exp(-lambda) / p / p;
}

// The three terms above at once, exp(-lambda) formed once for all three:
// (log_click, click_weight, click_curvature), each as its function gives it
// (log_click's tail takes exp(-lambda)^2 for exp(-2 lambda)). The weight
// fit's objective takes all three at every click and step.
PRISM_FN vec3 click_terms(float lambda) {
  float e = exp(-lambda);
  float p = lambda < 0.1f ? click_probability_series(lambda) : 1.0f - e;
  float log_p = lambda > 8.0f ? -e - 0.5f * (e * e) : log(p);
  float curvature = lambda > 80.0f ? 0.0f : (p < 1e-19f ? 3.0e38f : e / p / p);
  return vec3(log_p, 1.0f / p, curvature);
}

// A lower bound on what one candidate's NLL can reach over its weight,
//   min over 0 <= alpha <= alpha_max of
//   f(alpha) = alpha (S - q) - sum_c b_c + sum_c h_c(alpha),
//   h_c(alpha) = -log(1 - exp(-lambda_c)),  lambda_c = b_c + alpha P_c,  q = sum_c P_c,
// from sums over the clicks at its shift, without fitting the weight (the
// support scan fits weights only for candidates whose bound can still win).
// Each h_c is convex and falls with alpha; it is bounded below two ways.
//  - Curved, for clicks the candidate explains: 1 - exp(-lambda) <= lambda
//    gives h_c >= -log P_c - log(alpha + r_c), r_c = b_c / P_c, and the
//    concavity of log gives sum_c log(alpha + r_c) <= n log(alpha + mean r).
//    Nearly equal where every r_c << alpha; one faint click (r_c >> alpha)
//    inflates mean r and loosens it for all (a high dark rate makes many).
//  - Tangent, for clicks the background dominates (b_c > alpha0 P_c): h_c
//    lies above its tangent at alpha0 (convex), which is nearly h_c itself
//    there, since such an h_c is nearly linear in alpha.
// alpha0 is the weight's moment estimate, the event's clicks over S.
// Clicks the candidate does not reach (P_c = 0) give terms free of alpha,
// exact in fixed_part (-b_c - log(1 - exp(-b_c)) each), as is -b_c of the
// reached ones. What is left, A alpha - log_p - n log(alpha + ratio / n),
// is convex with its minimum in closed form. The bound is the larger of
// this with every reached click curved and with the faint ones on their
// tangent (both are bounds). Exact (to rounding) when no click is reached.
// The double reference is ref::nll_lower_bound.
struct BoundSums {
  float reached;         // clicks with P_c > 0
  float q;               // their sum of P_c
  float log_p;           // their sum of log P_c
  float ratio;           // their sum of r_c
  float fixed_part;      // -b_c of every click, -log(1 - exp(-b_c)) of the unreached
  float curved;          // reached clicks with b_c <= alpha0 P_c: their count,
  float curved_log_p;    //   sum of log P_c
  float curved_ratio;    //   and sum of r_c
  float tangent_slope;   // the others: sum of h_c'(alpha0) (<= 0)
  float tangent_offset;  //   and of h_c(alpha0) - alpha0 h_c'(alpha0)
};

PRISM_FN BoundSums no_bound_sums() {
  BoundSums z;
  z.reached = 0.0f, z.q = 0.0f, z.log_p = 0.0f, z.ratio = 0.0f, z.fixed_part = 0.0f;
  z.curved = 0.0f, z.curved_log_p = 0.0f, z.curved_ratio = 0.0f, z.tangent_slope = 0.0f, z.tangent_offset = 0.0f;
  return z;
}

// The tangent point: the moment estimate of the weight (clicks over S), in (0, alpha_max].
PRISM_FN float bound_tangent_alpha(float clicks, float s, float alpha_max) {
  return s > 0.0f ? min(max(clicks, 1.0f) / s, alpha_max) : alpha_max;
}

// One click into the sums: P_c = p, b_c = b.
PRISM_FN BoundSums bound_sums_add(BoundSums t, float p, float b, float alpha0) {
  t.fixed_part -= b;
  if (p <= 0.0f) {
    t.fixed_part -= log_click(b);
    return t;
  }
  float lp = log(p), r = b / p;
  t.reached += 1.0f, t.q += p, t.log_p += lp, t.ratio += r;
  if (b <= alpha0 * p) {
    t.curved += 1.0f, t.curved_log_p += lp, t.curved_ratio += r;
  } else {
    float lambda0 = b + alpha0 * p;
    // h'(alpha0) = -P exp(-lambda0) / (1 - exp(-lambda0)), without cancellation.
    float slope = -p * exp(-lambda0) * click_weight(lambda0);
    t.tangent_slope += slope;
    t.tangent_offset += -log_click(lambda0) - alpha0 * slope;
  }
  return t;
}

// min over [0, alpha_max] of linear alpha + offset - log_p - n log(alpha + ratio / n),
// less an allowance for float sums (2e-4 of their magnitudes; the tests
// measure the float form against the double one at up to 1e-5).
PRISM_FN float convex_bound_min(float n, float linear, float offset, float log_p, float ratio, float alpha_max) {
  if (n <= 0.0f) {
    float a0 = linear < 0.0f ? alpha_max : 0.0f;
    return offset + linear * a0 - 2e-4f * (abs(offset) + abs(linear * a0) + 1.0f);
  }
  float a = alpha_max;  // linear <= 0: the bound falls all the way to alpha_max
  if (linear > 0.0f) a = clamp(n / linear - ratio / n, 0.0f, alpha_max);
  float spread = n * log(a + ratio / n);
  return offset + a * linear - log_p - spread -
         2e-4f * (abs(offset) + abs(log_p) + abs(a * linear) + abs(spread) + 1.0f);
}

PRISM_FN float nll_lower_bound(BoundSums t, float s, float alpha_max) {
  float free_mass = s - t.q;  // S - sum_c P_c >= 0 up to rounding: the mass off the clicks
  float all_curved = convex_bound_min(t.reached, free_mass, t.fixed_part, t.log_p, t.ratio, alpha_max);
  if (t.curved == t.reached) return all_curved;
  float split = convex_bound_min(t.curved, free_mass + t.tangent_slope, t.fixed_part + t.tangent_offset,
                                 t.curved_log_p, t.curved_ratio, alpha_max);
  return max(all_curved, split);
}

// ScanOut.newton of a serial weight fit that ran out of loop budget (support_scan.comp).
const uint FIT_UNFINISHED = 0xffffffffu;
// ScanOut.newton of a candidate whose weight was not fitted: its NLL bound
// could not win (support_scan.comp, phase 1).
const uint FIT_SKIPPED = 0xfffffffeu;

// Push constants of both support-scan kernels (std430, 68 bytes).
struct ScanParams {
  uint psf_first;     // dictionary entry of the first PSF in this dispatch (its chunk)
  uint psf_count;     // PSFs in this dispatch
  uint psf_total;     // PSFs in the dictionary: the output's row length
  uint event_first;   // first event of the batch this dispatch scores
  uint event_count;
  uint width;         // pixels per row of the scan level
  uint height;        // rows of the scan level
  uint step;          // shifts tried: multiples of step within +-radius, per axis
  uint max_newton;    // cap on the weight's Newton iterations
  float half_scale;   // half-float PSF values are stored times this (the dictionary's 2^15)
  float alpha_max;    // upper bound on a weight, expected photons
  uint dense_words;   // uint words per event image of the dense kernel (0 for the sparse one)
  uint phase;         // 0: score one block of shifts per workgroup (z); 1: pick the best block and bound the
                      // NLL there (the dense kernel: fit the weight); 2: fit the weights of a list of candidates
  uint block_shifts;  // shifts per block: keeps one invocation's loop iterations bounded (see support_scan.cpp)
  uint blocks;        // blocks per (event, PSF)
  uint list_first;    // phase 2: first entry of the candidate list in this dispatch
  uint list_count;    // phase 2: its entries
};

#endif
