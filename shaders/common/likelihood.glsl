// Device math of the binary-sensor likelihood (paper eq. 12; DESIGN.md
// "Reconstruction"): a pixel with rate lambda clicks with probability
// 1 - exp(-lambda). The three per-click terms the support search needs, in
// float, finite for every lambda > 0, plus the scan's push constants.
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

// ScanOut.newton of a serial weight fit that ran out of loop budget (support_scan.comp).
const uint FIT_UNFINISHED = 0xffffffffu;

// Push constants of both support-scan kernels (std430, 60 bytes).
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
  uint phase;         // 0: score one block of shifts per workgroup (z); 1: pick the best block, fit the weight
  uint block_shifts;  // shifts per block: keeps one invocation's loop iterations bounded (see support_scan.cpp)
  uint blocks;        // blocks per (event, PSF)
};

#endif
