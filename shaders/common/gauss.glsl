// The Gaussian pixel response of effect diffraction: the share of a Gaussian
// (mean mu, sigma s) that falls in [lo, hi], with its derivatives. The tails
// keep their relative accuracy: a pixel far from a sharp image must see a
// small light with a small error, or its Fisher term g^2 / b is wrong.
//
// Same GLSL/C++ subset as dual.glsl (engine/shared_math.h compiles it).
#ifndef PRISM_GAUSS_GLSL
#define PRISM_GAUSS_GLSL

#include "dual.glsl"

// erfc(x) for x >= 0 with relative error below 1.2e-7 (Chebyshev fit of
// Numerical Recipes, erfcc; W. H. Press et al., 2nd ed., sec. 6.2).
PRISM_FN float erfc_positive(float x) {
  float t = 1.0f / (1.0f + 0.5f * x);
  float p = -1.26551223f +
            t * (1.00002368f +
                 t * (0.37409196f +
                      t * (0.09678418f +
                           t * (-0.18628806f +
                                t * (0.27886807f +
                                     t * (-1.13520398f + t * (1.48851587f + t * (-0.82215223f + t * 0.17087277f))))))));
  return t * exp(-x * x + p);
}

// The upper tail Q(z) = P(Z > z) of the standard normal, z >= 0.
PRISM_FN float normal_tail(float z) { return 0.5f * erfc_positive(z * 0.70710678f); }

// The standard normal density.
PRISM_FN float normal_density(float z) { return 0.39894228f * exp(-0.5f * z * z); }

// P(z0 < Z < z1), z0 <= z1, formed from the tails on the side where both lie
// (no cancellation of 1 - 1), with d/d(theta) = phi(z1) z1' - phi(z0) z0'.
PRISM_FN Dual normal_share(Dual z0, Dual z1) {
  float v;
  if (z0.v >= 0.0f) v = normal_tail(z0.v) - normal_tail(z1.v);
  else if (z1.v <= 0.0f) v = normal_tail(-z1.v) - normal_tail(-z0.v);
  else v = 1.0f - normal_tail(-z0.v) - normal_tail(z1.v);
  return Dual(max(v, 0.0f), z1.d * normal_density(z1.v) - z0.d * normal_density(z0.v));
}

// The share of a Gaussian (mean mu, sigma s; grid pixels) in [lo, hi].
PRISM_FN Dual gaussian_share(Dual mu, Dual s, float lo, float hi) {
  return normal_share(d_div(d_sub(d_const(lo), mu), s), d_div(d_sub(d_const(hi), mu), s));
}

// Reach of a Gaussian deposit, in sigmas: the light beyond is below 6e-7.
const float GAUSS_REACH = 5.0f;

#endif
