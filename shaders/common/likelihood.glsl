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

// 1 - exp(-lambda), relative error ~1e-7 for every lambda > 0.
PRISM_FN float click_probability(float lambda) {
  if (lambda < 0.1f) {
    // lambda (1 - lambda/2 (1 - lambda/3 (1 - lambda/4 (1 - lambda/5 (1 - lambda/6))))):
    // the omitted term is below lambda^7 / 5040 = 2e-11 lambda.
    float l = lambda;
    return l * (1.0f - 0.5f * l * (1.0f - l / 3.0f * (1.0f - 0.25f * l * (1.0f - 0.2f * l * (1.0f - l / 6.0f)))));
  }
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

// A lower bound on what one candidate's NLL can reach over its weight,
//   min over 0 <= alpha <= alpha_max of
//   f(alpha) = alpha S - sum_c [lambda_c + log(1 - exp(-lambda_c))],  lambda_c = b_c + alpha P_c,
// from sums over the clicks at its shift, without fitting the weight (the
// support scan fits weights only for candidates whose bound can still win).
// The clicks it does not reach (P_c = 0) give terms free of alpha, summed
// exactly in `fixed_part` (-b_c - log(1 - exp(-b_c)) each) along with -b_c of
// the reached ones. Of those, `reached` clicks with mass `q` (sum P_c),
// `log_p` (sum log P_c) and `ratio` (sum b_c / P_c): 1 - exp(-lambda) <=
// lambda gives -log(1 - exp(-lambda_c)) >= -log P_c - log(alpha + b_c / P_c),
// and the concavity of log sum_c log(alpha + r_c) <= n log(alpha + ratio / n)
// (nearly equal: b_c / P_c << alpha wherever the candidate explains a click).
// What is left, alpha (S - q) - log_p - n log(alpha + ratio / n), is convex
// in alpha with its minimum in closed form. Exact (to rounding) when no click
// is reached.
// The double reference is ref::nll_lower_bound.
PRISM_FN float nll_lower_bound(float reached, float q, float log_p, float ratio, float fixed_part, float s,
                               float alpha_max) {
  float free_mass = s - q;  // S - sum_c P_c >= 0 up to rounding: the mass off the clicks
  // The sums came from float terms: the bound allows for their rounding
  // (2e-4 of their magnitudes; the tests measure the float form against the
  // double one at up to 1e-5).
  if (reached <= 0.0f) return fixed_part + min(0.0f, alpha_max * free_mass) - 2e-4f * (abs(fixed_part) + 1.0f);
  float a = alpha_max;  // free_mass <= 0: the bound falls all the way to alpha_max
  if (free_mass > 0.0f) a = clamp(reached / free_mass - ratio / reached, 0.0f, alpha_max);
  float spread = reached * log(a + ratio / reached);
  float rounding = 2e-4f * (abs(fixed_part) + abs(log_p) + abs(a * free_mass) + abs(spread) + 1.0f);
  return fixed_part + a * free_mass - log_p - spread - rounding;
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
